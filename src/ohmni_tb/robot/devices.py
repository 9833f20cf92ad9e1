"""Handles for the Robot's neck and external servos: checked commands on the bus.

Commands go through the Robot's bus at :data:`COMMAND_PRIORITY`, the feedback reads'
priority: below the control slot, so the control tick never waits for a move, and in
order of arrival with the feedback reads, so a move waits at most for the reads already
due (a few ms) and a stream of commands cannot starve the feedback.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable

from ohmni_tb.bus import Bus
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import TorqueControl
from ohmni_tb.herkulex.servo import Servo
from ohmni_tb.herkulex.units import check_zero_offset_raw
from ohmni_tb.protocol import Packet
from ohmni_tb.protocol.worm_neck import check_worm_target, set_target

__all__ = ["COMMAND_PRIORITY", "ServoHandle", "WormNeckHandle"]

#: Bus priority of commands: the feedback reads' (the control slot is 10).
COMMAND_PRIORITY = 5
#: The playtime of a rest move, seconds.
REST_PLAYTIME_S = 1.0

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
    ) -> None:
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
        # The torque mode this handle last set (None: none yet). The servo's cached
        # status can predate it (writes get no reply under ACK policy 1), so a move
        # after free() would otherwise skip the torque and be refused.
        self._torque_set: TorqueControl | None = None

    def __repr__(self) -> str:
        return f"<ServoHandle sid={self.sid} range={self.min_raw}..{self.max_raw}>"

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
    ) -> None:
        """Turn torque on if needed and move to ``raw`` counts or ``rad`` over ``playtime_s``.

        Raises:
            InvalidArgumentError: Neither or both of ``raw`` and ``rad``, or not numbers.
            OutOfRangeError: Outside ``min_raw..max_raw`` or a playtime outside
                0..2.84 s; nothing sent.
            DeviceStatusError: The servo has a latched fault.
            StateError: ``check`` refused (the Robot's port is released); nothing sent.
        """
        target = self.servo.target(raw, angle_rad=rad)  # checks before anything is sent
        if isinstance(playtime_s, bool) or not isinstance(playtime_s, int | float):
            raise InvalidArgumentError(f"playtime_s must be a number, not {playtime_s!r}")
        if not math.isfinite(playtime_s) or not 0.0 <= playtime_s <= 2.84:
            raise OutOfRangeError("playtime_s", playtime_s, 0.0, 2.84, "s")
        self._touched()
        status = self.servo.last_status
        if (
            status is None
            or not status.torque_on
            or self._torque_set not in (None, TorqueControl.ON)
        ):
            await self.torque(TorqueControl.ON)
        await self.servo.move_to(target.value, playtime_s=playtime_s)

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
        """Every EEP and RAM register's value."""
        return await self.servo.info()

    async def write(self, register: str, value: int, *, persist: bool = False) -> None:
        """Write a register (to EEP as well with ``persist``); checked before sending."""
        await self.servo.write(register, value, persist=persist)

    async def set_id(self, new_sid: int) -> None:
        """Give the servo a new id (in EEP); this handle then speaks to it."""
        await self.servo.set_id(new_sid)
        self.sid = self.servo.sid


class WormNeckHandle:
    """The worm-gear neck: position targets, refused outside the configured range.

    The hardware stalls its motor until a power cycle on a target beyond its travel, so
    every target is checked against ``min_raw..max_raw`` (inside −127000…120000) first.
    ``check``, if given, is called before anything is sent and raises to refuse.
    """

    def __init__(
        self, bus: Bus, *, min_raw: int, max_raw: int, check: Callable[[], None] | None = None
    ) -> None:
        self._bus = bus
        self._check = check
        self.min_raw = min_raw
        self.max_raw = max_raw
        self.sid = 4

    def __repr__(self) -> str:
        return f"<WormNeckHandle range={self.min_raw}..{self.max_raw}>"

    async def move(self, raw: int | None = None, **unsupported: object) -> None:
        """Drive the neck to ``raw`` (−127000 up … 120000 down, within the configured range).

        Raises:
            InvalidArgumentError: Not an int, or an argument only a HerkuleX neck takes.
            OutOfRangeError: Outside the configured range; nothing sent.
            StateError: ``check`` refused (the Robot's port is released); nothing sent.
        """
        if unsupported:
            raise InvalidArgumentError(
                f"the worm-gear neck takes raw= only, not {', '.join(sorted(unsupported))}"
            )
        position = check_worm_target(raw)  # type: ignore[arg-type]  # checked: None is refused there
        if not self.min_raw <= position <= self.max_raw:
            raise OutOfRangeError("worm neck position", position, self.min_raw, self.max_raw, "raw")
        if self._check is not None:
            self._check()
        await self._bus.request(set_target(position), expect_reply=False, priority=COMMAND_PRIORITY)

    async def rest(self, *, free: bool = True) -> None:
        """Nothing to do: the worm gear holds its position without power."""
