"""The asyncio Robot: tb_control's job on one bus — streams, commands and safety.

::

    from ohmni_tb import Robot

    async with Robot.open("sim://") as robot:
        robot.drive(0.3, 0.0)                        # m/s, rad/s: sets the target
        await asyncio.sleep(1.0)
        print(robot.latest("wheel_odom"))
        async for status in robot.subscribe("tbcore_status"):
            print(status.pack_v)
            break

The Robot owns one schedule on the bus (:mod:`ohmni_tb.robot.schedule`): the control
slot every 20 ms at top priority (the wheel command computed at send time, then both
wheel counts, in one atomic slot), each HerkuleX servo's feedback at 30 Hz, the
worm-gear neck at 30 Hz, the core board at 10 Hz, on absolute deadlines with staggered
phases. Commands (neck moves, light ring, PID writes) go in the free time at a priority
between the control slot and the feedback reads.

:meth:`Robot.release_port` hands the serial port to another program for a while (the
vendor's tb-node, a flashing tool) and :meth:`Robot.reclaim_port` takes it back, on the
same Robot: its streams, statistics and subscriptions carry on.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import AsyncIterator, Callable, Coroutine, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

from ohmni_tb._checks import bounded, check_seconds, number
from ohmni_tb.bus import Bus, ReplyPacket, Slot
from ohmni_tb.config import RobotConfig
from ohmni_tb.control.defaults import MAX_POSE_M, WHEEL_GAIN_RANGES
from ohmni_tb.control.encoder import COUNT_BITS, WheelEncoder, WheelSample, unwrap_delta
from ohmni_tb.control.kinematics import (
    LimitedTwist,
    Twist,
    WheelSpeeds,
    limit_twist,
    saturate_wheel_speeds,
)
from ohmni_tb.control.odometry import Odometry
from ohmni_tb.control.pid import PidController, PidGains, PidStep
from ohmni_tb.errors import (
    BusClosedError,
    BusTimeoutError,
    ConfigError,
    InvalidArgumentError,
    MalformedReplyError,
    OhmniError,
    OutOfRangeError,
    RobotClosedError,
    StateError,
    StopNotConfirmedError,
    TransportError,
)
from ohmni_tb.eventloop import MILLISECOND_S, timer_resolution_s
from ohmni_tb.herkulex import TorqueControl, stat
from ohmni_tb.herkulex.units import angle_rad_from_raw, voltage_v_from_raw
from ohmni_tb.protocol import Memory, Packet, ReadReply, read_request
from ohmni_tb.protocol.core import parse_status, read_status, set_light_ring
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import PWM_LIMIT, parse_count, read_count, wheel_command
from ohmni_tb.protocol.messages import STATUS_DETAILS, STATUS_ERRORS, StatusError
from ohmni_tb.protocol.worm_neck import parse_feedback, read_feedback
from ohmni_tb.robot.api import Robot, SampleStream
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle, WormNeckHandle
from ohmni_tb.robot.motion import MotionGoals, MotionResult
from ohmni_tb.robot.samples import (
    STREAM_NAMES,
    STREAMS,
    Link,
    PidDebugSample,
    RobotStateSample,
    ServoSample,
    TbcoreStatusSample,
    WheelEncoderSample,
    WheelOdomSample,
    WormNeckSample,
)
from ohmni_tb.robot.schedule import CycleResult, Periodic
from ohmni_tb.robot.stats import BusFigures, RobotStats
from ohmni_tb.robot.streams import Subscription, Topic
from ohmni_tb.safety import stop_wheels
from ohmni_tb.transport import SerialTransport, Transport, open_transport

__all__ = ["BusFigures", "LocalRobot", "RobotStats"]

_log = logging.getLogger(__name__)
#: What a polled stream's parser makes of a read reply.
_P = TypeVar("_P")
#: What a shielded coroutine returns.
_R = TypeVar("_R")

#: Bus priorities: the control slot first; commands (devices.COMMAND_PRIORITY) and every
#: feedback read share one priority, so they go in the order they fall due: a near-full
#: line slows them all a little instead of starving the least urgent.
CONTROL_PRIORITY = 10
FEEDBACK_PRIORITY = 5
PROBE_PRIORITY = 0
#: The status error bits the thermal guard acts on.
_HOT_BITS = int(StatusError.TEMPERATURE | StatusError.OVERLOAD)
#: A servo's torque control byte to its mode (an enum call per sample costs more).
_TORQUE_MODES = {int(mode): mode for mode in TorqueControl}
#: Control-slot tuples kept by command value (``Robot._control_cycles``).
_CONTROL_CYCLES_MAX = 256
#: The control slot must start this share of a period after its due time, or it is
#: skipped (a late wheel command is worse than the next one on time). Its count reads
#: wait until the previous cycle's replies are seen, which an adapter's latency timer
#: can hold 16 ms (of a 20 ms period): at half a period 2 % of the cycles were lost
#: that way (49.0 Hz); a slot that starts at three quarters still ends, with its
#: command computed at send time, before the next cycle is due.
CONTROL_SLACK = 0.75
#: The speed governor, on the PWM after the PID (or the open-loop PWM): at most the PWM
#: the configured feed-forward (``pid_kff``, ``pid_ff_offset``) gives for this share of
#: ``max_wheel_mps``; and none at all for a wheel measured faster than that share of it
#: plus a margin for the speed estimate's noise (a model that is wrong, a slope).
OVERSPEED_SHARE = 1.1
OVERSPEED_MARGIN_MPS = 0.03
#: Phase of the first servo read and of the core read after the control slot, seconds:
#: between control slots, so the 50 Hz and 30 Hz grids do not pile up.
SERVO_PHASE_S = 0.010
CORE_PHASE_S = 0.013
#: HerkuleX feedback block: RAM 48 (status error) … 59 (calibrated position, high byte).
SERVO_BLOCK_ADDR = 48
SERVO_BLOCK_LEN = 12
#: Extra attempts for each device at open (a lossy line should not hide a board).
DISCOVERY_RETRIES = 3
#: Absent devices are asked again this often.
REPROBE_S = 5.0
#: Wheel reads rejected in a row before the count is taken as a new origin.
REBASE_AFTER = 3
#: A thermal fault clears this many raw degrees below the limit.
THERMAL_HYSTERESIS_RAW = 10
#: Servo sample index for the stream names of the external servos.
EXT_STREAMS = ("servo_ext1", "servo_ext2")
#: A timed port release (:meth:`Robot.release_port`), seconds: long enough for the
#: other program to open the port at all, and at most an hour — longer, or open-ended,
#: is ``duration_s=None`` (until :meth:`Robot.reclaim_port`).
RELEASE_MIN_S = 0.1
RELEASE_MAX_S = 3600.0
#: The wait before the second attempt to reopen a port another program still holds
#: (then doubling, up to ``reconnect_max_backoff_s``).
RECLAIM_BACKOFF_S = 0.1


@dataclass
class _Wheel:
    """One wheel's feedback state."""

    encoder: WheelEncoder
    pid: PidController
    last_raw: int | None = None
    last_t: float | None = None
    rejected_in_row: int = 0
    last_step: PidStep | None = None


@dataclass
class _ServoWatch:
    """What the thermal and hold guards know of one HerkuleX servo."""

    handle: ServoHandle
    stream: str
    last_command_s: float = -math.inf
    tripped: bool = False
    guard: asyncio.Task[None] | None = None
    sample: ServoSample | None = None


@dataclass
class _State:
    link: Link = Link.CONNECTED
    estopped: bool = False
    watchdog_tripped: bool = False
    faults: set[str] = field(default_factory=set)


class LocalRobot(Robot):
    """One Ohmni robot on its bus, run by this process (module docstring); the API is
    :class:`~ohmni_tb.robot.api.Robot`'s. Create it with :meth:`open`."""

    def __init__(self, bus: Bus, config: RobotConfig, *, sim: Any = None) -> None:
        self._bus = bus
        self.config = config
        #: The simulated robot (ground truth) on ``sim://``, else ``None``.
        self.sim = sim
        self._loop = asyncio.get_running_loop()
        self._opened_at = self._loop.time()
        self._closed = False
        self._topics: dict[str, Topic[Any]] = {name: Topic(name) for name in STREAM_NAMES}
        self._topics["pid_debug"].enabled = config.pid_debug
        self._periodic: dict[str, Periodic] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._state = _State()
        self._neck_kind = "none"
        self._present: set[int] = set()
        self._expected: set[int] = set()
        self._state_timer: asyncio.TimerHandle | None = None
        self._reprobe_timer: asyncio.TimerHandle | None = None
        # Control.
        self._drive = config.drive()
        self._limits = config.velocity_limits()
        self._limiter = config.twist_limiter()
        left_cfg, right_cfg = config.encoders()
        gains = config.pid_gains()
        self._wheels = (
            _Wheel(WheelEncoder(left_cfg), PidController(gains)),
            _Wheel(WheelEncoder(right_cfg), PidController(gains)),
        )
        self._odometry = Odometry(config.wheel_separation_m)
        self._mode: Literal["twist", "wheels", "pwm"] = "twist"
        self._target = Twist()
        self._target_wheels = WheelSpeeds(0.0, 0.0)
        self._target_pwm = (0, 0)
        self._controllers = config.controllers
        self._pwm = (0, 0)
        self._last_step_s: float | None = None
        self._last_command_s = -math.inf
        self._watchdog_timer: asyncio.TimerHandle | None = None
        self._closing: asyncio.Task[Any] | None = None  # the task closing the Robot
        self._overspeed_max_mps = self._limits.max_wheel_mps * OVERSPEED_SHARE + (
            OVERSPEED_MARGIN_MPS
        )
        self._pwm_cap = (
            min(
                PWM_LIMIT,
                round(
                    config.pid_kff * self._limits.max_wheel_mps * OVERSPEED_SHARE
                    + config.pid_ff_offset
                ),
            )
            if config.pid_kff > 0
            else PWM_LIMIT
        )
        self._overspeed = 0
        self._stale_ticks = 0
        self._rejected = 0
        self._clamped = 0
        self._neck: ServoHandle | WormNeckHandle | None = None
        self._servos: dict[int, _ServoWatch] = {}
        self._write_cost_s = bus.cost_s(wheel_command(0, 0))
        self._read_cost_s = bus.cost_s(read_count(DeviceId.LEFT_DRIVE))
        self._count_reads = (read_count(DeviceId.LEFT_DRIVE), read_count(DeviceId.RIGHT_DRIVE))
        self._control_cycles: dict[tuple[int, int], tuple[Packet, ...]] = {}
        # Each polled stream's packets of one cycle (the control slot's with a stop).
        self._packets: dict[str, Sequence[Packet]] = {
            "wheel_encoder": [wheel_command(0, 0), *self._count_reads]
        }
        #: Why the stop on the way out was not confirmed, if it was not (also raised
        #: from ``async with`` when the block itself ended without an error).
        self.exit_error: StopNotConfirmedError | None = None
        self._early_pending = False
        self._early_slot: Slot | None = None
        self._early_writes = 0
        # Port hand-off: the link watcher (or a reclaim that becomes it), the timer of a
        # timed release, and the first attempt of a reclaim under way.
        self._link_task: asyncio.Task[None] | None = None
        self._reclaim_timer: asyncio.TimerHandle | None = None
        self._reclaim: asyncio.Future[None] | None = None
        self._releasing: asyncio.Task[Any] | None = None  # the task releasing the port
        self._port_lock = asyncio.Lock()
        # Motion goals: every other motion command preempts the one under way.
        self._motion = MotionGoals(self, check=self._check_can_drive)

    # -- opening and closing -----------------------------------------------------------

    @classmethod
    def _opens(cls, port: str | Transport | None) -> bool:
        """Every port but a daemon's URL."""
        return not (isinstance(port, str) and port.lower().startswith(("ws://", "wss://")))

    @classmethod
    @contextlib.asynccontextmanager
    async def open(
        cls,
        port: str | Transport | None = None,
        *,
        token: str | None = None,
        config: RobotConfig | None = None,
        **overrides: Any,
    ) -> AsyncIterator[LocalRobot]:
        """:meth:`Robot.open <ohmni_tb.robot.api.Robot.open>` on a port this process opens;
        after an error in the block, that error goes on and :attr:`exit_error` holds the
        stop's. A :class:`~ohmni_tb.transport.Transport` given is reopened after a loss
        only when it is a simulated line."""
        if not cls._opens(port):
            raise ConfigError(
                f"{port!r} is a daemon's URL: open it with Robot.open({port!r}) "
                "(LocalRobot opens a serial port or sim://)"
            )
        if token is not None:
            raise ConfigError("a token is for a daemon's URL (ws://, wss://), not for a port")
        if config is None:
            config = RobotConfig(**overrides)
        elif overrides:
            config = config.replace(**overrides)
        if isinstance(port, Transport):
            # An open link, injected (a test's, a tap's): reopened only if simulated.
            transport = port
            reopen = _reopener(None, transport)
        else:
            url = port if port is not None else config.port
            transport = await open_transport(url)
            reopen = _reopener(url, transport)
        sim = getattr(transport, "robot", None)
        _warn_if_coarse_timers(transport)
        bus = Bus(transport, timeout_s=config.bus_timeout_s(), reopen=reopen)
        bus.start()
        robot: LocalRobot | None = None
        try:
            robot = cls(bus, config, sim=sim)
            await robot._start()
        except BaseException:
            await bus.aclose(final=[wheel_command(0, 0)])
            raise
        try:
            yield robot
        except BaseException:
            await robot._close_shielded()
            raise
        # A clean exit whose stop the wheel counts did not confirm raises: the robot may
        # be moving and nobody else would say so.
        await robot._close_shielded()
        if robot.exit_error is not None:
            raise robot.exit_error

    async def _start(self) -> None:
        await self._discover()
        self._build_schedule()
        t0 = self._loop.time() + 0.005
        for periodic in self._periodic.values():
            periodic.start(t0)
        self._state_timer = self._loop.call_later(1.0 / self.config.state_hz, self._state_tick)
        self._link_task = self._spawn(self._watch_link(), "link watcher")
        if self._expected - self._present:
            self._reprobe_timer = self._loop.call_later(REPROBE_S, self._reprobe)
        self._publish_state("opened")

    async def _close_shielded(self) -> None:
        """Close, and finish closing even if the caller is cancelled meanwhile."""
        await self._shielded(self._close(), "close")

    async def _shielded(self, work: Coroutine[Any, Any, _R], name: str) -> _R:
        """Run ``work`` to its end even if the caller is cancelled meanwhile (the
        cancellation is raised afterwards): a stop must never be cut short."""
        task = self._loop.create_task(work, name=f"ohmni robot {name}")
        cancelled: asyncio.CancelledError | None = None
        while not task.done():
            try:
                await asyncio.shield(task)
            except asyncio.CancelledError as exc:
                cancelled = exc
        result = task.result()
        if cancelled is not None:
            raise cancelled
        return result

    async def _close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._closing = asyncio.current_task()
        self._motion.close()
        for periodic in self._periodic.values():
            periodic.stop()
        for timer in (
            self._state_timer,
            self._reprobe_timer,
            self._reclaim_timer,
            self._watchdog_timer,
        ):
            if timer is not None:
                timer.cancel()
        await self._cancel_tasks()
        bus = self._bus
        stop = wheel_command(0, 0)
        # Not when the port is released (or lost): there is nothing to send the stop on.
        if bus.connected:
            self.exit_error = await self._stop_and_rest("closing")
        self._state.link = Link.CLOSED
        self._publish_state("closed")
        for topic in self._topics.values():
            topic.close()
        await bus.aclose(final=[stop])

    async def _cancel_tasks(self) -> None:
        """Cancel every background task (the link watcher, reprobes, guards); wait."""
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _stop_and_rest(self, why: str) -> StopNotConfirmedError | None:
        """Stop the wheels until their counts confirm it (``stop_timeout_s``) and rest or
        free the neck (``on_exit_neck``): what closing and releasing the port do before
        the port goes. Returns the stop's error when the counts did not confirm it."""
        for periodic in self._periodic.values():
            periodic.cancel_in_flight()
        error: StopNotConfirmedError | None = None
        try:
            if self._present.isdisjoint((DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE)):
                # Neither drive board ever answered this Robot: it drove nothing, and no
                # count can confirm a stop (robot_state shows them absent). The stop still
                # goes, last, as the port closes.
                _log.info(
                    "%s: the drive boards never answered; the wheel stop is sent but cannot "
                    "be confirmed",
                    why,
                )
            else:
                await stop_wheels(self._bus, timeout_s=self.config.stop_timeout_s)
        except StopNotConfirmedError as exc:
            error = exc
            _log.warning("%s: %s", why, exc)
        except OhmniError as exc:
            _log.warning("%s: stop not confirmed: %s", why, exc)
        await self._neck_on_exit(why)
        return error

    async def _neck_on_exit(self, why: str) -> None:
        choice = self.config.on_exit_neck
        if choice == "keep" or not isinstance(self._neck, ServoHandle):
            return
        try:
            async with asyncio.timeout(self.config.stop_timeout_s + 1.5):
                if choice == "rest":
                    await self._neck.rest()
                else:
                    await self._neck.free()
        except (OhmniError, TimeoutError) as exc:
            _log.warning(
                "%s: the neck was not %s: %s", why, "rested" if choice == "rest" else "freed", exc
            )

    @property
    def closed(self) -> bool:
        """Whether the Robot was closed."""
        return self._closed

    @property
    def bus(self) -> Bus:
        """The bus the Robot schedules (for figures and raw access; mind the schedule)."""
        return self._bus

    # -- discovery -----------------------------------------------------------------------

    async def _answers(self, packet: Packet) -> ReplyPacket | None:
        try:
            return await self._bus.request(
                packet, expect_reply=True, retries=DISCOVERY_RETRIES, priority=PROBE_PRIORITY
            )
        except (BusTimeoutError, MalformedReplyError):
            return None

    async def _discover(self) -> None:
        config = self.config
        for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
            self._expected.add(int(sid))
            if await self._answers(read_count(sid)) is not None:
                self._present.add(int(sid))
        if config.core_hz > 0:
            self._expected.add(int(DeviceId.CORE))
            if await self._answers(read_status()) is not None:
                self._present.add(int(DeviceId.CORE))
        kind = config.neck
        if kind in ("auto", "herkulex") and await self._answers(stat(config.neck_id)):
            self._neck_kind = "herkulex"
            self._present.add(config.neck_id)
        elif kind in ("auto", "worm") and await self._answers(read_feedback()):
            self._neck_kind = "worm"
            self._present.add(int(DeviceId.WORM_NECK))
        else:
            # Not found: looked for again slowly (a neck powered up late, a loose cable).
            if kind in ("auto", "herkulex"):
                self._expected.add(config.neck_id)
            if kind in ("auto", "worm"):
                self._expected.add(int(DeviceId.WORM_NECK))
        if self._neck_kind == "herkulex":
            self._neck = self._servo_handle(config.neck_id, "servo_neck", neck=True)
        elif self._neck_kind == "worm":
            self._neck = WormNeckHandle(
                self._bus,
                min_raw=config.worm_min_raw,
                max_raw=config.worm_max_raw,
                check=self._check_port,
                feedback=lambda maxlen: self._feedback_subscription("new_neck", maxlen),
            )
        for ext_id, stream in zip(config.ext_servo_ids, EXT_STREAMS, strict=False):
            self._expected.add(ext_id)
            if await self._answers(stat(ext_id)):
                self._present.add(ext_id)
                self._servo_handle(ext_id, stream, neck=False)
        for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
            if int(sid) not in self._present:
                self._state.faults.add(f"drive_absent:{int(sid)}")

    def _servo_handle(self, sid: int, stream: str, *, neck: bool) -> ServoHandle:
        config = self.config
        handle = ServoHandle(
            self._bus,
            sid,
            min_raw=config.neck_min_raw if neck else 21,
            max_raw=config.neck_max_raw if neck else 1002,
            rest_raw=config.neck_rest_raw if neck else 512,
            zero_offset_raw=config.neck_zero_offset_raw if neck else 0,
            on_command=self._servo_commanded,
            check=self._check_port,
            feedback=lambda maxlen: self._feedback_subscription(stream, maxlen),
        )
        # The hold time counts from when this Robot found the servo: a neck some earlier
        # process left holding is rested neck_hold_s from now, not at the first sample
        # (which would move it the moment any Robot opens, a read-only one included).
        self._servos[sid] = _ServoWatch(handle, stream, last_command_s=self._loop.time())
        return handle

    def _feedback_subscription(self, stream: str, maxlen: int) -> Subscription[Any]:
        """A device's feedback stream, for a move that waits for its read-back.

        Raises:
            StateError: The stream is off (its rate setting is 0, or enable_stream).
        """
        topic = self._topic(stream)
        if not topic.enabled:
            raise StateError(
                f"a move waits on the {stream} stream, which is off: "
                f"robot.enable_stream({stream!r}) first (or wait=False); nothing was sent"
            )
        return topic.subscribe(maxlen)

    def _servo_commanded(self, sid: int) -> None:
        watch = self._servos.get(sid)
        if watch is not None:
            watch.last_command_s = self._loop.time()

    def _reprobe(self) -> None:
        self._reprobe_timer = None
        if self._closed:
            return
        self._spawn(self._reprobe_once(), "reprobe")

    async def _reprobe_once(self) -> None:
        config = self.config
        for sid in sorted(self._expected - self._present):
            if not self._bus.connected:
                break
            if sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
                packet = read_count(sid)
            elif sid == DeviceId.CORE:
                packet = read_status()
            elif sid == DeviceId.WORM_NECK:
                packet = read_feedback()
            else:
                packet = stat(sid)
            if await self._answers(packet) is None:
                continue
            self._present.add(sid)
            self._state.faults.discard(f"drive_absent:{sid}")
            if sid in config.ext_servo_ids:
                index = config.ext_servo_ids.index(sid)
                if index < len(EXT_STREAMS):
                    self._servo_handle(sid, EXT_STREAMS[index], neck=False)
                    self._add_servo_stream(sid, EXT_STREAMS[index], index + 1)
            elif sid == config.neck_id and self._neck_kind == "none":
                self._neck_kind = "herkulex"
                self._neck = self._servo_handle(sid, "servo_neck", neck=True)
                self._add_servo_stream(sid, "servo_neck", 0)
                self._expected.discard(int(DeviceId.WORM_NECK))
            elif sid == DeviceId.WORM_NECK and self._neck_kind == "none":
                self._neck_kind = "worm"
                self._neck = WormNeckHandle(
                    self._bus,
                    min_raw=config.worm_min_raw,
                    max_raw=config.worm_max_raw,
                    check=self._check_port,
                    feedback=lambda maxlen: self._feedback_subscription("new_neck", maxlen),
                )
                self._add_worm_stream()
                self._expected.discard(config.neck_id)
            elif sid == DeviceId.CORE and "tbcore_status" not in self._periodic:
                self._add_core_stream()
            self._publish_state(f"device {sid} answers")
        if not self._closed and self._expected - self._present:
            self._reprobe_timer = self._loop.call_later(REPROBE_S, self._reprobe)

    # -- the schedule ----------------------------------------------------------------------

    def _build_schedule(self) -> None:
        config = self.config
        period = 1.0 / config.wheel_hz
        self._periodic["wheel_encoder"] = Periodic(
            self._bus,
            "control",
            config.wheel_hz,
            phase_s=0.0,
            priority=CONTROL_PRIORITY,
            slack_s=period * CONTROL_SLACK,
            build=self._control_packets,
            handle=self._control_result,
            fail=self._control_failed,
            skipped=self._control_skipped,
        )
        for name, spec in STREAMS.items():
            if spec.source != "polled":  # the control tick's and the state's own rates
                self._topics[name].requested_hz = getattr(config, spec.rate_setting)
        for index, (sid, watch) in enumerate(self._servos.items()):
            self._add_servo_stream(sid, watch.stream, index)
        if self._neck_kind == "worm":
            self._add_worm_stream()
        if int(DeviceId.CORE) in self._present:
            self._add_core_stream()
        for name, spec in STREAMS.items():
            if spec.source == "polled" and name not in self._periodic:
                self._topics[name].enabled = False  # no device: no reads

    def _add_servo_stream(self, sid: int, stream: str, index: int) -> None:
        hz = self.config.servo_hz
        self._add_feedback_stream(
            stream,
            hz,
            # Three servos spread over their period, between control slots.
            phase_s=SERVO_PHASE_S + index / hz / 3 if hz > 0 else 0.0,
            packets=[read_request(sid, SERVO_BLOCK_ADDR, SERVO_BLOCK_LEN)],
            handle=lambda result: self._servo_result(sid, result),
        )

    def _add_worm_stream(self) -> None:
        self._add_feedback_stream(
            "new_neck",
            self.config.new_neck_hz,
            phase_s=SERVO_PHASE_S,
            packets=[read_feedback()],
            handle=self._worm_result,
        )

    def _add_core_stream(self) -> None:
        self._add_feedback_stream(
            "tbcore_status",
            self.config.core_hz,
            phase_s=CORE_PHASE_S,
            packets=[read_status()],
            handle=self._core_result,
        )

    def _add_feedback_stream(
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
        topic = self._topics[stream]
        topic.requested_hz = hz
        topic.enabled = True
        self._packets[stream] = packets
        cycle = tuple(packets)  # the same tuple each cycle: the bus checks it once
        periodic = Periodic(
            self._bus,
            stream,
            hz,
            phase_s=phase_s,
            priority=FEEDBACK_PRIORITY,
            slack_s=1.0 / hz,
            build=lambda due: cycle,
            handle=handle,
            fail=self._feedback_failed(stream),
            skipped=self._counter(stream, "skipped"),
            ahead=True,  # the same reads every cycle: queued on the bus ahead of time
        )
        self._periodic[stream] = periodic
        control = self._periodic.get("wheel_encoder")
        if control is not None and control.running:
            periodic.start(control.next_due_s)

    def _schedule_share(self) -> float:
        """The enabled streams' share of the line by the cost model."""
        return sum(hz * line_time_s for _, hz, _, line_time_s in self.schedule())

    def schedule(self) -> list[tuple[str, float, float, float]]:
        """The schedule (:meth:`Robot.schedule <ohmni_tb.robot.api.Robot.schedule>`)."""
        rows = []
        for name, periodic in self._periodic.items():
            if name != "wheel_encoder" and not self._topics[name].enabled:
                continue
            rows.append(
                (
                    name,
                    1.0 / periodic.period_s,
                    periodic.phase_s,
                    sum(self._bus.cost_s(p) for p in self._packets[name]),
                )
            )
        return rows

    def _counter(self, stream: str, what: Literal["skipped", "missed"]) -> Callable[[int], None]:
        topic = self._topics[stream]

        def count(n: int) -> None:
            setattr(topic, what, getattr(topic, what) + n)

        return count

    def _feedback_failed(self, stream: str) -> Callable[[float, BaseException], None]:
        topic = self._topics[stream]

        def failed(due: float, exc: BaseException) -> None:
            topic.missed += 1
            if not isinstance(exc, OhmniError):
                _log.error("%s: cycle failed", stream, exc_info=exc)

        return failed

    # -- control ---------------------------------------------------------------------------

    def _control_packets(self, due: float) -> tuple[Packet, ...]:
        pwm = self._control_step(self._loop.time())
        cycle = self._control_cycles.get(pwm)
        if cycle is None:
            # One tuple per command value: the bus checks a tuple it has seen only once.
            if len(self._control_cycles) >= _CONTROL_CYCLES_MAX:
                self._control_cycles.clear()
            cycle = self._control_cycles[pwm] = (wheel_command(*pwm), *self._count_reads)
        return cycle

    def _control_step(self, now: float) -> tuple[int, int]:
        """The wheel PWM to send now: watchdog, estop, limits, ramps and the PIDs."""
        config = self.config
        previous = self._last_step_s
        self._last_step_s = now
        dt = 1.0 / config.wheel_hz if previous is None else max(now - previous, 1e-6)
        state = self._state
        self._watchdog_check(now)
        if state.estopped or state.link is not Link.CONNECTED or "stale_feedback" in state.faults:
            self._limiter.reset()
            self._reset_pids()
            self._pwm = (0, 0)
            return self._pwm
        if self._mode == "pwm" or not self._controllers:
            self._limiter.reset()
            self._pwm = self._governed(*self._target_pwm) if self._mode == "pwm" else (0, 0)
            return self._pwm
        if self._mode == "wheels":
            wheels = self._target_wheels
            twist = self._drive.twist(wheels)
            self._limiter.reset(twist)
        else:
            twist = self._limiter.step(self._target, dt)
            wheels = saturate_wheel_speeds(
                self._drive.wheel_speeds(twist), self._limits.max_wheel_mps
            )
        if twist.linear_mps == 0.0 and twist.angular_radps == 0.0:
            # Standing: no PWM at all, and no integral left to creep with.
            self._reset_pids()
            self._pwm = (0, 0)
            return self._pwm
        outputs = []
        for wheel, setpoint in zip(self._wheels, (wheels.left_mps, wheels.right_mps), strict=True):
            last = wheel.encoder.last
            measured = 0.0 if last is None else last.velocity_mps
            step = wheel.pid.step(setpoint, measured, dt)
            wheel.last_step = step
            outputs.append(round(step.output))
        self._pwm = self._governed(outputs[0], outputs[1])
        return self._pwm

    def _governed(self, left: int, right: int) -> tuple[int, int]:
        """The PWM that reaches the wheels, whatever the command, the gains or the
        open-loop PWM asked: within the PWM that ``max_wheel_mps`` needs by the configured
        feed-forward, and none for a wheel measured faster than ``max_wheel_mps`` (with a
        margin) in the direction it is driven (each counted in ``clamped_commands``)."""
        limit = self._overspeed_max_mps
        cap = self._pwm_cap
        pwm = [left, right]
        for index, wheel in enumerate(self._wheels):
            if pwm[index] == 0:
                continue
            if abs(pwm[index]) > cap:
                pwm[index] = cap if pwm[index] > 0 else -cap
                self._clamped += 1
            last = wheel.encoder.last
            if last is None:
                continue
            speed = last.velocity_mps
            if abs(speed) > limit and (pwm[index] > 0) == (speed > 0):
                pwm[index] = 0
                self._overspeed += 1
                self._clamped += 1
                if self._overspeed == 1:
                    _log.warning(
                        "a wheel measured %.2f m/s, over max_wheel_mps=%g: its power is cut "
                        "until it slows (counted in clamped_commands)",
                        speed,
                        self._limits.max_wheel_mps,
                    )
        return pwm[0], pwm[1]

    def _watchdog_check(self, now: float) -> bool:
        """Trip the motion watchdog if the last drive command is older than ``watchdog_s``
        and the target still moves; whether it tripped now."""
        config = self.config
        state = self._state
        if (
            config.watchdog_s <= 0
            or state.watchdog_tripped
            or not self._moving_target()
            or now - self._last_command_s < config.watchdog_s
        ):
            return False
        state.watchdog_tripped = True
        self._stop_targets()
        self._publish_state(f"watchdog: no drive command for {config.watchdog_s:g} s, stopping")
        return True

    def _watchdog_due(self) -> None:
        """The watchdog's own timer: it trips at ``watchdog_s`` after the last drive command
        whatever the control tick's rate, and puts the braking command on the wire at once."""
        self._watchdog_timer = None
        if self._closed:
            return
        due = self._last_command_s + self.config.watchdog_s
        if self._loop.time() < due:  # commanded again meanwhile: wait for the new time
            self._watchdog_timer = self._loop.call_at(due, self._watchdog_due)
        elif self._watchdog_check(self._loop.time()):
            self._write_early(force=True)

    def _control_skipped(self, cycles: int) -> None:
        """Control cycles that did not run (a late loop, a busy line): counted; while the
        wheels are braking, the braking command goes anyway, late rather than never."""
        self._topics["wheel_encoder"].skipped += cycles
        if self._pwm != (0, 0) and not self._moving_target():
            self._write_early(force=True)

    def _moving_target(self) -> bool:
        if self._mode == "pwm":
            return self._target_pwm != (0, 0)
        if self._mode == "wheels":
            return self._target_wheels != WheelSpeeds(0.0, 0.0)
        return self._target != Twist()

    def _reset_pids(self) -> None:
        for wheel in self._wheels:
            wheel.pid.reset()
            wheel.last_step = None

    def _control_result(self, result: CycleResult) -> None:
        replies = result.replies
        t_left = result.started_s + self._write_cost_s
        t_right = t_left + self._read_cost_s
        self._topics["wheel_encoder"].note_lateness(result.started_s - result.due_s)
        # Both wheels or neither: an encoder that moved on alone would hand odometry an
        # increment the other wheel's never matches (the motion of a tick with one
        # failed read arrives whole with the next good pair).
        raw_left = self._wheel_check(self._wheels[0], replies[1], t_left)
        raw_right = self._wheel_check(self._wheels[1], replies[2], t_right)
        left = right = None
        if raw_left is not None and raw_right is not None:
            left = self._wheel_accept(self._wheels[0], raw_left, t_left)
            right = self._wheel_accept(self._wheels[1], raw_right, t_right)
        if left is None or right is None:
            self._topics["wheel_encoder"].missed += 1
            self._stale_ticks += 1
            if (
                self._stale_ticks >= self.config.stale_ticks
                and "stale_feedback" not in self._state.faults
            ):
                self._state.faults.add("stale_feedback")
                self._stop_targets()
                self._publish_state(
                    f"stale feedback: no wheel counts for {self._stale_ticks} ticks, stopping"
                )
            return
        self._stale_ticks = 0
        if "stale_feedback" in self._state.faults:
            self._state.faults.discard("stale_feedback")
            self._publish_state("wheel feedback is back")
        lw, rw = self._wheels
        assert lw.last_raw is not None
        assert rw.last_raw is not None
        encoder = WheelEncoderSample(
            stamp_s=t_left,
            left_raw=lw.last_raw,
            right_raw=rw.last_raw,
            left_ticks=left.count,
            right_ticks=right.count,
            left_m=left.position_m,
            right_m=right.position_m,
            left_mps=left.velocity_mps,
            right_mps=right.velocity_mps,
        )
        if self._topics["wheel_encoder"].enabled:
            self._topics["wheel_encoder"].publish(encoder, t_left)
        odometry = self._odometry
        odom_topic = self._topics["wheel_odom"]
        if odometry.t_s is None or t_left > odometry.t_s:
            odometry.update(left.delta_m, right.delta_m, t_left)
            pose = odometry.pose
            twist = odometry.twist
            commanded = self._limiter.current
            odom = WheelOdomSample(
                stamp_s=t_left,
                x_m=pose.x,
                y_m=pose.y,
                yaw_rad=pose.yaw,
                heading_rad=odometry.heading_rad,
                linear_mps=twist.linear_mps,
                angular_radps=twist.angular_radps,
                covariance=odometry.covariance_rows,
                commanded_linear_mps=commanded.linear_mps,
                commanded_angular_radps=commanded.angular_radps,
            )
            if odom_topic.enabled:
                odom_topic.publish(odom, t_left)
        debug = self._topics["pid_debug"]
        if debug.enabled and lw.last_step is not None and rw.last_step is not None:
            debug.publish(PidDebugSample(t_left, lw.last_step, rw.last_step), t_left)

    def _wheel_check(self, wheel: _Wheel, reply: ReplyPacket | None, t: float) -> int | None:
        """The count in ``reply`` if it is one to take, else ``None`` (counted)."""
        if reply is None:
            return None
        try:
            raw = parse_count(ReadReply.parse(reply))
        except OhmniError:
            self._rejected += 1
            return None
        if wheel.last_raw is not None and wheel.last_t is not None and t > wheel.last_t:
            ticks = abs(unwrap_delta(wheel.last_raw, raw, COUNT_BITS))
            delta_m = ticks * wheel.encoder.config.metres_per_tick
            # A jump no wheel can make: a bit flipped past the 7-bit checksum.
            if delta_m > self.config.implausible_mps * (t - wheel.last_t) + 0.002:
                self._rejected += 1
                wheel.rejected_in_row += 1
                if wheel.rejected_in_row < REBASE_AFTER:
                    return None
                # The count really moved (a board reset): start again from here.
                _log.warning("wheel count jumped for %d reads in a row: new origin", REBASE_AFTER)
                wheel.encoder.reset()
                wheel.encoder.update(raw, t)
                wheel.last_raw, wheel.last_t, wheel.rejected_in_row = raw, t, 0
                return None
        if wheel.last_t is not None and t <= wheel.last_t:
            return None
        return raw

    @staticmethod
    def _wheel_accept(wheel: _Wheel, raw: int, t: float) -> WheelSample | None:
        wheel.rejected_in_row = 0
        wheel.last_raw, wheel.last_t = raw, t
        return wheel.encoder.update(raw, t)

    def _control_failed(self, due: float, exc: BaseException) -> None:
        self._topics["wheel_encoder"].missed += 1
        if not isinstance(exc, OhmniError):
            _log.error("control cycle failed", exc_info=exc)

    def _stop_targets(self) -> None:
        self._target = Twist()
        self._target_wheels = WheelSpeeds(0.0, 0.0)
        self._target_pwm = (0, 0)
        if self._mode == "pwm":
            self._mode = "twist"

    # -- feedback streams ------------------------------------------------------------------

    @staticmethod
    def _feedback(
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
        watch = self._servos.get(sid)
        if watch is None:
            return
        topic = self._topics[watch.stream]

        def block(read: ReadReply) -> tuple[bytes, TorqueControl]:
            if len(read.data) != SERVO_BLOCK_LEN:
                raise MalformedReplyError(
                    f"servo {sid}: {len(read.data)} bytes, not {SERVO_BLOCK_LEN}"
                )
            torque = _TORQUE_MODES.get(read.data[4])
            if torque is None:
                raise MalformedReplyError(f"servo {sid}: torque byte {read.data[4]}")
            return read.data, torque

        parsed = self._feedback(topic, result, block)
        if parsed is None:
            return
        data, torque = parsed
        position = (data[10] | data[11] << 8) & 0x3FF
        handle = watch.handle
        sample = ServoSample(
            stamp_s=result.started_s,
            sid=sid,
            position_raw=position,
            angle_rad=angle_rad_from_raw(position, zero_offset_raw=handle.zero_offset_raw),
            temperature_raw=data[7],
            voltage_v=voltage_v_from_raw(data[6]),
            torque=torque,
            status_error=STATUS_ERRORS[data[0]],
            status_detail=STATUS_DETAILS[data[1]],
        )
        watch.sample = sample
        topic.publish(sample, result.started_s)
        self._thermal_check(watch, sample)

    def _worm_result(self, result: CycleResult) -> None:
        topic = self._topics["new_neck"]
        feedback = self._feedback(topic, result, parse_feedback)
        if feedback is None:
            return
        sample = WormNeckSample(result.started_s, feedback.position, feedback.flags)
        topic.publish(sample, result.started_s)
        fault = "neck_stalled"
        if sample.stalled and fault not in self._state.faults:
            self._state.faults.add(fault)
            self._publish_state("the worm-gear neck stalled: power-cycle the robot")

    def _core_result(self, result: CycleResult) -> None:
        topic = self._topics["tbcore_status"]
        status = self._feedback(topic, result, parse_status)
        if status is None:
            return
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

    # -- the thermal and hold guards ---------------------------------------------------------

    def _thermal_check(self, watch: _ServoWatch, sample: ServoSample) -> None:
        config = self.config
        if not config.thermal_guard:
            return
        # On the flags' int value: an IntFlag's own & makes a new flag each time.
        hot_bits = int(sample.status_error) & _HOT_BITS
        hot = bool(hot_bits) or sample.temperature_raw >= config.thermal_limit_raw
        if hot and not watch.tripped:
            watch.tripped = True
            self._state.faults.add(f"thermal:{sample.sid}")
            rest = watch.stream == "servo_neck"
            self._publish_state(
                f"thermal guard: servo {sample.sid} at temperature {sample.temperature_raw} "
                f"(limit {config.thermal_limit_raw}), errors {sample.status_error!r}: "
                + ("resting, then freeing it" if rest else "freeing it")
            )
            self._guard(watch, rest=rest)
            return
        cool = (
            not hot_bits
            and sample.temperature_raw < config.thermal_limit_raw - THERMAL_HYSTERESIS_RAW
        )
        if watch.tripped and cool:
            watch.tripped = False
            self._state.faults.discard(f"thermal:{sample.sid}")
            self._publish_state(f"thermal guard: servo {sample.sid} cooled down")
        held = self._loop.time() - watch.last_command_s
        if (
            config.neck_hold_s > 0
            and watch.stream == "servo_neck"
            and sample.torque is TorqueControl.ON
            and held > config.neck_hold_s
            and (watch.guard is None or watch.guard.done())
        ):
            self._publish_state(
                f"hold guard: neck torque on for {held:.0f} s since its last command: resting"
            )
            watch.last_command_s = self._loop.time()
            self._guard(watch, rest=True)

    def _guard(self, watch: _ServoWatch, *, rest: bool) -> None:
        if watch.guard is not None and not watch.guard.done():
            return

        async def run() -> None:
            handle = watch.handle
            try:
                if rest and sample_ok(watch.sample):
                    await handle.rest()
                else:
                    await handle.free()
            except OhmniError as exc:
                # A servo in a fault refuses moves: freeing still takes the load off.
                _log.warning("guard: servo %d: %s; freeing it", handle.sid, exc)
                with contextlib.suppress(OhmniError):
                    await handle.free()

        watch.guard = self._spawn(run(), f"guard servo {watch.handle.sid}")

    # -- link loss -------------------------------------------------------------------------

    async def _watch_link(self) -> None:
        """Wait for a lost link; stop the targets and reopen it (``reconnect``).

        Not running while the port is released: :meth:`release_port` cancels it before
        it closes the port, and the reclaim becomes the watcher again.
        """
        bus = self._bus
        while not self._closed:
            reason = await bus.wait_lost()
            if self.closed:  # close() may have run while this waited
                return
            for periodic in self._periodic.values():
                periodic.stop()
            self._state.link = Link.LOST
            self._state.faults.add("link_lost")
            self._halt()
            self._publish_state(f"link lost: {reason}")
            if not self.config.reconnect:
                return
            try:
                await bus.reconnect(max_backoff_s=self.config.reconnect_max_backoff_s)
            except StateError as exc:  # an injected link that cannot be reopened
                self._publish_state(f"not reconnecting: {exc}")
                return
            await self._link_back("link back: reconnected")

    async def _link_back(self, event: str) -> None:
        """The port is open again: a wheel stop first, then the schedule on a fresh phase
        (the control slot and the streams that are on)."""
        with contextlib.suppress(OhmniError):
            await self._bus.send_now(wheel_command(0, 0))
        self._state.link = Link.CONNECTED
        self._state.faults.discard("link_lost")
        self._last_step_s = None
        t0 = self._loop.time() + 0.005
        for name, periodic in self._periodic.items():
            if name == "wheel_encoder" or self._topics[name].enabled:
                periodic.start(t0)
        self._publish_state(event)

    def _halt(self) -> None:
        """Drop the drive targets, the ramp and the PIDs' state (the link went)."""
        self._stop_targets()
        self._limiter.reset()
        self._reset_pids()

    # -- port hand-off (public) ----------------------------------------------------------

    async def release_port(self, duration_s: float | None = None) -> None:
        """Hand the port to another program (the contract: ohmni_tb.robot.api.Robot)."""
        if duration_s is not None:
            check_seconds("duration_s", duration_s, RELEASE_MIN_S, RELEASE_MAX_S)
            duration_s = float(duration_s)
        self._check_open()
        if not self._bus.can_reconnect:
            raise StateError(
                "this Robot cannot reopen its port, so it will not release it: it was opened "
                "on an injected transport; open it by URL (Robot.open('/dev/ttyUSB0'))"
            )
        async with self._port_lock:
            self._check_open()
            self._motion.preempt("release_port")
            error = await self._shielded(self._release(duration_s), "release port")
        if error is not None:
            raise error

    async def reclaim_port(self) -> None:
        """Take the port back (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        async with self._port_lock:
            self._check_open()
            if self._state.link is not Link.RELEASED:
                return
            first = self._reclaim
            if first is None:
                first = self._start_reclaim()
            await asyncio.shield(first)
        self._check_open()

    def _check_open(self) -> None:
        """Refuse a command to a closed Robot (but for the closing's own: the neck is
        rested or freed on the way)."""
        if self._closed and asyncio.current_task() is not self._closing:
            raise RobotClosedError

    async def _release(self, duration_s: float | None) -> StopNotConfirmedError | None:
        """:meth:`release_port`'s work, under the port lock; the stop's error, if any."""
        bus = self._bus
        if self._state.link is Link.RELEASED:
            # A reclaim waiting for the port, or a timed one due, stops: released again.
            await self._cancel_tasks()
            if bus.connected:
                # That reclaim had just reopened the port (nothing drove since the stop).
                await bus.release()
            self._arm_reclaim(duration_s)
            self._publish_state(f"port release renewed: {_released_for(duration_s)}")
            return None
        self._releasing = asyncio.current_task()
        try:
            for periodic in self._periodic.values():
                periodic.stop()
            if self._reprobe_timer is not None:
                self._reprobe_timer.cancel()
                self._reprobe_timer = None
            # Nothing of the Robot's may use the port from here: the link watcher (or it
            # would take the release for a loss), a reprobe, a guard (the neck is done
            # with below).
            await self._cancel_tasks()
            error: StopNotConfirmedError | None = None
            if bus.connected:
                error = await self._stop_and_rest("releasing the port")
                # The last word before the port goes, as closing's (the stop of a Robot
                # whose drive boards never answered, too).
                with contextlib.suppress(OhmniError):
                    await bus.send_now(wheel_command(0, 0))
            try:
                await bus.release()
            except BusClosedError as exc:  # close() ran meanwhile
                raise StateError("the robot was closed while releasing its port") from exc
            self._state.link = Link.RELEASED
            # Not lost any more: nobody tries to reopen it now.
            self._state.faults.discard("link_lost")
            self._halt()
        finally:
            self._releasing = None
        self._arm_reclaim(duration_s)
        unconfirmed = "" if error is None else f" (the wheel stop was not confirmed: {error})"
        self._publish_state(
            f"port released to another program {_released_for(duration_s)}{unconfirmed}"
        )
        return error

    def _arm_reclaim(self, duration_s: float | None) -> None:
        if self._reclaim_timer is not None:
            self._reclaim_timer.cancel()
            self._reclaim_timer = None
        if duration_s is not None:
            self._reclaim_timer = self._loop.call_later(duration_s, self._reclaim_due)

    def _reclaim_due(self) -> None:
        self._reclaim_timer = None
        if self._closed or self._state.link is not Link.RELEASED:
            return
        self._publish_state("port release time is up: reclaiming the port")
        self._spawn(self.reclaim_port(), "timed reclaim")

    def _start_reclaim(self) -> asyncio.Future[None]:
        """Start reopening the released port; the future is done after the first try."""
        if self._reclaim_timer is not None:
            self._reclaim_timer.cancel()
            self._reclaim_timer = None
        first: asyncio.Future[None] = self._loop.create_future()
        self._reclaim = first
        self._link_task = self._spawn(self._reclaim_link(first), "reclaim port")
        return first

    async def _reclaim_link(self, first: asyncio.Future[None]) -> None:
        """Reopen the released port, retrying while another program holds it; then watch
        the link as before. ``first`` is done after the first attempt."""
        bus = self._bus
        try:
            try:
                await bus.reconnect(attempts=1)
            except TransportError as exc:
                self._publish_state(
                    f"reclaiming the port: another program still holds it ({exc}); "
                    f"waiting for it, trying again every {RECLAIM_BACKOFF_S:g}.."
                    f"{self.config.reconnect_max_backoff_s:g} s"
                )
                if not first.done():
                    first.set_result(None)
                await asyncio.sleep(RECLAIM_BACKOFF_S)
                await bus.reconnect(
                    backoff_s=RECLAIM_BACKOFF_S * 2,
                    max_backoff_s=self.config.reconnect_max_backoff_s,
                )
            await self._link_back("port reclaimed")
            if self._expected - self._present and self._reprobe_timer is None:
                self._reprobe_timer = self._loop.call_later(REPROBE_S, self._reprobe)
        finally:
            self._reclaim = None
            if not first.done():
                first.set_result(None)
        await self._watch_link()

    def _check_port(self) -> None:
        """Refuse a command while the port is released, or being released (but for the
        release's own: the neck is rested or freed on the way), or to a closed Robot."""
        self._check_open()
        if self._releasing is not None and asyncio.current_task() is not self._releasing:
            raise StateError("the port is being released to another program (release_port())")
        if self._state.link is not Link.RELEASED:
            return
        if self._reclaim is not None and self._reclaim.done():
            raise StateError(
                "the port is released and another program still holds it: the robot is "
                "waiting for it (robot_state says 'port reclaimed' when it is back)"
            )
        raise StateError("the port is released to another program; reclaim_port() first")

    # -- robot_state -----------------------------------------------------------------------

    def _state_sample(self, event: str | None) -> RobotStateSample:
        state = self._state
        return RobotStateSample(
            stamp_s=self._loop.time(),
            link=state.link,
            estopped=state.estopped,
            watchdog_tripped=state.watchdog_tripped,
            faults=tuple(sorted(state.faults)),
            neck=self._neck_kind,
            present=tuple(sorted(self._present)),
            absent=tuple(sorted(self._expected - self._present)),
            event=event,
        )

    def _publish_state(self, event: str | None) -> None:
        sample = self._state_sample(event)
        if event is not None:
            _log.info("robot: %s", event)
        self._topics["robot_state"].publish(sample, sample.stamp_s)

    def _state_tick(self) -> None:
        if self._closed:
            return
        if self._topics["robot_state"].enabled:
            self._publish_state(None)
        self._state_timer = self._loop.call_later(1.0 / self.config.state_hz, self._state_tick)

    # -- tasks -------------------------------------------------------------------------------

    def _spawn(self, coro: Any, name: str) -> asyncio.Task[Any]:
        task = self._loop.create_task(coro, name=f"ohmni robot: {name}")
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            _log.error("%s failed", task.get_name(), exc_info=exc)
            self._publish_state(f"{task.get_name()} failed: {exc}")

    # -- streams (public) --------------------------------------------------------------------

    def _topic(self, name: str) -> Topic[Any]:
        topic = self._topics.get(name)
        if topic is None:
            raise InvalidArgumentError(
                f"no stream {name!r}: the streams are {', '.join(STREAM_NAMES)}"
            )
        return topic

    def _latest(self, name: str) -> Any:
        return self._topic(name).latest

    def _subscribe(self, name: str, maxlen: int) -> SampleStream[Any]:
        return self._topic(name).subscribe(maxlen)

    def enable_stream(self, name: str, enabled: bool = True) -> None:
        """A stream on or off (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        topic = self._topic(name)
        if not isinstance(enabled, bool):
            raise InvalidArgumentError(f"enabled must be True or False, not {enabled!r}")
        periodic = self._periodic.get(name)
        if STREAMS[name].source != "polled":
            topic.enabled = enabled  # the control slot and the state keep running
            return
        if periodic is None:
            if enabled:
                raise StateError(f"stream {name!r} has no device on this robot")
            topic.enabled = False
            return
        topic.enabled = enabled
        if enabled and not periodic.running and self._state.link is Link.CONNECTED:
            periodic.start(self._periodic["wheel_encoder"].next_due_s)
        elif not enabled:
            periodic.stop()

    def set_rate(self, name: str, hz: float) -> None:
        """A polled stream's rate (:meth:`Robot.set_rate <ohmni_tb.robot.api.Robot.set_rate>`)."""
        self._check_open()
        self._topic(name)
        spec = STREAMS[name]
        if spec.rate_range_hz is None:
            how = (
                f"it comes with every {spec.follows} sample (set that one's rate)"
                if spec.follows
                else f"its rate is the {spec.rate_setting} setting"
            )
            raise InvalidArgumentError(f"stream {name!r} is not polled: {how}")
        low, high = spec.rate_range_hz
        if not low <= number("hz", hz) <= high:
            raise OutOfRangeError(f"{name} rate", hz, low, high, "Hz")
        periodic = self._periodic.get(name)
        if periodic is None:
            raise InvalidArgumentError(f"stream {name!r} is not polled on this robot")
        periodic.set_rate(hz)
        if spec.source == "control":
            periodic.slack_s = CONTROL_SLACK / hz
            for linked, other in STREAMS.items():
                if name in (linked, other.follows):
                    self._topics[linked].requested_hz = hz
        else:
            periodic.slack_s = 1.0 / hz
            self._topics[name].requested_hz = hz

    def stats(self) -> RobotStats:
        """Per-stream rates, jitter, missed/skipped cycles and the bus's figures."""
        now = self._loop.time()
        bus = self._bus.stats
        return RobotStats(
            streams={name: topic.stats(now) for name, topic in self._topics.items()},
            bus=BusFigures(
                wire_utilisation=bus.wire_utilisation,
                budget_share=self._schedule_share(),
                transactions_per_s=bus.transactions_per_s,
                timeouts=sum(d.timeouts for d in bus.devices.values()),
                rejected_samples=self._rejected,
                clamped_commands=self._clamped,
                deadline_misses=bus.deadline_misses,
                link_losses=bus.link_losses,
                reconnects=bus.reconnects,
            ),
            uptime_s=now - self._opened_at,
        )

    @property
    def state(self) -> RobotStateSample:
        """The Robot's state now (as ``robot_state`` would publish it)."""
        return self._state_sample(None)

    # -- motion commands (public) ----------------------------------------------------------

    def _check_can_drive(self) -> None:
        self._check_port()
        if self._state.estopped:
            raise StateError("an emergency stop is latched: call robot.clear_estop() first")

    def _commanded(self, changed: bool) -> None:
        now = self._last_command_s = self._loop.time()
        if self._watchdog_timer is None and self.config.watchdog_s > 0:
            self._watchdog_timer = self._loop.call_at(
                now + self.config.watchdog_s, self._watchdog_due
            )
        if changed:
            self._write_early()
        if self._state.watchdog_tripped:
            self._state.watchdog_tripped = False
            self._publish_state("watchdog re-armed by a drive command")

    def drive(self, linear_mps: float, angular_radps: float = 0.0) -> LimitedTwist:
        """The body velocity target (:meth:`Robot.drive <ohmni_tb.robot.api.Robot.drive>`)."""
        twist = Twist(number("linear_mps", linear_mps), number("angular_radps", angular_radps))
        self._check_can_drive()
        limited = limit_twist(twist, self._limits, self._drive)
        if limited.limited:
            self._clamped += 1
            _log.debug(
                "drive(%g, %g) scaled by %.3f into the limits",
                linear_mps,
                angular_radps,
                limited.scale,
            )
        self._motion.preempt("drive")
        changed = self._mode != "twist" or self._target != limited.twist
        self._mode = "twist"
        self._target = limited.twist
        self._commanded(changed)
        return limited

    def drive_wheels(self, left_mps: float, right_mps: float) -> WheelSpeeds:
        """Each wheel's speed target (the contract: ohmni_tb.robot.api.Robot)."""
        asked = WheelSpeeds(number("left_mps", left_mps), number("right_mps", right_mps))
        self._check_can_drive()
        wheels = saturate_wheel_speeds(asked, self._limits.max_wheel_mps)
        if wheels != asked:
            self._clamped += 1
        self._motion.preempt("drive_wheels")
        changed = self._mode != "wheels" or self._target_wheels != wheels
        self._mode = "wheels"
        self._target_wheels = wheels
        self._commanded(changed)
        return wheels

    def drive_pwm(self, left: int, right: int) -> None:
        """Open-loop PWM (:meth:`Robot.drive_pwm <ohmni_tb.robot.api.Robot.drive_pwm>`)."""
        for name, value in (("left", left), ("right", right)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise InvalidArgumentError(f"{name} PWM must be an int, not {value!r}")
            if not -PWM_LIMIT <= value <= PWM_LIMIT:
                raise OutOfRangeError(f"{name} PWM", value, -PWM_LIMIT, PWM_LIMIT)
        self._check_can_drive()
        self._motion.preempt("drive_pwm")
        changed = self._mode != "pwm" or self._target_pwm != (left, right)
        self._mode = "pwm"
        self._target_pwm = (left, right)
        self._commanded(changed)

    def _write_early(self, *, force: bool = False) -> None:
        """Get a changed command to the wheels well within one control period.

        A control slot (or an early command) still waiting for the line gets the new
        command in place of the one computed before. Otherwise, when the next control slot
        is over a quarter period away (or ``force``: the control cycles are being skipped),
        the command goes now in a slot of its own (at most one between two control slots).
        A command that moves is due before the next control slot; one that stops or brakes
        has no deadline: late, it still goes.
        """
        control = self._periodic.get("wheel_encoder")
        if control is None or not control.running:
            return
        now = self._loop.time()
        for waiting in (control.unstarted(), self._early_slot):
            if waiting is not None and waiting.started_at is None:
                with contextlib.suppress(OhmniError):
                    waiting.replace_unsent(0, wheel_command(*self._control_step(now)))
                    self._early_writes += 1
                    return
        if self._early_pending or (not force and control.next_due_s - now <= control.period_s / 4):
            return
        pwm = self._control_step(now)
        try:
            slot = self._bus.submit(
                [wheel_command(*pwm)],
                priority=CONTROL_PRIORITY,
                deadline=control.next_due_s if self._moving_target() else None,
            )
        except OhmniError:
            return
        self._early_pending = True
        self._early_slot = slot
        self._early_writes += 1

        def done(future: asyncio.Future[list[ReplyPacket | None]]) -> None:
            self._early_pending = False
            self._early_slot = None
            if not future.cancelled():
                future.exception()  # retrieved: a missed deadline needs no report

        slot.future.add_done_callback(done)

    def stop(self) -> None:
        """Target zero, the first braking command at once."""
        self._check_open()
        self._motion.preempt("stop")
        self._stop_targets()
        self._last_command_s = self._loop.time()
        if self._state.link is Link.CONNECTED:
            self._write_early(force=True)

    async def estop(self) -> None:
        """Zero PWM ahead of everything, latched (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        self._motion.preempt("estop")
        self._state.estopped = True
        self._stop_targets()
        self._limiter.reset()
        self._reset_pids()
        self._pwm = (0, 0)
        # Wheel commands computed before now and still queued must not follow the stop.
        control = self._periodic.get("wheel_encoder")
        if control is not None:
            control.withdraw_unstarted()
        early = self._early_slot
        if early is not None and early.started_at is None:
            self._bus.cancel(early)
        self._publish_state("emergency stop latched")
        if self._bus.connected:
            await self._bus.send_now(wheel_command(0, 0))

    def clear_estop(self) -> None:
        """Release a latched emergency stop (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        if self._state.estopped:
            self._state.estopped = False
            self._publish_state("emergency stop cleared")

    def enable_controllers(self, enabled: bool = True) -> None:
        """The wheel PIDs on or off (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        if not isinstance(enabled, bool):
            raise InvalidArgumentError(f"enabled must be True or False, not {enabled!r}")
        if not enabled:
            self._motion.preempt("enable_controllers")
        self._controllers = enabled
        self._reset_pids()

    def get_pid(self) -> PidGains:
        """The wheel PIDs' gains (both wheels share them)."""
        return self._wheels[0].pid.gains

    def set_pid(self, gains: PidGains) -> None:
        """New wheel PID gains, bumplessly (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        if not isinstance(gains, PidGains):
            raise InvalidArgumentError(f"gains must be PidGains, not {type(gains).__name__}")
        for name, (low, high) in WHEEL_GAIN_RANGES.items():
            value = getattr(gains, name)
            if not low <= value <= high:
                raise OutOfRangeError(f"pid {name}", value, low, high)
        for wheel in self._wheels:
            wheel.pid.set_gains(gains)

    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """Set the odometry pose (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_open()
        pose = []
        for name, value, unit in (
            ("x_m", x_m, "m"),
            ("y_m", y_m, "m"),
            ("yaw_rad", yaw_rad, "rad"),
        ):
            pose.append(bounded(name, number(name, value), -MAX_POSE_M, MAX_POSE_M, unit))
        # A goal steering by the odometry cannot go on in a new frame.
        self._motion.preempt("reset_odometry", stop=True)
        self._odometry.reset(*pose)

    # -- motion goals (public): ohmni_tb.robot.motion ---------------------------------------

    async def drive_distance(
        self,
        distance_m: float,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
    ) -> MotionResult:
        """Drive straight ``distance_m`` by odometry and stop there, at rest.

        Cruises at ``speed_mps``, slows on a braking curve near the goal and ends within
        about 1 mm of it by odometry (the wheel counts), then waits until the counts show
        the robot at rest. Another motion command meanwhile (``drive``, ``stop``,
        ``estop``, another goal…) ends it and stands; cancelling the awaiting task sets
        the target to zero (the wheels ramp down) and the cancellation goes on.

        Args:
            distance_m: How far, m, −100..100 (negative: backward).
            speed_mps: The cruising speed, m/s, from 0.03 up to ``max_linear_mps`` (and
                ``max_wheel_mps``); default 0.3 within them.
            timeout_s: The time it may take, 0..3600 s; default twice the plan's + 2 s.

        Returns:
            What it did: distance and heading change by odometry, the pose, what is
            left, the time taken, and ``reason="arrived"``.

        Raises:
            InvalidArgumentError: A value is not a finite number; nothing sent.
            OutOfRangeError: A value is outside its range (named with it); nothing sent.
            StateError: An emergency stop is latched, the port is released, the robot
                is closed, or the wheel_encoder or wheel_odom stream is off.
            MotionPreemptedError: Another motion command took over (``.by``).
            WheelStallError: A wheel commanded to turn did not (0.5 s); stopped.
            MotionTimeoutError: Not there in time; stopped.
            MotionAbortedError: The watchdog tripped, the link was lost, no wheel counts
                came for 0.5 s, or the Robot closed.
            StopNotConfirmedError: The counts did not show the robot at rest after the
                stop: it may be moving.
        """
        return await self._motion.drive_distance(
            distance_m, speed_mps=speed_mps, timeout_s=timeout_s
        )

    async def rotate(
        self,
        angle_rad: float,
        *,
        speed_radps: float | None = None,
        timeout_s: float | None = None,
    ) -> MotionResult:
        """Turn on the spot ``angle_rad`` by odometry (positive: counter-clockwise, as
        ``wheel_odom``'s heading) and stop there, at rest: within about 0.1° by odometry.

        As :meth:`drive_distance` (preemption, cancellation, the errors).

        Args:
            angle_rad: How far, rad, −20π..20π (ten turns either way).
            speed_radps: The turning rate, rad/s, from 0.2 up to ``max_angular_radps``
                (and what ``max_wheel_mps`` allows); default 1.0 within them.
            timeout_s: The time it may take, 0..3600 s; default twice the plan's + 2 s.

        Returns:
            What it did (:class:`~ohmni_tb.errors.MotionResult`).
        """
        return await self._motion.rotate(angle_rad, speed_radps=speed_radps, timeout_s=timeout_s)

    async def go_to(
        self,
        x_m: float,
        y_m: float,
        yaw_rad: float | None = None,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
    ) -> MotionResult:
        """Go to the point (``x_m``, ``y_m``) of the odometry frame (``wheel_odom``), then
        turn to ``yaw_rad`` if given; stop there, at rest.

        It turns on the spot to face the point, drives there steering toward it and
        slowing on the braking curve, and faces and drives again while the point is more
        than 1 cm away; then turns to ``yaw_rad`` (within about 0.1°). As
        :meth:`drive_distance` otherwise (preemption, cancellation, the errors).

        Args:
            x_m: The point, m (±1e6; at most 100 m from where the robot is).
            y_m: The point, m.
            yaw_rad: The heading to end with, rad, or ``None`` to keep the one it
                arrives with.
            speed_mps: The cruising speed, m/s, as :meth:`drive_distance`'s; the turns
                go at 1.0 rad/s within the limits.
            timeout_s: The time it may take, 0..3600 s; default twice the plan's + 2 s
                for each part.

        Returns:
            What it did (:class:`~ohmni_tb.errors.MotionResult`); ``remaining_m`` is the
            distance left to the point.
        """
        return await self._motion.go_to(x_m, y_m, yaw_rad, speed_mps=speed_mps, timeout_s=timeout_s)

    # -- devices (public) --------------------------------------------------------------------

    @property
    def neck_kind(self) -> str:
        """``herkulex``, ``worm`` or ``none``: which neck answered at open."""
        return self._neck_kind

    @property
    def neck(self) -> ServoHandle | WormNeckHandle:
        """The neck's handle (:attr:`Robot.neck <ohmni_tb.robot.api.Robot.neck>`)."""
        if self._neck is None:
            raise StateError(
                f"no neck answered (looked for {self.config.neck}: HerkuleX at "
                f"{self.config.neck_id}, worm gear at 4)"
            )
        return self._neck

    def servo(self, sid: int) -> ServoHandle:
        """A HerkuleX servo's handle (:meth:`Robot.servo <ohmni_tb.robot.api.Robot.servo>`)."""
        watch = self._servos.get(sid)
        if watch is None:
            found = ", ".join(map(str, sorted(self._servos))) or "none"
            raise StateError(f"no HerkuleX servo {sid!r} on this robot (found: {found})")
        return watch.handle

    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        """The light ring's colour (the contract: ohmni_tb.robot.api.Robot)."""
        packet = set_light_ring(hue, saturation, value)
        self._check_port()
        await self._bus.request(packet, expect_reply=False, priority=COMMAND_PRIORITY)

    async def info(self) -> dict[str, Any]:
        """Firmware tags, servo models, the neck kind (the contract: ohmni_tb.robot.api.Robot)."""
        self._check_port()
        tags: dict[str, str | None] = {}
        for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE):
            try:
                reply = await self._bus.read(sid, 0xF1, 0, Memory.EEP)
                tags[sid.name.lower()] = reply.data.decode("ascii", errors="replace")
            except OhmniError:
                tags[sid.name.lower()] = None
        models: dict[int, str | None] = {}
        for servo_id, watch in self._servos.items():
            try:
                models[servo_id] = (await watch.handle.servo.model()).name
            except OhmniError:
                models[servo_id] = None
        return {
            "firmware": tags,
            "servos": models,
            "neck": self._neck_kind,
            "present": sorted(self._present),
            "absent": sorted(self._expected - self._present),
        }

    @staticmethod
    def ports() -> list[dict[str, Any]]:
        """Serial ports on this machine with their USB ids, the likely bus adapter first
        (``likely_bus``; :func:`ohmni_tb.transport.ports.list_ports`)."""
        from ohmni_tb.transport.ports import list_ports  # noqa: PLC0415  # slow: when asked

        return [port.as_dict() for port in list_ports()]


_coarse_timers_told = False


def _warn_if_coarse_timers(transport: Transport) -> None:
    """Tell once per process when a serial port runs on a loop with millisecond timers.

    Behind an adapter that holds replies, every request of the schedule goes out on a
    timer, and each one late by up to a millisecond does not fit a line booked to 81 %
    (ohmni_tb.eventloop). The simulator in this process delivers at once: not told.
    """
    global _coarse_timers_told  # noqa: PLW0603  # once per process, not per Robot
    if _coarse_timers_told or not isinstance(transport, SerialTransport):
        return
    if timer_resolution_s() < MILLISECOND_S:
        return
    _coarse_timers_told = True
    _log.warning(
        "this event loop's timers fire up to 1 ms late (asyncio's epoll waits in whole "
        "milliseconds): behind a USB adapter that holds replies the servo streams can miss "
        "their rates; run the program with ohmni_tb.run(main()) instead of asyncio.run"
    )


def sample_ok(sample: ServoSample | None) -> bool:
    """Whether a servo may still move: no error that blocks moves."""
    if sample is None:
        return True
    return not sample.status_error & (
        StatusError.TEMPERATURE | StatusError.OVERLOAD | StatusError.DRIVER_FAULT
    )


def _reopener(url: str | None, transport: Transport) -> Callable[[], Any] | None:
    """How the bus reopens the port: the same simulated line, or the URL again."""
    line = getattr(transport, "line", None)
    if line is not None:
        from ohmni_tb.sim.transport import SimTransport  # noqa: PLC0415  # sim only

        robot = getattr(transport, "robot", None)

        async def reopen_sim() -> Transport:
            return SimTransport(line, robot=robot)

        return reopen_sim
    if url is None:
        return None

    async def reopen() -> Transport:
        return await open_transport(url)

    return reopen


def _released_for(duration_s: float | None) -> str:
    """How long a release lasts, in words for ``robot_state``."""
    if duration_s is None:
        return "until reclaim_port()"
    return f"for {duration_s:g} s"
