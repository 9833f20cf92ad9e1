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

An optional jerk limit (:attr:`AccelLimits.max_jerk`, :func:`jerk_ramp`) also bounds how
fast the acceleration changes, so a drive starts and ends in an S-curve instead of a
corner. It plans ahead: the acceleration eases off in time to land on the target (and,
when reversing, to cross zero within the acceleration limit), never by overshooting it.
The acceleration and braking limits always hold; where they and the jerk limit cannot
both (a target changed too late), the jerk limit yields.
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
    "jerk_ramp",
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
    """Rate limits of one axis, in the axis unit per second (m/s² or rad/s²) and per second
    squared (m/s³ or rad/s³).

    ``math.inf`` turns a limit off.

    Attributes:
        max_accel: Largest rate while the speed's magnitude grows.
        max_decel: Largest rate while the speed's magnitude shrinks (braking).
        max_jerk: Largest change of the acceleration per second (default off). Only
            :func:`jerk_ramp` and :class:`TwistLimiter` apply it: :func:`ramp` keeps no
            acceleration to limit.
    """

    max_accel: float
    max_decel: float
    max_jerk: float = math.inf

    def __post_init__(self) -> None:
        positive_or_inf("max_accel", self.max_accel)
        positive_or_inf("max_decel", self.max_decel)
        positive_or_inf("max_jerk", self.max_jerk)


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
    # Braking, but not through zero (signs compared, not multiplied: a product of two
    # tiny speeds underflows to zero).
    if (target >= 0.0) if current > 0.0 else (target <= 0.0):
        return _toward(current, target, limits.max_decel * dt_s)
    time_to_stop_s = abs(current) / limits.max_decel
    if time_to_stop_s >= dt_s:
        return _toward(current, 0.0, limits.max_decel * dt_s)
    return _toward(0.0, target, limits.max_accel * (dt_s - time_to_stop_s))


def jerk_ramp(
    current: float, accel: float, target: float, dt_s: float, limits: AccelLimits
) -> tuple[float, float]:
    """Move a speed toward a target for one step, within acceleration, braking and jerk
    limits.

    The acceleration changes by at most ``limits.max_jerk * dt_s`` a step, and eases off in
    time for the speed to land on the target. A target across zero is a reversal: the speed
    brakes to zero (at most ``max_decel``) arriving there with no more acceleration than it
    may keep on the other side, and carries on. The speed never crosses zero, nor leaves
    it, away from the target. With ``max_jerk`` off this is :func:`ramp`.

    From a steady speed the target is never passed. A target changed while the speed still
    accelerates toward an earlier one may be passed by the speed the acceleration needs to
    ease off (at most ``a² / (2·max_jerk)``), then met from the other side. The acceleration
    and braking limits always hold; where they leave no room for the jerk limit, the jerk
    limit yields.

    Args:
        current: The speed now.
        accel: The acceleration of the previous step (0 from a standstill or a steady
            speed).
        target: The speed wanted.
        dt_s: Length of the step, > 0.
        limits: Acceleration, braking and jerk limits.

    Returns:
        The speed at the end of the step, and the acceleration of the step.

    Raises:
        InvalidArgumentError: An argument is NaN or infinite, ``dt_s <= 0``, or the step
            has no finite result.
    """
    # Finite floats pass without a call (x - x is 0.0 for those only), as in ramp().
    if type(current) is not float or current - current:
        finite("current", current)
    if type(accel) is not float or accel - accel:
        finite("accel", accel)
    if type(target) is not float or target - target:
        finite("target", target)
    if type(dt_s) is not float or not 0.0 < dt_s < math.inf:
        positive("dt_s", dt_s, "s")
    given: object = limits  # typed, but callers may pass a number
    if not isinstance(given, AccelLimits):
        raise InvalidArgumentError(f"limits must be AccelLimits, not {type(given).__name__}")
    jerk = limits.max_jerk
    if jerk == math.inf:
        speed = ramp(current, target, dt_s, limits)
        return _finite_step(speed, (speed - current) / dt_s, current, target, dt_s)
    max_accel, max_decel = limits.max_accel, limits.max_decel
    change = jerk * dt_s  # the most the acceleration may change in this step
    # Signs compared, not multiplied: a product of two tiny speeds rounds to zero.
    reversing = current > 0.0 > target or current < 0.0 < target
    if reversing:
        # Reversing: make for zero first, arriving with no more acceleration than the
        # other side allows and than can still ease off before the target.
        point = 0.0
        keep = min(max_accel, max_decel, math.sqrt(2.0 * jerk * abs(target)))
    else:
        point, keep = target, 0.0
    gap = point - current
    if gap == 0.0:
        # At the target: stay. (Landed within the jerk limit of the landing step; a
        # shorter step now may allow less change, but passing the target is worse.)
        return target, 0.0
    # Heading away from zero the speed's magnitude grows (the acceleration limit), toward
    # zero it shrinks (the braking limit).
    bound = max_accel if current == 0.0 or (current > 0.0) == (gap > 0.0) else max_decel
    peak = _peak(abs(gap), keep, jerk, dt_s)
    want = peak if peak < bound else bound  # a NaN peak (overflow) takes the bound
    if gap < 0.0:
        want = -want
    if current > 0.0:
        low, high = -max_decel, max_accel
    elif current < 0.0:
        low, high = -max_accel, max_decel
    else:
        low, high = -max_accel, max_accel
    # Land on the target when one step gets there, within every limit (through zero: at
    # most the smaller one), leaving an acceleration the next step may drop to zero.
    land = (target - current) / dt_s
    if (
        abs(land) <= change
        and accel - change <= land <= accel + change
        and (abs(land) <= min(max_accel, max_decel) if reversing else low <= land <= high)
    ):
        return target, land
    new_accel = min(max(want, accel - change), accel + change, high)
    new_accel = max(new_accel, low)  # the acceleration limits win over the jerk limit
    speed = current + new_accel * dt_s
    if current > 0.0 > speed or current < 0.0 < speed:
        if reversing:
            # Through zero within the step: braking before, speeding up after, each
            # within its own limit.
            cap = min(max_accel, max_decel)
            new_accel = min(max(new_accel, -cap), cap)
            speed = current + new_accel * dt_s
            if speed < target < current or current < target < speed:  # nor past the target
                speed, new_accel = target, land
        else:
            speed, new_accel = 0.0, -current / dt_s
    elif current == 0.0 and not (speed > 0.0 < target or speed < 0.0 > target):
        speed, new_accel = 0.0, 0.0
    return _finite_step(speed, new_accel, current, target, dt_s)


class TwistLimiter:
    """Acceleration limits on a body velocity, per axis.

    The linear and angular speeds are ramped independently, each with its own
    acceleration and deceleration, and, when a jerk limit is set, each with its own jerk
    limit (:func:`jerk_ramp`; the limiter keeps each axis' acceleration for it).

    Args:
        linear: Linear limits, m/s² (default 0.5 up, 1.0 down, no jerk limit).
        angular: Angular limits, rad/s² (default 2.0 up, 4.0 down, no jerk limit).
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
        self._accel = (0.0, 0.0)

    @property
    def current(self) -> Twist:
        """The latest limited velocity."""
        return self._current

    @property
    def accel(self) -> tuple[float, float]:
        """The latest step's accelerations, (m/s², rad/s²); kept only while a jerk limit is
        set (it is what the jerk limit limits), else (0, 0)."""
        return self._accel

    def step(self, target: Twist, dt_s: float, *, jerk_limited: bool = True) -> Twist:
        """Advance one step toward ``target``.

        Args:
            target: The requested velocity.
            dt_s: Time since the previous step, measured by the caller; > 0.
            jerk_limited: False for a step the jerk limit must not hold back: a stop's (it
                would only lengthen the stop), or a command's that plans its own speed
                profile. The acceleration and braking limits apply either way.

        Returns:
            The limited velocity to command now.

        Raises:
            InvalidArgumentError: ``target`` is not a :class:`Twist`, or ``dt_s`` is bad.
        """
        given: object = target  # typed, but callers may pass a number
        if not isinstance(given, Twist):
            raise InvalidArgumentError(f"target must be a Twist, not {type(given).__name__}")
        linear, angular = self.linear, self.angular
        current = self._current
        if linear.max_jerk == math.inf and angular.max_jerk == math.inf:
            self._current = Twist(
                ramp(current.linear_mps, target.linear_mps, dt_s, linear),
                ramp(current.angular_radps, target.angular_radps, dt_s, angular),
            )
            return self._current
        if not jerk_limited:
            v = ramp(current.linear_mps, target.linear_mps, dt_s, linear)
            w = ramp(current.angular_radps, target.angular_radps, dt_s, angular)
            self._current = Twist(v, w)
            # Kept, so a jerk-limited step after this one goes on smoothly from here.
            self._accel = (
                (v - current.linear_mps) / dt_s,
                (w - current.angular_radps) / dt_s,
            )
            return self._current
        v, linear_accel = jerk_ramp(
            current.linear_mps, self._accel[0], target.linear_mps, dt_s, linear
        )
        w, angular_accel = jerk_ramp(
            current.angular_radps, self._accel[1], target.angular_radps, dt_s, angular
        )
        self._current = Twist(v, w)
        self._accel = (linear_accel, angular_accel)
        return self._current

    def reset(self, twist: Twist | None = None) -> None:
        """Restart from ``twist`` (default: standing), e.g. after a measured stop."""
        self._current = twist if twist is not None else Twist()
        self._accel = (0.0, 0.0)


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


def _peak(gap: float, keep: float, jerk: float, dt_s: float) -> float:
    """The largest acceleration toward a point ``gap`` (> 0) away that can still ease off to
    ``keep`` at ``jerk`` by the time the speed gets there."""
    # After this step, gap − a·dt must be left for the acceleration to fall from a to
    # keep, which takes (a² − keep²) / (2·jerk) of speed on a continuous ramp (the steps
    # take a little less: the speed arrives a touch early, never late). The largest root
    # of a² + 2·jerk·dt·a − (2·jerk·gap + keep²) = 0, written without cancellation.
    change = jerk * dt_s
    c = 2.0 * jerk * gap + keep * keep
    denominator = change + math.sqrt(change * change + c)
    return c / denominator if denominator > 0.0 else 0.0


def _finite_step(
    speed: float, accel: float, current: float, target: float, dt_s: float
) -> tuple[float, float]:
    """``(speed, accel)`` if both are finite numbers, else the step's error."""
    if speed - speed or accel - accel:  # inf - inf and NaN - NaN are NaN, never 0.0
        raise InvalidArgumentError(
            f"a step from current={current!r} toward target={target!r} in dt_s={dt_s!r} s "
            "has no finite result"
        )
    return speed, accel
