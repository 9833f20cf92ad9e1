"""Whole profiles of the acceleration limiter, and the wheel saturation's turn radius.

Properties over many steps (where tests/control/test_limiter.py checks single steps and
worked examples): speeding up uses the acceleration limit and braking the braking limit in
either direction of travel, so a reversal takes the braking time to zero plus the
acceleration time beyond it, however the two limits compare; the target is reached and
held. The wheel saturation scales both wheels by one factor, so the robot drives the same
circle, only slower.
"""

from __future__ import annotations

import itertools
import math

from hypothesis import given, settings
from hypothesis import strategies as st

from ohmni_tb.control import (
    AccelLimits,
    DiffDrive,
    Twist,
    TwistLimiter,
    WheelSpeeds,
    saturate_wheel_speeds,
)

#: Float slack for sums of steps.
EPS = 1e-9

rates = st.floats(0.1, 5.0)
speeds_mps = st.floats(-1.0, 1.0)


def steps_needed(start: float, target: float, limits: AccelLimits, dt_s: float) -> int:
    """Steps an exact limiter takes: braking toward zero (or toward a target on the same
    side), then speeding up beyond it; +1 for the rounding of the last partial step."""
    if start * target >= 0.0 and abs(target) <= abs(start):
        seconds = abs(start - target) / limits.max_decel
    elif start * target >= 0.0:
        seconds = abs(target - start) / limits.max_accel
    else:
        seconds = abs(start) / limits.max_decel + abs(target) / limits.max_accel
    return math.ceil(seconds / dt_s - EPS) + 1


@settings(max_examples=100, deadline=None)
@given(
    accel=rates,
    decel=rates,
    angular_accel=rates,
    angular_decel=rates,
    start=speeds_mps,
    target=speeds_mps,
    dt_s=st.floats(0.005, 0.1),
)
def test_profiles_keep_the_limits_in_both_directions_and_reach_the_target(
    *,
    accel: float,
    decel: float,
    angular_accel: float,
    angular_decel: float,
    start: float,
    target: float,
    dt_s: float,
) -> None:
    linear = AccelLimits(accel, decel)
    angular = AccelLimits(angular_accel, angular_decel)
    limiter = TwistLimiter(linear, angular, initial=Twist(start, -start))
    wanted = Twist(target, -target)
    profile = [limiter.current]
    steps = max(
        steps_needed(start, target, linear, dt_s), steps_needed(-start, -target, angular, dt_s)
    )
    profile += [limiter.step(wanted, dt_s) for _ in range(steps)]
    for axis, limits, goal in (
        ("linear_mps", linear, target),
        ("angular_radps", angular, -target),
    ):
        speeds = [getattr(twist, axis) for twist in profile]
        for before, after in itertools.pairwise(speeds):
            change = after - before
            if before * after < 0.0:
                # Through zero inside a step: brake to zero, speed up the rest of it.
                braking_s = abs(before) / limits.max_decel
                assert braking_s <= dt_s + EPS
                assert abs(after) <= limits.max_accel * (dt_s - braking_s) + EPS
            elif abs(after) > abs(before):  # speeding up, forward or backward
                assert abs(change) <= limits.max_accel * dt_s * (1 + EPS)
            else:  # braking, forward or backward
                assert abs(change) <= limits.max_decel * dt_s * (1 + EPS)
            # Never past the target, never a step away from it.
            assert (goal - after) * (goal - before) >= 0.0
        # Reached in the time the braking and acceleration limits allow, no later (a
        # limiter that swapped the limits when backing up would take longer one way).
        assert speeds[-1] == goal


@settings(max_examples=200, deadline=None)
@given(st.floats(-3.0, 3.0), st.floats(-3.0, 3.0), st.floats(0.05, 2.0))
def test_wheel_saturation_keeps_the_turn_radius(left: float, right: float, top: float) -> None:
    asked = WheelSpeeds(left, right)
    driven = saturate_wheel_speeds(asked, top)
    fastest = max(abs(left), abs(right))
    assert max(abs(driven.left_mps), abs(driven.right_mps)) <= top * (1 + EPS)
    if fastest <= top:
        assert driven == asked
        return
    # One factor for both wheels: the faster one at the limit, the ratio kept.
    scale = top / fastest
    assert math.isclose(driven.left_mps, left * scale, rel_tol=1e-12, abs_tol=1e-15)
    assert math.isclose(driven.right_mps, right * scale, rel_tol=1e-12, abs_tol=1e-15)
    # So the body drives the same circle: radius v/ω unchanged (or both straight/spinning).
    drive = DiffDrive()
    before, after = drive.twist(asked), drive.twist(driven)
    assert math.isclose(
        before.linear_mps * after.angular_radps,
        after.linear_mps * before.angular_radps,
        rel_tol=1e-9,
        abs_tol=1e-12,
    )
