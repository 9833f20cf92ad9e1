"""The public surface of ohmni_tb.control is pinned."""

from __future__ import annotations

from ohmni_tb import control

EXPECTED = {
    "COUNT_BITS",
    "DEFAULT_MAX_ANGULAR_RADPS",
    "DEFAULT_MAX_LINEAR_MPS",
    "DEFAULT_TICKS_PER_REV",
    "DEFAULT_WHEEL_RADIUS_M",
    "DEFAULT_WHEEL_SEPARATION_M",
    "DELTA_VELO_RAW_MAX",
    "DELTA_VELO_RAW_MIN",
    "MOTOR_POSITION_BITS",
    "MOTOR_TICKS_PER_REV",
    "MPS2_PER_DELTA_VELO_RAW",
    "PID_RATE_HZ",
    "PWM_LIMIT",
    "AccelLimits",
    "DiffDrive",
    "EncoderConfig",
    "LimitedTwist",
    "Odometry",
    "PidController",
    "PidGains",
    "PidStep",
    "Pose",
    "Twist",
    "TwistLimiter",
    "Unwrapper",
    "VelocityEstimator",
    "VelocityLimits",
    "WheelCalibration",
    "WheelEncoder",
    "WheelNoise",
    "WheelSample",
    "WheelSpeeds",
    "accel_from_delta_velo_raw",
    "calibrate_straight_line",
    "calibrate_umbmark",
    "integrate_batch",
    "jerk_ramp",
    "limit_twist",
    "ramp",
    "saturate_wheel_speeds",
    "unwrap_delta",
    "wrap_angle",
}


def test_all_is_pinned() -> None:
    assert set(control.__all__) == EXPECTED
    assert len(control.__all__) == len(EXPECTED)


def test_every_public_name_resolves() -> None:
    for name in control.__all__:
        assert getattr(control, name) is not None, name


def test_robot_defaults_match_the_design() -> None:
    assert control.DEFAULT_WHEEL_RADIUS_M == 0.0760
    assert control.DEFAULT_WHEEL_SEPARATION_M == 0.330
    assert round(control.DEFAULT_TICKS_PER_REV) == 44_684
    assert control.DEFAULT_MAX_LINEAR_MPS == 1.0
    assert control.PID_RATE_HZ == 50.0
    assert control.PWM_LIMIT == 1000.0
    assert control.MOTOR_POSITION_BITS == 14
