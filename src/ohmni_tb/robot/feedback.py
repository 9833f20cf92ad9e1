"""The Robot's schedule and its streams: which reads go when, and their replies as samples.

The control slot (:mod:`ohmni_tb.robot.control_loop`) leads the schedule at top priority;
each HerkuleX servo's feedback block, the worm-gear neck's feedback and the core board's
status are polled at their own rates on absolute deadlines, with phases that keep them
between control slots. A read's reply is decoded by its device's codec
(:func:`~ohmni_tb.herkulex.registers.decode_feedback`,
:func:`~ohmni_tb.protocol.worm_neck.parse_feedback`,
:func:`~ohmni_tb.protocol.core.parse_status`) into a sample; one that is missing or does
not decode is a missed cycle, counted. ``robot_state`` is published on every change and
at ``state_hz``.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import Callable
from typing import Any, Literal, TypeVar

from ohmni_tb.errors import InvalidArgumentError, OhmniError, StateError
from ohmni_tb.herkulex.registers import FEEDBACK_ADDR, FEEDBACK_SIZE, decode_feedback
from ohmni_tb.herkulex.units import angle_rad_from_raw, voltage_v_from_raw
from ohmni_tb.protocol import Packet, ReadReply, read_request
from ohmni_tb.protocol.core import cells_plausible, parse_status, read_status
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.worm_neck import parse_feedback, read_feedback
from ohmni_tb.robot.control_loop import CONTROL_SLACK, ControlLoop
from ohmni_tb.robot.devices import WormNeckHandle
from ohmni_tb.robot.discovery import EXT_STREAMS
from ohmni_tb.robot.guards import Guards
from ohmni_tb.robot.samples import (
    STREAMS,
    Link,
    ServoSample,
    TbcoreStatusSample,
    WormNeckSample,
)
from ohmni_tb.robot.schedule import CycleResult, Periodic
from ohmni_tb.robot.state import RobotState
from ohmni_tb.robot.stats import BusFigures, RobotStats
from ohmni_tb.robot.streams import Topic
from ohmni_tb.robot.wheels import WheelCounts

__all__ = ["CORE_PHASE_S", "FEEDBACK_PRIORITY", "SERVO_PHASE_S", "Feedback"]

_log = logging.getLogger(__name__)
#: What a polled stream's parser makes of a read reply.
_P = TypeVar("_P")

#: Bus priority of the feedback reads: the commands' (devices.COMMAND_PRIORITY), so they
#: go in the order they fall due: a near-full line slows them all a little instead of
#: starving the least urgent.
FEEDBACK_PRIORITY = 5
#: Phase of the first servo read and of the core read after the control slot, seconds:
#: between control slots, so the 50 Hz and 30 Hz grids do not pile up.
SERVO_PHASE_S = 0.010
CORE_PHASE_S = 0.013
#: Battery reads in a row that are not a LiFePO4 pack before ``battery_implausible``
#: (one bad read is a glitch; a wrong profile reads wrong every time).
_IMPLAUSIBLE_READS = 5


class Feedback:
    """The schedule's feedback streams and ``robot_state`` (module docstring)."""

    def __init__(
        self, state: RobotState, control: ControlLoop, counts: WheelCounts, guards: Guards
    ) -> None:
        self._state = state
        self._control = control
        self._counts = counts
        self._guards = guards
        self._state_timer: asyncio.TimerHandle | None = None
        # The profile's decoders of the worm neck's and the core board's replies.
        profile = state.profile
        self._parse_worm = functools.partial(parse_feedback, profile=profile.worm)
        self._parse_core = functools.partial(parse_status, profile=profile.core)
        #: Battery reads in a row that were not a pack.
        self._implausible = 0

    # -- the schedule --------------------------------------------------------------------

    def build(self) -> None:
        """The schedule for the devices found at open (not started)."""
        state = self._state
        config = state.config
        topics = state.topics
        state.periodic["wheel_encoder"] = self._control.periodic()
        for name, spec in STREAMS.items():
            if spec.source != "polled":  # the control tick's and the state's own rates
                topics[name].requested_hz = getattr(config, spec.rate_setting)
        for index, (sid, watch) in enumerate(state.servos.items()):
            self._add_servo_stream(sid, watch.stream, index)
        if state.neck_kind == "worm":
            self._add_worm_stream()
        if int(DeviceId.CORE) in state.present:
            self._add_core_stream()
        for name, spec in STREAMS.items():
            if spec.source == "polled" and name not in state.periodic:
                topics[name].enabled = False  # no device: no reads

    def start(self) -> None:
        """Start the schedule and the ``robot_state`` timer."""
        state = self._state
        t0 = state.loop.time() + 0.005
        for periodic in state.periodic.values():
            periodic.start(t0)
        self._state_timer = state.loop.call_later(1.0 / state.config.state_hz, self._state_tick)

    def restart(self) -> None:
        """Start the control slot and the streams that are on, on a fresh phase (the
        link is back)."""
        state = self._state
        t0 = state.loop.time() + 0.005
        for name, periodic in state.periodic.items():
            if name == "wheel_encoder" or state.topics[name].enabled:
                periodic.start(t0)

    def stop(self) -> None:
        """Stop every periodic read (the timer of ``robot_state`` keeps running)."""
        for periodic in self._state.periodic.values():
            periodic.stop()

    def close(self) -> None:
        """Stop the schedule and the ``robot_state`` timer."""
        self.stop()
        if self._state_timer is not None:
            self._state_timer.cancel()

    def found(self, sid: int) -> None:
        """Start the stream of device ``sid``, found after open."""
        state = self._state
        watch = state.servos.get(sid)
        if watch is not None:
            index = 0 if watch.stream == "servo_neck" else EXT_STREAMS.index(watch.stream) + 1
            self._add_servo_stream(sid, watch.stream, index)
        elif sid == DeviceId.CORE:
            if "tbcore_status" not in state.periodic:
                self._add_core_stream()
        elif sid == DeviceId.WORM_NECK:
            self._add_worm_stream()

    def enable(self, name: str, topic: Topic[Any], enabled: bool) -> None:
        """Turn stream ``name`` on or off (``Robot.enable_stream``, checked there).

        Raises:
            StateError: The stream's device is absent (it cannot be turned on).
        """
        state = self._state
        periodic = state.periodic.get(name)
        spec = STREAMS[name]
        if spec.source != "polled":
            if enabled and topic.requested_hz <= 0:
                raise StateError(
                    f"stream {name!r} is off by its setting {spec.rate_setting}=0: open the "
                    f"robot with {spec.rate_setting} above 0 to have it"
                )
            topic.enabled = enabled  # the control slot and the state keep running
            return
        if periodic is None:
            if enabled:
                raise StateError(f"stream {name!r} has no device on this robot")
            topic.enabled = False
            return
        topic.enabled = enabled
        if enabled and not periodic.running and state.link is Link.CONNECTED:
            periodic.start(state.periodic["wheel_encoder"].next_due_s)
        elif not enabled:
            periodic.stop()

    def rows(self) -> list[tuple[str, float, float, float]]:
        """The schedule: per stream its rate (Hz), phase (s) and line time per cycle (s)."""
        state = self._state
        cost_s = state.bus.cost_s
        rows = []
        for name, periodic in state.periodic.items():
            if name != "wheel_encoder" and not state.topics[name].enabled:
                continue
            rows.append(
                (
                    name,
                    1.0 / periodic.period_s,
                    periodic.phase_s,
                    sum(cost_s(p) for p in state.packets[name]),
                )
            )
        return rows

    def share(self) -> float:
        """The enabled streams' share of the line by the cost model."""
        return sum(hz * line_time_s for _, hz, _, line_time_s in self.rows())

    def stats(self, opened_at_s: float) -> RobotStats:
        """Every stream's figures and the bus's (``Robot.stats``)."""
        state = self._state
        now = state.loop.time()
        bus = state.bus.stats
        return RobotStats(
            streams={name: topic.stats(now) for name, topic in state.topics.items()},
            bus=BusFigures(
                wire_utilisation=bus.wire_utilisation,
                budget_share=self.share(),
                transactions_per_s=bus.transactions_per_s,
                timeouts=sum(d.timeouts for d in bus.devices.values()),
                rejected_samples=self._counts.rejected,
                clamped_commands=state.clamped,
                deadline_misses=bus.deadline_misses,
                link_losses=bus.link_losses,
                reconnects=bus.reconnects,
            ),
            uptime_s=now - opened_at_s,
        )

    # -- the feedback streams --------------------------------------------------------------

    def _add_servo_stream(self, sid: int, stream: str, index: int) -> None:
        hz = self._state.config.servo_hz
        self._add(
            stream,
            hz,
            # Three servos spread over their period, between control slots.
            phase_s=SERVO_PHASE_S + index / hz / 3 if hz > 0 else 0.0,
            packets=[read_request(sid, FEEDBACK_ADDR, FEEDBACK_SIZE)],
            handle=lambda result: self._servo_result(sid, result),
        )

    def renumber_servo(self, sid: int, stream: str, old: Periodic, running: bool) -> None:
        """Read servo stream ``stream`` from id ``sid`` from now on, at the rate and phase
        of its old reads ``old`` (stopped), running again if it was."""
        topic = self._state.topics[stream]
        enabled = topic.enabled
        self._add(
            stream,
            1.0 / old.period_s,
            phase_s=old.phase_s,
            packets=[read_request(sid, FEEDBACK_ADDR, FEEDBACK_SIZE)],
            handle=lambda result: self._servo_result(sid, result),
        )
        topic.enabled = enabled
        new = self._state.periodic[stream]
        if not running:
            new.stop()
        elif not new.running:
            new.start(self._state.periodic["wheel_encoder"].next_due_s)

    def _add_worm_stream(self) -> None:
        self._add(
            "new_neck",
            self._state.config.new_neck_hz,
            phase_s=SERVO_PHASE_S,
            packets=[read_feedback(self._state.profile.worm)],
            handle=self._worm_result,
        )

    def _add_core_stream(self) -> None:
        self._add(
            "tbcore_status",
            self._state.config.core_hz,
            phase_s=CORE_PHASE_S,
            packets=[read_status(self._state.profile.core)],
            handle=self._core_result,
        )

    def _add(
        self,
        stream: str,
        hz: float,
        *,
        phase_s: float,
        packets: list[Packet],
        handle: Callable[[CycleResult], None],
    ) -> None:
        """Poll ``packets`` at ``hz`` as ``stream`` (0 Hz: not at all); start it at once
        if the schedule runs."""
        if hz <= 0:
            return
        state = self._state
        topic = state.topics[stream]
        topic.requested_hz = hz
        topic.enabled = True
        state.packets[stream] = packets
        cycle = tuple(packets)  # the same tuple each cycle: the bus checks it once
        periodic = Periodic(
            state.bus,
            stream,
            hz,
            phase_s=phase_s,
            priority=FEEDBACK_PRIORITY,
            slack_s=1.0 / hz,
            build=lambda due: cycle,
            handle=handle,
            fail=self._failed(topic),
            skipped=self._counter(topic, "skipped"),
            ahead=True,  # the same reads every cycle: queued on the bus ahead of time
        )
        state.periodic[stream] = periodic
        control = state.periodic.get("wheel_encoder")
        if control is not None and control.running:
            periodic.start(control.next_due_s)

    @staticmethod
    def _counter(topic: Topic[Any], what: Literal["skipped", "missed"]) -> Callable[[int], None]:
        def count(n: int) -> None:
            setattr(topic, what, getattr(topic, what) + n)

        return count

    @staticmethod
    def _failed(topic: Topic[Any]) -> Callable[[float, BaseException], None]:
        def failed(due: float, exc: BaseException) -> None:
            topic.missed += 1
            if not isinstance(exc, OhmniError):
                _log.error("%s: cycle failed", topic.name, exc_info=exc)

        return failed

    @staticmethod
    def _parsed(
        topic: Topic[Any], result: CycleResult, parse: Callable[[ReadReply], _P]
    ) -> _P | None:
        """A polled stream's cycle: note its lateness; the reply parsed, or ``None`` when
        there was none or it did not parse (a missed cycle, counted)."""
        topic.note_lateness(result.started_s - result.due_s)
        reply = result.replies[0]
        if reply is None:
            topic.missed += 1
            return None
        try:
            return parse(ReadReply.parse(reply))
        except OhmniError:
            topic.missed += 1
            return None

    def _servo_result(self, sid: int, result: CycleResult) -> None:
        state = self._state
        watch = state.servos.get(sid)
        if watch is None:
            return
        topic = state.topics[watch.stream]
        block = self._parsed(topic, result, lambda read: decode_feedback(read.data))
        if block is None:
            return
        position = block.position_raw
        handle = watch.handle
        zero_offset = handle.zero_offset_raw
        position_cmd = handle.position_raw_cmd
        sample = ServoSample(
            stamp_s=result.started_s,
            sid=sid,
            position_raw=position,
            angle_rad=angle_rad_from_raw(position, zero_offset_raw=zero_offset),
            temperature_raw=block.temperature_raw,
            voltage_v=voltage_v_from_raw(block.voltage_raw),
            torque=block.torque,
            status_error=block.status_error,
            status_detail=block.status_detail,
            position_raw_cmd=position_cmd,
            pos_rad_cmd=None
            if position_cmd is None
            else angle_rad_from_raw(position_cmd, zero_offset_raw=zero_offset),
            torque_cmd=handle.torque_cmd,
        )
        watch.sample = sample
        topic.publish(sample, result.started_s)
        self._guards.check(watch, sample)

    def _worm_result(self, result: CycleResult) -> None:
        state = self._state
        topic = state.topics["new_neck"]
        feedback = self._parsed(topic, result, self._parse_worm)
        if feedback is None:
            return
        neck = state.neck
        sample = WormNeckSample(
            result.started_s,
            feedback.position,
            feedback.flags,
            neck.position_raw_cmd if isinstance(neck, WormNeckHandle) else None,
        )
        topic.publish(sample, result.started_s)
        fault = "neck_stalled"
        if sample.stalled and fault not in state.faults:
            state.faults.add(fault)
            state.publish("the worm-gear neck stalled: power-cycle the robot")

    def _core_result(self, result: CycleResult) -> None:
        topic = self._state.topics["tbcore_status"]
        status = self._parsed(topic, result, self._parse_core)
        if status is None:
            return
        self._judge_cells(status.cell_mv)
        sample = TbcoreStatusSample(
            stamp_s=result.started_s,
            cell_v=tuple(mv / 1000 for mv in status.cell_mv),
            pack_v=status.pack_mv / 1000,
            current_a=status.charging_current_ma / 1000,
            docked=status.docked,
            charging=status.charging,
            percent=status.percent,
            fet_status=status.fet_status,
            status=status.status,
        )
        topic.publish(sample, result.started_s)

    def _judge_cells(self, cell_mv: tuple[int, ...]) -> None:
        """A battery block that does not read as a pack, :data:`_IMPLAUSIBLE_READS` reads
        in a row, is the ``battery_implausible`` fault (the profile's battery settings are
        likely wrong); it clears on the first plausible read."""
        state = self._state
        fault = "battery_implausible"
        if cells_plausible(cell_mv):
            self._implausible = 0
            if fault in state.faults:
                state.faults.discard(fault)
                state.publish("the battery block reads as a LiFePO4 pack again")
            return
        self._implausible += 1
        if self._implausible >= _IMPLAUSIBLE_READS and fault not in state.faults:
            state.faults.add(fault)
            core = state.profile.core
            cells = "/".join(map(str, cell_mv))
            state.publish(
                f"the battery block at RAM 0x{core.status_addr:02X} reads cells {cells} mV, "
                "not a LiFePO4 pack: the battery settings (battery_addr, battery_layout) may "
                "not be this robot's; `ohmni probe` finds them"
            )

    # -- robot_state -----------------------------------------------------------------------

    def _state_tick(self) -> None:
        state = self._state
        if state.closed:
            return
        if state.topics["robot_state"].enabled:
            state.publish(None)
        self._state_timer = state.loop.call_later(1.0 / state.config.state_hz, self._state_tick)

    # -- rates -----------------------------------------------------------------------------

    def set_rate(self, name: str, hz: float) -> None:
        """Poll stream ``name`` at ``hz`` (``Robot.set_rate``, checked there).

        Raises:
            InvalidArgumentError: The stream is not polled on this robot.
        """
        state = self._state
        periodic = state.periodic.get(name)
        if periodic is None:
            raise InvalidArgumentError(f"stream {name!r} is not polled on this robot")
        periodic.set_rate(hz)
        if STREAMS[name].source == "control":
            periodic.slack_s = CONTROL_SLACK / hz
            for linked, spec in STREAMS.items():
                if name in (linked, spec.follows):
                    state.topics[linked].requested_hz = hz
        else:
            periodic.slack_s = 1.0 / hz
            state.topics[name].requested_hz = hz
