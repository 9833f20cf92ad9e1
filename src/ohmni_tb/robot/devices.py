"""Handles for the Robot's neck and external servos: checked commands on the bus.

Commands go through the Robot's bus at :data:`COMMAND_PRIORITY`, the feedback reads'
priority: below the control slot, so the control tick never waits for a move, and in
order of arrival with the feedback reads, so a move waits at most for the reads already
due (a few ms) and a stream of commands cannot starve the feedback.

``move(..., wait=True)`` returns once the device's feedback stream reads back at the
target: a HerkuleX servo within :data:`HERKULEX_TOLERANCE_RAW` and done moving (by
``playtime_s`` + :data:`HERKULEX_SETTLE_S`), the worm-gear neck within
:data:`WORM_TOLERANCE_RAW` and at rest (by :data:`WORM_TIMEOUT_S`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, TypeVar

from ohmni_tb._checks import check_seconds
from ohmni_tb.bus import Bus
from ohmni_tb.errors import (
    InvalidArgumentError,
    OutOfRangeError,
    PositionError,
    PositionTimeoutError,
)
from ohmni_tb.herkulex import TorqueControl
from ohmni_tb.herkulex.servo import Servo, ServoStatus
from ohmni_tb.herkulex.units import check_playtime_s, check_zero_offset_raw
from ohmni_tb.protocol import Memory, Packet
from ohmni_tb.protocol.worm_neck import (
    WORM_PROFILE,
    WormProfile,
    check_worm_target,
    set_target,
)
from ohmni_tb.robot.checks import check_servo_write

if TYPE_CHECKING:
    from ohmni_tb.robot.samples import ServoSample, WormNeckSample
    from ohmni_tb.robot.streams import Subscription

__all__ = [
    "COMMAND_PRIORITY",
    "HERKULEX_SETTLE_S",
    "HERKULEX_TOLERANCE_RAW",
    "MAX_WAIT_S",
    "WORM_TIMEOUT_S",
    "WORM_TOLERANCE_RAW",
    "ServoHandle",
    "WormNeckHandle",
    "servo_arrival",
    "worm_arrival",
]

#: Bus priority of commands: the feedback reads' (the control slot is 10).
COMMAND_PRIORITY = 5
#: The playtime of a rest move, seconds.
REST_PLAYTIME_S = 1.0
#: How close the read-back must come to the target, raw counts: ~1.6° on a HerkuleX
#: servo (its own in-position margin is 3), 0.4 % of the travel on the worm gear.
HERKULEX_TOLERANCE_RAW = 5
WORM_TOLERANCE_RAW = 1000
#: How long after the playtime a HerkuleX servo may take to read back at its target, s.
HERKULEX_SETTLE_S = 1.5
#: How long the worm gear may take to get there, s (the simulated one crosses its whole
#: travel in ~3 s; the real one's speed is not public).
WORM_TIMEOUT_S = 15.0
#: The longest ``timeout_s`` of a waiting move, s.
MAX_WAIT_S = 600.0
#: A sample older than this when a wait gives up means the device went silent, s.
_SILENT_S = 1.0
#: Samples a waiting move keeps (the stream runs at 30 Hz).
_QUEUE = 8

_S = TypeVar("_S", "ServoSample", "WormNeckSample")

_TORQUE_NAMES = {"on": TorqueControl.ON, "brake": TorqueControl.BRAKE, "free": TorqueControl.FREE}


class _CommandRequester:
    """The bus as a servo's Requester, at command priority; ``check`` may refuse first."""

    def __init__(self, bus: Bus, check: Callable[[], None] | None = None) -> None:
        self._bus = bus
        self._check = check

    async def request(
        self,
        packet: Packet,
        *,
        expect_reply: bool | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> Packet | None:
        if self._check is not None:
            self._check()
        return await self._bus.request(
            packet,
            expect_reply=expect_reply,
            timeout_s=timeout_s,
            retries=retries,
            priority=COMMAND_PRIORITY,
        )

    async def send(self, packet: Packet) -> None:
        if self._check is not None:
            self._check()
        await self._bus.request(packet, expect_reply=False, priority=COMMAND_PRIORITY)

    def ack_policy(self, sid: int) -> int:
        return self._bus.ack_policy(sid)

    def set_ack_policy(self, sid: int, policy: int) -> None:
        self._bus.set_ack_policy(sid, policy)


def torque_mode(mode: TorqueControl | str) -> TorqueControl:
    """``"on"``, ``"brake"``, ``"free"`` or a :class:`TorqueControl`.

    Raises:
        InvalidArgumentError: Anything else.
    """
    if isinstance(mode, TorqueControl):
        return mode
    if isinstance(mode, str) and mode.lower() in _TORQUE_NAMES:
        return _TORQUE_NAMES[mode.lower()]
    raise InvalidArgumentError(f"torque mode {mode!r} is not one of on, brake, free")


class ServoHandle:
    """A HerkuleX servo of the Robot (the neck at sid 3, or an external servo).

    Positions are held inside ``min_raw..max_raw``; out-of-range targets are refused
    before anything is sent.

    Args:
        bus: The Robot's bus.
        sid: The servo id.
        min_raw: Lowest allowed position.
        max_raw: Highest allowed position.
        rest_raw: Where :meth:`rest` moves it.
        zero_offset_raw: Raw counts added to 512 to define 0 rad.
        on_command: Called with the loop time of every command (the hold-time guard).
        check: Called before anything is sent; it raises to refuse (the Robot's: its
            port is released to another program).
        feedback: Subscribes to the servo's feedback stream, for ``move(wait=True)``
            (raises to refuse when there is none); ``None``: waiting is refused.
        renumber: Changes the servo's id for :meth:`set_id` (the Robot's: it checks the
            new id against the devices it knows and moves the servo's stream along);
            ``None``: the servo is told directly.
        on_zero_offset: Called with the id and the new zero offset (the Robot's: the
            neck's setting follows).
    """

    def __init__(
        self,
        bus: Bus,
        sid: int,
        *,
        min_raw: int,
        max_raw: int,
        rest_raw: int,
        zero_offset_raw: int = 0,
        on_command: Callable[[int], None] | None = None,
        check: Callable[[], None] | None = None,
        feedback: Callable[[int], Subscription[ServoSample]] | None = None,
        renumber: Callable[[ServoHandle, int], Awaitable[None]] | None = None,
        on_zero_offset: Callable[[int, int], None] | None = None,
    ) -> None:
        self._renumber = renumber
        self._on_zero_offset = on_zero_offset
        self.servo = Servo(
            _CommandRequester(bus, check),
            sid,
            zero_offset_raw=zero_offset_raw,
            min_raw=min_raw,
            max_raw=max_raw,
        )
        self.sid = sid
        self.rest_raw = rest_raw
        self._on_command = on_command
        self._feedback = feedback
        # The torque mode this handle last set (None: none yet). The servo's cached
        # status can predate it (writes get no reply under ACK policy 1), so a move
        # after free() would otherwise skip the torque and be refused.
        self._torque_set: TorqueControl | None = None
        self._position_cmd: int | None = None

    def __repr__(self) -> str:
        return f"<ServoHandle sid={self.sid} range={self.min_raw}..{self.max_raw}>"

    @property
    def position_raw_cmd(self) -> int | None:
        """The last position target sent, raw (``None`` before the first move)."""
        return self._position_cmd

    @property
    def torque_cmd(self) -> TorqueControl | None:
        """The last torque mode set (``None`` before the first)."""
        return self._torque_set

    @property
    def min_raw(self) -> int:
        """Lowest allowed position."""
        return self.servo.min_raw

    @property
    def max_raw(self) -> int:
        """Highest allowed position."""
        return self.servo.max_raw

    @property
    def zero_offset_raw(self) -> int:
        """Raw counts added to 512 to define 0 rad (tb_control's ``set_servo_zero_offset``).

        Setting it changes how angles are read and commanded from then on; nothing is
        sent to the servo.

        Raises:
            OutOfRangeError: Outside −512..511 (on setting).
        """
        return self.servo.zero_offset_raw

    @zero_offset_raw.setter
    def zero_offset_raw(self, value: int) -> None:
        self.servo.zero_offset_raw = check_zero_offset_raw(value)

    def _touched(self) -> None:
        if self._on_command is not None:
            self._on_command(self.sid)

    async def move(
        self,
        raw: int | None = None,
        *,
        rad: float | None = None,
        playtime_s: float = 1.0,
        wait: bool = False,
        timeout_s: float | None = None,
    ) -> ServoSample | None:
        """Turn torque on if needed and move to ``raw`` counts or ``rad`` over ``playtime_s``.

        With ``wait``, return once the servo's feedback stream reads back within
        :data:`HERKULEX_TOLERANCE_RAW` of the target and done moving (at the deadline, a
        read-back within the tolerance that still says moving will do).

        Args:
            raw: The target, raw counts within ``min_raw..max_raw``.
            rad: Or the target in radians (0 = 512 + ``zero_offset_raw``).
            playtime_s: How long the move takes, 0..2.8448 s, sent to the nearest 11.2 ms
                tick (2.84 s goes as 254 ticks, 2.8448 s).
            wait: Wait until the position reads back at the target.
            timeout_s: With ``wait``, the longest wait from the move, 0..600 s;
                default ``playtime_s`` + :data:`HERKULEX_SETTLE_S`.

        Returns:
            With ``wait``, the sample that read back at the target; else ``None``.

        Raises:
            InvalidArgumentError: Neither or both of ``raw`` and ``rad``, not numbers, or
                ``timeout_s`` without ``wait``.
            OutOfRangeError: Outside ``min_raw..max_raw``, a playtime outside
                0..2.8448 s or a timeout outside 0..600 s; nothing sent.
            DeviceStatusError: The servo has a latched fault.
            StateError: ``check`` refused (the Robot's port is released), or ``wait``
                and the servo's stream is off; nothing sent.
            PositionTimeoutError: ``wait``, and not there in time (or no sample came).
        """
        target = self.servo.target(raw, angle_rad=rad)  # checks before anything is sent
        # The one playtime range of every caller (0..2.8448 s, sent to the nearest tick).
        playtime_s = check_playtime_s(playtime_s)
        limit_s = _wait_limit(wait, timeout_s, playtime_s + HERKULEX_SETTLE_S)
        samples = self._subscribe() if wait else None
        try:
            self._touched()
            status = self.servo.last_status
            if (
                status is None
                or not status.torque_on
                or self._torque_set not in (None, TorqueControl.ON)
            ):
                await self.torque(TorqueControl.ON)
            await self.servo.move_to(target.value, playtime_s=playtime_s)
            self._position_cmd = target.value
            if samples is None:
                return None
            return await servo_arrival(
                samples,
                sid=self.sid,
                target_raw=target.value,
                sent_s=asyncio.get_running_loop().time(),
                limit_s=limit_s,
            )
        finally:
            if samples is not None:
                samples.close()

    def _subscribe(self) -> Subscription[ServoSample]:
        if self._feedback is None:
            raise InvalidArgumentError(
                f"servo {self.sid} has no feedback stream to wait on: wait=False"
            )
        return self._feedback(_QUEUE)

    async def torque(self, mode: TorqueControl | str) -> None:
        """Set the torque mode: ``"on"``, ``"brake"`` or ``"free"``.

        Raises:
            InvalidArgumentError: Another mode.
        """
        chosen = torque_mode(mode)
        self._touched()
        await self.servo.torque(chosen)
        self._torque_set = chosen

    async def free(self) -> None:
        """Torque off: the servo can be turned by hand and draws no holding current."""
        await self.torque(TorqueControl.FREE)

    async def rest(self, *, free: bool = True) -> None:
        """Move to the rest position over :data:`REST_PLAYTIME_S`, then free it."""
        await self.move(self.rest_raw, playtime_s=REST_PLAYTIME_S)
        if free:
            await asyncio.sleep(REST_PLAYTIME_S)
            await self.free()

    async def info(self) -> dict[str, dict[str, int]]:
        """Every EEP and RAM register's value (tb_control's ``get_servo_info``)."""
        return await self.servo.info()

    async def write(
        self,
        register: str | int,
        value: int,
        *,
        persist: bool = False,
        memory: Memory | str = Memory.RAM,
    ) -> None:
        """Write a register by name or address: RAM (acts now; with ``persist`` the EEP
        copy too), or with ``memory="eep"`` the EEP register alone (acts after a reboot:
        tb_control's ``servo_write_eep``, e.g. ``write(30, 200, memory="eep")``).

        Checked against the register map before anything is sent: the address names a
        register of that memory, it is writable, the value is in its range.

        Raises:
            InvalidArgumentError: Unknown register or memory, no register at that address,
                a read-only one, a bad value, the id (:meth:`set_id` changes it), or ``persist``
                with an EEP write; nothing sent.
            OutOfRangeError: The value is out of the register's range; nothing sent.
            StateError: The Robot's port is released; nothing sent.
        """
        check_servo_write(self.sid, register, value, persist, memory)
        await self.servo.write(register, value, persist=persist, memory=memory)

    async def set_id(self, new_sid: int) -> None:
        """Give the servo a new id (EEP and RAM); this handle then speaks to it, and the
        Robot's stream and ``servo(new_sid)`` follow (``renumber``)."""
        if self._renumber is not None:
            await self._renumber(self, new_sid)
            return
        await self.servo.set_id(new_sid)
        self.sid = self.servo.sid

    async def set_zero_offset(self, raw: int) -> None:
        """Set :attr:`zero_offset_raw` (tb_control's ``set_servo_zero_offset``); nothing is
        sent to the servo.

        Raises:
            OutOfRangeError: Outside −512..511.
        """
        self.zero_offset_raw = raw
        if self._on_zero_offset is not None:
            self._on_zero_offset(self.sid, self.zero_offset_raw)

    async def status(self) -> ServoStatus:
        """The servo's status bytes, asked now (STAT).

        Raises:
            StateError: ``check`` refused (the Robot's port is released); nothing sent.
            BusTimeoutError: No answer.
        """
        return await self.servo.status()

    async def clear_errors(self) -> ServoStatus:
        """Clear the servo's latched errors; the torque stays as the fault left it.

        Raises:
            StateError: ``check`` refused (the Robot's port is released); nothing sent.
            BusTimeoutError: No answer.
        """
        # Not a command of the hold-time guard: the torque stays as it was.
        return await self.servo.clear_errors(restore_torque=False)


class WormNeckHandle:
    """The worm-gear neck: position targets, refused outside the configured range.

    The hardware stalls its motor until a power cycle on a target beyond its travel, so
    every target is checked against ``min_raw..max_raw`` (inside −127000…120000) first.
    ``check``, if given, is called before anything is sent and raises to refuse;
    ``feedback`` subscribes to the ``new_neck`` stream for ``move(wait=True)``;
    ``profile`` says where the target register is.
    """

    def __init__(
        self,
        bus: Bus,
        *,
        min_raw: int,
        max_raw: int,
        check: Callable[[], None] | None = None,
        feedback: Callable[[int], Subscription[WormNeckSample]] | None = None,
        profile: WormProfile = WORM_PROFILE,
    ) -> None:
        self._bus = bus
        self._profile = profile
        self._check = check
        self._feedback = feedback
        self.min_raw = min_raw
        self.max_raw = max_raw
        self.sid = 4
        self._position_cmd: int | None = None

    def __repr__(self) -> str:
        return f"<WormNeckHandle range={self.min_raw}..{self.max_raw}>"

    @property
    def position_raw_cmd(self) -> int | None:
        """The last target sent, raw (``None`` before the first move)."""
        return self._position_cmd

    async def move(
        self,
        raw: int | None = None,
        *,
        wait: bool = False,
        timeout_s: float | None = None,
        **unsupported: object,
    ) -> WormNeckSample | None:
        """Drive the neck to ``raw`` (−127000 up … 120000 down, within the configured range).

        With ``wait``, return once the ``new_neck`` stream reads back within
        :data:`WORM_TOLERANCE_RAW` of the target, at rest.

        Args:
            raw: The target, raw.
            wait: Wait until the position reads back at the target.
            timeout_s: With ``wait``, the longest wait from the move, 0..600 s; default
                :data:`WORM_TIMEOUT_S`.

        Returns:
            With ``wait``, the sample that read back at the target; else ``None``.

        Raises:
            InvalidArgumentError: Not an int, an argument only a HerkuleX neck takes, or
                ``timeout_s`` without ``wait``.
            OutOfRangeError: Outside the configured range, or a timeout outside
                0..600 s; nothing sent.
            StateError: ``check`` refused (the Robot's port is released), or ``wait``
                and the ``new_neck`` stream is off; nothing sent.
            PositionError: ``wait``, and the neck stalled (only a power cycle clears it).
            PositionTimeoutError: ``wait``, and not there in time (or no sample came).
        """
        if unsupported:
            raise InvalidArgumentError(
                f"the worm-gear neck takes raw= only, not {', '.join(sorted(unsupported))}"
            )
        position = check_worm_target(raw)  # type: ignore[arg-type]  # checked: None is refused there
        if not self.min_raw <= position <= self.max_raw:
            raise OutOfRangeError("worm neck position", position, self.min_raw, self.max_raw, "raw")
        limit_s = _wait_limit(wait, timeout_s, WORM_TIMEOUT_S)
        if self._check is not None:
            self._check()
        samples = None
        if wait:
            if self._feedback is None:
                raise InvalidArgumentError("the worm-gear neck has no feedback stream to wait on")
            samples = self._feedback(_QUEUE)
        try:
            await self._bus.request(
                set_target(position, self._profile), expect_reply=False, priority=COMMAND_PRIORITY
            )
            self._position_cmd = position
            if samples is None:
                return None
            return await worm_arrival(
                samples,
                target_raw=position,
                sent_s=asyncio.get_running_loop().time(),
                limit_s=limit_s,
            )
        finally:
            if samples is not None:
                samples.close()

    async def rest(self, *, free: bool = True) -> None:
        """Nothing to do: the worm gear holds its position without power."""


# -- waiting for a move ------------------------------------------------------------------------


async def servo_arrival(
    samples: Subscription[ServoSample],
    *,
    sid: int,
    target_raw: int,
    sent_s: float,
    limit_s: float,
) -> ServoSample:
    """The first sample read after ``sent_s`` within :data:`HERKULEX_TOLERANCE_RAW` of
    ``target_raw`` and done moving; at ``sent_s + limit_s``, the last one if it is within
    the tolerance (the MOVING bit stays set until the trajectory's end).

    Raises:
        PositionTimeoutError: Not there by then, or no sample came at all.
    """
    deadline = sent_s + limit_s
    last: ServoSample | None = None
    what = "the HerkuleX neck" if samples.name == "servo_neck" else f"HerkuleX servo {sid}"
    while True:
        sample = await _next_after(samples, sent_s, deadline)
        if sample is None:
            break
        last = sample
        there = abs(sample.position_raw - target_raw) <= HERKULEX_TOLERANCE_RAW
        if there and (not sample.moving or asyncio.get_running_loop().time() >= deadline):
            return sample
    if last is None:
        who = "the neck" if samples.name == "servo_neck" else f"servo {sid}"
        raise PositionTimeoutError(
            f"no {samples.name} sample came within {limit_s:.1f} s: is {who} still answering?",
            sid=sid,
            target_raw=target_raw,
            sample=None,
        )
    if abs(last.position_raw - target_raw) <= HERKULEX_TOLERANCE_RAW:
        return last
    raise PositionTimeoutError(
        f"{what} did not reach {target_raw} within {limit_s:g} s: "
        f"{_read_back(last.stamp_s)} {last.position_raw} raw, torque "
        f"{last.torque.name.lower()}"
        + (f", errors {last.status_error!r}" if last.status_error else ""),
        sid=sid,
        target_raw=target_raw,
        sample=last,
    )


async def worm_arrival(
    samples: Subscription[WormNeckSample], *, target_raw: int, sent_s: float, limit_s: float
) -> WormNeckSample:
    """The first sample read after ``sent_s`` at rest within :data:`WORM_TOLERANCE_RAW` of
    ``target_raw``.

    Raises:
        PositionError: The neck stalled (only a power cycle clears it).
        PositionTimeoutError: Not there within ``limit_s``, or no sample came at all.
    """
    deadline = sent_s + limit_s
    last: WormNeckSample | None = None
    while True:
        sample = await _next_after(samples, sent_s, deadline)
        if sample is None:
            break
        last = sample
        if sample.stalled:
            raise PositionError(
                f"the worm-gear neck stalled at {sample.position_raw}: only a power cycle "
                "clears it",
                sid=4,
                target_raw=target_raw,
                sample=sample,
            )
        if not sample.moving and abs(sample.position_raw - target_raw) <= WORM_TOLERANCE_RAW:
            return sample
    if last is None:
        raise PositionTimeoutError(
            f"no {samples.name} sample came within {limit_s:.1f} s: is the neck still answering?",
            sid=4,
            target_raw=target_raw,
            sample=None,
        )
    raise PositionTimeoutError(
        f"the worm-gear neck did not reach {target_raw} within {limit_s:g} s: "
        f"{_read_back(last.stamp_s)} {last.position_raw}"
        + (" (still moving)" if last.moving else ""),
        sid=4,
        target_raw=target_raw,
        sample=last,
    )


def _wait_limit(wait: bool, timeout_s: float | None, default_s: float) -> float:
    """How long a move waits for its read-back; checks ``wait`` and ``timeout_s``.

    Raises:
        InvalidArgumentError: ``wait`` is not a bool, or ``timeout_s`` is given without it.
        OutOfRangeError: ``timeout_s`` outside 0..600 s.
    """
    if not isinstance(wait, bool):
        raise InvalidArgumentError(f"wait must be True or False, not {wait!r}")
    if timeout_s is None:
        return default_s
    if not wait:
        raise InvalidArgumentError("timeout_s is the wait's: give it with wait=True")
    check_seconds("timeout_s", timeout_s, 0.0, MAX_WAIT_S)
    return float(timeout_s)


async def _next_after(samples: Subscription[_S], after_s: float, deadline: float) -> _S | None:
    """The next sample read at or after ``after_s``, or ``None`` at ``deadline`` or when
    the stream ends."""
    while True:
        try:
            async with asyncio.timeout_at(deadline):
                sample = await anext(samples)
        except (TimeoutError, StopAsyncIteration):
            return None
        if sample.stamp_s >= after_s:
            return sample


def _read_back(stamp_s: float) -> str:
    """How a failure names the last sample: current, or stale (the device went silent)."""
    age = asyncio.get_running_loop().time() - stamp_s
    if age <= _SILENT_S:
        return "it reads back"
    return f"it stopped answering {age:.1f} s ago (no sample since), when it read back"
