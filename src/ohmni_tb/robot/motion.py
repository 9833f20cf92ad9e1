"""Motion goals: drive a distance, turn an angle, go to a point — by odometry, on the Robot.

::

    result = await robot.drive_distance(0.5)                 # m, negative: backward
    result = await robot.rotate(math.pi / 2)                 # rad, counter-clockwise
    result = await robot.go_to(1.0, 0.5, yaw_rad=0.0)        # the wheel_odom frame
    print(result.distance_m, result.heading_change_rad, result.remaining_m)

Each goal steers by the wheel counts of every control tick (``wheel_encoder``, with
``wheel_odom`` of the same tick): it cruises at its speed, slows on a braking curve
planned with half the configured deceleration (the wheel PIDs trail the ramp), creeps at
no less than :data:`MIN_GOAL_LINEAR_MPS` / :data:`MIN_GOAL_ANGULAR_RADPS` (out of the
motors' dead band), and stops when the wheels, still running on at their speed, would
reach the goal :data:`STOP_LEAD_S` later. Then it waits until the wheel counts show the
robot at rest and returns a :class:`~ohmni_tb.errors.MotionResult`.

- ``drive_distance`` drives straight; it ends within :data:`GOAL_TOLERANCE_M` of the
  distance by odometry, plus the stop's run-out (on the simulator the truth lands within
  ~1 mm).
- ``rotate`` turns on the spot; within :data:`GOAL_TOLERANCE_RAD` by odometry (~0.2° by
  the simulator's truth).
- ``go_to`` turns to face the point, drives there correcting its heading on the way,
  and turns to ``yaw_rad`` if given; it faces and drives again while the point is more
  than :data:`GO_TO_TOLERANCE_M` away. The turns and the drive are the two goals above,
  each ending at rest.

One goal runs at a time. Any other motion command — ``drive``, ``drive_wheels``,
``drive_pwm``, ``stop``, ``estop``, ``enable_controllers(False)``, ``release_port`` or
another goal — ends it with :class:`~ohmni_tb.errors.MotionPreemptedError` naming the
command, and the newer command stands (the goal sends nothing more). A goal runs under
the command source that started it (:mod:`ohmni_tb.robot.sources`), which stays live
while it runs: a drive command of a lower source is refused meanwhile and leaves it
alone; one of a higher source takes over and ends it. So does
``reset_odometry``, which moves the frame the goal steers in; then the goal also sets
the target to zero. The Robot's guards end it too (:meth:`MotionGoals.wheel_fault`, from
the control loop, :mod:`ohmni_tb.robot.control_loop`): a stall with
:class:`~ohmni_tb.errors.WheelStallError` at once (the guard has cut the wheels' power
already), a slip with :class:`~ohmni_tb.errors.WheelSlipError` once the goal's stop is at
rest. The goal ends with :class:`~ohmni_tb.errors.MotionTimeoutError` past its time, and
with :class:`~ohmni_tb.errors.MotionAbortedError` when the watchdog trips, the link is
lost, no wheel counts come for :data:`FEEDBACK_GAP_S` or the Robot closes. After a slip
or a timeout the robot is stopped and at rest. Cancelling the task that awaits a goal
sets the target to zero at once — the wheels ramp down at the deceleration limits — and
the cancellation goes on; nothing waits.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Literal, Protocol

from ohmni_tb._checks import bounded, check_seconds, number
from ohmni_tb.control.defaults import MAX_POSE_M
from ohmni_tb.errors import (
    MotionAbortedError,
    MotionEnd,
    MotionError,
    MotionKind,
    MotionPreemptedError,
    MotionResult,
    MotionTimeoutError,
    OhmniError,
    OutOfRangeError,
    StateError,
    StopNotConfirmedError,
    StopReport,
    WheelSlipError,
    WheelStallError,
)
from ohmni_tb.robot.samples import Link
from ohmni_tb.safety import DEFAULT_SETTLE_S, DEFAULT_TOLERANCE_TICKS, SettleWindow

if TYPE_CHECKING:
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.robot.control_loop import WheelFault
    from ohmni_tb.robot.samples import RobotStateSample, WheelEncoderSample, WheelOdomSample
    from ohmni_tb.robot.stats import RobotStats

__all__ = [
    "DEFAULT_ANGULAR_RADPS",
    "DEFAULT_LINEAR_MPS",
    "FEEDBACK_GAP_S",
    "GOAL_TOLERANCE_M",
    "GOAL_TOLERANCE_RAD",
    "GO_TO_TOLERANCE_M",
    "MAX_ANGLE_RAD",
    "MAX_DISTANCE_M",
    "MAX_TIMEOUT_S",
    "MIN_GOAL_ANGULAR_RADPS",
    "MIN_GOAL_LINEAR_MPS",
    "PLAN_DECEL_SHARE",
    "STOP_LEAD_S",
    "CountStream",
    "GoalSources",
    "MotionGoals",
    "MotionHost",
    "MotionResult",
    "goal_timeout_s",
]

#: Speeds of a goal given none: the config's limits cap them.
DEFAULT_LINEAR_MPS = 0.3
DEFAULT_ANGULAR_RADPS = 1.0
#: The slowest a goal creeps near its end, and the least speed it takes: slower, the
#: wheels sit in the motors' dead band.
MIN_GOAL_LINEAR_MPS = 0.03
MIN_GOAL_ANGULAR_RADPS = 0.2
#: The farthest ``drive_distance`` (and ``go_to`` from where the robot is), m: a slip of
#: the keyboard (1000 for 1.0) must not send the robot off.
MAX_DISTANCE_M = 100.0
#: The largest ``rotate`` either way: ten turns.
MAX_ANGLE_RAD = 20 * math.pi
#: The longest ``timeout_s``, s.
MAX_TIMEOUT_S = 3600.0
#: A goal plans its slow-down with this share of the braking limit: the wheel PIDs trail
#: the ramp, so the plan leaves them room.
PLAN_DECEL_SHARE = 0.5
#: The wheels trail the command (the PIDs, the 0.1 s speed estimate): a goal plans its
#: slow-down from where they will be PROFILE_LEAD_S later, and stops when they would reach
#: the goal STOP_LEAD_S later. Tuned on the simulator: goals land within ~1 mm, 0.2°.
PROFILE_LEAD_S = 0.02
STOP_LEAD_S = 0.08
#: A drive or turn this close to its goal by odometry counts as there (the stop's own
#: run-out adds about as much).
GOAL_TOLERANCE_M = 0.001
GOAL_TOLERANCE_RAD = math.radians(0.1)
#: ``go_to`` faces the point and drives again while it is farther than this.
GO_TO_TOLERANCE_M = 0.01
#: ``go_to`` turns on the spot to face the point first when it is off by more than this.
FACE_TOLERANCE_RAD = math.radians(1.0)
#: ``go_to`` steers toward the point at this rate per radian of heading error, at most
#: HEADING_MAX_RADPS; nearer than HEADING_HOLD_M it holds its heading (the bearing of a
#: point that close swings with every millimetre).
HEADING_GAIN_PER_S = 2.0
HEADING_MAX_RADPS = 0.5
HEADING_HOLD_M = 0.05
#: No wheel counts for this long: the goal stops (a cable, a silent board), whatever the
#: watchdog and stale-feedback settings say.
FEEDBACK_GAP_S = 0.5
#: A goal's subscription to the wheel counts: a few ticks of slack for a busy loop.
_QUEUE = 8
#: The reasons after which the goal stops the robot itself, and waits for it to rest. A
#: stall is neither: the stall guard has cut the wheels' power and holds them so (a stop
#: would end its hold), and its error is due at once.
_STOPS: frozenset[str] = frozenset(
    {"arrived", "slipped", "timeout", "watchdog", "link_lost", "no_counts"}
)
_SETTLES: frozenset[str] = frozenset({"arrived", "slipped", "timeout"})
#: What is left of a goal, from the pose, the distance and the heading change since it
#: began: (m, rad) as :class:`MotionResult` has them.
_Remaining = Callable[["WheelOdomSample", float, float], tuple[float, float]]


def goal_timeout_s(goal: float, speed: float, accel: float, decel: float) -> float:
    """Time a drive or turn of ``goal`` (m or rad) may take at ``speed`` by default: twice
    the plan (the cruise, the ramp up at ``accel``, the slow-down at :data:`PLAN_DECEL_SHARE`
    of ``decel``), + 2 s."""
    plan_decel = decel * PLAN_DECEL_SHARE
    expected = abs(goal) / speed + speed / accel + 2 * speed / plan_decel
    return 2 * expected + 2.0


class CountStream(Protocol):
    """What a goal uses of a ``wheel_encoder`` subscription."""

    @property
    def closed(self) -> bool: ...

    def close(self) -> None: ...

    def get_nowait(self) -> WheelEncoderSample | None: ...

    async def __anext__(self) -> WheelEncoderSample: ...


class MotionHost(Protocol):
    """What the goals use of a Robot: its settings, its drive commands and its streams."""

    @property
    def config(self) -> RobotConfig: ...

    @property
    def state(self) -> RobotStateSample: ...

    def drive(
        self, linear_mps: float, angular_radps: float = 0.0, *, source: str | None = None
    ) -> object: ...

    def stop(self, *, source: str | None = None) -> None: ...

    def latest(self, name: Literal["wheel_odom"]) -> WheelOdomSample | None: ...

    def subscribe(self, name: Literal["wheel_encoder"], *, maxlen: int = ...) -> CountStream: ...

    def stats(self) -> RobotStats: ...


class GoalSources(Protocol):
    """What the goals use of the Robot's command sources (:mod:`ohmni_tb.robot.sources`)."""

    def check(self, source: str, what: str) -> None: ...

    def hold(self, source: str) -> None: ...

    def release(self, source: str) -> None: ...


class _Ended(Exception):  # noqa: N818  # control flow inside this module, never raised out
    """The goal ends now, for ``reason``."""

    def __init__(self, reason: MotionEnd) -> None:
        super().__init__(reason)
        self.reason: MotionEnd = reason


class _Run:
    """One goal under way: its wheel counts, its start, its commands and its end."""

    def __init__(
        self,
        goals: MotionGoals,
        kind: MotionKind,
        *,
        sub: CountStream,
        enc: WheelEncoderSample,
        odom: WheelOdomSample,
        started_s: float,
        source: str | None = None,
    ) -> None:
        self.goals = goals
        self.kind: MotionKind = kind
        #: The command source it runs under (its own commands are that source's).
        self.source = source
        self.sub = sub
        self.enc = self.start_enc = enc
        self.odom = self.start_odom = odom
        self.started_s = started_s
        self.deadline_s = math.inf
        self.timeout_s = math.inf
        #: Set from outside (another command, closing): why, and by what.
        self.ended: MotionEnd | None = None
        self.by = ""
        self.by_source: str | None = None
        self.commanded = False  # a drive command went since the last stop
        # The watchdog flag was seen clear: a trip from before the goal is not its own.
        self.watchdog_clear = False
        #: The guard that ended the goal (a stall or a slip), if one did.
        self.fault: WheelFault | None = None
        self.top_speed = 0.0  # the fastest this goal drives a wheel, for the rest wait

    @property
    def travel_m(self) -> float:
        """The mean of both wheels' travel since the Robot opened."""
        return (self.enc.left_m + self.enc.right_m) / 2

    @property
    def distance_m(self) -> float:
        """The mean travel of both wheels since the goal began."""
        return self.travel_m - (self.start_enc.left_m + self.start_enc.right_m) / 2

    @property
    def heading_change_rad(self) -> float:
        """The heading's change since the goal began (unwrapped)."""
        return self.odom.heading_rad - self.start_odom.heading_rad

    def end(self, reason: MotionEnd, by: str = "", source: str | None = None) -> None:
        """End the goal from outside: it sends nothing more and raises at its next step."""
        if self.ended is None:
            self.ended, self.by, self.by_source = reason, by, source
        self.sub.close()  # wakes a goal waiting for counts

    async def next(self, *, checks: bool = True) -> None:
        """Wait for the next control tick's counts (the newest, if several wait).

        Raises:
            _Ended: Ended from outside (another command, a guard), past the deadline,
                no counts for :data:`FEEDBACK_GAP_S`, the Robot closed; with ``checks``,
                the watchdog tripped.
        """
        loop = asyncio.get_running_loop()
        if self.ended is not None:
            raise _Ended(self.ended)
        now = loop.time()
        until = min(self.deadline_s, now + FEEDBACK_GAP_S)
        try:
            # asyncio.timeout, not wait_for, which on 3.11 can swallow a cancellation
            # arriving with a sample.
            async with asyncio.timeout_at(until):
                enc = await anext(self.sub)
        except TimeoutError:
            if loop.time() >= self.deadline_s:
                raise _Ended("timeout") from None
            raise _Ended(self.goals.silence_reason()) from None
        except StopAsyncIteration:
            raise _Ended(self.ended or "closed") from None
        if self.ended is not None:
            raise _Ended(self.ended)
        while (newer := self.sub.get_nowait()) is not None:
            enc = newer
        odom = self.goals.host.latest("wheel_odom")
        self.enc = enc
        if odom is not None:  # published with every wheel_encoder sample
            self.odom = odom
        if checks:
            self._check()

    def _check(self) -> None:
        tripped = self.goals.host.state.watchdog_tripped
        if tripped and self.commanded and self.watchdog_clear:
            raise _Ended("watchdog")
        self.watchdog_clear = self.watchdog_clear or not tripped
        if self.fault is not None:  # the slip guard (a stall ends the goal at once)
            raise _Ended("slipped")

    def command(self, linear_mps: float, angular_radps: float) -> None:
        """The goal's own drive command (it does not preempt the goal); none once ended."""
        if self.ended is not None:
            raise _Ended(self.ended)
        self.goals.own(lambda: self.goals.host.drive(linear_mps, angular_radps, source=self.source))
        self.commanded = True

    def stop(self) -> None:
        """The goal's own stop; best effort (the Robot may be closing or released)."""
        with contextlib.suppress(OhmniError):
            self.goals.own(lambda: self.goals.host.stop(source=self.source))
        self.commanded = False

    async def settle(self) -> None:
        """Wait until both wheel counts hold still (the rule of
        :func:`ohmni_tb.safety.stop_wheels`), within the ramp down + ``stop_timeout_s``.

        Raises:
            _Ended: Ended from outside, or the Robot closed.
            StopNotConfirmedError: Not at rest in time: the robot may still be moving.
        """
        loop = asyncio.get_running_loop()
        config = self.goals.host.config
        ramp_s = self.top_speed / min(config.linear_decel_mps2, config.angular_decel_radps2)
        started = loop.time()
        limit = started + ramp_s + config.stop_timeout_s
        windows = (SettleWindow(), SettleWindow())
        reads = 0
        counts: tuple[int, int] | None = None
        saved, self.deadline_s = self.deadline_s, limit
        try:
            while True:
                try:
                    await self.next(checks=False)
                except _Ended as end:
                    if end.reason in ("preempted", "closed", "stalled"):
                        raise
                    break  # the time is up, or the counts stopped: not confirmed
                reads += 1
                counts = (self.enc.left_raw, self.enc.right_raw)
                for window, count in zip(windows, counts, strict=True):
                    window.add(count, self.enc.stamp_s, DEFAULT_TOLERANCE_TICKS)
                if all(window.settled(DEFAULT_SETTLE_S) for window in windows):
                    return
        finally:
            self.deadline_s = saved
        reason = (
            "no wheel counts arrived"
            if reads == 0
            else f"the wheel counts did not hold still ({reads} wheel_encoder samples)"
        )
        report = StopReport(False, 1, reads, 0, loop.time() - started, counts)
        raise StopNotConfirmedError(sid=0, report=report, reason=reason)

    async def halt(self) -> None:
        """Stop and wait for the robot to rest (between the parts of a goal)."""
        self.stop()
        await self.settle()

    def result(self, reason: MotionEnd, remaining: _Remaining) -> MotionResult:
        odom = self.odom
        left_m, left_rad = remaining(odom, self.distance_m, self.heading_change_rad)
        return MotionResult(
            kind=self.kind,
            reason=reason,
            distance_m=self.distance_m,
            heading_change_rad=self.heading_change_rad,
            x_m=odom.x_m,
            y_m=odom.y_m,
            yaw_rad=odom.yaw_rad,
            remaining_m=left_m,
            remaining_rad=left_rad,
            elapsed_s=asyncio.get_running_loop().time() - self.started_s,
        )


class MotionGoals:
    """The Robot's motion goals (the module docstring): one at a time, preempted by any
    other motion command (the Robot calls :meth:`preempt` from each) and ended when the
    Robot closes (:meth:`close`).

    Args:
        host: The Robot (or what stands for it: its commands, settings and streams).
        check: Called before a goal sends anything; raises to refuse (an emergency stop
            latched, the port released, the Robot closed).
        sources: The Robot's command sources: a goal is refused while a source above its
            own drives, and holds its own live while it runs.
    """

    def __init__(
        self,
        host: MotionHost,
        *,
        check: Callable[[], None] | None = None,
        sources: GoalSources | None = None,
    ) -> None:
        self.host = host
        self._check = check
        self._sources = sources
        self._active: _Run | None = None
        self._own = False  # a goal's own command is being given

    # -- the hooks -------------------------------------------------------------------------

    def preempt(self, what: str, *, stop: bool = False, source: str | None = None) -> None:
        """Another motion command (``what``, as the error names it, from command source
        ``source`` if it has one) takes over: the running goal ends with
        :class:`~ohmni_tb.errors.MotionPreemptedError`. A goal's own commands do not count.
        ``stop``: ``what`` does not drive the wheels itself (an odometry reset), so the
        goal sets the target to zero as it ends."""
        run = self._active
        if run is not None and not self._own:
            run.end("preempted", what, source)
            if stop:
                run.stop()

    def close(self) -> None:
        """The Robot closes: the running goal ends with
        :class:`~ohmni_tb.errors.MotionAbortedError` (closing stops the wheels)."""
        run = self._active
        if run is not None:
            run.end("closed")

    def wheel_fault(self, fault: WheelFault) -> None:
        """A guard of the control loop tripped: the running goal ends with
        :class:`~ohmni_tb.errors.WheelStallError` or
        :class:`~ohmni_tb.errors.WheelSlipError`."""
        run = self._active
        if run is None or run.ended is not None or run.fault is not None:
            return
        run.fault = fault
        if fault.kind == "stall":
            run.end("stalled")  # at once: the guard has stopped the wheels
        # A slip ends the goal at its next tick, which then stops and settles.

    @property
    def active(self) -> MotionKind | None:
        """The goal under way, if any."""
        return None if self._active is None else self._active.kind

    @property
    def owning(self) -> bool:
        """Whether the command being given is the running goal's own."""
        return self._own

    def own(self, command: Callable[[], object]) -> None:
        """Give ``command`` as the running goal's own: it does not preempt the goal."""
        self._own = True
        try:
            command()
        finally:
            self._own = False

    def silence_reason(self) -> MotionEnd:
        """Why the wheel counts stopped: the link, or something else."""
        try:
            link = self.host.state.link
        except OhmniError:
            return "no_counts"
        return "no_counts" if link is Link.CONNECTED else "link_lost"

    # -- the goals -------------------------------------------------------------------------

    async def drive_distance(
        self,
        distance_m: float,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Drive straight ``distance_m`` by odometry (negative: backward) and stop there,
        under command source ``source``.

        See :meth:`ohmni_tb.robot.Robot.drive_distance`.
        """
        distance = _within("distance_m", distance_m, -MAX_DISTANCE_M, MAX_DISTANCE_M, "m")
        config = self.host.config
        speed = _speed(
            "speed_mps",
            speed_mps,
            default=DEFAULT_LINEAR_MPS,
            low=MIN_GOAL_LINEAR_MPS,
            top=config.top_linear_mps(),
        )
        timeout = _timeout(
            timeout_s,
            goal_timeout_s(distance, speed, config.linear_accel_mps2, config.linear_decel_mps2),
        )

        async def body(run: _Run) -> None:
            run.top_speed = speed
            await self._axis(run, linear=True, goal=distance, top=speed)

        def remaining(_odom: WheelOdomSample, went: float, _turned: float) -> tuple[float, float]:
            return distance - went, 0.0

        def goal_text() -> str:
            return f"drive_distance({distance:+.3f} m)"

        return await self._run(
            "drive_distance", lambda _: timeout, body, remaining, goal_text, source=source
        )

    async def rotate(
        self,
        angle_rad: float,
        *,
        speed_radps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Turn on the spot ``angle_rad`` by odometry (positive: counter-clockwise), under
        command source ``source``.

        See :meth:`ohmni_tb.robot.Robot.rotate`.
        """
        angle = _within("angle_rad", angle_rad, -MAX_ANGLE_RAD, MAX_ANGLE_RAD, "rad")
        config = self.host.config
        speed = _speed(
            "speed_radps",
            speed_radps,
            default=DEFAULT_ANGULAR_RADPS,
            low=MIN_GOAL_ANGULAR_RADPS,
            top=config.top_angular_radps(),
            unit="rad/s",
        )
        timeout = _timeout(
            timeout_s,
            goal_timeout_s(angle, speed, config.angular_accel_radps2, config.angular_decel_radps2),
        )

        async def body(run: _Run) -> None:
            run.top_speed = speed
            await self._axis(run, linear=False, goal=angle, top=speed)

        def remaining(_odom: WheelOdomSample, _went: float, turned: float) -> tuple[float, float]:
            return 0.0, angle - turned

        def goal_text() -> str:
            return f"rotate({math.degrees(angle):+.1f}°)"

        return await self._run(
            "rotate", lambda _: timeout, body, remaining, goal_text, source=source
        )

    async def go_to(
        self,
        x_m: float,
        y_m: float,
        yaw_rad: float | None = None,
        *,
        speed_mps: float | None = None,
        timeout_s: float | None = None,
        source: str | None = None,
    ) -> MotionResult:
        """Go to the point (``x_m``, ``y_m``) of the odometry frame, then turn to
        ``yaw_rad`` if given, under command source ``source``. See
        :meth:`ohmni_tb.robot.Robot.go_to`."""
        x = _within("x_m", x_m, -MAX_POSE_M, MAX_POSE_M, "m")
        y = _within("y_m", y_m, -MAX_POSE_M, MAX_POSE_M, "m")
        yaw = (
            None if yaw_rad is None else _within("yaw_rad", yaw_rad, -MAX_POSE_M, MAX_POSE_M, "rad")
        )
        config = self.host.config
        speed = _speed(
            "speed_mps",
            speed_mps,
            default=DEFAULT_LINEAR_MPS,
            low=MIN_GOAL_LINEAR_MPS,
            top=config.top_linear_mps(),
        )
        turn_speed = min(DEFAULT_ANGULAR_RADPS, config.top_angular_radps())
        if timeout_s is not None:
            _timeout(timeout_s, 0.0)

        def timeout_from(odom: WheelOdomSample) -> float:
            # Checked on the first counts of the goal, before anything is sent.
            dx, dy = x - odom.x_m, y - odom.y_m
            distance = math.hypot(dx, dy)
            if distance > MAX_DISTANCE_M:
                raise OutOfRangeError(
                    f"go_to's distance from the pose ({odom.x_m:.3f}, {odom.y_m:.3f}) m",
                    round(distance, 3),
                    0,
                    MAX_DISTANCE_M,
                    "m",
                )
            face = _wrap(math.atan2(dy, dx) - odom.yaw_rad) if distance > 0 else 0.0
            last = 0.0 if yaw is None else _wrap(yaw - odom.yaw_rad - face)
            plan = goal_timeout_s(
                distance, speed, config.linear_accel_mps2, config.linear_decel_mps2
            )
            for turn in (face, last):
                plan += goal_timeout_s(
                    turn, turn_speed, config.angular_accel_radps2, config.angular_decel_radps2
                )
            return _timeout(timeout_s, plan)

        async def body(run: _Run) -> None:
            run.top_speed = max(speed, turn_speed * config.wheel_separation_m / 2)
            # Judged at rest: the drive's own run-out is part of where it ends.
            while math.hypot(x - run.odom.x_m, y - run.odom.y_m) > GO_TO_TOLERANCE_M:
                odom = run.odom
                face = _wrap(math.atan2(y - odom.y_m, x - odom.x_m) - odom.yaw_rad)
                if abs(face) > FACE_TOLERANCE_RAD:
                    await self._axis(run, linear=False, goal=face, top=turn_speed)
                    await run.halt()
                await self._drive_to(run, x, y, speed, config)
                await run.halt()
            if yaw is not None:
                turn = _wrap(yaw - run.odom.yaw_rad)
                if abs(turn) > GOAL_TOLERANCE_RAD:
                    await self._axis(run, linear=False, goal=turn, top=turn_speed)

        def remaining(odom: WheelOdomSample, _went: float, _turned: float) -> tuple[float, float]:
            left_rad = 0.0 if yaw is None else _wrap(yaw - odom.yaw_rad)
            return math.hypot(x - odom.x_m, y - odom.y_m), left_rad

        def goal_text() -> str:
            towards = "" if yaw is None else f", yaw {math.degrees(yaw):+.1f}°"
            return f"go_to({x:+.3f} m, {y:+.3f} m{towards})"

        return await self._run("go_to", timeout_from, body, remaining, goal_text, source=source)

    # -- running a goal ----------------------------------------------------------------------

    async def _run(
        self,
        kind: MotionKind,
        timeout_from: Callable[[WheelOdomSample], float],
        body: Callable[[_Run], Awaitable[None]],
        remaining: _Remaining,
        goal_text: Callable[[], str],
        *,
        source: str | None = None,
    ) -> MotionResult:
        """Start a goal on fresh counts, run ``body``, stop, and say how it ended.

        Nothing is sent before the first counts came and every check passed.
        """
        if self._check is not None:
            self._check()
        sources = self._sources if source is not None else None
        if sources is not None and source is not None:
            sources.check(source, kind)
        for stream in ("wheel_encoder", "wheel_odom"):
            if not self.host.stats().streams[stream].enabled:
                raise StateError(
                    f"a motion goal steers by the {stream} stream, which is off: "
                    f"robot.enable_stream({stream!r}) first"
                )
        started = asyncio.get_running_loop().time()
        sub = self.host.subscribe("wheel_encoder", maxlen=_QUEUE)
        try:
            try:
                async with asyncio.timeout(FEEDBACK_GAP_S):
                    enc = await anext(sub)
            except (TimeoutError, StopAsyncIteration):
                why: MotionEnd = "closed" if sub.closed else self.silence_reason()
                raise _abort(kind, why, goal_text(), self.host, remaining, started) from None
            odom = self.host.latest("wheel_odom")
            if odom is None:
                raise _abort(kind, "no_counts", goal_text(), self.host, remaining, started)
            timeout = timeout_from(odom)  # may refuse (go_to's distance): nothing sent
            if sources is not None and source is not None:
                # Again, with no wait before the goal starts: a higher source may have
                # taken over while the first counts came.
                sources.check(source, kind)
            self.preempt(kind, source=source)  # a goal is a motion command too
            run = _Run(self, kind, sub=sub, enc=enc, odom=odom, started_s=started, source=source)
            run.timeout_s = timeout
            run.deadline_s = started + timeout
            self._active = run
            if sources is not None and source is not None:
                sources.hold(source)
            try:
                reason = await self._steer(run, body, remaining, goal_text)
            except BaseException:
                # A cancellation (or an error): the target goes to zero now and the
                # wheels ramp down at the deceleration limits; nothing here waits.
                if run.ended is None:
                    run.stop()
                raise
            finally:
                if self._active is run:
                    self._active = None
                if sources is not None and source is not None:
                    sources.release(source)
        finally:
            sub.close()
        result = run.result(reason, remaining)
        if reason == "arrived":
            return result
        raise _error(result, run, goal_text())

    @staticmethod
    async def _steer(
        run: _Run,
        body: Callable[[_Run], Awaitable[None]],
        remaining: _Remaining,
        goal_text: Callable[[], str],
    ) -> MotionEnd:
        """Run ``body``; stop and wait for rest as the end asks; why it ended."""
        reason: MotionEnd
        try:
            await body(run)
            reason = "arrived"
        except _Ended as end:
            reason = end.reason
        if reason in _STOPS:
            run.stop()
        if reason in _SETTLES:
            try:
                await run.settle()
            except _Ended as end:  # preempted or closed while coming to rest
                reason = end.reason
            except StopNotConfirmedError as exc:
                if reason == "arrived":
                    raise
                # The stall or the timeout is why it stopped: say both.
                raise exc from _error(run.result(reason, remaining), run, goal_text())
        return reason

    async def _axis(self, run: _Run, *, linear: bool, goal: float, top: float) -> None:
        """Drive straight (``linear``) or turn on the spot ``goal`` (m or rad, signed) from
        where the robot is, slowing on the braking curve; return once there (still moving
        at the crawl: the caller stops)."""
        config = self.host.config
        sign = 1.0 if goal >= 0 else -1.0
        target = abs(goal)
        if linear:
            floor = min(MIN_GOAL_LINEAR_MPS, top)
            plan_decel = config.linear_decel_mps2 * PLAN_DECEL_SHARE
            tolerance = GOAL_TOLERANCE_M
        else:
            floor = min(MIN_GOAL_ANGULAR_RADPS, top)
            plan_decel = config.angular_decel_radps2 * PLAN_DECEL_SHARE
            tolerance = GOAL_TOLERANCE_RAD
        start_travel = run.travel_m
        start_heading = run.odom.heading_rad
        while True:
            if linear:
                done = sign * (run.travel_m - start_travel)
                speed = sign * (run.enc.left_mps + run.enc.right_mps) / 2
            else:
                done = sign * (run.odom.heading_rad - start_heading)
                speed = sign * run.odom.angular_radps
            # The wheels trail the command: they run on a little at the speed they have.
            ahead = max(speed, 0.0)
            if target - done - ahead * STOP_LEAD_S <= tolerance:
                return
            left = max(target - done - ahead * PROFILE_LEAD_S, 0.0)
            command = sign * max(floor, min(top, math.sqrt(2 * plan_decel * left)))
            if linear:
                run.command(command, 0.0)
            else:
                run.command(0.0, command)
            await run.next()

    async def _drive_to(
        self, run: _Run, x: float, y: float, top: float, config: RobotConfig
    ) -> None:
        """Drive forward to the point (``x``, ``y``), steering toward it, slowing on the
        braking curve; return once the distance left along the heading is covered."""
        floor = min(MIN_GOAL_LINEAR_MPS, top)
        plan_decel = config.linear_decel_mps2 * PLAN_DECEL_SHARE
        while True:
            odom = run.odom
            dx, dy = x - odom.x_m, y - odom.y_m
            distance = math.hypot(dx, dy)
            error = _wrap(math.atan2(dy, dx) - odom.yaw_rad) if distance > 0 else 0.0
            along = distance * math.cos(error)
            speed = (run.enc.left_mps + run.enc.right_mps) / 2
            ahead = max(speed, 0.0)
            if along - ahead * STOP_LEAD_S <= GOAL_TOLERANCE_M:
                return
            left = max(along - ahead * PROFILE_LEAD_S, 0.0)
            linear = max(floor, min(top, math.sqrt(2 * plan_decel * left)))
            angular = 0.0
            if distance > HEADING_HOLD_M:
                angular = max(
                    -HEADING_MAX_RADPS, min(HEADING_MAX_RADPS, HEADING_GAIN_PER_S * error)
                )
            run.command(linear, angular)
            await run.next()


# -- helpers -----------------------------------------------------------------------------------


def _speed(
    name: str, value: float | None, *, default: float, low: float, top: float, unit: str = "m/s"
) -> float:
    """The goal's speed: ``value`` checked against ``low..top``, else the default within
    the limit."""
    if value is None:
        return min(default, top)
    return _within(name, value, min(low, top), top, unit)


def _within(name: str, value: float, low: float, high: float, unit: str) -> float:
    """``value`` as a float if it is a number in ``low..high``; the error names it as given.

    Raises:
        InvalidArgumentError: Not a number, NaN or infinite.
        OutOfRangeError: Outside ``low..high``.
    """
    number(name, value, unit)
    return bounded(name, value, low, high, unit)


def _timeout(value: float | None, planned: float) -> float:
    if value is None:
        return planned
    check_seconds("timeout_s", value, 0.0, MAX_TIMEOUT_S)
    return float(value)


def _wrap(angle: float) -> float:
    return math.atan2(math.sin(angle), math.cos(angle))


def _abort(  # noqa: PLR0917  # one private call site, in the order of the message
    kind: MotionKind,
    reason: MotionEnd,
    goal: str,
    host: MotionHost,
    remaining: _Remaining,
    started: float,
) -> MotionAbortedError:
    """The error of a goal that could not start: nothing was sent."""
    odom = host.latest("wheel_odom")
    pose = (math.nan,) * 3 if odom is None else (odom.x_m, odom.y_m, odom.yaw_rad)
    left = (math.nan, math.nan) if odom is None else remaining(odom, 0.0, 0.0)
    result = MotionResult(
        kind=kind,
        reason=reason,
        distance_m=0.0,
        heading_change_rad=0.0,
        x_m=pose[0],
        y_m=pose[1],
        yaw_rad=pose[2],
        remaining_m=left[0],
        remaining_rad=left[1],
        elapsed_s=asyncio.get_running_loop().time() - started,
    )
    why = {
        "closed": "the Robot closed",
        "link_lost": "the link is lost",
    }.get(reason, f"no wheel counts came within {FEEDBACK_GAP_S:g} s")
    return MotionAbortedError(f"{goal} did not start: {why}; nothing was sent", result=result)


def _went(result: MotionResult) -> str:
    if result.kind == "rotate":
        return f"turned {math.degrees(result.heading_change_rad):+.1f}°"
    if result.kind == "drive_distance":
        return f"went {result.distance_m:+.3f} m"
    return (
        f"at ({result.x_m:+.3f} m, {result.y_m:+.3f} m, {math.degrees(result.yaw_rad):+.1f}°), "
        f"{result.remaining_m:.3f} m from the point"
    )


def _error(result: MotionResult, run: _Run, goal: str) -> MotionError:
    """The error of a goal that ended short of its goal."""
    went = _went(result)
    reason = result.reason
    if reason == "preempted":
        by = run.by_source
        higher = by is not None and run.source is not None and by != run.source
        whence = f" of command source {by!r}" if higher else ""
        return MotionPreemptedError(
            f"{goal} was preempted by {run.by}(){whence} after it {went} by odometry: the "
            "newer command stands",
            result=result,
            by=run.by,
            source=by,
        )
    if reason == "timeout":
        if result.kind == "drive_distance":
            goal_m = result.distance_m + result.remaining_m
            went = f"went {result.distance_m:+.3f} m of {goal_m:+.3f} m"
        elif result.kind == "rotate":
            turned = math.degrees(result.heading_change_rad)
            of = math.degrees(result.heading_change_rad + result.remaining_rad)
            went = f"went {turned:+.1f}° of {of:+.1f}°"
        return MotionTimeoutError(
            f"the goal was not reached within {run.timeout_s:.1f} s: {went} by odometry; "
            "the robot is stopped",
            result=result,
            timeout_s=run.timeout_s,
        )
    fault = run.fault
    if reason == "stalled" and fault is not None:
        names = fault.names
        wheels = " and ".join(names)
        pwm = " and ".join(map(str, fault.pwm))
        return WheelStallError(
            f"{goal}: the {wheels} wheel{'s' if len(names) > 1 else ''} did not turn for "
            f"{fault.duration_s:.2f} s driven at PWM {pwm} (an obstacle? on a new robot, "
            "boards that take another wheel command: `ohmni probe --allow-motion`); the "
            f"wheels' power is cut, after it {went} by odometry",
            result=result,
            wheels=names,
            pwm=fault.pwm,
            stalled_s=fault.duration_s,
        )
    if reason == "slipped" and fault is not None:
        (name,) = fault.names
        return WheelSlipError(
            f"{goal}: the {name} wheel ran at {fault.measured_mps[0]:+.3f} m/s, set to "
            f"{fault.setpoint_mps[0]:+.3f} m/s, off the commanded curve for "
            f"{fault.duration_s:.2f} s (slipping, lifted or dragging?): the odometry no "
            f"longer follows the ground; the robot is stopped, after it {went} by odometry",
            result=result,
            wheel=name,
            setpoint_mps=fault.setpoint_mps[0],
            measured_mps=fault.measured_mps[0],
            slipped_s=fault.duration_s,
        )
    why = {
        "watchdog": "the motion watchdog tripped (the goal's commands came too late: a "
        "blocked event loop?)",
        "link_lost": "the link to the robot was lost",
        "no_counts": f"no wheel counts came for {FEEDBACK_GAP_S:g} s (is a drive board "
        "silent? `ohmni status`)",
        "closed": "the Robot closed",
        "stalled": "a wheel stalled",
        "slipped": "the wheels ran off the commanded curve",
    }[reason]
    stopped = "" if reason == "closed" else "; the target is zero"
    return MotionAbortedError(
        f"{goal} ended: {why}, after it {went} by odometry{stopped}", result=result
    )
