"""The jerk limit: S-curves that land on the target, reversals through zero, stops.

By hand first (50 Hz, the numbers worked out in the comments), then properties over whole
profiles: the acceleration and braking limits always hold, the jerk limit holds from a
steady start, the target is landed on exactly and never passed, and the speed never
crosses zero away from the target.
"""

from __future__ import annotations

import itertools
import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ohmni_tb.control import AccelLimits, Twist, TwistLimiter, jerk_ramp, ramp
from ohmni_tb.errors import InvalidArgumentError

DT = 0.02
#: Up 0.5 m/s², braking 1 m/s², jerk 2 m/s³: the acceleration moves 0.04 m/s² a step.
LIMITS = AccelLimits(max_accel=0.5, max_decel=1.0, max_jerk=2.0)
#: Float slack for sums of steps.
EPS = 1e-9


def profile(
    start: float, target: float, steps: int, limits: AccelLimits = LIMITS, dt_s: float = DT
) -> tuple[list[float], list[float]]:
    """Speeds and accelerations of ``steps`` steps from ``start`` at rest-steady."""
    speeds, accels = [start], [0.0]
    for _ in range(steps):
        speed, accel = jerk_ramp(speeds[-1], accels[-1], target, dt_s, limits)
        speeds.append(speed)
        accels.append(accel)
    return speeds, accels


def first_at(speeds: list[float], accels: list[float], target: float) -> int:
    """The first step that is at the target and stays (acceleration zero after it)."""
    return next(
        i for i, (v, a) in enumerate(zip(speeds, accels, strict=True)) if v == target and a == 0
    )


def allowed(before: float, after: float, accel: float, limits: AccelLimits) -> bool:
    """Whether one step's acceleration is within the acceleration and braking limits: on
    the forward side speeding up is positive, on the backward side negative; a step
    through zero brakes and speeds up with the same acceleration, within both."""
    a, d = limits.max_accel * (1 + EPS), limits.max_decel * (1 + EPS)
    if before >= 0.0 and after >= 0.0:
        return -d <= accel <= a
    if before <= 0.0 and after <= 0.0:
        return -a <= accel <= d
    return abs(accel) <= min(a, d)


# -- by hand ---------------------------------------------------------------------------------


def test_a_start_is_an_s_curve_that_lands_on_the_target() -> None:
    speeds, accels = profile(0.0, 0.5, 80)
    # The acceleration grows 0.04 m/s² a step, holds at the limit, eases off to zero.
    assert accels[1:4] == pytest.approx([0.04, 0.08, 0.12])
    assert max(accels) == pytest.approx(0.5)
    assert all(abs(b - a) <= 0.04 + EPS for a, b in itertools.pairwise(accels))
    # The ideal S-curve takes v/a + a/j = 1.0 + 0.25 s: 63 steps; a step or two more
    # for the discrete landing, never an overshoot.
    at = first_at(speeds, accels, 0.5)
    assert 63 <= at <= 66
    assert max(speeds) == 0.5
    assert all(b >= a for a, b in itertools.pairwise(speeds))
    assert speeds[at:] == [0.5] * (len(speeds) - at)


def test_without_a_jerk_limit_the_acceleration_jumps() -> None:
    speeds, accels = profile(0.0, 0.5, 60, AccelLimits(0.5, 1.0))
    assert accels[1] == pytest.approx(0.5)
    assert speeds[1:] == pytest.approx([ramp(0.0, 0.5, t * DT, LIMITS) for t in range(1, 61)])


def test_a_reversal_brakes_then_crosses_zero_within_the_acceleration_limit() -> None:
    # +0.5 → −0.5: braking (positive side, negative acceleration) may reach 1 m/s², but
    # by zero it has eased to 0.5 m/s² so backing up starts within its own limit, without
    # a jump in the acceleration.
    speeds, accels = profile(0.5, -0.5, 140)
    crossing = next(i for i, v in enumerate(speeds) if v < 0.0)
    braking = accels[1:crossing]
    assert min(braking) == pytest.approx(-1.0)
    assert accels[crossing] >= -0.5 - EPS
    assert all(abs(b - a) <= 0.04 + EPS for a, b in itertools.pairwise(accels))
    for before, after, accel in zip(speeds, speeds[1:], accels[1:], strict=False):
        assert allowed(before, after, accel, LIMITS)
    assert all(b <= a for a, b in itertools.pairwise(speeds))
    assert speeds[-1] == -0.5


def test_braking_to_zero_never_goes_past_it() -> None:
    speeds, accels = profile(0.5, 0.0, 70)
    assert min(speeds) == 0.0
    assert speeds[-1] == 0.0
    assert first_at(speeds, accels, 0.0) <= 55  # 0.5/1 + 1/2 s: 50 steps, and the landing


def test_a_target_changed_while_speeding_up_is_passed_by_at_most_a2_over_2j() -> None:
    speeds, accels = [0.0], [0.0]
    for target, steps in ((0.5, 25), (0.2, 60)):
        for _ in range(steps):
            speed, accel = jerk_ramp(speeds[-1], accels[-1], target, DT, LIMITS)
            speeds.append(speed)
            accels.append(accel)
    # At the change the speed was 0.188 m/s and accelerating at 0.5 m/s²: easing off at
    # 2 m/s³ takes 0.0625 m/s more, so it passes 0.2 m/s and comes back, smoothly.
    peak = max(speeds)
    assert 0.2 < peak <= speeds[25] + 0.5**2 / (2 * 2.0) + EPS
    assert all(abs(b - a) <= 0.04 + EPS for a, b in itertools.pairwise(accels))
    assert speeds[-1] == 0.2


def test_the_twist_limiter_applies_each_axis_jerk_limit() -> None:
    limiter = TwistLimiter(AccelLimits(0.5, 1.0, 2.0), AccelLimits(2.0, 4.0, 10.0))
    first = limiter.step(Twist(0.5, -1.0), DT)
    assert (first.linear_mps, first.angular_radps) == pytest.approx((0.04 * DT, -0.2 * DT))
    assert limiter.accel == pytest.approx((0.04, -0.2))
    limiter.reset(Twist(0.3, 0.0))
    assert limiter.accel == (0.0, 0.0)


def test_a_stop_is_not_held_back_by_the_jerk_limit() -> None:
    smooth = TwistLimiter(LIMITS, AccelLimits(2.0, 4.0, 10.0), initial=Twist(0.5, 1.0))
    eased = smooth.step(Twist(), DT)
    assert eased.linear_mps == pytest.approx(0.5 - 0.04 * DT)  # the jerk limit eases in
    stop = TwistLimiter(LIMITS, AccelLimits(2.0, 4.0, 10.0), initial=Twist(0.5, 1.0))
    braking = stop.step(Twist(), DT, jerk_limited=False)
    # The braking limits from the first step: 1 m/s², 4 rad/s².
    assert (braking.linear_mps, braking.angular_radps) == pytest.approx((0.48, 0.92))
    assert stop.accel == pytest.approx((-1.0, -4.0))
    # A drive command after the stop goes on from the braking acceleration, smoothly.
    after = stop.step(Twist(), DT)
    assert stop.accel[0] == pytest.approx(-1.0)
    assert after.linear_mps == pytest.approx(0.46)


def test_the_jerk_limit_is_off_by_default() -> None:
    assert AccelLimits(1.0, 2.0).max_jerk == math.inf
    limiter = TwistLimiter()
    assert limiter.step(Twist(1.0, 0.0), DT).linear_mps == pytest.approx(0.5 * DT)


def test_bad_values_are_rejected_by_name() -> None:
    with pytest.raises(InvalidArgumentError, match=r"max_jerk=0\.0"):
        AccelLimits(1.0, 2.0, 0.0)
    with pytest.raises(InvalidArgumentError, match="accel=nan"):
        jerk_ramp(0.0, math.nan, 1.0, DT, LIMITS)
    with pytest.raises(InvalidArgumentError, match=r"dt_s=-1\.0"):
        jerk_ramp(0.0, 0.0, 1.0, -1.0, LIMITS)
    with pytest.raises(InvalidArgumentError, match="limits must be AccelLimits"):
        jerk_ramp(0.0, 0.0, 1.0, DT, 2.0)  # type: ignore[arg-type]  # the wrong type on purpose


# -- properties ------------------------------------------------------------------------------

rates = st.floats(0.5, 4.0)
speeds_mps = st.floats(-1.0, 1.0)


@settings(max_examples=50, deadline=None)
@given(
    accel=rates,
    decel=rates,
    jerk=st.floats(1.0, 50.0),
    start=speeds_mps,
    target=speeds_mps,
    dt_s=st.floats(0.01, 0.05),
)
def test_from_a_steady_speed_every_limit_holds_and_the_target_is_landed_on(
    *, accel: float, decel: float, jerk: float, start: float, target: float, dt_s: float
) -> None:
    limits = AccelLimits(accel, decel, jerk)
    # Time enough: the change at the lower limit, plus easing in and off twice.
    steps = math.ceil(
        (abs(target - start) / min(accel, decel) + 4 * max(accel, decel) / jerk) / dt_s
    )
    speeds, accels = profile(start, target, steps + 3, limits, dt_s)
    for i in range(1, len(speeds)):
        before, after = speeds[i - 1], speeds[i]
        assert allowed(before, after, (after - before) / dt_s, limits), i
        assert abs(accels[i] - accels[i - 1]) <= jerk * dt_s * (1 + EPS) + 1e-12, i
        # Monotone toward the target, never past it.
        assert min(start, target) <= after <= max(start, target), i
        assert (target - after) * (target - before) >= 0.0, i
    at = first_at(speeds, accels, target)
    assert speeds[at:] == [target] * (len(speeds) - at)


@settings(max_examples=50, deadline=None)
@given(
    accel=rates,
    decel=rates,
    jerk=st.floats(1.0, 50.0),
    start=speeds_mps,
    targets=st.lists(st.tuples(speeds_mps, st.integers(1, 30)), min_size=1, max_size=5),
    dt_s=st.floats(0.01, 0.05),
    jitter=st.randoms(use_true_random=False),
)
def test_with_changing_targets_and_jittery_steps_the_limits_and_zero_hold(
    *,
    accel: float,
    decel: float,
    jerk: float,
    start: float,
    targets: list[tuple[float, int]],
    dt_s: float,
    jitter: random.Random,
) -> None:
    limits = AccelLimits(accel, decel, jerk)
    speed, acceleration = start, 0.0
    fastest = abs(start)
    for target, steps in targets:
        fastest = max(fastest, abs(target))
        for _ in range(steps):
            step_s = dt_s * jitter.uniform(0.7, 1.3)
            new, acceleration = jerk_ramp(speed, acceleration, target, step_s, limits)
            assert allowed(speed, new, (new - speed) / step_s, limits)
            # Through zero only toward a target across it; away from zero only toward it.
            if speed > 0.0 > new or speed < 0.0 < new:
                assert speed > 0.0 > target or speed < 0.0 < target
            if speed == 0.0 and new != 0.0:
                assert new > 0.0 < target or new < 0.0 > target
            # Never faster than the start or a target asked for, but for what a target
            # changed mid-ramp may be passed by while the acceleration eases off (as
            # jerk_ramp documents: at most a² / (2·max_jerk)).
            assert abs(new) <= fastest + max(accel, decel) ** 2 / (2.0 * jerk) + EPS
            speed = new
