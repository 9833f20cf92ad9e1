"""The math that drives the robot straight and knows where it is; no I/O, no clock.

Everything here is a pure function or a small class fed with numbers; time comes in as an
argument (``dt_s``, ``t_s``), so the same code runs on the robot, in the simulator and on
a recorded log. See ``docs/control.md`` for the models and the limits a user sets.

- :mod:`~ohmni_tb.control.pid`: per-wheel velocity PID (feed-forward, anti-windup,
  derivative on measurement, bumpless gain change, ``pid_debug`` terms).
- :mod:`~ohmni_tb.control.kinematics`: twist ↔ wheel speeds, curvature-keeping limits.
- :mod:`~ohmni_tb.control.limiter`: acceleration/braking ramps, the jerk limit,
  ``delta_velo_raw``.
- :mod:`~ohmni_tb.control.encoder`: counter unwrapping, ticks ↔ metres, speed estimate.
- :mod:`~ohmni_tb.control.odometry`: exact arc odometry, streaming and batch.
- :mod:`~ohmni_tb.control.calibration`: UMBmark and straight-line corrections.
"""

from __future__ import annotations

from ohmni_tb.control.calibration import (
    WheelCalibration,
    calibrate_straight_line,
    calibrate_umbmark,
)
from ohmni_tb.control.defaults import (
    DEFAULT_MAX_ANGULAR_RADPS,
    DEFAULT_MAX_LINEAR_MPS,
    DEFAULT_TICKS_PER_REV,
    DEFAULT_WHEEL_RADIUS_M,
    DEFAULT_WHEEL_SEPARATION_M,
    MOTOR_TICKS_PER_REV,
    PID_RATE_HZ,
    PWM_LIMIT,
)
from ohmni_tb.control.encoder import (
    COUNT_BITS,
    MOTOR_POSITION_BITS,
    EncoderConfig,
    Unwrapper,
    VelocityEstimator,
    WheelEncoder,
    WheelSample,
    unwrap_delta,
)
from ohmni_tb.control.kinematics import (
    DiffDrive,
    LimitedTwist,
    Twist,
    VelocityLimits,
    WheelSpeeds,
    limit_twist,
    saturate_wheel_speeds,
)
from ohmni_tb.control.limiter import (
    DELTA_VELO_RAW_MAX,
    DELTA_VELO_RAW_MIN,
    MPS2_PER_DELTA_VELO_RAW,
    AccelLimits,
    TwistLimiter,
    accel_from_delta_velo_raw,
    jerk_ramp,
    ramp,
)
from ohmni_tb.control.odometry import Odometry, Pose, WheelNoise, integrate_batch, wrap_angle
from ohmni_tb.control.pid import PidController, PidGains, PidStep

__all__ = [
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
]
