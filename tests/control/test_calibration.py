"""UMBmark and straight-line calibration against simulated runs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ohmni_tb.control import calibrate_straight_line, calibrate_umbmark, integrate_batch
from ohmni_tb.errors import InvalidArgumentError

NOMINAL_R = 0.0756
NOMINAL_B = 0.330
TRUE_LEFT_R = 0.0755
TRUE_RIGHT_R = 0.0757  # E_d = 1.00265: veers left
TRUE_B = 0.336  # E_b = 1.01818: every turn comes out short
SIDE = 4.0


def _square_run(sign: float, scale: float = 1.0) -> tuple[float, float]:
    """The real end point of a square steered by nominal odometry (+1 CCW, -1 CW).

    ``scale`` multiplies both true radii (a mean radius error UMBmark alone cannot see).
    """
    leg = SIDE / NOMINAL_R  # wheel turn, rad
    turn = sign * (math.pi / 2) * (NOMINAL_B / 2) / NOMINAL_R
    wheel_turns = np.tile([[leg, leg], [-turn, turn]], (4, 1))
    end = integrate_batch(
        wheel_turns[:, 0] * TRUE_LEFT_R * scale, wheel_turns[:, 1] * TRUE_RIGHT_R * scale, TRUE_B
    )[-1]
    return float(end[0]), float(end[1])


def test_umbmark_recovers_the_true_geometry() -> None:
    cw, ccw = _square_run(-1.0), _square_run(1.0)
    result = calibrate_umbmark(
        [cw, cw], [ccw], SIDE, wheel_radius_m=NOMINAL_R, wheel_separation_m=NOMINAL_B
    )
    assert result.left_wheel_radius_m == pytest.approx(TRUE_LEFT_R, rel=1e-9)
    assert result.right_wheel_radius_m == pytest.approx(TRUE_RIGHT_R, rel=1e-9)
    assert result.wheel_separation_m == pytest.approx(TRUE_B, rel=1e-9)
    assert result.diameter_ratio == pytest.approx(TRUE_RIGHT_R / TRUE_LEFT_R, rel=1e-9)
    assert result.wheelbase_scale == pytest.approx(TRUE_B / NOMINAL_B, rel=1e-9)
    # The turn error of a 90° turn and the curve of a leg that geometry implies.
    assert result.alpha_rad == pytest.approx(math.pi / 2 * (1 - NOMINAL_B / TRUE_B))
    assert result.beta_rad == pytest.approx(SIDE * 0.0002 / NOMINAL_R / TRUE_B)


def test_umbmark_first_order_matches_the_paper_formulas() -> None:
    cw, ccw = _square_run(-1.0), _square_run(1.0)
    result = calibrate_umbmark(
        [cw], [ccw], SIDE, wheel_radius_m=NOMINAL_R, wheel_separation_m=NOMINAL_B, refine=False
    )
    alpha = 0.5 * ((cw[0] + ccw[0]) + (cw[1] - ccw[1])) / (-4.0 * SIDE)
    beta = 0.5 * ((cw[0] - ccw[0]) + (cw[1] + ccw[1])) / (-4.0 * SIDE)
    e_b = (math.pi / 2) / (math.pi / 2 - alpha)
    radius = (SIDE / 2) / math.sin(beta / 2)
    e_d = (radius + e_b * NOMINAL_B / 2) / (radius - e_b * NOMINAL_B / 2)
    assert (result.alpha_rad, result.beta_rad) == pytest.approx((alpha, beta))
    assert result.wheelbase_scale == pytest.approx(e_b)
    assert result.diameter_ratio == pytest.approx(e_d)
    # First order: off by the square of the errors, still within 0.1 %.
    assert result.wheel_separation_m == pytest.approx(TRUE_B, rel=1e-3)
    assert result.diameter_ratio == pytest.approx(TRUE_RIGHT_R / TRUE_LEFT_R, rel=1e-4)


def test_straight_line_then_umbmark_recovers_a_mean_radius_error_too() -> None:
    scale = 1.012
    odometry_m = 3.0
    wheel_turn = odometry_m / NOMINAL_R
    end = integrate_batch(
        [wheel_turn * TRUE_LEFT_R * scale], [wheel_turn * TRUE_RIGHT_R * scale], TRUE_B
    )[-1]
    line = calibrate_straight_line(
        odometry_m, float(end[0]), float(end[1]), wheel_radius_m=NOMINAL_R
    )
    assert line.distance_scale == pytest.approx(scale, rel=1e-9)
    result = calibrate_umbmark(
        [_square_run(-1.0, scale)],
        [_square_run(1.0, scale)],
        SIDE,
        wheel_radius_m=NOMINAL_R,
        wheel_separation_m=NOMINAL_B,
        distance_scale=line.distance_scale,
    )
    assert result.left_wheel_radius_m == pytest.approx(TRUE_LEFT_R * scale, rel=1e-9)
    assert result.right_wheel_radius_m == pytest.approx(TRUE_RIGHT_R * scale, rel=1e-9)
    assert result.wheel_separation_m == pytest.approx(TRUE_B, rel=1e-9)


def test_umbmark_without_errors_keeps_the_geometry() -> None:
    result = calibrate_umbmark([(0.0, 0.0)], [(0.0, 0.0)], SIDE)
    assert result.left_wheel_radius_m == pytest.approx(0.076)
    assert result.right_wheel_radius_m == pytest.approx(0.076)
    assert result.wheel_separation_m == pytest.approx(0.330)
    assert result.alpha_rad == pytest.approx(0.0, abs=1e-15)


def test_umbmark_applies_a_distance_scale_to_radii_and_separation() -> None:
    result = calibrate_umbmark([(0.0, 0.0)], [(0.0, 0.0)], SIDE, distance_scale=1.01)
    assert result.left_wheel_radius_m == pytest.approx(0.07676)
    assert result.wheel_separation_m == pytest.approx(0.3333)
    assert result.distance_scale == 1.01


def test_straight_line_gives_scale_and_diameter_ratio_exactly() -> None:
    odometry_m = 3.0
    wheel_turn = odometry_m / NOMINAL_R
    end = integrate_batch([wheel_turn * TRUE_LEFT_R], [wheel_turn * TRUE_RIGHT_R], TRUE_B)[-1]
    result = calibrate_straight_line(
        odometry_m,
        float(end[0]),
        float(end[1]),
        wheel_radius_m=NOMINAL_R,
        wheel_separation_m=TRUE_B,
    )
    assert result.left_wheel_radius_m == pytest.approx(TRUE_LEFT_R, rel=1e-12)
    assert result.right_wheel_radius_m == pytest.approx(TRUE_RIGHT_R, rel=1e-12)
    assert result.wheel_separation_m == TRUE_B


def test_straight_line_without_drift_is_a_pure_scale() -> None:
    result = calibrate_straight_line(1.98, 2.0)
    assert result.distance_scale == pytest.approx(2.0 / 1.98)
    assert result.diameter_ratio == 1.0
    assert result.left_wheel_radius_m == pytest.approx(0.076 * 2.0 / 1.98)


def test_bad_inputs_are_rejected_by_name() -> None:
    with pytest.raises(InvalidArgumentError, match="cw_errors_m is empty"):
        calibrate_umbmark([], [(0.0, 0.0)], SIDE)
    with pytest.raises(InvalidArgumentError, match=r"ccw_errors_m\[1\].y=nan"):
        calibrate_umbmark([(0.0, 0.0)], [(0.0, 0.0), (0.0, math.nan)], SIDE)
    with pytest.raises(InvalidArgumentError, match="too large"):
        calibrate_umbmark([(5.0, 0.0)], [(5.0, 0.0)], 1.0)
    with pytest.raises(InvalidArgumentError, match=r"measured_x_m=-1\.0"):
        calibrate_straight_line(1.0, -1.0)
