"""Which devices answer: asked once at open, and the absent ones again every few seconds.

Each device is asked with a read it answers (the wheel count, the core board's status,
a HerkuleX STAT, the worm neck's feedback), with retries, at the lowest bus priority. A
device found late (a neck powered up after the Robot opened, a loose cable) gets its
handle and its stream then (:meth:`Discovery.reprobe`).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

from ohmni_tb.bus import ReplyPacket
from ohmni_tb.errors import BusTimeoutError, MalformedReplyError, OhmniError, StateError
from ohmni_tb.herkulex import stat
from ohmni_tb.protocol import Memory, Packet, ReadReply
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import read_count, read_firmware_tag
from ohmni_tb.protocol.worm_neck import read_feedback
from ohmni_tb.robot.devices import ServoHandle, WormNeckHandle
from ohmni_tb.robot.state import RobotState, ServoWatch
from ohmni_tb.robot.streams import Subscription

__all__ = ["DISCOVERY_RETRIES", "EXT_STREAMS", "PROBE_PRIORITY", "REPROBE_S", "Discovery"]

#: Bus priority of the probes: below every command and feedback read.
PROBE_PRIORITY = 0
#: Extra attempts for each device at open (a lossy line should not hide a board).
DISCOVERY_RETRIES = 3
#: Absent devices are asked again this often.
REPROBE_S = 5.0
#: The stream names of the external servos, in the order of ``ext_servo_ids``.
EXT_STREAMS = ("servo_ext1", "servo_ext2")
_DRIVES = (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE)


class Discovery:
    """Finds the Robot's devices and keeps looking for the absent ones.

    Args:
        state: The Robot's state: ``present``, ``expected``, the neck and the servos.
        found: Called with a device id found after open, to start its stream.
    """

    def __init__(self, state: RobotState, found: Callable[[int], None]) -> None:
        self._state = state
        self._found = found
        self._timer: asyncio.TimerHandle | None = None
        #: Changes a servo's id, the Robot following (the façade's; see ServoHandle).
        self.renumber: Callable[[ServoHandle, int], Awaitable[None]] | None = None
        #: Called with a servo's id and its new zero offset (the façade's).
        self.zero_offset: Callable[[int, int], None] | None = None
        #: Old id → new id of the servos given another id.
        self.moved: dict[int, int] = {}

    async def discover(self) -> None:
        """Ask every device the settings name (at open)."""
        state = self._state
        config = state.config
        for sid in _DRIVES:
            state.expected.add(int(sid))
            if await self._answers(read_count(sid, self._state.profile.drive)) is not None:
                state.present.add(int(sid))
        if config.core_hz > 0:
            state.expected.add(int(DeviceId.CORE))
            if await self._answers(read_status(self._state.profile.core)) is not None:
                state.present.add(int(DeviceId.CORE))
        kind = config.neck
        if kind in ("auto", "herkulex") and await self._answers(stat(config.neck_id)):
            state.neck_kind = "herkulex"
            state.present.add(config.neck_id)
        elif kind in ("auto", "worm") and await self._answers(
            read_feedback(self._state.profile.worm)
        ):
            state.neck_kind = "worm"
            state.present.add(int(DeviceId.WORM_NECK))
        else:
            # Not found: looked for again slowly (a neck powered up late, a loose cable).
            if kind in ("auto", "herkulex"):
                state.expected.add(config.neck_id)
            if kind in ("auto", "worm"):
                state.expected.add(int(DeviceId.WORM_NECK))
        if state.neck_kind == "herkulex":
            state.neck = self._servo_handle(config.neck_id, "servo_neck", neck=True)
        elif state.neck_kind == "worm":
            state.neck = self._worm_handle()
        for ext_id, stream in zip(config.ext_servo_ids, EXT_STREAMS, strict=False):
            state.expected.add(ext_id)
            if await self._answers(stat(ext_id)):
                state.present.add(ext_id)
                self._servo_handle(ext_id, stream, neck=False)
        for sid in _DRIVES:
            if int(sid) not in state.present:
                state.faults.add(f"drive_absent:{int(sid)}")
        await self._read_tags()

    async def _read_tags(self) -> None:
        """Each board's firmware tag, while the line is still idle (at open): a tag's read
        books the line for the longest reply it could get, which the schedule's control
        slot might otherwise wait behind."""
        state = self._state
        tag_addr = state.profile.drive.tag_addr
        for sid in (*_DRIVES, DeviceId.CORE, DeviceId.WORM_NECK):
            if int(sid) in state.present:
                reply = await self._answers(read_firmware_tag(sid, tag_addr))
                state.firmware[int(sid)] = _tag(reply)

    def neck(self) -> ServoHandle | WormNeckHandle:
        """The neck's handle (``Robot.neck``).

        Raises:
            StateError: No neck answered.
        """
        state = self._state
        if state.neck is None:
            raise StateError(
                f"no neck answered (looked for {state.config.neck}: HerkuleX at "
                f"{state.config.neck_id}, worm gear at 4)"
            )
        return state.neck

    def servo(self, sid: int) -> ServoHandle:
        """HerkuleX servo ``sid``'s handle (``Robot.servo``).

        Raises:
            StateError: No such servo answered.
        """
        servos = self._state.servos
        watch = servos.get(sid)
        if watch is None:
            found = ", ".join(map(str, sorted(servos))) or "none"
            moved = self.moved.get(sid) if isinstance(sid, int) else None
            if moved is not None and moved in servos:
                raise StateError(
                    f"no HerkuleX servo {sid!r} on this robot: it was given id {moved} "
                    f"(robot.servo({moved})); found: {found}"
                )
            raise StateError(f"no HerkuleX servo {sid!r} on this robot (found: {found})")
        return watch.handle

    async def info(self) -> dict[str, Any]:
        """Firmware tags, servo models and the neck kind (``Robot.info``)."""
        state = self._state
        tags: dict[str, str | None] = {}
        for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE):
            try:
                reply = await state.bus.read(sid, 0xF1, 0, Memory.EEP)
                tags[sid.name.lower()] = reply.data.decode("ascii", errors="replace")
                state.firmware[int(sid)] = tags[sid.name.lower()] or None
            except OhmniError:
                tags[sid.name.lower()] = None
        models: dict[int, str | None] = {}
        for servo_id, watch in state.servos.items():
            try:
                models[servo_id] = (await watch.handle.servo.model()).name
            except OhmniError:
                models[servo_id] = None
        return {
            "firmware": tags,
            "servos": models,
            "neck": state.neck_kind,
            "present": sorted(state.present),
            "absent": sorted(state.expected - state.present),
        }

    def arm(self) -> None:
        """Ask the absent devices again in :data:`REPROBE_S` (unless that is set already)."""
        state = self._state
        if self._timer is None and not state.closed and state.expected - state.present:
            self._timer = state.loop.call_later(REPROBE_S, self._reprobe)

    def disarm(self) -> None:
        """Stop asking (closing, or the port is released)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    async def _answers(self, packet: Packet) -> ReplyPacket | None:
        try:
            return await self._state.bus.request(
                packet, expect_reply=True, retries=DISCOVERY_RETRIES, priority=PROBE_PRIORITY
            )
        except (BusTimeoutError, MalformedReplyError):
            return None

    def _servo_handle(self, sid: int, stream: str, *, neck: bool) -> ServoHandle:
        state = self._state
        config = state.config
        handle = ServoHandle(
            state.bus,
            sid,
            min_raw=config.neck_min_raw if neck else 21,
            max_raw=config.neck_max_raw if neck else 1002,
            rest_raw=config.neck_rest_raw if neck else 512,
            zero_offset_raw=config.neck_zero_offset_raw if neck else 0,
            on_command=self._servo_commanded,
            check=state.check_port,
            feedback=lambda maxlen: self._feedback_subscription(stream, maxlen),
            renumber=self.renumber,
            on_zero_offset=self.zero_offset,
        )
        # The hold time counts from when this Robot found the servo: a neck some earlier
        # process left holding is rested neck_hold_s from now, not at the first sample
        # (which would move it the moment any Robot opens, a read-only one included).
        state.servos[sid] = ServoWatch(handle, stream, last_command_s=state.loop.time())
        return handle

    def _worm_handle(self) -> WormNeckHandle:
        state = self._state
        return WormNeckHandle(
            state.bus,
            min_raw=state.config.worm_min_raw,
            max_raw=state.config.worm_max_raw,
            check=state.check_port,
            feedback=lambda maxlen: self._feedback_subscription("new_neck", maxlen),
            profile=state.profile.worm,
        )

    def _feedback_subscription(self, stream: str, maxlen: int) -> Subscription[Any]:
        """A device's feedback stream, for a move that waits for its read-back.

        Raises:
            StateError: The stream is off (its rate setting is 0, or enable_stream).
        """
        topic = self._state.topic(stream)
        if not topic.enabled:
            raise StateError(
                f"a move waits on the {stream} stream, which is off: "
                f"robot.enable_stream({stream!r}) first (or wait=False); nothing was sent"
            )
        return topic.subscribe(maxlen)

    def _servo_commanded(self, sid: int) -> None:
        watch = self._state.servos.get(sid)
        if watch is not None:
            watch.last_command_s = self._state.loop.time()

    def _reprobe(self) -> None:
        self._timer = None
        if self._state.closed:
            return
        self._state.spawn(self._reprobe_once(), "reprobe")

    async def _reprobe_once(self) -> None:
        state = self._state
        config = state.config
        for sid in sorted(state.expected - state.present):
            if not state.bus.connected:
                break
            if sid in _DRIVES:
                packet = read_count(sid, self._state.profile.drive)
            elif sid == DeviceId.CORE:
                packet = read_status(self._state.profile.core)
            elif sid == DeviceId.WORM_NECK:
                packet = read_feedback(self._state.profile.worm)
            else:
                packet = stat(sid)
            if await self._answers(packet) is None:
                continue
            state.present.add(sid)
            state.faults.discard(f"drive_absent:{sid}")
            if sid in config.ext_servo_ids:
                index = config.ext_servo_ids.index(sid)
                if index < len(EXT_STREAMS):
                    self._servo_handle(sid, EXT_STREAMS[index], neck=False)
                    self._found(sid)
            elif sid == config.neck_id and state.neck_kind == "none":
                state.neck_kind = "herkulex"
                state.neck = self._servo_handle(sid, "servo_neck", neck=True)
                self._found(sid)
                state.expected.discard(int(DeviceId.WORM_NECK))
            elif sid == DeviceId.WORM_NECK and state.neck_kind == "none":
                state.neck_kind = "worm"
                state.neck = self._worm_handle()
                self._found(sid)
                state.expected.discard(config.neck_id)
            elif sid == DeviceId.CORE:
                self._found(sid)
            state.publish(f"device {sid} answers")
        self.arm()


def _tag(reply: ReplyPacket | None) -> str | None:
    """The firmware tag in a tag read's reply (``None``: no reply, or an empty tag)."""
    if reply is None:
        return None
    try:
        return ReadReply.parse(reply).data.decode("ascii", errors="replace") or None
    except OhmniError:
        return None
