"""Odometry calibration from driven test paths (UMBmark and a straight line).

UMBmark (Borenstein & Feng, 1996) separates the two systematic odometry errors of a
differential drive:

- type A, a wrong wheel separation: every 90° turn comes out ``α`` short (or long);
- type B, unequal wheel diameters: every straight leg curves by ``β``.

Drive a square of side ``L`` several times clockwise and several times counter-clockwise,
steering by odometry alone (so odometry believes every run ends where it began). After
each run measure where the robot really stopped, in the start frame (x forward, y left).
To first order in ``α`` and ``β`` the return errors are::

    counter-clockwise:  x = 2L(β - α),   y = -2L(β - α)
    clockwise:          x = -2L(β + α),  y = -2L(β + α)

so both are read from the centres of gravity of the two clusters, from x and from y
(the two estimates are averaged), and converted to corrections::

    E_b = (π/2) / (π/2 - α)                          wheel separation × E_b
    E_d = D_right/D_left = (L + b·sin(β/2)) / (L - b·sin(β/2))

The diameters are corrected keeping their mean (UMBmark cannot see a common scale
error); a straight-line run measures that scale, and its lateral drift gives ``E_d`` too.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ohmni_tb._checks import finite, positive
from ohmni_tb.control.defaults import DEFAULT_WHEEL_RADIUS_M, DEFAULT_WHEEL_SEPARATION_M
from ohmni_tb.control.odometry import integrate_batch
from ohmni_tb.errors import InvalidArgumentError

__all__ = ["WheelCalibration", "calibrate_straight_line", "calibrate_umbmark"]


@dataclass(frozen=True, slots=True)
class WheelCalibration:
    """Corrected geometry and the errors it was derived from.

    Attributes:
        left_wheel_radius_m: Corrected left wheel radius.
        right_wheel_radius_m: Corrected right wheel radius.
        wheel_separation_m: Corrected wheel separation.
        diameter_ratio: ``E_d``, right over left wheel diameter.
        wheelbase_scale: ``E_b``, true over nominal wheel separation.
        distance_scale: True over nominal mean wheel radius.
        alpha_rad: Type-A error: how much a commanded 90° turn fell short.
        beta_rad: Type-B error: heading change over one straight leg (positive = veers
            left).
    """

    left_wheel_radius_m: float
    right_wheel_radius_m: float
    wheel_separation_m: float
    diameter_ratio: float
    wheelbase_scale: float
    distance_scale: float
    alpha_rad: float
    beta_rad: float


def calibrate_umbmark(
    cw_errors_m: Sequence[tuple[float, float]],
    ccw_errors_m: Sequence[tuple[float, float]],
    side_m: float,
    *,
    wheel_radius_m: float = DEFAULT_WHEEL_RADIUS_M,
    wheel_separation_m: float = DEFAULT_WHEEL_SEPARATION_M,
    distance_scale: float = 1.0,
    refine: bool = True,
) -> WheelCalibration:
    """Wheel radius and separation corrections from a UMBmark square test.

    Args:
        cw_errors_m: For each clockwise run, ``(x, y)``: where the robot really stopped
            minus where odometry says it stopped, metres, in the start frame (x forward
            along the first leg, y to the left).
        ccw_errors_m: The same for each counter-clockwise run.
        side_m: The side of the square, metres (UMBmark uses 4 m).
        wheel_radius_m: The radius odometry used for both wheels during the runs.
        wheel_separation_m: The separation odometry used during the runs.
        distance_scale: The mean radius scale from :func:`calibrate_straight_line`
            (default 1: keep the mean radius). It scales the separation too: a turn's
            error depends on the ratio of radius to separation, so a larger radius means
            a larger separation for the same measured turn error.
        refine: Start from the first-order UMBmark formulas, then solve the square's
            exact kinematics for the ``E_d`` and ``E_b`` that reproduce the measured
            errors (Gauss-Newton). Off: the paper's first-order result, which is off by
            the square of the errors (~5e-4 in ``E_b`` for a 2 % separation error).

    Returns:
        The corrected geometry; with ``refine``, ``alpha_rad`` and ``beta_rad`` are the
        errors that geometry implies.

    Raises:
        InvalidArgumentError: A list is empty, a value is NaN or infinite, or the errors
            are too large for the first-order model (a turn error near 90°).
    """
    side = positive("side_m", side_m, "m")
    radius = positive("wheel_radius_m", wheel_radius_m, "m")
    separation = positive("wheel_separation_m", wheel_separation_m, "m")
    scale = positive("distance_scale", distance_scale)
    x_cw, y_cw = _centre("cw_errors_m", cw_errors_m)
    x_ccw, y_ccw = _centre("ccw_errors_m", ccw_errors_m)
    alpha = 0.5 * ((x_cw + x_ccw) + (y_cw - y_ccw)) / (-4.0 * side)
    beta = 0.5 * ((x_cw - x_ccw) + (y_cw + y_ccw)) / (-4.0 * side)
    if not math.isfinite(beta):
        raise InvalidArgumentError(
            f"leg curve beta={beta!r} rad is not a finite number; check the units of the errors"
        )
    if not abs(alpha) < math.pi / 4:
        raise InvalidArgumentError(
            f"turn error alpha={alpha!r} rad is too large for UMBmark; check the units "
            "and the sign of the errors (measured minus odometry, start frame)"
        )
    wheelbase_scale = scale * (math.pi / 2) / (math.pi / 2 - alpha)
    ratio = _diameter_ratio(side * scale, separation * wheelbase_scale, beta)
    if refine:
        measured = np.array([x_cw, y_cw, x_ccw, y_ccw])
        ratio, wheelbase_scale = _refine(
            measured, _Square(side, separation, scale), ratio, wheelbase_scale
        )
        alpha = math.pi / 2 * (1.0 - scale / wheelbase_scale)
        beta = side * scale * 2.0 * (ratio - 1.0) / (ratio + 1.0) / (separation * wheelbase_scale)
    return _corrected(
        radius,
        separation_m=separation * wheelbase_scale,
        diameter_ratio=ratio,
        wheelbase_scale=wheelbase_scale,
        distance_scale=scale,
        alpha_rad=alpha,
        beta_rad=beta,
    )


def calibrate_straight_line(
    odometry_distance_m: float,
    measured_x_m: float,
    measured_y_m: float = 0.0,
    *,
    wheel_radius_m: float = DEFAULT_WHEEL_RADIUS_M,
    wheel_separation_m: float = DEFAULT_WHEEL_SEPARATION_M,
) -> WheelCalibration:
    """Wheel radius corrections from one straight run.

    Drive straight ahead by odometry (both wheels turning the same) until odometry says
    ``odometry_distance_m``; measure where the robot stopped in the start frame. Unequal
    diameters make the real path an arc; its length and turn follow exactly from the end
    point (``β = 2·atan2(y, x)``, length = chord / sinc(β/2)), giving the mean radius
    scale and the diameter ratio.

    Args:
        odometry_distance_m: Distance odometry reported, metres (> 0).
        measured_x_m: Measured forward distance of the end point, metres.
        measured_y_m: Measured leftward drift of the end point, metres.
        wheel_radius_m: The radius odometry used for both wheels.
        wheel_separation_m: The wheel separation (used to turn the curve into ``E_d``).

    Returns:
        The corrected geometry (separation unchanged, ``alpha_rad`` 0).
    """
    distance = positive("odometry_distance_m", odometry_distance_m, "m")
    x = positive("measured_x_m", measured_x_m, "m")
    y = finite("measured_y_m", measured_y_m, "m")
    radius = positive("wheel_radius_m", wheel_radius_m, "m")
    separation = positive("wheel_separation_m", wheel_separation_m, "m")
    beta = 2.0 * math.atan2(y, x)
    half = 0.5 * beta
    arc_m = math.hypot(x, y) / (math.sin(half) / half if half != 0.0 else 1.0)
    shorter = arc_m - half * separation
    if not shorter > 0.0:
        raise InvalidArgumentError(
            f"measured_y_m={measured_y_m!r} m curves the run more than wheel_separation_m="
            f"{wheel_separation_m!r} m allows; check the units"
        )
    ratio = (arc_m + half * separation) / shorter
    return _corrected(
        radius,
        separation_m=separation,
        diameter_ratio=ratio,
        wheelbase_scale=1.0,
        distance_scale=arc_m / distance,
        alpha_rad=0.0,
        beta_rad=beta,
    )


def _diameter_ratio(side_m: float, separation_m: float, beta_rad: float) -> float:
    """``E_d`` of a leg of ``side_m`` curving by ``beta_rad``: ``(R + b/2) / (R - b/2)``."""
    offset = separation_m * math.sin(0.5 * beta_rad)
    if not abs(offset) < side_m:
        raise InvalidArgumentError(f"leg curve beta={beta_rad!r} rad is too large for UMBmark")
    return (side_m + offset) / (side_m - offset)


@dataclass(frozen=True, slots=True)
class _Square:
    """A UMBmark square as odometry drove it: nominal side, separation, and radius scale."""

    side_m: float
    separation_m: float
    distance_scale: float

    def errors(self, diameter_ratio: float, wheelbase_scale: float) -> npt.NDArray[np.float64]:
        """Return ``(x_cw, y_cw, x_ccw, y_ccw)`` of a robot with this true geometry.

        The robot is steered by nominal odometry (equal radii, nominal separation), so
        each leg turns both wheels by the same angle and each turn spins them equally
        apart; the real distances follow from the true radii and the true separation.
        """
        left = self.distance_scale * 2.0 / (diameter_ratio + 1.0)
        right = self.distance_scale * 2.0 * diameter_ratio / (diameter_ratio + 1.0)
        turn = 0.25 * math.pi * self.separation_m
        side = self.side_m
        errors: list[float] = []
        for sign in (-1.0, 1.0):
            wheel = np.tile([[side, side], [-sign * turn, sign * turn]], (4, 1))
            end = integrate_batch(
                wheel[:, 0] * left, wheel[:, 1] * right, self.separation_m * wheelbase_scale
            )[-1]
            errors.extend((end[0], end[1]))
        return np.array(errors)


def _refine(
    measured: npt.NDArray[np.float64],
    square: _Square,
    diameter_ratio: float,
    wheelbase_scale: float,
) -> tuple[float, float]:
    """Gauss-Newton on ``(E_d, E_b)`` so the simulated square errors match ``measured``."""
    try:
        # Extreme geometry may overflow on the way; the result is checked below.
        with np.errstate(all="ignore"):
            return _gauss_newton(measured, square, diameter_ratio, wheelbase_scale)
    except (InvalidArgumentError, np.linalg.LinAlgError):
        raise InvalidArgumentError("the UMBmark errors fit no plausible geometry") from None


def _gauss_newton(
    measured: npt.NDArray[np.float64],
    square: _Square,
    diameter_ratio: float,
    wheelbase_scale: float,
) -> tuple[float, float]:
    params = np.array([diameter_ratio, wheelbase_scale])
    step = 1e-7  # central differences: truncation ~1e-14, rounding ~1e-9 of the slope
    for _ in range(20):
        residual = square.errors(*params) - measured
        jacobian = np.empty((4, 2))
        for j in range(2):
            delta = np.zeros(2)
            delta[j] = step
            jacobian[:, j] = (
                square.errors(*(params + delta)) - square.errors(*(params - delta))
            ) / (2.0 * step)
        update = np.linalg.lstsq(jacobian, -residual, rcond=None)[0]
        params += update
        if np.max(np.abs(update)) < 1e-13:
            break
    if not (np.all(np.isfinite(params)) and np.all(params > 0.0)):
        raise InvalidArgumentError("the UMBmark errors fit no plausible geometry")
    return float(params[0]), float(params[1])


def _corrected(
    radius_m: float,
    *,
    separation_m: float,
    diameter_ratio: float,
    wheelbase_scale: float,
    distance_scale: float,
    alpha_rad: float,
    beta_rad: float,
) -> WheelCalibration:
    """Split a diameter ratio into two radii with mean ``radius_m · distance_scale``."""
    if not diameter_ratio > 0.0:
        # A wheel turning backwards: no geometry (and a ratio of exactly -1 divides by 0).
        raise InvalidArgumentError(
            f"the measurements give diameter_ratio={diameter_ratio!r}: no usable geometry; "
            "check their units"
        )
    mean = radius_m * distance_scale
    result = WheelCalibration(
        left_wheel_radius_m=mean * 2.0 / (diameter_ratio + 1.0),
        right_wheel_radius_m=mean * 2.0 * diameter_ratio / (diameter_ratio + 1.0),
        wheel_separation_m=separation_m,
        diameter_ratio=diameter_ratio,
        wheelbase_scale=wheelbase_scale,
        distance_scale=distance_scale,
        alpha_rad=alpha_rad,
        beta_rad=beta_rad,
    )
    for name in WheelCalibration.__slots__:
        value = getattr(result, name)
        if not math.isfinite(value) or (name.endswith("_m") and value <= 0.0):
            raise InvalidArgumentError(
                f"the measurements give {name}={value!r}: no usable geometry; check their units"
            )
    return result


def _centre(name: str, errors: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """Centre of gravity of a cluster of (x, y) return errors."""
    if not errors:
        raise InvalidArgumentError(f"{name} is empty: give at least one run")
    for i, pair in enumerate(errors):
        if not isinstance(pair, tuple | list) or len(pair) != 2:
            raise InvalidArgumentError(f"{name}[{i}] must be an (x, y) pair, not {pair!r}")
        finite(f"{name}[{i}].x", pair[0], "m")
        finite(f"{name}[{i}].y", pair[1], "m")
    return (
        math.fsum(x for x, _ in errors) / len(errors),
        math.fsum(y for _, y in errors) / len(errors),
    )
