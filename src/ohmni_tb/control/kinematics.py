"""Differential-drive kinematics and velocity limits.

Frame: x forward, y left, yaw counter-clockwise positive (REP 103). Wheel speeds are rim
speeds in m/s, forward positive for *both* wheels; the right wheel's mirrored counts and
PWM are handled at the encoder and the PWM codec, never here::

    left  = v - ω·b/2          v = (left + right) / 2
    right = v + ω·b/2          ω = (right - left) / b

Limits scale the whole command by one factor, so the commanded curvature ``ω / v`` (the
circle the robot drives) is kept; clamping each wheel, or the linear and angular speed
separately, would drive a different circle than the one asked for.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ohmni_tb._checks import FLOAT_MAX, finite, finite_result, positive, positive_or_inf
from ohmni_tb.control.defaults import (
    DEFAULT_MAX_ANGULAR_RADPS,
    DEFAULT_MAX_LINEAR_MPS,
    DEFAULT_WHEEL_RADIUS_M,
    DEFAULT_WHEEL_SEPARATION_M,
)
from ohmni_tb.errors import InvalidArgumentError

__all__ = [
    "DiffDrive",
    "LimitedTwist",
    "Twist",
    "VelocityLimits",
    "WheelSpeeds",
    "limit_twist",
    "saturate_wheel_speeds",
]


@dataclass(frozen=True, slots=True)
class Twist:
    """A body velocity.

    Attributes:
        linear_mps: Forward speed, m/s.
        angular_radps: Yaw rate, rad/s, counter-clockwise positive.
    """

    linear_mps: float = 0.0
    angular_radps: float = 0.0

    def __post_init__(self) -> None:
        # A finite float passes without a call (x - x is 0.0 for those only); anything
        # else gets the full check, and its error.
        linear, angular = self.linear_mps, self.angular_radps
        if type(linear) is not float or linear - linear:
            finite("linear_mps", linear, "m/s")
        if type(angular) is not float or angular - angular:
            finite("angular_radps", angular, "rad/s")


@dataclass(frozen=True, slots=True)
class WheelSpeeds:
    """Rim speeds of the two wheels, forward positive for both.

    Attributes:
        left_mps: Left wheel, m/s.
        right_mps: Right wheel, m/s (not mirrored).
    """

    left_mps: float = 0.0
    right_mps: float = 0.0

    def __post_init__(self) -> None:
        left, right = self.left_mps, self.right_mps  # finite floats pass without a call
        if type(left) is not float or left - left:
            finite("left_mps", left, "m/s")
        if type(right) is not float or right - right:
            finite("right_mps", right, "m/s")


@dataclass(frozen=True, slots=True)
class DiffDrive:
    """The geometry of a differential drive.

    Attributes:
        wheel_radius_m: Wheel radius (default 0.0760 m).
        wheel_separation_m: Distance between the wheels' contact points (default 0.330 m).
    """

    wheel_radius_m: float = DEFAULT_WHEEL_RADIUS_M
    wheel_separation_m: float = DEFAULT_WHEEL_SEPARATION_M

    def __post_init__(self) -> None:
        positive("wheel_radius_m", self.wheel_radius_m, "m")
        positive("wheel_separation_m", self.wheel_separation_m, "m")

    def wheel_speeds(self, twist: Twist) -> WheelSpeeds:
        """Wheel rim speeds that realise ``twist``.

        Raises:
            InvalidArgumentError: ``twist`` is not a :class:`Twist`, or a wheel speed
                would not be a finite number.
        """
        _check_type("twist", twist, Twist)
        half = 0.5 * twist.angular_radps * self.wheel_separation_m
        return WheelSpeeds(twist.linear_mps - half, twist.linear_mps + half)

    def twist(self, wheels: WheelSpeeds) -> Twist:
        """The body velocity that wheel rim speeds ``wheels`` produce.

        Raises:
            InvalidArgumentError: ``wheels`` is not :class:`WheelSpeeds`, or the velocity
                would not be a finite number.
        """
        _check_type("wheels", wheels, WheelSpeeds)
        return Twist(
            0.5 * (wheels.left_mps + wheels.right_mps),
            (wheels.right_mps - wheels.left_mps) / self.wheel_separation_m,
        )

    def rim_speed_mps(self, wheel_speed_radps: float) -> float:
        """Rim speed of a wheel turning at ``wheel_speed_radps``.

        Raises:
            InvalidArgumentError: Not a number, NaN or infinite.
            OutOfRangeError: The rim speed would not be a finite number.
        """
        speed = finite("wheel_speed_radps", wheel_speed_radps, "rad/s")
        limit = FLOAT_MAX / max(self.wheel_radius_m, 1.0)
        return finite_result(
            speed * self.wheel_radius_m, "wheel_speed_radps", wheel_speed_radps, -limit, limit
        )

    def wheel_speed_radps(self, rim_speed_mps: float) -> float:
        """Turn rate of a wheel whose rim moves at ``rim_speed_mps``.

        Raises:
            InvalidArgumentError: Not a number, NaN or infinite.
            OutOfRangeError: The turn rate would not be a finite number.
        """
        speed = finite("rim_speed_mps", rim_speed_mps, "m/s")
        limit = FLOAT_MAX * min(self.wheel_radius_m, 1.0)
        return finite_result(
            speed / self.wheel_radius_m, "rim_speed_mps", rim_speed_mps, -limit, limit
        )


@dataclass(frozen=True, slots=True)
class VelocityLimits:
    """Speed limits a command is scaled into. ``math.inf`` turns a limit off.

    Attributes:
        max_linear_mps: Largest forward or backward speed (default 1.0 m/s).
        max_angular_radps: Largest yaw rate either way (default 2.0 rad/s).
        max_wheel_mps: Largest rim speed of either wheel (default 1.0 m/s, the no-load
            top speed): a fast turn while driving fast asks more of the outer wheel than
            of the body.
    """

    max_linear_mps: float = DEFAULT_MAX_LINEAR_MPS
    max_angular_radps: float = DEFAULT_MAX_ANGULAR_RADPS
    max_wheel_mps: float = DEFAULT_MAX_LINEAR_MPS

    def __post_init__(self) -> None:
        positive_or_inf("max_linear_mps", self.max_linear_mps, "m/s")
        positive_or_inf("max_angular_radps", self.max_angular_radps, "rad/s")
        positive_or_inf("max_wheel_mps", self.max_wheel_mps, "m/s")


@dataclass(frozen=True, slots=True)
class LimitedTwist:
    """A command after :func:`limit_twist`.

    Attributes:
        requested: The twist asked for.
        twist: The twist to drive: ``requested`` times ``scale``.
        wheels: The wheel speeds of ``twist``.
        scale: The factor applied, in (0, 1]; 1 when no limit was hit.
    """

    requested: Twist
    twist: Twist
    wheels: WheelSpeeds
    scale: float

    @property
    def limited(self) -> bool:
        """Whether a limit changed the command (so it can be reported)."""
        return self.scale < 1.0


def limit_twist(
    twist: Twist, limits: VelocityLimits | None = None, drive: DiffDrive | None = None
) -> LimitedTwist:
    """Scale a command into the speed limits, keeping its curvature.

    One factor, the smallest that each limit needs, scales both the linear and the angular
    speed, so the robot drives the same circle, only slower.

    Args:
        twist: The requested body velocity.
        limits: The limits (default :class:`VelocityLimits`).
        drive: The geometry (default :class:`DiffDrive`).

    Returns:
        The command to drive, its wheel speeds and the factor applied.
    """
    _check_type("twist", twist, Twist)
    limits = limits if limits is not None else VelocityLimits()
    drive = drive if drive is not None else DiffDrive()
    _check_type("limits", limits, VelocityLimits)
    _check_type("drive", drive, DiffDrive)
    wheels = drive.wheel_speeds(twist)
    scale = min(
        1.0,
        _ratio(limits.max_linear_mps, twist.linear_mps),
        _ratio(limits.max_angular_radps, twist.angular_radps),
        _ratio(limits.max_wheel_mps, max(abs(wheels.left_mps), abs(wheels.right_mps))),
    )
    if scale == 1.0:
        return LimitedTwist(twist, twist, wheels, 1.0)
    limited = Twist(twist.linear_mps * scale, twist.angular_radps * scale)
    scaled_wheels = WheelSpeeds(wheels.left_mps * scale, wheels.right_mps * scale)
    return LimitedTwist(twist, limited, scaled_wheels, scale)


def saturate_wheel_speeds(wheels: WheelSpeeds, max_wheel_mps: float) -> WheelSpeeds:
    """Scale both wheel speeds so the faster one is at most ``max_wheel_mps``.

    Both wheels are scaled by the same factor, so their ratio (the curvature) is kept.

    Args:
        wheels: The wheel speeds.
        max_wheel_mps: The largest allowed rim speed, > 0.

    Returns:
        ``wheels`` unchanged if within the limit, else both scaled down.
    """
    if type(wheels) is not WheelSpeeds:
        _check_type("wheels", wheels, WheelSpeeds)
    if type(max_wheel_mps) is not float or not max_wheel_mps > 0.0:
        positive_or_inf("max_wheel_mps", max_wheel_mps, "m/s")
    scale = _ratio(max_wheel_mps, max(abs(wheels.left_mps), abs(wheels.right_mps)))
    if scale >= 1.0:
        return wheels
    return WheelSpeeds(wheels.left_mps * scale, wheels.right_mps * scale)


def _ratio(limit: float, value: float) -> float:
    """``limit / |value|``, or inf when value is zero (no constraint)."""
    magnitude = abs(value)
    return math.inf if magnitude == 0.0 else limit / magnitude


def _check_type(name: str, value: object, kind: type) -> None:
    if not isinstance(value, kind):
        raise InvalidArgumentError(f"{name} must be a {kind.__name__}, not {type(value).__name__}")
