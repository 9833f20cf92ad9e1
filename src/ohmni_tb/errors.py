"""Every error ohmni_tb raises, in one tree.

Catch :class:`OhmniError` to catch them all. Timeouts are also :class:`TimeoutError` and
bad arguments are also :class:`ValueError`, so code that knows only the built-ins still
catches the right thing::

    OhmniError
    ├── TransportError              the byte link failed (port missing, unplugged, I/O error)
    │   └── TransportClosedError    the link is closed, or the peer went away
    ├── ProtocolError               bytes arrived that break the protocol
    │   └── MalformedReplyError     a reply whose layout does not fit its request
    ├── DeviceError                 a device on the bus misbehaved          (.sid)
    │   ├── BusTimeoutError         no reply in time    (+ TimeoutError)    (.sid, .cmd)
    │   │   └── DeviceUnavailableError  silent for a while: fails fast until it answers
    │   ├── DeviceStatusError       a reply carried error bits (.status_error, .status_detail)
    │   ├── StopNotConfirmedError   the wheels were not seen to stop: they may still move
    │   │                                                           (.sid, .report)
    │   └── PositionError           a servo or the neck did not get to its target: stalled
    │       │                                           (.sid, .target_raw, .sample)
    │       └── PositionTimeoutError  not there in time, or it went silent (+ TimeoutError)
    ├── StateError                  the call does not fit the object's state
    │   ├── BusClosedError          the bus is closed
    │   ├── RobotClosedError        a command to a Robot (or client) already closed
    │   ├── DeadlineMissedError     a slot could not start before its deadline
    │   │                                                 (+ TimeoutError)  (.deadline, .late_s)
    │   ├── LeaseError              a daemon command without its control lease (.holder)
    │   ├── SourceOverriddenError   a higher command source drives: refused, nothing sent
    │   │                                               (.source, .active, .lapses_in_s)
    │   └── MotionError             a motion goal ended short of its goal          (.result)
    │       ├── MotionPreemptedError  another motion command took over             (.by)
    │       ├── MotionAbortedError  the watchdog, a lost link, no wheel counts or closing
    │       ├── MotionTimeoutError  not there within its time  (+ TimeoutError) (.timeout_s)
    │       ├── WheelStallError     a wheel driven did not turn   (.wheels, .pwm, .stalled_s)
    │       └── WheelSlipError      the wheels ran off the commanded curve
    │                                             (.wheel, .setpoint_mps, .measured_mps)
    ├── ConfigError                 bad settings or URL             (+ ValueError)
    └── InvalidArgumentError        a bad argument; nothing was sent (+ ValueError)
        └── OutOfRangeError         a value outside its allowed range (.name, .value, .low, .high)

Foreign errors (``serial.SerialException``, ``OSError``) are turned into ours at the
transport boundary with ``raise ... from exc``, so the original stays in ``__cause__``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

__all__ = [
    "BusClosedError",
    "BusTimeoutError",
    "ConfigError",
    "DeadlineMissedError",
    "DeviceError",
    "DeviceStatusError",
    "DeviceUnavailableError",
    "InvalidArgumentError",
    "LeaseError",
    "MalformedReplyError",
    "MotionAbortedError",
    "MotionError",
    "MotionPreemptedError",
    "MotionTimeoutError",
    "OhmniError",
    "OutOfRangeError",
    "PositionError",
    "PositionTimeoutError",
    "ProtocolError",
    "RobotClosedError",
    "SourceOverriddenError",
    "StateError",
    "StopNotConfirmedError",
    "TransportClosedError",
    "TransportError",
    "WheelSlipError",
    "WheelStallError",
]


#: Longest repr of a value an error message quotes in full.
_MAX_REPR = 60


def _brief(value: object) -> str:
    """``repr(value)`` for a one-line message: long ones (a huge int) are shortened."""
    try:
        text = repr(value)
    except ValueError:  # an int past the interpreter's digit limit has no repr
        return f"<{type(value).__name__} too large to show>"
    if len(text) > _MAX_REPR:
        return f"{text[: _MAX_REPR // 2]}…({len(text)} chars)"
    return text


# Defined here, beside the error that carries it, so that this module imports nothing of
# the project; ohmni_tb.safety, which makes it, exports it.
@dataclass(frozen=True, slots=True)
class StopReport:
    """What :func:`stop_wheels` did.

    Attributes:
        confirmed: Whether the counts showed the wheels standing still (always ``True``
            in a returned report; ``False`` in :attr:`StopNotConfirmedError.report`).
        stops_sent: Wheel stops handed to the port.
        reads: Count reads that were answered (each board's counted).
        missed_reads: Count reads that got no reply.
        elapsed_s: From the first stop to the confirmation (or to giving up).
        counts: The last count read from each board, left and right as the boards hold
            them (the right one mirrored), or ``None`` until both were read.
    """

    confirmed: bool
    stops_sent: int
    reads: int
    missed_reads: int
    elapsed_s: float
    counts: tuple[int, int] | None


#: Which goal a :class:`MotionResult` is of.
MotionKind = Literal["drive_distance", "rotate", "go_to"]
#: Why a motion goal ended (:attr:`MotionResult.reason`).
MotionEnd = Literal[
    "arrived",
    "preempted",
    "stalled",
    "slipped",
    "timeout",
    "watchdog",
    "link_lost",
    "no_counts",
    "closed",
]


# Here for the same reason as StopReport; ohmni_tb.robot.motion and ohmni_tb export it.
@dataclass(frozen=True, slots=True)
class MotionResult:
    """What a motion goal did (``Robot.drive_distance``, ``rotate``, ``go_to``), by odometry.

    A goal returns it when it got there; every :class:`MotionError` carries the one of a
    goal that ended short of it (:attr:`MotionError.result`).

    Attributes:
        kind: ``"drive_distance"``, ``"rotate"`` or ``"go_to"``.
        reason: Why it ended: ``"arrived"``, else ``"preempted"`` (another motion
            command), ``"stalled"`` (a wheel did not turn), ``"slipped"`` (the wheels ran
            off the commanded curve), ``"timeout"``, ``"watchdog"``,
            ``"link_lost"``, ``"no_counts"`` (the wheel counts stopped coming) or
            ``"closed"`` (the Robot closed).
        distance_m: The mean travel of both wheels since the goal began, forward positive.
        heading_change_rad: The heading's change since the goal began, counter-clockwise
            positive (unwrapped: a full turn is 2π).
        x_m: The odometry pose at the end (``wheel_odom``'s frame), x.
        y_m: The odometry pose at the end, y.
        yaw_rad: The odometry pose at the end, yaw wrapped to −π..π.
        remaining_m: What is left of the goal's distance: for ``drive_distance`` the
            distance still to go along the drive (negative: past the goal); for ``go_to``
            the straight-line distance from the pose to the point; 0 for ``rotate``.
        remaining_rad: What is left of the goal's angle: for ``rotate`` the angle still to
            turn (negative: past the goal); for ``go_to`` with ``yaw_rad`` the yaw still to
            turn, wrapped to −π..π; else 0.
        elapsed_s: From the call to the end; when the goal stopped the robot, up to the
            wheel counts showing it at rest.
    """

    kind: MotionKind
    reason: MotionEnd
    distance_m: float
    heading_change_rad: float
    x_m: float
    y_m: float
    yaw_rad: float
    remaining_m: float
    remaining_rad: float
    elapsed_s: float


class OhmniError(Exception):
    """The root of every error ohmni_tb raises."""


class TransportError(OhmniError):
    """The byte link failed: the port is missing, was unplugged, or an I/O call failed."""


class TransportClosedError(TransportError):
    """The transport is closed, or its peer closed it (end of stream)."""


class ProtocolError(OhmniError):
    """Bytes arrived that do not follow the bus protocol."""


class MalformedReplyError(ProtocolError):
    """A reply's layout does not fit the request it answers (length, address)."""


class DeviceError(OhmniError):
    """A device on the bus misbehaved.

    Attributes:
        sid: The bus id of the device.
    """

    def __init__(self, message: str, *, sid: int) -> None:
        super().__init__(message)
        self.sid = sid


class BusTimeoutError(DeviceError, TimeoutError):
    """A device did not answer in time.

    Attributes:
        sid: The bus id the request went to.
        cmd: The request's command code.
        attempts: How many times the request was sent.
        timeout_s: The per-attempt timeout.
    """

    def __init__(self, *, sid: int, cmd: int, attempts: int, timeout_s: float) -> None:
        super().__init__(
            f"no reply from sid {sid} (0x{sid:02X}) to command 0x{cmd:02X} "
            f"after {attempts} attempt(s) of {timeout_s * 1000:.1f} ms",
            sid=sid,
        )
        self.cmd = cmd
        self.attempts = attempts
        self.timeout_s = timeout_s


class DeviceUnavailableError(BusTimeoutError):
    """A device has stopped answering, so requests to it fail at once, unsent.

    After several timeouts in a row with no reply for a while, the bus opens a breaker
    for the device: one request a second goes through as a probe, and the rest fail fast
    with this error until the device answers again.

    Attributes:
        sid: The silent device.
        cmd: The command that was not sent.
        retry_in_s: When the next probe may go, from now.
    """

    def __init__(self, *, sid: int, cmd: int, silent_s: float | None, retry_in_s: float) -> None:
        since = "never answered" if silent_s is None else f"no reply for {silent_s:.1f} s"
        DeviceError.__init__(
            self,
            f"sid {sid} (0x{sid:02X}) is not answering ({since}); command 0x{cmd:02X} "
            f"not sent, next probe in {max(0.0, retry_in_s):.1f} s",
            sid=sid,
        )
        self.cmd = cmd
        self.attempts = 0
        self.timeout_s = 0.0
        self.retry_in_s = retry_in_s


class DeviceStatusError(DeviceError):
    """A device replied with error bits set.

    Attributes:
        sid: The device's bus id.
        status_error: The status error byte (RAM 48 on a HerkuleX servo).
        status_detail: The status detail byte (RAM 49).
    """

    def __init__(self, message: str, *, sid: int, status_error: int, status_detail: int) -> None:
        super().__init__(message, sid=sid)
        self.status_error = status_error
        self.status_detail = status_detail


class StopNotConfirmedError(DeviceError):
    """The wheel stop could not be confirmed: **the robot may still be moving**.

    Raised by :func:`ohmni_tb.safety.stop_wheels` once its time is up. The stops were
    sent over and over until then; what did not happen is the drive boards showing, by
    wheel counts that stopped changing, that the wheels stand still: a board did not
    answer, the counts kept changing, or the link failed.

    Attributes:
        sid: The drive board that did not confirm (0 left, 1 right; 0 when neither could).
        report: What was tried: stops sent, counts read, time spent, the last counts.
        reason: Why it was not confirmed, in words.
    """

    def __init__(self, *, sid: int, report: StopReport, reason: str) -> None:
        super().__init__(
            f"WHEEL STOP NOT CONFIRMED, the robot may still be moving: {reason}; sent "
            f"{report.stops_sent} stop(s) over {report.elapsed_s:.2f} s; {report.reads} wheel "
            f"count read(s) answered, {report.missed_reads} unanswered",
            sid=sid,
        )
        self.report = report
        self.reason = reason


class PositionError(DeviceError):
    """A servo or the worm-gear neck did not get to its target (``move(..., wait=True)``):
    the worm gear stalled (only a power cycle clears it).

    Attributes:
        sid: The servo or neck.
        target_raw: The target it was sent to.
        sample: The last feedback sample read after the move (a ``ServoSample`` or a
            ``WormNeckSample``), or ``None`` when none came.
    """

    def __init__(self, message: str, *, sid: int, target_raw: int, sample: object) -> None:
        super().__init__(message, sid=sid)
        self.target_raw = target_raw
        self.sample = sample


class PositionTimeoutError(PositionError, TimeoutError):
    """The position did not read back at the target within the time allowed, or no
    feedback came (the device went silent)."""


class StateError(OhmniError):
    """The call does not fit the object's current state."""


class BusClosedError(StateError):
    """The bus is closed; open a new one."""


class RobotClosedError(StateError):
    """A command to a Robot that is closed: nothing was sent. Open a new one."""

    def __init__(self, message: str = "the robot is closed: open a new one") -> None:
        super().__init__(message)


class DeadlineMissedError(StateError, TimeoutError):
    """A bus slot could not start before its deadline, so nothing of it was sent.

    Attributes:
        deadline: The slot's deadline (``loop.time()`` seconds).
        late_s: How far past the deadline the slot would have started.
    """

    def __init__(self, *, deadline: float, late_s: float, what: str = "slot") -> None:
        super().__init__(
            f"{what} dropped: it could not start before its deadline "
            f"({late_s * 1000:.1f} ms late); nothing was sent"
        )
        self.deadline = deadline
        self.late_s = late_s


class LeaseError(StateError):
    """A command through the daemon needs its control lease, which this client does not
    hold (nobody's, or another client's; ``RobotClient.acquire`` takes it).

    Attributes:
        holder: Who holds the lease (``host:port`` as the daemon names it), if known.
    """

    def __init__(self, message: str, *, holder: str | None = None) -> None:
        super().__init__(message)
        self.holder = holder


class SourceOverriddenError(StateError):
    """A drive command or motion goal from one command source, refused because a source
    of higher priority drives now (``robot_state``'s ``active_source``): nothing was sent
    and nothing changed. Its commands are taken again once that source lapses (no command
    from it for its timeout, its motion goal ended).

    Attributes:
        source: The source the refused command came from (``"remote"``…).
        active: The source that drives (``"local"``…).
        lapses_in_s: When ``active`` lapses if it gives no other command, seconds from the
            refusal; ``None`` while a motion goal of it runs (it lapses after the goal).
    """

    def __init__(
        self, message: str, *, source: str, active: str, lapses_in_s: float | None
    ) -> None:
        super().__init__(message)
        self.source = source
        self.active = active
        self.lapses_in_s = lapses_in_s


class MotionError(StateError):
    """A motion goal (``Robot.drive_distance``, ``rotate``, ``go_to``) ended short of its goal.

    Attributes:
        result: What the goal did up to its end, by odometry (``result.reason`` says why
            it ended).
    """

    def __init__(self, message: str, *, result: MotionResult) -> None:
        super().__init__(message)
        self.result = result


class MotionPreemptedError(MotionError):
    """Another motion command took over the goal: ``drive``, ``drive_wheels``,
    ``drive_pwm``, ``stop``, ``estop``, ``enable_controllers(False)``, ``release_port`` or
    another goal — from the goal's own command source, a higher one, or (a stop) any.
    The newer command stands: the goal sent nothing after it.

    Attributes:
        by: The command that took over (``"drive"``, ``"stop"``, ``"rotate"``…).
        source: The command source it came from (``"local"``…), or ``None`` for a command
            that has none (``release_port``, ``set_odometry``…).
    """

    def __init__(
        self, message: str, *, result: MotionResult, by: str, source: str | None = None
    ) -> None:
        super().__init__(message, result=result)
        self.by = by
        self.source = source


class MotionAbortedError(MotionError):
    """The goal could not go on: the motion watchdog tripped, the link was lost, the wheel
    counts stopped coming, or the Robot closed (``result.reason``: ``"watchdog"``,
    ``"link_lost"``, ``"no_counts"``, ``"closed"``). The wheels' target is zero."""


class MotionTimeoutError(MotionError, TimeoutError):
    """The goal was not reached within its time; the robot was stopped.

    Attributes:
        timeout_s: The time it had.
    """

    def __init__(self, message: str, *, result: MotionResult, timeout_s: float) -> None:
        super().__init__(message, result=result)
        self.timeout_s = timeout_s


class WheelStallError(MotionError):
    """A wheel driven to turn did not turn (an obstacle, a jammed motor, a board that
    does not take the wheel command): the Robot's stall guard cut the wheels' power (the
    fault ``wheel_stall:<sid>`` of ``robot_state``).

    Attributes:
        wheels: The stalled wheels, ``("left",)``, ``("right",)`` or both.
        pwm: The PWM each of them was driven with when the guard tripped, in the order of
            ``wheels`` (forward positive; empty when not known).
        stalled_s: How long they were driven without turning, s (NaN when not known).
    """

    def __init__(
        self,
        message: str,
        *,
        result: MotionResult,
        wheels: tuple[str, ...],
        pwm: tuple[int, ...] = (),
        stalled_s: float = math.nan,
    ) -> None:
        super().__init__(message, result=result)
        self.wheels = wheels
        self.pwm = pwm
        self.stalled_s = stalled_s


class WheelSlipError(MotionError):
    """The wheels ran off the curve the goal commanded for the Robot's ``slip_s`` (one
    wheel slipping or lifted, or dragging): the odometry no longer says where the robot
    is (the fault ``wheel_slip:<sid>`` of ``robot_state``). The goal set the target to
    zero; the robot is at rest.

    Attributes:
        wheel: The wheel furthest off its setpoint, ``"left"`` or ``"right"``.
        setpoint_mps: Its setpoint when the guard tripped, m/s (forward positive).
        measured_mps: Its measured speed then, m/s.
        slipped_s: How long the wheels were off the curve, s.
    """

    def __init__(
        self,
        message: str,
        *,
        result: MotionResult,
        wheel: str,
        setpoint_mps: float = math.nan,
        measured_mps: float = math.nan,
        slipped_s: float = math.nan,
    ) -> None:
        super().__init__(message, result=result)
        self.wheel = wheel
        self.setpoint_mps = setpoint_mps
        self.measured_mps = measured_mps
        self.slipped_s = slipped_s


class ConfigError(OhmniError, ValueError):
    """A setting or URL is invalid."""


class InvalidArgumentError(OhmniError, ValueError):
    """An argument is invalid. Raised before anything reaches the wire."""


class OutOfRangeError(InvalidArgumentError):
    """A value lies outside its allowed range. Raised before anything reaches the wire.

    Attributes:
        name: What the value is (``"sid"``, ``"playtime_ticks"``…).
        value: The value given.
        low: The smallest allowed value.
        high: The largest allowed value.
        unit: The unit of the value, if it has one.
    """

    def __init__(self, name: str, value: object, low: float, high: float, unit: str = "") -> None:
        suffix = f" {unit}" if unit else ""
        super().__init__(f"{name}={_brief(value)} is out of range: allowed {low}..{high}{suffix}")
        self.name = name
        self.value = value
        self.low = low
        self.high = high
        self.unit = unit
