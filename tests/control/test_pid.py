"""PID: closed-form terms, step response, saturation and recovery, bumpless gains."""

from __future__ import annotations

import math

import pytest

from ohmni_tb.control import PidController, PidGains
from ohmni_tb.errors import InvalidArgumentError

DT = 0.02  # 50 Hz


def test_first_step_is_the_sum_of_hand_computed_terms() -> None:
    pid = PidController(PidGains(kp=500.0, ki=2500.0, kff=1000.0, ff_offset=30.0))
    step = pid.step(setpoint=0.5, measurement=0.1, dt_s=DT)
    assert step.error == pytest.approx(0.4)
    assert step.p == pytest.approx(200.0)
    assert step.i == pytest.approx(2500.0 * 0.4 * DT)  # 20
    assert step.d == 0.0
    assert step.feed_forward == pytest.approx(530.0)
    assert step.output == pytest.approx(750.0)
    assert not step.saturated
    assert (step.setpoint, step.feedback, step.dt_s) == (0.5, 0.1, DT)
    assert pid.last is step


def test_dead_band_offset_follows_the_setpoint_sign_and_vanishes_at_zero() -> None:
    pid = PidController(PidGains(ff_offset=40.0, kff=100.0))
    assert pid.step(-0.5, -0.5, DT).output == pytest.approx(-90.0)
    assert pid.step(0.0, 0.0, DT).output == 0.0


def _first_order_plant(pwm: float, speed_mps: float) -> float:
    """A wheel 20 % weaker than the feed-forward assumes: 1000 PWM → 0.8 m/s, τ = 0.1 s."""
    return speed_mps + DT / 0.1 * (0.8 * pwm / 1000.0 - speed_mps)


def test_step_response_settles_on_the_setpoint_without_steady_state_error() -> None:
    # PI zero on the plant pole (Ti = kp / ki = τ): closed loop τ / 0.8 = 0.125 s.
    pid = PidController(PidGains(kp=1000.0, ki=10000.0, kff=1000.0))
    speed = 0.0
    peak = 0.0
    for _ in range(100):  # 2 s
        speed = _first_order_plant(pid.step(0.5, speed, DT).output, speed)
        peak = max(peak, speed)
    assert speed == pytest.approx(0.5, abs=1e-5)
    assert peak < 0.5 * 1.05  # less than 5 % overshoot
    # Feed-forward alone would stop at 0.4 m/s: the integral made up the 20 %.
    assert pid.integral == pytest.approx(125.0, abs=0.1)


def test_feed_forward_is_clamped_with_the_rest() -> None:
    pid = PidController(PidGains(kp=100.0, ki=1000.0, kff=3000.0))
    step = pid.step(0.5, 0.0, DT)
    assert step.output == 1000.0
    assert step.saturated
    # No headroom, so the integral did not grow.
    assert step.i == 0.0


def test_saturation_stops_the_integral_at_the_limit_and_recovery_is_immediate() -> None:
    pid = PidController(PidGains(kp=500.0, ki=2500.0, kff=1000.0))
    # Stalled wheel: feed-forward 500 + P 250 = 750, the integral adds 25 a step.
    outputs = [pid.step(0.5, 0.0, DT).output for _ in range(250)]  # 5 s stalled
    assert outputs[:3] == pytest.approx([775.0, 800.0, 825.0])
    assert outputs[9] == pytest.approx(1000.0)
    assert all(out == 1000.0 for out in outputs[10:])
    # A naive integral would hold 2500 · 0.5 · 5 = 3125; this one stopped at the limit.
    assert pid.integral == pytest.approx(250.0)
    # Released, the wheel reaches the setpoint: the output leaves the limit at once.
    assert pid.step(0.5, 0.5, DT).output == pytest.approx(750.0)
    # Overshoot: P -50, integral -5.
    assert pid.step(0.5, 0.6, DT).output == pytest.approx(695.0)


def test_negative_saturation_is_symmetric() -> None:
    pid = PidController(PidGains(kp=500.0, ki=2500.0, kff=1000.0))
    for _ in range(100):
        step = pid.step(-0.5, 0.0, DT)
    assert step.output == -1000.0
    assert pid.integral == pytest.approx(-250.0)


def test_saturated_by_proportional_alone_leaves_the_integral_untouched() -> None:
    pid = PidController(PidGains(kp=5000.0, ki=2500.0))
    pid.step(0.0, 0.0, DT)
    pid.step(0.1, 0.05, DT)  # P 250, integral 2.5
    step = pid.step(1.0, 0.0, DT)  # P 5000 > limit
    assert step.output == 1000.0
    # Neither grown nor pulled down to make room for P (back-calculation would).
    assert step.i == pytest.approx(2.5)


def test_derivative_acts_on_the_measurement_and_is_low_passed() -> None:
    pid = PidController(PidGains(kd=10.0))
    assert pid.step(0.0, 0.0, DT).d == 0.0
    # A setpoint step gives no derivative kick.
    assert pid.step(1.0, 0.0, DT).d == 0.0
    # Measurement rises 0.1 in 20 ms: 5 m/s², D = -50.
    assert pid.step(1.0, 0.1, DT).d == pytest.approx(-50.0)

    filtered = PidController(PidGains(kd=10.0), derivative_tau_s=DT)  # alpha = 0.5
    filtered.step(0.0, 0.0, DT)
    assert filtered.step(0.0, 0.1, DT).d == pytest.approx(-25.0)
    assert filtered.step(0.0, 0.1, DT).d == pytest.approx(-12.5)


def test_gain_change_is_bumpless() -> None:
    old = PidGains(kp=500.0, ki=2500.0, kff=1000.0)
    new = PidGains(kp=800.0, ki=1000.0, kff=1200.0, ff_offset=20.0)
    pid = PidController(old)
    for _ in range(3):
        before = pid.step(0.5, 0.4, DT).output
    pid.set_gains(new)
    after = pid.step(0.5, 0.4, DT).output
    # Only the new integral increment moves the output: 1000 · 0.1 · 0.02 = 2.
    assert after - before == pytest.approx(2.0)
    # Swapping the gains without the transfer would have jumped by P 30 + FF 100 + 20 + 2.
    assert pid.gains == new
    assert pid.step(0.5, 0.4, DT).output - after == pytest.approx(2.0)


def test_reset_forgets_history_and_presets_the_integral() -> None:
    pid = PidController(PidGains(kp=100.0, ki=100.0, kd=10.0))
    pid.step(1.0, 0.0, DT)
    pid.step(1.0, 0.5, DT)
    pid.reset(integral=300.0)
    assert pid.last is None
    step = pid.step(0.0, 0.9, DT)  # no derivative: no previous measurement
    assert step.d == 0.0
    assert step.i == pytest.approx(300.0 - 100.0 * 0.9 * DT)
    pid.reset(integral=5000.0)
    assert pid.integral == 1000.0  # held within the output limits


@pytest.mark.parametrize(
    ("setpoint", "measurement", "dt_s", "named"),
    [
        (math.nan, 0.0, DT, "setpoint=nan"),
        (0.0, math.inf, DT, "measurement=inf"),
        (0.0, 0.0, 0.0, "dt_s=0.0"),
        (0.0, 0.0, -DT, "dt_s=-0.02"),
        (0.0, 0.0, math.nan, "dt_s=nan"),
    ],
)
def test_bad_inputs_are_rejected_by_name(
    setpoint: float, measurement: float, dt_s: float, named: str
) -> None:
    pid = PidController(PidGains(kp=1.0))
    with pytest.raises(InvalidArgumentError, match=named):
        pid.step(setpoint, measurement, dt_s)
    assert pid.last is None


def test_bad_gains_and_limits_are_rejected() -> None:
    with pytest.raises(InvalidArgumentError, match=r"kp=-1\.0"):
        PidGains(kp=-1.0)
    with pytest.raises(InvalidArgumentError, match="ki=nan"):
        PidGains(ki=math.nan)
    with pytest.raises(InvalidArgumentError, match="output_min"):
        PidController(PidGains(), output_min=10.0, output_max=-10.0)
