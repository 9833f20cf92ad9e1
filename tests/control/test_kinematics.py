"""Diff-drive kinematics and curvature-keeping limits."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.control import (
    DiffDrive,
    Twist,
    VelocityLimits,
    WheelSpeeds,
    limit_twist,
    saturate_wheel_speeds,
)
from ohmni_tb.errors import InvalidArgumentError

DRIVE = DiffDrive()  # r 0.076 m, b 0.330 m
speeds = st.floats(-5.0, 5.0, allow_nan=False)


def test_twist_to_wheel_speeds_closed_form() -> None:
    wheels = DRIVE.wheel_speeds(Twist(0.5, 1.0))
    assert wheels.left_mps == pytest.approx(0.5 - 0.165)
    assert wheels.right_mps == pytest.approx(0.5 + 0.165)
    spin = DRIVE.wheel_speeds(Twist(0.0, -2.0))
    assert (spin.left_mps, spin.right_mps) == pytest.approx((0.33, -0.33))


def test_wheel_speeds_to_twist_closed_form() -> None:
    twist = DRIVE.twist(WheelSpeeds(0.2, 0.53))
    assert twist.linear_mps == pytest.approx(0.365)
    assert twist.angular_radps == pytest.approx(1.0)


@given(speeds, speeds)
def test_twist_and_wheel_speeds_round_trip(linear: float, angular: float) -> None:
    back = DRIVE.twist(DRIVE.wheel_speeds(Twist(linear, angular)))
    assert back.linear_mps == pytest.approx(linear, abs=1e-12)
    assert back.angular_radps == pytest.approx(angular, abs=1e-12)


def test_rim_speed_and_wheel_turn_rate() -> None:
    assert DRIVE.rim_speed_mps(10.0) == pytest.approx(0.76)
    assert DRIVE.wheel_speed_radps(0.76) == pytest.approx(10.0)


def test_command_inside_the_limits_is_untouched() -> None:
    result = limit_twist(Twist(0.5, 0.5))
    assert result.twist == Twist(0.5, 0.5)
    assert result.scale == 1.0
    assert not result.limited


def test_limits_scale_the_whole_command_and_keep_the_curvature() -> None:
    # Wheels 1.835 / 2.165 m/s: the right wheel needs the strongest cut, 1 / 2.165.
    result = limit_twist(Twist(2.0, 1.0))
    scale = 1.0 / 2.165
    assert result.scale == pytest.approx(scale)
    assert result.limited
    assert result.twist.linear_mps == pytest.approx(2.0 * scale)
    assert result.twist.angular_radps == pytest.approx(scale)
    assert result.twist.angular_radps / result.twist.linear_mps == pytest.approx(0.5)
    assert result.wheels.right_mps == pytest.approx(1.0)
    assert result.wheels.left_mps == pytest.approx(1.835 * scale)
    assert result.requested == Twist(2.0, 1.0)


def test_angular_limit_on_a_spin() -> None:
    result = limit_twist(Twist(0.0, -10.0))
    assert result.twist.angular_radps == pytest.approx(-2.0)
    assert result.twist.linear_mps == 0.0
    assert result.wheels.left_mps == pytest.approx(0.33)


def test_infinite_limits_turn_a_limit_off() -> None:
    limits = VelocityLimits(math.inf, math.inf, math.inf)
    assert not limit_twist(Twist(5.0, 9.0), limits).limited


@given(speeds, speeds)
def test_limited_commands_respect_every_limit_and_keep_curvature(
    linear: float, angular: float
) -> None:
    result = limit_twist(Twist(linear, angular))
    tol = 1e-12
    assert abs(result.twist.linear_mps) <= 1.0 + tol
    assert abs(result.twist.angular_radps) <= 2.0 + tol
    assert max(abs(result.wheels.left_mps), abs(result.wheels.right_mps)) <= 1.0 + tol
    # Curvature kept: the cross product of requested and driven is zero.
    cross = linear * result.twist.angular_radps - angular * result.twist.linear_mps
    assert cross == pytest.approx(0.0, abs=1e-9)


def test_wheel_saturation_scales_both_wheels() -> None:
    wheels = saturate_wheel_speeds(WheelSpeeds(1.5, -0.5), 1.0)
    assert (wheels.left_mps, wheels.right_mps) == pytest.approx((1.0, -1.0 / 3.0))
    same = WheelSpeeds(0.3, 0.4)
    assert saturate_wheel_speeds(same, 1.0) is same


def test_bad_values_are_rejected_by_name() -> None:
    with pytest.raises(InvalidArgumentError, match="linear_mps=nan"):
        Twist(math.nan, 0.0)
    with pytest.raises(InvalidArgumentError, match="right_mps=inf"):
        WheelSpeeds(0.0, math.inf)
    with pytest.raises(InvalidArgumentError, match=r"wheel_separation_m=0\.0"):
        DiffDrive(wheel_separation_m=0.0)
    with pytest.raises(InvalidArgumentError, match="max_linear_mps=nan"):
        VelocityLimits(max_linear_mps=math.nan)
    with pytest.raises(InvalidArgumentError, match="max_wheel_mps=-1"):
        saturate_wheel_speeds(WheelSpeeds(), -1.0)
