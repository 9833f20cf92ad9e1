"""Acceleration limits with separate acceleration and deceleration.

"Acceleration" means the speed's *magnitude* grows, "deceleration" that it shrinks, in
either direction of travel. So backing up speeds up at the acceleration limit and a
reversing robot brakes at the deceleration limit (ROS1's diff_drive_controller limited the
*signed* velocity, which swapped the two when driving backwards).

When a command reverses the direction, one step may brake through zero: the limiter brakes
at the deceleration limit until the speed reaches zero, then spends the rest of the step
speeding up the other way at the acceleration limit. It never overshoots the target.

Worked example, 50 Hz, accel 1 m/s², decel 2 m/s², from +0.5 m/s to -0.5 m/s: the speed
falls 0.04 m/s a step to +0.02 m/s after step 12; step 13 brakes 10 ms to zero and speeds
up 10 ms backwards, ending at -0.01 m/s; then -0.02 m/s a step, reaching -0.5 m/s at step 38.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ohmni_tb._checks import finite, integer, positive, positive_or_inf
from ohmni_tb.control.kinematics import Twist
from ohmni_tb.errors import InvalidArgumentError

__all__ = [
    "DELTA_VELO_RAW_MAX",
    "DELTA_VELO_RAW_MIN",
    "MPS2_PER_DELTA_VELO_RAW",
    "AccelLimits",
    "TwistLimiter",
    "accel_from_delta_velo_raw",
    "ramp",
]

#: Slowest ramp level of tb_control's ``delta_velo_raw``.
DELTA_VELO_RAW_MIN = 1
#: Fastest ramp level of tb_control's ``delta_velo_raw``.
DELTA_VELO_RAW_MAX = 10
#: m/s² per ``delta_velo_raw`` level. tb_control's raw speed setpoint spans -200..200 for
#: ±1 m/s (5 mm/s a unit); one level is read as one raw unit per 50 Hz tick, i.e.
#: 5 mm/s / 20 ms = 0.25 m/s². An assumption: the vendor does not publish the scale.
MPS2_PER_DELTA_VELO_RAW = 0.25


@dataclass(frozen=True, slots=True)
class AccelLimits:
    """Rate limits of one axis, in the axis unit per second (m/s² or rad/s²).

    ``math.inf`` turns a limit off.

    Attributes:
        max_accel: Largest rate while the speed's magnitude grows.
        max_decel: Largest rate while the speed's magnitude shrinks (braking).
    """

    max_accel: float
    max_decel: float

    def __post_init__(self) -> None:
        positive_or_inf("max_accel", self.max_accel)
        positive_or_inf("max_decel", self.max_decel)


def ramp(current: float, target: float, dt_s: float, limits: AccelLimits) -> float:
    """Move a speed toward a target for one step, within acceleration limits.

    Args:
        current: The speed now.
        target: The speed wanted.
        dt_s: Length of the step, > 0.
        limits: Acceleration and deceleration limits.

    Returns:
        The speed at the end of the step; exactly ``target`` once it is reachable.

    Raises:
        InvalidArgumentError: An argument is NaN or infinite, or ``dt_s <= 0``.
    """
    # Finite floats pass without a call (x - x is 0.0 for those only); anything else gets
    # the full check, and its error.
    if type(current) is not float or current - current:
        finite("current", current)
    if type(target) is not float or target - target:
        finite("target", target)
    if type(dt_s) is not float or not 0.0 < dt_s < math.inf:
        positive("dt_s", dt_s, "s")
    given: object = limits  # typed, but callers may pass a number
    if not isinstance(given, AccelLimits):
        raise InvalidArgumentError(f"limits must be AccelLimits, not {type(given).__name__}")
    if target == current:
        return target
    if current == 0.0 or (target > current > 0.0) or (target < current < 0.0):
        return _toward(current, target, limits.max_accel * dt_s)
    if target * current >= 0.0:  # braking, but not through zero
        return _toward(current, target, limits.max_decel * dt_s)
    time_to_stop_s = abs(current) / limits.max_decel
    if time_to_stop_s >= dt_s:
        return _toward(current, 0.0, limits.max_decel * dt_s)
    return _toward(0.0, target, limits.max_accel * (dt_s - time_to_stop_s))


class TwistLimiter:
    """Acceleration limits on a body velocity, per axis.

    The linear and angular speeds are ramped independently, each with its own
    acceleration and deceleration.

    Args:
        linear: Linear limits, m/s² (default 0.5 up, 1.0 down).
        angular: Angular limits, rad/s² (default 2.0 up, 4.0 down).
        initial: The velocity to start from (default: standing).
    """

    def __init__(
        self,
        linear: AccelLimits | None = None,
        angular: AccelLimits | None = None,
        initial: Twist | None = None,
    ) -> None:
        self.linear = linear if linear is not None else AccelLimits(0.5, 1.0)
        self.angular = angular if angular is not None else AccelLimits(2.0, 4.0)
        self._current = initial if initial is not None else Twist()

    @property
    def current(self) -> Twist:
        """The latest limited velocity."""
        return self._current

    def step(self, target: Twist, dt_s: float) -> Twist:
        """Advance one step toward ``target``.

        Args:
            target: The requested velocity.
            dt_s: Time since the previous step, measured by the caller; > 0.

        Returns:
            The limited velocity to command now.

        Raises:
            InvalidArgumentError: ``target`` is not a :class:`Twist`, or ``dt_s`` is bad.
        """
        given: object = target  # typed, but callers may pass a number
        if not isinstance(given, Twist):
            raise InvalidArgumentError(f"target must be a Twist, not {type(given).__name__}")
        self._current = Twist(
            ramp(self._current.linear_mps, target.linear_mps, dt_s, self.linear),
            ramp(self._current.angular_radps, target.angular_radps, dt_s, self.angular),
        )
        return self._current

    def reset(self, twist: Twist | None = None) -> None:
        """Restart from ``twist`` (default: standing), e.g. after a measured stop."""
        self._current = twist if twist is not None else Twist()


def accel_from_delta_velo_raw(level: int) -> float:
    """The acceleration, m/s², of tb_control's ``delta_velo_raw`` ramp level.

    Level 1 (slow) is 0.25 m/s², level 10 (fast) 2.5 m/s², linear in between
    (:data:`MPS2_PER_DELTA_VELO_RAW` per level).

    Args:
        level: An integer 1..10.

    Raises:
        OutOfRangeError: ``level`` is not an integer in 1..10.
    """
    integer("delta_velo_raw", level, DELTA_VELO_RAW_MIN, DELTA_VELO_RAW_MAX)
    return level * MPS2_PER_DELTA_VELO_RAW


def _toward(value: float, target: float, max_step: float) -> float:
    """``value`` moved toward ``target`` by at most ``max_step`` (may be inf)."""
    if abs(target - value) <= max_step:
        return target
    return value + math.copysign(max_step, target - value)
