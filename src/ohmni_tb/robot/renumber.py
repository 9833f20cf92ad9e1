"""Changing a device's bus id while the Robot runs, and the Robot following it.

A HerkuleX servo given a new id (:meth:`ServoHandle.set_id
<ohmni_tb.robot.devices.ServoHandle.set_id>`) keeps its handle, its stream and its place
in the settings: the stream's reads pause, the id goes out (EEP, then RAM), and the reads
go on from the new id with the same rate and phase, so no cycle is missed. A new id that
another device the Robot knows answers to is refused before anything is sent.

A drive board's id (tb_control's ``reset_servo_id`` on sid 0 or 1) is changed only with
an explicit confirmation: the Robot drives the wheels by ids 0 and 1, so a board given
another id no longer takes the wheel command. The wheels are stopped first.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from ohmni_tb.errors import InvalidArgumentError, StateError
from ohmni_tb.protocol.devices import DeviceId, device_name
from ohmni_tb.protocol.drive import set_board_id, wheel_command
from ohmni_tb.robot.checks import check_board_id, check_servo_id
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle
from ohmni_tb.robot.feedback import Feedback
from ohmni_tb.robot.state import RobotState
from ohmni_tb.safety import stop_wheels

__all__ = ["Renumbering"]

_log = logging.getLogger(__name__)
_DRIVES = (int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE))
_NAMES = {
    int(DeviceId.LEFT_DRIVE): "the left drive board",
    int(DeviceId.RIGHT_DRIVE): "the right drive board",
    int(DeviceId.HERKULEX_NECK): "the HerkuleX neck",
    int(DeviceId.WORM_NECK): "the worm-gear neck",
    int(DeviceId.CORE): "the core board",
}


class Renumbering:
    """Id changes of the Robot's servos and drive boards (module docstring).

    Args:
        state: The Robot's state.
        feedback: The schedule's streams (a servo's stream moves to its new id).
        reconfigure: Replaces the Robot's settings with the given changes.
    """

    def __init__(
        self, state: RobotState, feedback: Feedback, reconfigure: Callable[..., None]
    ) -> None:
        self._state = state
        self._feedback = feedback
        self._reconfigure = reconfigure
        #: Old id → new id of the servos renumbered, for ``servo(old)``'s error.
        self.moved: dict[int, int] = {}
        #: The drive boards given an id other than 0 and 1: their id now → the one they had.
        self.boards: dict[int, int] = {}

    def owner(self, sid: int) -> str | None:
        """Which known device answers to ``sid`` (its name), or ``None``."""
        state = self._state
        config = state.config
        known = set(state.present) | set(state.expected) | set(state.servos)
        known |= {int(d) for d in DeviceId} | set(config.ext_servo_ids) | {config.neck_id}
        if sid not in known:
            return None
        if sid in state.servos:
            return f"HerkuleX servo {sid}"
        return f"{_NAMES.get(sid, device_name(sid))} (id {sid})"

    async def servo(self, handle: ServoHandle, new_sid: int) -> None:
        """Give ``handle``'s servo the id ``new_sid``, the Robot following.

        Raises:
            OutOfRangeError: ``new_sid`` is not 0..253; nothing sent.
            StateError: Another known device has that id, or the port is released;
                nothing sent.
        """
        state = self._state
        check_servo_id(new_sid)
        old = handle.sid
        if new_sid == old:
            return
        state.check_port()
        owner = self.owner(new_sid)
        if owner is not None:
            raise StateError(
                f"servo {old} cannot take id {new_sid}: {owner} answers to it; nothing was sent"
            )
        watch = state.servos.get(old)
        periodic = None if watch is None else state.periodic.get(watch.stream)
        running = periodic is not None and periodic.running
        if periodic is not None:
            periodic.stop()  # no read of the old id after the change: no missed cycle
        try:
            await handle.servo.set_id(new_sid)
        except BaseException:
            if periodic is not None and running:
                periodic.start(state.periodic["wheel_encoder"].next_due_s)
            raise
        handle.sid = new_sid
        bus = state.bus
        bus.set_ack_policy(new_sid, bus.ack_policy(old))
        for ids in (state.present, state.expected):
            if old in ids:
                ids.discard(old)
                ids.add(new_sid)
        self.moved[old] = new_sid
        self.moved.pop(new_sid, None)
        config = state.config
        if old == config.neck_id:
            self._reconfigure(neck_id=new_sid)
        elif old in config.ext_servo_ids:
            ext = tuple(new_sid if sid == old else sid for sid in config.ext_servo_ids)
            self._reconfigure(ext_servo_ids=ext)
        if watch is not None:
            state.servos[new_sid] = state.servos.pop(old)
            if periodic is not None:
                self._feedback.renumber_servo(new_sid, watch.stream, periodic, running)
        state.publish(f"servo {old} is now servo {new_sid}")

    async def board(
        self, sid: int, new_sid: int, *, confirm: bool, stop: Callable[[], Any]
    ) -> None:
        """Give drive board ``sid`` (0, 1, or the id this Robot gave one) the id
        ``new_sid`` (``Robot.reset_board_id``).

        Raises:
            OutOfRangeError: An id is not 0..253; nothing sent.
            InvalidArgumentError: ``sid`` is not a drive board's, or no ``confirm``;
                nothing sent.
            StateError: Another known device has ``new_sid``, the board did not answer,
                or the port is released; nothing sent.
            StopNotConfirmedError: The wheels were not confirmed stopped; nothing sent.
        """
        state = self._state
        check_board_id(sid, new_sid, confirm)
        boards = self.boards
        if sid not in _DRIVES and sid not in boards:
            raise InvalidArgumentError(
                f"sid={sid!r} is not a drive board: 0 (left) or 1 (right); a servo's id "
                "is changed with robot.servo(sid).set_id()"
            )
        if new_sid == sid:
            return
        state.check_port()
        if sid in _DRIVES and sid not in state.present:
            raise StateError(f"drive board {sid} does not answer; nothing was sent")
        owner = self.owner(new_sid)
        if new_sid in boards or (
            owner is not None and not (new_sid in _DRIVES and new_sid not in state.present)
        ):
            raise StateError(
                f"drive board {sid} cannot take id {new_sid}: "
                f"{owner or f'drive board {boards[new_sid]}'} answers to it; nothing was sent"
            )
        stop()
        if state.present.issuperset(_DRIVES):
            await stop_wheels(
                state.bus, timeout_s=state.config.stop_timeout_s, profile=state.profile.drive
            )
        else:
            # A board away at another id takes no wheel command (it was stopped then).
            await state.bus.send_now(wheel_command(0, 0, state.profile.drive))
        for packet in set_board_id(sid, new_sid, state.profile.drive):
            await state.bus.request(packet, expect_reply=False, priority=COMMAND_PRIORITY)
        side = boards.pop(sid, sid)
        if sid in _DRIVES:
            state.present.discard(sid)
            state.faults.add(f"drive_absent:{sid}")
        if new_sid in _DRIVES:
            state.present.add(new_sid)
            state.faults.discard(f"drive_absent:{new_sid}")
        else:
            boards[new_sid] = side
        _log.warning("drive board %d now answers to id %d", sid, new_sid)
        state.publish(f"drive board {sid} now answers to id {new_sid}")
