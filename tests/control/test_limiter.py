"""Acceleration limiter: reversing, braking through zero and stopping, by hand."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.control import (
    AccelLimits,
    Twist,
    TwistLimiter,
    accel_from_delta_velo_raw,
    ramp,
)
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

DT = 0.02
LIMITS = AccelLimits(max_accel=1.0, max_decel=2.0)  # 0.02 / 0.04 m/s per 50 Hz step


def _profile(start: float, target: float, steps: int, limits: AccelLimits = LIMITS) -> list[float]:
    speeds = []
    speed = start
    for _ in range(steps):
        speed = ramp(speed, target, DT, limits)
        speeds.append(speed)
    return speeds


def test_accelerating_from_rest() -> None:
    assert _profile(0.0, 0.1, 6) == pytest.approx([0.02, 0.04, 0.06, 0.08, 0.1, 0.1])


def test_stop_brakes_at_the_deceleration_limit_and_lands_on_zero() -> None:
    # 0.5 m/s at 2 m/s² stops in 0.25 s: 12 steps of 0.04, then the last 0.02.
    profile = _profile(0.5, 0.0, 14)
    assert profile[:3] == pytest.approx([0.46, 0.42, 0.38])
    assert profile[11] == pytest.approx(0.02)
    assert profile[12:] == [0.0, 0.0]


def test_stop_when_backing_up_uses_the_deceleration_limit_too() -> None:
    # ROS1 used the "acceleration" limit here because the signed speed rises.
    assert _profile(-0.5, 0.0, 14) == pytest.approx([-v for v in _profile(0.5, 0.0, 14)])
    assert _profile(-0.5, 0.0, 1) == pytest.approx([-0.46])


def test_reversing_brakes_through_zero_inside_one_step() -> None:
    # +0.5 → -0.5: brake 0.04/step to +0.02 (step 12); step 13 brakes 10 ms to zero and
    # accelerates 10 ms backwards (-0.01); then -0.02/step to -0.5 at step 38.
    profile = _profile(0.5, -0.5, 40)
    assert profile[11] == pytest.approx(0.02)
    assert profile[12] == pytest.approx(-0.01)
    assert profile[13] == pytest.approx(-0.03)
    assert profile[36] == pytest.approx(-0.49)
    assert profile[37:] == [-0.5, -0.5, -0.5]


def test_reversing_from_backwards_mirrors_forwards() -> None:
    forward = _profile(0.5, -0.5, 40)
    backward = _profile(-0.5, 0.5, 40)
    assert backward == pytest.approx([-v for v in forward])


def test_speeding_up_backwards_uses_the_acceleration_limit() -> None:
    assert _profile(-0.1, -0.2, 3) == pytest.approx([-0.12, -0.14, -0.16])


def test_braking_to_a_lower_speed_in_the_same_direction() -> None:
    assert _profile(0.5, 0.4, 4) == pytest.approx([0.46, 0.42, 0.4, 0.4])


def test_crossing_zero_exactly_at_the_end_of_a_step() -> None:
    # 0.04 m/s takes one full step to brake: nothing left to accelerate.
    assert ramp(0.04, -1.0, DT, LIMITS) == pytest.approx(0.0)


def test_unlimited_axis_jumps_to_the_target() -> None:
    assert ramp(0.5, -0.5, DT, AccelLimits(math.inf, math.inf)) == -0.5


@given(
    st.floats(-2.0, 2.0),
    st.floats(-2.0, 2.0),
    st.floats(0.001, 0.5),
)
def test_never_overshoots_and_never_exceeds_the_limits(
    current: float, target: float, dt_s: float
) -> None:
    new = ramp(current, target, dt_s, LIMITS)
    assert min(current, target) - 1e-12 <= new <= max(current, target) + 1e-12
    # Never faster than the larger limit; a reversal costs at least the braking time.
    assert abs(new - current) <= 2.0 * dt_s + 1e-12
    assert ramp(-current, -target, dt_s, LIMITS) == pytest.approx(-new, abs=1e-15)


def test_twist_limiter_ramps_each_axis_with_its_own_limits() -> None:
    limiter = TwistLimiter(AccelLimits(0.5, 1.0), AccelLimits(2.0, 4.0))
    first = limiter.step(Twist(1.0, -1.0), DT)
    assert (first.linear_mps, first.angular_radps) == pytest.approx((0.01, -0.04))
    limiter.reset(Twist(0.3, 0.5))
    braking = limiter.step(Twist(0.0, 0.0), DT)
    assert braking.linear_mps == pytest.approx(0.28)
    assert braking.angular_radps == pytest.approx(0.42)
    assert limiter.current is braking


def test_delta_velo_raw_levels_map_to_documented_accelerations() -> None:
    assert accel_from_delta_velo_raw(1) == pytest.approx(0.25)
    assert accel_from_delta_velo_raw(4) == pytest.approx(1.0)
    assert accel_from_delta_velo_raw(10) == pytest.approx(2.5)
    for bad in (0, 11, True):
        with pytest.raises(OutOfRangeError, match="delta_velo_raw"):
            accel_from_delta_velo_raw(bad)


def test_bad_values_are_rejected_by_name() -> None:
    with pytest.raises(InvalidArgumentError, match="target=nan"):
        ramp(0.0, math.nan, DT, LIMITS)
    with pytest.raises(InvalidArgumentError, match=r"dt_s=0\.0"):
        ramp(0.0, 1.0, 0.0, LIMITS)
    with pytest.raises(InvalidArgumentError, match=r"max_decel=0\.0"):
        AccelLimits(1.0, 0.0)


def test_a_tiny_speed_reversed_brakes_to_zero_then_speeds_up_at_the_acceleration_limit() -> None:
    # The product of the two speeds underflows to -0.0: the step must still be a reversal
    # (speeding up the other way at max_accel), not a braking at max_decel through zero.
    limits = AccelLimits(max_accel=1.0, max_decel=2.0)
    assert ramp(5e-324, -0.5, 0.0625, limits) == pytest.approx(-0.0625)
    assert ramp(-5e-324, 0.5, 0.0625, limits) == pytest.approx(0.0625)
