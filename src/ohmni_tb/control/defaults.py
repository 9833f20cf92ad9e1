"""The robot's defaults (its geometry, limits and gains), in one place so a measured robot
changes one line.

The drive boards' own facts (the PWM range, the 14-bit motor position) are defined once,
in :mod:`ohmni_tb.protocol.drive`, and only re-exported here under the names control uses.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from ohmni_tb.protocol.drive import MOTOR_POSITION_MODULUS as MOTOR_TICKS_PER_REV
from ohmni_tb.protocol.drive import PWM_LIMIT

__all__ = [
    "CONTROL_HZ_RANGE",
    "DEFAULT_BASE_FRAME",
    "DEFAULT_MAX_ANGULAR_RADPS",
    "DEFAULT_MAX_LINEAR_MPS",
    "DEFAULT_ODOM_FRAME",
    "DEFAULT_TICKS_PER_REV",
    "DEFAULT_WHEEL_RADIUS_M",
    "DEFAULT_WHEEL_SEPARATION_M",
    "MAX_POSE_M",
    "MOTOR_TICKS_PER_REV",
    "PID_RATE_HZ",
    "PWM_LIMIT",
    "WHEEL_GAIN_RANGES",
]

#: Wheel radius of the vendor's simulation model; robots measure 0.07525 m.
DEFAULT_WHEEL_RADIUS_M = 0.0760
#: Distance between the wheel contact points; robots measure 0.330-0.332 m.
DEFAULT_WHEEL_SEPARATION_M = 0.330
#: Ticks per wheel turn: 14-bit motor encoder (``MOTOR_TICKS_PER_REV``, the drive board's
#: motor position modulus) behind a 30/11 gear (inferred, ≈44,684).
DEFAULT_TICKS_PER_REV = MOTOR_TICKS_PER_REV * 30 / 11
#: No-load top speed of the robot.
DEFAULT_MAX_LINEAR_MPS = 1.0
#: Project choice (not a vendor figure): a telepresence robot spinning faster than
#: ~115 °/s is hard to watch through its own camera.
DEFAULT_MAX_ANGULAR_RADPS = 2.0
#: tb_control runs the wheel PIDs at 50 Hz.
PID_RATE_HZ = 50.0
#: The control tick's allowed rate, Hz, wherever it is set (``wheel_hz``,
#: ``Robot.set_rate("wheel_encoder", …)``, the daemon, Foxglove). The floor keeps the
#: braking ramp and stale-feedback detection (``stale_ticks`` ticks) within a fraction of a
#: second; the motion watchdog has a timer of its own and does not depend on the tick.
CONTROL_HZ_RANGE = (10.0, 100.0)
#: Each wheel PID gain's allowed range, wherever it is set (config, ``Robot.set_pid``, the
#: daemon, Foxglove): ten times and more the gains that drive the robot well, and a
#: dead-band offset of at most a fifth of the PWM range. Whatever the gains, the wheels
#: are held to ``max_wheel_mps`` after the PID (``Robot``'s speed governor).
WHEEL_GAIN_RANGES: Mapping[str, tuple[float, float]] = MappingProxyType(
    {
        "kp": (0.0, 10_000.0),
        "ki": (0.0, 10_000.0),
        "kd": (0.0, 1_000.0),
        "kff": (0.0, 10_000.0),
        "ff_offset": (0.0, PWM_LIMIT / 5),
    }
)
#: The odometry pose that may be set, metres from the origin each way (1,000 km; the yaw
#: in radians likewise): beyond, a float's resolution (about 1e-10 m at 1e6 m) is no
#: longer a wheel's.
MAX_POSE_M = 1e6
#: The odometry's frames, as tb_control names them by default (``~frame_id_odom``,
#: ``~frame_id_baselink``): where the robot was when the odometry started, and the body
#: between the wheels on the floor (ROS's conventions).
DEFAULT_ODOM_FRAME = "odom"
DEFAULT_BASE_FRAME = "base_link"
