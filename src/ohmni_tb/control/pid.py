"""A velocity PID for one wheel, stepped at a measured interval.

The loop tb_control runs per wheel at 50 Hz, written so that none of its classic failure
modes is left to the caller::

    feed-forward ─────────────────────────┐
    setpoint ─┬─(+)─ error ─┬─ kp ────────(+)─► clamp ─► output (PWM)
              │   ▲         └─ ki ∫ (clamped) ┘
    measurement ──┴──────── -kd · d/dt (low-pass) ┘

- The feed-forward sits *inside* the output clamp, so it can never push the output past
  the PWM limit.
- Anti-windup by conditional integration: the integral only grows while the output has
  headroom, and never beyond the point where the output reaches its limit. It is never
  driven backwards either, so recovery from saturation starts on the first step the
  error reverses.
- The derivative acts on the measurement, not the error, so a setpoint step gives no kick;
  an optional first-order low-pass tames encoder quantisation.
- ``dt_s`` is measured by the caller and passed in: the controller never reads a clock.
- Changing gains is bumpless: the integral absorbs the change in the other terms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ohmni_tb._checks import bounded, finite
from ohmni_tb.control.defaults import PWM_LIMIT
from ohmni_tb.errors import InvalidArgumentError

__all__ = ["PidController", "PidGains", "PidStep"]

# Limits far beyond any wheel loop, chosen so that no product or quotient of the loop's
# terms can overflow: every output stays a finite number inside the clamp.
#: Largest gain: a wheel loop uses hundreds to thousands of PWM per m/s.
MAX_GAIN = 1e12
#: Largest setpoint or measurement magnitude (m/s for a wheel).
MAX_SIGNAL = 1e9
#: Shortest step: below a microsecond a derivative is noise divided by nothing.
MIN_DT_S = 1e-6
#: Longest step: a loop stalled for hours should be reset, not stepped.
MAX_DT_S = 1e4
#: Largest output limit magnitude.
MAX_OUTPUT = 1e15


@dataclass(frozen=True, slots=True)
class PidGains:
    """Gains of a :class:`PidController`. All are 0..1e12.

    The loop is written in the wheel's forward-positive frame; the mirrored right wheel
    is handled where the PWM is encoded, so no gain is ever negative.

    Attributes:
        kp: Output per unit of error (PWM per m/s for a wheel loop).
        ki: Output per unit of error and second.
        kd: Output per unit of measurement rate (PWM per m/s²), on the measurement.
        kff: Velocity feed-forward: output per unit of setpoint.
        ff_offset: Output added in the direction of a non-zero setpoint, to overcome the
            motor's dead band; zero when the setpoint is zero.
    """

    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    kff: float = 0.0
    ff_offset: float = 0.0

    def __post_init__(self) -> None:
        for name in ("kp", "ki", "kd", "kff", "ff_offset"):
            value = getattr(self, name)
            finite(name, value)
            if value < 0.0:
                raise InvalidArgumentError(f"{name}={value!r} must be >= 0")
            bounded(name, value, 0.0, MAX_GAIN)


@dataclass(frozen=True, slots=True)
class PidStep:
    """What one :meth:`PidController.step` computed: tb_control's ``pid_debug`` and more.

    ``output == clamp(feed_forward + p + i + d)``, with ``i`` the integral after the step.

    Attributes:
        setpoint: The setpoint of the step.
        feedback: The measurement of the step.
        error: ``setpoint - feedback``.
        p: Proportional term.
        i: Integral term (in output units).
        d: Derivative term (on the measurement, filtered).
        feed_forward: Feed-forward term.
        output: The clamped output.
        saturated: Whether the clamp changed the output.
        dt_s: The interval the step integrated over.
    """

    setpoint: float
    feedback: float
    error: float
    p: float
    i: float
    d: float
    feed_forward: float
    output: float
    saturated: bool
    dt_s: float


class PidController:
    """A PID with feed-forward, anti-windup, derivative on measurement and bumpless gains.

    Example:
        >>> pid = PidController(PidGains(kp=400.0, ki=2000.0, kff=900.0))
        >>> step = pid.step(setpoint=0.5, measurement=0.0, dt_s=0.02)
        >>> step.output
        670.0

    Args:
        gains: The initial gains.
        output_min: Lower output limit (default -1000, the PWM range); |limit| <= 1e15.
        output_max: Upper output limit (default +1000).
        derivative_tau_s: Time constant of the derivative's first-order low-pass, 0..1e4 s;
            0 turns the filter off.

    Raises:
        InvalidArgumentError: ``gains`` is not :class:`PidGains`, a limit is NaN or
            infinite, or ``output_min >= output_max``.
        OutOfRangeError: A limit or ``derivative_tau_s`` is out of range.
    """

    def __init__(
        self,
        gains: PidGains,
        *,
        output_min: float = -PWM_LIMIT,
        output_max: float = PWM_LIMIT,
        derivative_tau_s: float = 0.0,
    ) -> None:
        _check_gains(gains)
        bounded("output_min", output_min, -MAX_OUTPUT, MAX_OUTPUT)
        bounded("output_max", output_max, -MAX_OUTPUT, MAX_OUTPUT)
        if not output_min < output_max:
            raise InvalidArgumentError(
                f"output_min={output_min!r} must be below output_max={output_max!r}"
            )
        self._gains = gains
        self._output_min = float(output_min)
        self._output_max = float(output_max)
        self._derivative_tau_s = bounded("derivative_tau_s", derivative_tau_s, 0.0, MAX_DT_S, "s")
        self._integral = 0.0
        self._rate = 0.0  # filtered d(measurement)/dt
        self._last_measurement: float | None = None
        self._last: PidStep | None = None

    @property
    def gains(self) -> PidGains:
        """The gains in use."""
        return self._gains

    @property
    def integral(self) -> float:
        """The integral term, in output units."""
        return self._integral

    @property
    def last(self) -> PidStep | None:
        """The terms of the latest step, or None before the first step or after a reset."""
        return self._last

    def step(self, setpoint: float, measurement: float, dt_s: float) -> PidStep:
        """Run the loop once.

        A refused step changes nothing: the controller goes on as if it never came.

        Args:
            setpoint: The wanted value (m/s for a wheel), |setpoint| <= 1e9.
            measurement: The measured value, in the setpoint's unit, |measurement| <= 1e9.
            dt_s: Time since the previous step, measured by the caller; 1e-6..1e4 s.

        Returns:
            Every term of the step; ``.output`` is what goes to the motor: always a finite
            number within the output limits.

        Raises:
            InvalidArgumentError: An argument is not a number, NaN or infinite.
            OutOfRangeError: An argument is outside its range.
        """
        # Floats in range pass without a call; anything else (NaN fails every comparison)
        # gets the full check, and its error.
        if type(setpoint) is not float or not -MAX_SIGNAL <= setpoint <= MAX_SIGNAL:
            bounded("setpoint", setpoint, -MAX_SIGNAL, MAX_SIGNAL)
        if type(measurement) is not float or not -MAX_SIGNAL <= measurement <= MAX_SIGNAL:
            bounded("measurement", measurement, -MAX_SIGNAL, MAX_SIGNAL)
        if type(dt_s) is not float or not MIN_DT_S <= dt_s <= MAX_DT_S:
            bounded("dt_s", dt_s, MIN_DT_S, MAX_DT_S, "s")
        g = self._gains
        error = setpoint - measurement
        rate = self._rate
        if self._last_measurement is not None:
            raw_rate = (measurement - self._last_measurement) / dt_s
            # Discrete first-order low-pass; alpha == 1 when the filter is off.
            alpha = dt_s / (self._derivative_tau_s + dt_s)
            rate += alpha * (raw_rate - rate)

        p = g.kp * error
        d = -g.kd * rate
        ff = _feed_forward(g, setpoint)
        rest = ff + p + d
        integral = self._integral + g.ki * error * dt_s
        # Conditional integration: grow the integral only up to the point where the output
        # reaches its limit, and never shrink it on that account, so a long saturation
        # leaves nothing to unwind and the output leaves the limit as soon as the error
        # turns.
        if integral > self._integral:
            integral = min(integral, max(self._integral, self._output_max - rest))
        elif integral < self._integral:
            integral = max(integral, min(self._integral, self._output_min - rest))
        raw = rest + integral
        if not math.isfinite(raw):  # unreachable within the limits above; kept as a guard
            raise InvalidArgumentError(
                f"step(setpoint={setpoint!r}, measurement={measurement!r}, dt_s={dt_s!r}) "
                f"gives a non-finite output with {g}"
            )
        # Committed only now, so a refused step leaves no trace.
        self._rate = rate
        self._last_measurement = float(measurement)
        self._integral = integral
        output = min(max(raw, self._output_min), self._output_max)
        self._last = PidStep(
            setpoint=float(setpoint),
            feedback=float(measurement),
            error=error,
            p=p,
            i=integral,
            d=d,
            feed_forward=ff,
            output=output,
            saturated=output != raw,
            dt_s=float(dt_s),
        )
        return self._last

    def set_gains(self, gains: PidGains) -> None:
        """Change the gains without a bump in the output.

        The integral absorbs the change of the proportional, derivative and feed-forward
        terms at the latest inputs, so the next step with the same inputs gives the same
        output as the last one.

        Args:
            gains: The new gains.

        Raises:
            InvalidArgumentError: ``gains`` is not :class:`PidGains`.
        """
        _check_gains(gains)
        last = self._last
        if last is not None:
            new_rest = (
                gains.kp * last.error - gains.kd * self._rate + _feed_forward(gains, last.setpoint)
            )
            self._integral += last.p + last.d + last.feed_forward - new_rest
        self._gains = gains

    def reset(self, integral: float = 0.0) -> None:
        """Forget the history: integral, derivative state and last step.

        Args:
            integral: The integral to start from, in output units (clamped to the output
                limits). For a bumpless hand-over from open-loop driving, pass the output
                in use minus the feed-forward of the next setpoint.
        """
        finite("integral", integral)
        self._integral = min(max(float(integral), self._output_min), self._output_max)
        self._rate = 0.0
        self._last_measurement = None
        self._last = None


def _feed_forward(gains: PidGains, setpoint: float) -> float:
    """Feed-forward for a setpoint: linear term plus the dead-band offset in its direction."""
    if setpoint == 0.0:
        return 0.0
    return gains.kff * setpoint + math.copysign(gains.ff_offset, setpoint)


def _check_gains(gains: PidGains) -> None:
    given: object = gains  # typed, but callers may pass a dict or a tuple
    if not isinstance(given, PidGains):
        raise InvalidArgumentError(f"gains must be PidGains, not {type(given).__name__}")
