"""The async handle of one HerkuleX servo on the bus.

::

    import asyncio

    from ohmni_tb.bus import Bus
    from ohmni_tb.herkulex import TorqueControl
    from ohmni_tb.herkulex.servo import Servo
    from ohmni_tb.transport import open_transport

    async def main() -> None:
        async with Bus(await open_transport("sim://")) as bus:
            neck = Servo(bus, 3)  # sid 3 is the neck: 280..650 unless told otherwise
            await neck.torque(TorqueControl.ON)
            await neck.move_to(650, playtime_s=1.0)
            print(await neck.position_raw(), neck.last_status)

    asyncio.run(main())

A :class:`Servo` needs only a :class:`Requester` — the four calls it makes on whatever
carries its packets. The :class:`~ohmni_tb.bus.Bus` is one; a Robot or a daemon client can
be another.

Every reply updates :attr:`Servo.last_status` and :attr:`Servo.last_status_at`. A reply
carrying error bits does not raise by itself — a latched fault must stay readable so it
can be cleared — but the moves check the status first and raise
:class:`~ohmni_tb.errors.DeviceStatusError` when the servo would ignore them. That check
uses the cached status when it is younger than ``status_max_age_s`` and shows torque on
and no fault, and asks the servo (STAT) otherwise.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from ohmni_tb._checks import bounded, show
from ohmni_tb.errors import (
    DeviceStatusError,
    InvalidArgumentError,
    MalformedReplyError,
    OutOfRangeError,
)
from ohmni_tb.herkulex.commands import (
    JogMode,
    JogTarget,
    Reply,
    clear_status,
    eep_read,
    eep_write,
    i_jog,
    model_read,
    parse_model,
    parse_reply,
    ram_read,
    ram_write,
    reboot,
    s_jog,
    stat,
)
from ohmni_tb.herkulex.registers import (
    EEP,
    RAM,
    Led,
    Model,
    Register,
    TorqueControl,
    memory_of,
    resolve,
    write_targets,
)
from ohmni_tb.herkulex.units import (
    POSITION_MAX_RAW,
    angle_rad_from_raw,
    check_playtime_ticks,
    check_zero_offset_raw,
    playtime_ticks_from_s,
    pos_raw_from_rad,
)
from ohmni_tb.protocol import Command, Memory, Packet, StatusDetail, StatusError, flag_names
from ohmni_tb.protocol.devices import NECK_RAW_RANGE, DeviceId

__all__ = ["Requester", "Servo", "ServoStatus", "move_group"]

#: Largest block read in one request (the reply must fit the bus's packet limit).
_BLOCK = 64
#: Errors that make a servo ignore jogs until they are cleared.
_BLOCKING_ERRORS = StatusError.TEMPERATURE | StatusError.OVERLOAD | StatusError.DRIVER_FAULT

#: Time a servo needs after REBOOT before it answers (undocumented; drivers wait 1-2 s).
REBOOT_SETTLE_S = 1.0
#: The longest wait after a REBOOT a caller may ask for.
_MAX_SETTLE_S = 60.0

#: How old a cached status may be for a move to go without a STAT first. A 30 Hz poll
#: refreshes it every 33 ms, so 0.1 s survives two missed polls.
DEFAULT_STATUS_MAX_AGE_S = 0.1
#: The longest allowed: a fault that latched after the cached status goes unnoticed this
#: long (the servo ignores the jog), so the cache is kept short.
_MAX_STATUS_MAX_AGE_S = 1.0
#: RAM registers whose write changes what the status bytes say (clearing RAM 48/49, torque).
_STATUS_REGISTERS = tuple(RAM[name] for name in ("status_error", "status_detail", "torque_control"))


@runtime_checkable
class Requester(Protocol):
    """What a :class:`Servo` and :func:`move_group` need from whatever carries packets.

    :class:`~ohmni_tb.bus.Bus` has these four calls; anything else with them (a Robot
    that schedules the bus, a client of the daemon) can carry a Servo too.
    """

    async def request(
        self,
        packet: Packet,
        *,
        expect_reply: bool | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> Packet | None:
        """Send ``packet``; return its reply, or ``None`` when none is expected."""
        ...

    async def send(self, packet: Packet) -> None:
        """Send ``packet`` and wait for no reply."""
        ...

    def ack_policy(self, sid: int) -> int:
        """The ACK policy assumed for ``sid`` (what it answers)."""
        ...

    def set_ack_policy(self, sid: int, policy: int) -> None:
        """Record that ``sid`` now runs ACK policy ``policy``."""
        ...


@dataclass(frozen=True, slots=True)
class ServoStatus:
    """The two status bytes of a servo.

    Attributes:
        error: RAM 48.
        detail: RAM 49.
    """

    error: StatusError
    detail: StatusDetail

    @property
    def torque_on(self) -> bool:
        """Whether the servo reports torque on."""
        return bool(self.detail & StatusDetail.MOTOR_ON)

    @property
    def moving(self) -> bool:
        """Whether the servo is moving."""
        return bool(self.detail & StatusDetail.MOVING)

    @property
    def in_position(self) -> bool:
        """Whether the servo is within its in-position margin of the goal."""
        return bool(self.detail & StatusDetail.INPOSITION)

    @property
    def ok(self) -> bool:
        """No error bit is set."""
        return not self.error


class Servo:
    """One HerkuleX servo on a :class:`~ohmni_tb.bus.Bus` (or another :class:`Requester`).

    Args:
        requester: What carries the servo's packets: the bus it is on, or anything with
            the :class:`Requester` calls.
        sid: Its id, 0..0xFD.
        zero_offset_raw: Raw counts added to the centre (512) to define 0 rad, like
            tb_control's ``set_servo_zero_offset``.
        min_raw: The lowest position a move may ask for. Default: the neck's safe
            minimum (280, :data:`~ohmni_tb.protocol.devices.NECK_RAW_RANGE`) for sid 3,
            the servo's own factory minimum (21) for any other id.
        max_raw: The highest: the neck's 650 for sid 3, else 1002.
        status_max_age_s: How old (in loop time) a cached status may be for a move to
            trust it instead of asking the servo first, 0..1 s (0: always ask).

    Raises:
        InvalidArgumentError: ``requester`` lacks the :class:`Requester` calls, or the
            position range is inconsistent.
        OutOfRangeError: ``sid`` or ``status_max_age_s`` is out of range.
    """

    def __init__(
        self,
        requester: Requester,
        sid: int,
        *,
        zero_offset_raw: int = 0,
        min_raw: int | None = None,
        max_raw: int | None = None,
        status_max_age_s: float = DEFAULT_STATUS_MAX_AGE_S,
    ) -> None:
        given: object = requester  # typed, but callers may pass a transport or None
        if not isinstance(given, Requester):
            raise InvalidArgumentError(
                f"a Servo needs a Requester (request, send, ack_policy, set_ack_policy), "
                f"not {type(given).__name__}"
            )
        RAM["id"].check(sid)
        _check_status_max_age(status_max_age_s)
        check_zero_offset_raw(zero_offset_raw)
        default_low, default_high = _default_range(sid)
        low = default_low if min_raw is None else min_raw
        high = default_high if max_raw is None else max_raw
        for name, value in (("min_raw", low), ("max_raw", high)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise InvalidArgumentError(f"{name} must be an int, not {show(value)}")
        if not 0 <= low <= high <= POSITION_MAX_RAW:
            raise InvalidArgumentError(
                f"min_raw={show(low)} and max_raw={show(high)} must satisfy 0 <= min <= max <= 1023"
            )
        self._requester = requester
        self.sid = sid
        self.zero_offset_raw = zero_offset_raw
        self.min_raw = low
        self.max_raw = high
        self.status_max_age_s = float(status_max_age_s)
        #: The newest status bytes seen, from any reply or :meth:`note_status`.
        self.last_status: ServoStatus | None = None
        #: The loop time :attr:`last_status` was received at.
        self.last_status_at: float | None = None
        # Whether last_status may stand in for a STAT. A command that may change the status
        # without a reply (torque, clearing errors, reboot) withdraws the trust until a
        # newer status comes: a reply (after it, in program order) or a fed status read
        # strictly after it (equal loop times cannot be ordered).
        self._status_trusted = False
        self._status_changed_at = -math.inf
        self._torque_wanted = TorqueControl.FREE

    def __repr__(self) -> str:
        return f"<Servo sid={self.sid} range={self.min_raw}..{self.max_raw}>"

    # -- registers -------------------------------------------------------------------

    async def read(self, register: Register | str | int, memory: Memory | str = Memory.RAM) -> int:
        """Read one register's value.

        Args:
            register: The register: an object, its name, or its address in ``memory``.
            memory: RAM (the live value) or EEP (the power-up one); ``"ram"``/``"eep"``.

        Raises:
            InvalidArgumentError: Unknown register or memory, or no register at that
                address; nothing sent.
            BusTimeoutError: No reply.
        """
        memory = memory_of(memory)
        reg = resolve(register, memory)
        packet = ram_read(self.sid, reg) if memory is Memory.RAM else eep_read(self.sid, reg)
        return (await self._read(packet)).value(reg)

    async def write(
        self,
        register: Register | str | int,
        value: int,
        *,
        persist: bool = False,
        memory: Memory | str = Memory.RAM,
    ) -> None:
        """Write a RAM register (acts now); with ``persist``, the EEP copy too (survives
        reboot). With ``memory=EEP``, write the EEP register alone: it acts after a
        reboot (tb_control's ``servo_write_eep``).

        Every write is checked against the register map before anything is sent: the
        register exists in that memory (a name, or the address of its first byte), it is
        writable, and the value is in its range.

        Args:
            register: The register: an object, its name, or its address in ``memory``
                (``write(30, 200, memory="eep")`` is EEP 30, ``position_kp``).
            value: The value, checked against the register's range.
            persist: A RAM write: write the EEP copy too.
            memory: RAM or EEP (``"ram"``/``"eep"``).

        Raises:
            InvalidArgumentError: Unknown register or memory, no register at that address,
                a read-only register, a bad value, or ``persist`` with an EEP write;
                nothing sent.
            OutOfRangeError: The value is out of the register's range; nothing sent.
        """
        # Every target is checked before the first packet goes out.
        targets = write_targets(register, value, persist=persist, memory=memory)
        for reg in targets:
            build = eep_write if reg.memory is Memory.EEP else ram_write
            await self._send(build(self.sid, reg, value))
        if reg.memory is Memory.EEP:
            return  # acts after a reboot
        if reg.name == "ack_policy":
            self._requester.set_ack_policy(self.sid, value)
        elif reg.name == "torque_control":
            self._torque_wanted = TorqueControl(value)

    async def info(self) -> dict[str, dict[str, int]]:
        """Every register of both memories, by name (tb_control's ``get_servo_info``)."""
        out: dict[str, dict[str, int]] = {}
        for table in (EEP, RAM):
            values: dict[str, int] = {}
            regs = list(table)
            start = 0
            while start < len(regs):
                first = regs[start]
                end = start
                while end + 1 < len(regs) and regs[end + 1].end - first.addr <= _BLOCK:
                    end += 1
                last = regs[end]
                packet = (ram_read if table is RAM else eep_read)(self.sid, first, through=last)
                reply = await self._read(packet)
                for reg in regs[start : end + 1]:
                    values[reg.name] = reply.value(reg)
                start = end + 1
            out[table.memory.name.lower()] = values
        return out

    async def model(self) -> Model:
        """The servo's model (DRS-0101 or DRS-0201), from EEP 0.

        Raises:
            InvalidArgumentError: The servo reports a model this driver does not know.
        """
        return parse_model(await self._read(model_read(self.sid)))

    # -- state -----------------------------------------------------------------------

    async def status(self) -> ServoStatus:
        """Ask the servo for its two status bytes (STAT; always answered)."""
        reply = await self._requester.request(stat(self.sid), expect_reply=True)
        assert reply is not None
        return self._note(parse_reply(reply))

    def note_status(self, status: ServoStatus, at_s: float) -> None:
        """Feed a status read elsewhere, e.g. by an owner that polls RAM 48.. at 30 Hz.

        A move then trusts it while it is younger than ``status_max_age_s``, as it does
        the status of the servo's own replies. A status older than the one held is
        ignored.

        Args:
            status: The two status bytes.
            at_s: The event loop's time (``loop.time()``) when they were received.

        Raises:
            InvalidArgumentError: ``status`` is not a :class:`ServoStatus`, or ``at_s`` is
                not a number or lies in the loop's future.
        """
        given: tuple[object, object] = (status, at_s)  # typed, but checked at run time
        if not isinstance(given[0], ServoStatus):
            raise InvalidArgumentError(f"status must be a ServoStatus, not {status!r}")
        when = given[1]
        if isinstance(when, bool) or not isinstance(when, int | float) or math.isnan(when):
            raise InvalidArgumentError(f"at_s must be a loop time in seconds, not {at_s!r}")
        now = asyncio.get_running_loop().time()
        if at_s > now:
            raise InvalidArgumentError(
                f"at_s={at_s!r} s is after the loop's time now ({now!r} s); pass the loop "
                f"time the status was received at"
            )
        if self.last_status_at is not None and at_s < self.last_status_at:
            return
        self._store(status, float(at_s), trusted=at_s > self._status_changed_at)

    async def torque(self, mode: TorqueControl) -> None:
        """Set torque: FREE (limp), BRAKE (holds, ignores jogs) or ON."""
        await self.write("torque_control", TorqueControl(mode))

    async def clear_errors(self, *, restore_torque: bool = True) -> ServoStatus:
        """Clear latched errors (RAM 48/49 ← 0), then restore the torque that was asked for.

        Args:
            restore_torque: Restore it; ``False``: the torque stays as the fault left it
                (off, when the fault released it).

        Returns:
            The status after clearing. An error whose cause remains (still too hot) comes
            back at once; check :attr:`ServoStatus.ok`.
        """
        await self._send(clear_status(self.sid))
        if restore_torque and self._torque_wanted is not TorqueControl.FREE:
            await self._send(ram_write(self.sid, "torque_control", self._torque_wanted))
        return await self.status()

    async def position_raw(self) -> int:
        """The calibrated position (RAM 58, the jog coordinate), 0..1023."""
        return await self.read("calibrated_position") & 0x3FF

    async def angle_rad(self) -> float:
        """The position in radians from this servo's zero."""
        return angle_rad_from_raw(await self.position_raw(), zero_offset_raw=self.zero_offset_raw)

    async def temperature_raw(self) -> int:
        """The raw temperature (RAM 55); compare with :meth:`max_temperature_raw`."""
        return await self.read("temperature")

    # -- motion ----------------------------------------------------------------------

    def target(
        self,
        pos_raw: int | None = None,
        *,
        angle_rad: float | None = None,
        led: Led = Led.NONE,
    ) -> JogTarget:
        """A checked position target for this servo (for :func:`move_group`).

        Raises:
            InvalidArgumentError: Neither or both of ``pos_raw`` and ``angle_rad``.
            OutOfRangeError: Outside ``min_raw..max_raw``; nothing sent.
        """
        if (pos_raw is None) == (angle_rad is None):
            raise InvalidArgumentError("give exactly one of pos_raw or angle_rad")
        if angle_rad is not None:
            # Checked against this servo's range, so the error gives it in radians.
            pos_raw = pos_raw_from_rad(
                angle_rad,
                zero_offset_raw=self.zero_offset_raw,
                min_raw=self.min_raw,
                max_raw=self.max_raw,
            )
        assert pos_raw is not None
        if isinstance(pos_raw, bool) or not isinstance(pos_raw, int):
            raise InvalidArgumentError(f"pos_raw must be an int, not {pos_raw!r}")
        if not self.min_raw <= pos_raw <= self.max_raw:
            raise OutOfRangeError(
                f"servo {self.sid} position", pos_raw, self.min_raw, self.max_raw, "count"
            )
        return JogTarget(self.sid, pos_raw, led=led)

    async def move_to(
        self,
        pos_raw: int | None = None,
        *,
        angle_rad: float | None = None,
        playtime_s: float | None = None,
        playtime_ticks: int | None = None,
        led: Led = Led.NONE,
    ) -> None:
        """Move to a position (raw counts or radians) over a playtime.

        Raises:
            InvalidArgumentError: Bad combination of arguments.
            OutOfRangeError: Position or playtime out of range; nothing sent.
            DeviceStatusError: The servo has a latched fault (clear it first).
        """
        ticks = _ticks(playtime_s, playtime_ticks)
        target = self.target(pos_raw, angle_rad=angle_rad, led=led)
        await self._ensure_can_move()
        await self._send(s_jog(ticks, target))

    async def spin(self, pwm: int, *, led: Led = Led.NONE) -> None:
        """Turn continuously at a signed PWM, −1023..1023 (0 stops, holding torque).

        Switching from position to turn mode is done the manual's way: torque free, a
        turn-mode jog (which only sets the mode while torque is off), torque on; then the
        jog again, which the servo now runs.

        Raises:
            OutOfRangeError: ``pwm`` out of range; nothing sent.
            DeviceStatusError: The servo has a latched fault.
        """
        target = JogTarget(self.sid, pwm, mode=JogMode.TURN, led=led)
        await self._ensure_can_move()
        if await self.read("current_control_mode") != JogMode.TURN:
            await self._send(ram_write(self.sid, "torque_control", TorqueControl.FREE))
            await self._send(i_jog(target))
            await self._send(ram_write(self.sid, "torque_control", TorqueControl.ON))
        await self._send(i_jog(target))

    async def set_id(self, new_sid: int) -> None:
        """Give the servo a new id, in EEP and RAM; this handle follows it.

        Raises:
            OutOfRangeError: ``new_sid`` is not 0..0xFD.
        """
        RAM["id"].check(new_sid)
        await self._send(eep_write(self.sid, "id", new_sid))
        await self._send(ram_write(self.sid, "id", new_sid))
        self.sid = new_sid

    async def reboot(self, *, settle_s: float = REBOOT_SETTLE_S) -> None:
        """Reboot (EEP is copied to RAM, torque free) and wait for it to come back.

        Raises:
            OutOfRangeError: ``settle_s`` is not 0..60 s; nothing sent.
        """
        bounded("settle_s", settle_s, 0.0, _MAX_SETTLE_S, "s")
        await self._send(reboot(self.sid))
        self._torque_wanted = TorqueControl.FREE
        await asyncio.sleep(settle_s)

    # -- private ---------------------------------------------------------------------

    def _trusted_status(self) -> ServoStatus | None:
        """The cached status if it may stand in for a STAT now, else ``None``."""
        status, at = self.last_status, self.last_status_at
        if status is None or at is None or not self._status_trusted:
            return None
        # Strictly younger: a limit of 0 always asks, even within one loop instant.
        if asyncio.get_running_loop().time() - at >= self.status_max_age_s:
            return None
        return status

    async def _ensure_can_move(self) -> None:
        status = self._trusted_status()
        if status is None or status.error & _BLOCKING_ERRORS or not status.torque_on:
            # Only a good status is taken from the cache: a refusal always rests on the
            # servo's own answer, in case the fault was cleared since.
            status = await self.status()
        if status.error & _BLOCKING_ERRORS:
            raise DeviceStatusError(
                f"servo {self.sid} has a latched fault ({flag_names(status.error)}); "
                f"it ignores moves until clear_errors()",
                sid=self.sid,
                status_error=int(status.error),
                status_detail=int(status.detail),
            )
        if not status.torque_on:
            raise DeviceStatusError(
                f"servo {self.sid} has torque off; call torque(TorqueControl.ON) first",
                sid=self.sid,
                status_error=int(status.error),
                status_detail=int(status.detail),
            )

    async def _read(self, packet: Packet) -> Reply:
        reply = await self._requester.request(packet, expect_reply=True)
        assert reply is not None
        parsed = parse_reply(reply)
        if parsed.memory is None:
            raise MalformedReplyError(f"servo {self.sid} answered a read with {reply!r}")
        self._note(parsed)
        return parsed

    async def _send(self, packet: Packet) -> None:
        reply = await self._requester.request(packet)
        if _changes_status(packet):
            # The cached status may be wrong from here on; a reply (ACK policy 2) carries
            # the new one and is noted just below.
            self._status_changed_at = asyncio.get_running_loop().time()
            self._status_trusted = False
        if reply is not None:
            self._note(parse_reply(reply))

    def _note(self, reply: Reply) -> ServoStatus:
        status = ServoStatus(reply.status_error, reply.status_detail)
        # The servo's own answer is newer than anything it was sent before: trusted.
        self._store(status, asyncio.get_running_loop().time(), trusted=True)
        return status

    def _store(self, status: ServoStatus, at_s: float, *, trusted: bool) -> None:
        self.last_status = status
        self.last_status_at = at_s
        self._status_trusted = trusted


async def move_group(
    moves: Sequence[tuple[Servo, int]],
    *,
    playtime_s: float | None = None,
    playtime_ticks: int | None = None,
) -> None:
    """Move several servos on one bus together, in one S_JOG packet.

    Args:
        moves: ``(servo, pos_raw)`` pairs; each position is checked against its servo's
            range before anything is sent.
        playtime_s: The shared playtime in seconds, or
        playtime_ticks: the same in 11.2 ms ticks.

    Raises:
        InvalidArgumentError: No moves, servos on different buses, or a repeated servo.
        OutOfRangeError: A position or the playtime is out of range; nothing sent.
    """
    if not moves:
        raise InvalidArgumentError("move_group needs at least one (servo, position)")
    requester = moves[0][0]._requester
    if any(servo._requester is not requester for servo, _ in moves):
        raise InvalidArgumentError("move_group: every servo must be on the same bus")
    ticks = _ticks(playtime_s, playtime_ticks)
    targets = [servo.target(pos) for servo, pos in moves]
    await requester.send(s_jog(ticks, *targets))


def _check_status_max_age(value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidArgumentError(f"status_max_age_s must be seconds, not {value!r}")
    # NaN fails the comparison too, so it gets the same error.
    if not 0.0 <= value <= _MAX_STATUS_MAX_AGE_S:
        raise OutOfRangeError("status_max_age_s", value, 0.0, _MAX_STATUS_MAX_AGE_S, "s")


def _changes_status(packet: Packet) -> bool:
    """Whether ``packet`` may change the servo's status bytes without answering."""
    if packet.cmd in (Command.REBOOT, Command.ROLLBACK):
        return True
    if packet.cmd != Command.RAM_WRITE or len(packet.data) < 2:
        return False
    start, length = packet.data[0], packet.data[1]
    return any(start <= reg.addr < start + length for reg in _STATUS_REGISTERS)


def _default_range(sid: int) -> tuple[int, int]:
    """The positions a :class:`Servo` with id ``sid`` allows when none are given.

    The neck (sid 3) gets its safe range, :data:`~ohmni_tb.protocol.devices.NECK_RAW_RANGE`
    (280..650: beyond it the head hits its stops); any other servo its factory
    min/max position (21..1002).
    """
    if sid == DeviceId.HERKULEX_NECK:
        return NECK_RAW_RANGE
    return _factory_default("min_position"), _factory_default("max_position")


def _factory_default(register: str) -> int:
    """A register's factory value from the register table (the one place it is written)."""
    default = RAM[register].default
    if default is None:
        raise InvalidArgumentError(f"{register} has no factory default")
    return default


def _ticks(playtime_s: float | None, playtime_ticks: int | None) -> int:
    if playtime_s is not None and playtime_ticks is not None:
        raise InvalidArgumentError("give playtime_s or playtime_ticks, not both")
    if playtime_s is not None:
        return playtime_ticks_from_s(playtime_s)
    return check_playtime_ticks(0 if playtime_ticks is None else playtime_ticks)
