"""Issue 9: the control math never hands out NaN or inf, and bad inputs are OhmniErrors."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ohmni_tb.control import Odometry, PidController, PidGains, VelocityLimits
from ohmni_tb.errors import InvalidArgumentError, OhmniError, OutOfRangeError
from ohmni_tb.protocol.drive import set_torque


def test_a_subnormal_dt_does_not_poison_the_derivative() -> None:
    pid = PidController(PidGains(kp=1.0, kd=1.0), derivative_tau_s=0.05)
    pid.step(1.0, 0.0, 0.02)
    with pytest.raises(OutOfRangeError, match=r"dt_s=1e-320 is out of range"):
        pid.step(1.0, 0.5, 1e-320)
    for _ in range(5):
        step = pid.step(1.0, 0.5, 0.02)
        assert math.isfinite(step.output)
        assert math.isfinite(step.d)


def test_a_huge_measurement_is_refused_and_changes_nothing() -> None:
    pid = PidController(PidGains(kp=1.0, ki=1.0, kd=1.0))
    first = pid.step(1.0, -0.5, 0.02)
    with pytest.raises(OutOfRangeError, match="measurement=1e"):
        pid.step(1.0, 1e308, 0.02)
    assert pid.last == first
    assert math.isfinite(pid.step(1.0, 0.5, 0.02).output)


EXTREME = st.one_of(
    st.sampled_from([math.inf, -math.inf, math.nan, 1e308, -1e308, -0.0, 5e-324, 1e-320, 10**400]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(-10.0, 10.0),
)
DT = st.one_of(EXTREME, st.floats(1e-3, 0.1))


@settings(max_examples=300, deadline=None)
@given(
    gains=st.tuples(*(st.floats(0.0, 1e12) for _ in range(5))),
    tau=st.floats(0.0, 1.0),
    steps=st.lists(st.tuples(EXTREME, EXTREME, DT), min_size=1, max_size=30),
)
def test_any_sequence_of_steps_gives_finite_clamped_outputs(
    gains: tuple[float, float, float, float, float],
    tau: float,
    steps: list[tuple[float, float, float]],
) -> None:
    pid = PidController(
        PidGains(*gains), output_min=-1000.0, output_max=1000.0, derivative_tau_s=tau
    )
    for setpoint, measurement, dt_s in steps:
        try:
            step = pid.step(setpoint, measurement, dt_s)
        except OhmniError as exc:
            message = str(exc)
            assert "\n" not in message
            continue
        assert math.isfinite(step.output)
        assert -1000.0 <= step.output <= 1000.0
        for term in (step.p, step.i, step.d, step.feed_forward):
            assert math.isfinite(term)


def test_a_huge_odometry_increment_is_out_of_range_and_changes_nothing() -> None:
    odo = Odometry()
    odo.update(0.01, 0.01, 0.0)
    before = odo.pose
    with pytest.raises(OutOfRangeError, match="d_left_m=1e"):
        odo.update(1e308, 0, 1)
    assert odo.pose == before


def test_velocity_limits_of_the_wrong_type_are_named() -> None:
    with pytest.raises(InvalidArgumentError, match="max_linear_mps must be a number, not str"):
        VelocityLimits("1")  # type: ignore[arg-type]  # a caller's mistake


def test_an_unknown_drive_torque_is_an_invalid_argument() -> None:
    with pytest.raises(InvalidArgumentError, match=r"torque=5 is not one of FREE"):
        set_torque(0, 5)  # type: ignore[arg-type]  # a caller's mistake


def test_a_straight_run_that_makes_one_wheel_turn_backwards_is_refused_not_a_crash() -> None:
    # A drift almost square to the run on an absurd separation: the diameter ratio comes
    # out as exactly -1, which used to divide by zero.
    from ohmni_tb.control.calibration import calibrate_straight_line

    with pytest.raises(InvalidArgumentError, match=r"diameter_ratio=-1\.0: no usable geometry"):
        calibrate_straight_line(
            1e308, 5e-324, -1.0, wheel_radius_m=1.0, wheel_separation_m=1.146832227844532e16
        )
