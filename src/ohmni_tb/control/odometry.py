"""Wheel odometry by exact arc integration, streaming and batch.

Between two updates each wheel is assumed to roll at a constant speed, so the robot moves
on a circular arc (a line when both wheels roll the same). With ``ds = (dl + dr) / 2``,
``dθ = (dr - dl) / b`` and ``h = dθ / 2``, the arc's chord is exactly::

    x += ds · sinc(h) · cos(θ + h)        sinc(h) = sin(h) / h
    y += ds · sinc(h) · sin(θ + h)
    θ += dθ

For ``|h| < 1e-2`` ``sinc`` is its Taylor series to ``h⁶`` (remainder < 3e-22), so a straight
line needs no special case and no Euler or Runge-Kutta fallback is ever used: the result
is exact, to rounding, for any step the wheels roll at constant speed, at 50 Hz or 5 Hz.

The heading is integrated unwrapped; :attr:`Pose.yaw` reports it wrapped to ``(-π, π]``
and :attr:`Odometry.heading_rad` gives the unwrapped value. :func:`integrate_batch` runs
the same arithmetic vectorised over a log and agrees with :class:`Odometry` to ~1e-12.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ohmni_tb._checks import bounded, finite, integer, non_negative, positive
from ohmni_tb.control.defaults import DEFAULT_WHEEL_SEPARATION_M
from ohmni_tb.control.kinematics import Twist
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

__all__ = ["Odometry", "Pose", "WheelNoise", "integrate_batch", "wrap_angle"]

#: Largest wheel increment one update takes: a kilometre between two reads of a robot
#: that drives 1 m/s is a broken read, not a motion.
MAX_INCREMENT_M = 1e3
#: Most updates a twist window or the pose history may keep.
_MAX_KEPT = 10_000_000
#: Below this |dθ/2| the sinc terms use their series: exact to double precision, no 0/0.
_SERIES_BELOW = 1e-2
_TWO_PI = 2.0 * math.pi


@dataclass(frozen=True, slots=True)
class Pose:
    """A planar pose.

    Attributes:
        x: Metres, in the odometry frame.
        y: Metres, in the odometry frame.
        yaw: Heading in radians, counter-clockwise from x, in ``(-π, π]`` when it comes
            from :class:`Odometry`.
    """

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def __post_init__(self) -> None:
        x, y, yaw = self.x, self.y, self.yaw  # finite floats pass without a call
        if type(x) is not float or x - x:
            finite("x", x, "m")
        if type(y) is not float or y - y:
            finite("y", y, "m")
        if type(yaw) is not float or yaw - yaw:
            finite("yaw", yaw, "rad")


@dataclass(frozen=True, slots=True)
class WheelNoise:
    """Wheel-noise model for the pose covariance.

    Each wheel's distance error is independent, zero-mean, with a variance proportional
    to the distance it rolled in the step: ``var = k · |d|`` (the usual model of Chong and
    Kleeman; slip and tread wear make it grow with distance, not time).

    Attributes:
        k_left_m: Left wheel variance per metre rolled, m²/m.
        k_right_m: Right wheel variance per metre rolled, m²/m.

    The defaults (1e-4 m²/m, i.e. 1 cm standard deviation after 1 m) are a starting
    guess; fit them to a UMBmark run of your robot.
    """

    k_left_m: float = 1e-4
    k_right_m: float = 1e-4

    def __post_init__(self) -> None:
        non_negative("k_left_m", self.k_left_m, "m")
        non_negative("k_right_m", self.k_right_m, "m")


class Odometry:
    """Streaming wheel odometry: pose, smoothed twist, covariance and a pose history.

    Example:
        >>> odo = Odometry(0.33)
        >>> odo.update(0.01, 0.01, t_s=0.02)
        Pose(x=0.01, y=0.0, yaw=0.0)

    Args:
        wheel_separation_m: Distance between the wheels' contact points (default 0.330 m).
        twist_window: Number of updates the twist is averaged over (default 5 = 0.1 s at
            50 Hz). The pose always uses the raw increments.
        noise: Wheel-noise model for the covariance (default :class:`WheelNoise`).
        history_size: Number of poses kept for :meth:`pose_at` (default 500 = 10 s at 50 Hz).
    """

    def __init__(
        self,
        wheel_separation_m: float = DEFAULT_WHEEL_SEPARATION_M,
        *,
        twist_window: int = 5,
        noise: WheelNoise | None = None,
        history_size: int = 500,
    ) -> None:
        self.wheel_separation_m = positive("wheel_separation_m", wheel_separation_m, "m")
        integer("twist_window", twist_window, 1, _MAX_KEPT)
        integer("history_size", history_size, 1, _MAX_KEPT)
        self.noise = noise if noise is not None else WheelNoise()
        self._window: deque[tuple[float, float, float]] = deque(maxlen=twist_window)
        # History: times in one deque (for bisect) and (x, y, θ, ds, dθ) in another.
        self._times: deque[float] = deque(maxlen=history_size)
        self._states: deque[tuple[float, float, float, float, float]] = deque(maxlen=history_size)
        self._t_s: float | None = None
        self._twist = Twist()
        self._x = 0.0
        self._y = 0.0
        self._theta = 0.0  # unwrapped heading
        # Upper triangle of the covariance: xx, xy, xθ, yy, yθ, θθ.
        self._cov = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        # The pose as last made (pose), until the next update or reset.
        self._pose: Pose | None = None

    @property
    def pose(self) -> Pose:
        """The latest pose; ``yaw`` wrapped to ``(-π, π]``."""
        pose = self._pose
        if pose is None:
            pose = self._pose = Pose(self._x, self._y, wrap_angle(self._theta))
        return pose

    @property
    def heading_rad(self) -> float:
        """The heading, unwrapped: it keeps counting past ±π (turns are not lost)."""
        return self._theta

    @property
    def twist(self) -> Twist:
        """Body velocity, averaged over the last ``twist_window`` updates.

        The average is ``Σ ds / Σ dt`` (and likewise for ``dθ``), so jitter in the update
        interval does not bias it. Zero until two updates have given it a time base.
        """
        return self._twist

    @property
    def covariance(self) -> npt.NDArray[np.float64]:
        """3×3 covariance of ``(x, y, yaw)`` since the last reset (a fresh copy)."""
        a, b, c, d, e, f = self._cov
        return np.array([[a, b, c], [b, d, e], [c, e, f]], dtype=np.float64)

    @property
    def covariance_rows(self) -> tuple[float, ...]:
        """:attr:`covariance` as nine floats, row by row, without making an array (the
        Robot puts it in every odometry sample, 50 times a second)."""
        a, b, c, d, e, f = self._cov
        return (a, b, c, b, d, e, c, e, f)

    @property
    def t_s(self) -> float | None:
        """Time of the latest update, or None before the first."""
        return self._t_s

    def update(self, d_left_m: float, d_right_m: float, t_s: float) -> Pose:
        """Integrate one pair of wheel increments.

        Args:
            d_left_m: Distance the left wheel rolled since the previous update, forward
                positive.
            d_right_m: The same for the right wheel (already un-mirrored).
            t_s: Time of the reading the increments end at; increasing. The first update
                starts the clock: its increments move the pose but not the twist.

        Returns:
            The new pose (also :attr:`pose`).

        A refused update changes nothing.

        Raises:
            InvalidArgumentError: An argument is NaN or infinite, ``t_s`` is not after
                the previous update, or the step would take a value past a finite number.
            OutOfRangeError: An increment is beyond ±1000 m.
        """
        # Floats in range pass without a call (NaN fails every comparison); anything else
        # gets the full check, and its error.
        if type(d_left_m) is not float or not -MAX_INCREMENT_M <= d_left_m <= MAX_INCREMENT_M:
            bounded("d_left_m", d_left_m, -MAX_INCREMENT_M, MAX_INCREMENT_M, "m")
        if type(d_right_m) is not float or not -MAX_INCREMENT_M <= d_right_m <= MAX_INCREMENT_M:
            bounded("d_right_m", d_right_m, -MAX_INCREMENT_M, MAX_INCREMENT_M, "m")
        if type(t_s) is not float or t_s - t_s:
            finite("t_s", t_s, "s")
        if self._t_s is not None and t_s <= self._t_s:
            raise InvalidArgumentError(
                f"t_s={t_s!r} s is not after the previous update at {self._t_s!r} s"
            )
        ds = 0.5 * (d_left_m + d_right_m)
        dtheta = (d_right_m - d_left_m) / self.wheel_separation_m
        theta0 = self._theta
        h = 0.5 * dtheta
        mid = theta0 + h
        if not math.isfinite(mid):
            raise InvalidArgumentError(
                f"d_left_m={d_left_m!r} m and d_right_m={d_right_m!r} m turn the heading past "
                f"any finite angle with wheel_separation_m={self.wheel_separation_m!r}"
            )
        sinc_h = _sinc(h)
        chord = ds * sinc_h
        cos_mid = math.cos(mid)
        sin_mid = math.sin(mid)
        dx = chord * cos_mid
        dy = chord * sin_mid
        cov = self._propagated(
            d_left_m,
            d_right_m,
            ds=ds,
            h=h,
            sinc_h=sinc_h,
            dx=dx,
            dy=dy,
            cos_mid=cos_mid,
            sin_mid=sin_mid,
        )
        twist = self._twist
        window = list(self._window)
        if self._t_s is not None:
            # What the window holds after this update (the deque drops its oldest).
            keep = self._window.maxlen or 1
            window = [*window, (t_s - self._t_s, ds, dtheta)][-keep:]
        x, y, theta = self._x + dx, self._y + dy, theta0 + dtheta
        if self._t_s is not None:
            dts, dss, dthetas = zip(*window, strict=True)
            total_dt = math.fsum(dts)
            linear = math.fsum(dss) / total_dt
            angular = math.fsum(dthetas) / total_dt
            if not (math.isfinite(linear) and math.isfinite(angular)):
                raise InvalidArgumentError(
                    f"t_s={t_s!r} s is too close to the previous update at {self._t_s!r} s "
                    f"for increments of {d_left_m!r} m and {d_right_m!r} m: the speed overflows"
                )
            twist = Twist(linear, angular)
        if not all(map(math.isfinite, (x, y, theta, *cov))):
            raise InvalidArgumentError(
                f"d_left_m={d_left_m!r} m and d_right_m={d_right_m!r} m take the pose or its "
                f"covariance past a finite number; reset() the odometry"
            )
        # Committed only now, so a refused update changes nothing.
        self._x, self._y, self._theta, self._cov = x, y, theta, cov
        self._pose = None
        if self._t_s is not None:
            self._window.append(window[-1])
            self._twist = twist
        self._t_s = float(t_s)
        self._times.append(self._t_s)
        self._states.append((self._x, self._y, self._theta, ds, dtheta))
        return self.pose

    def reset(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None:
        """Set the pose; clear the covariance and the pose history.

        The clock and the twist are kept: moving the frame does not change how fast the
        robot goes. ``yaw`` may be any finite angle; it becomes the unwrapped heading.

        Args:
            x: Metres.
            y: Metres.
            yaw: Radians.
        """
        finite("x", x, "m")
        finite("y", y, "m")
        finite("yaw", yaw, "rad")
        self._x = float(x)
        self._y = float(y)
        self._theta = float(yaw)
        self._pose = None
        self._cov = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self._times.clear()
        self._states.clear()
        if self._t_s is not None:
            self._times.append(self._t_s)
            self._states.append((self._x, self._y, self._theta, 0.0, 0.0))

    def pose_at(self, t_s: float) -> Pose:
        """The pose at a past time, interpolated along the arc of the step around it.

        Each step is assumed at constant wheel speeds, so the pose between two updates is
        on the same arc the integration used, not on a straight line between the two.

        Args:
            t_s: A time between the oldest kept update (or the last reset) and the latest.

        Raises:
            OutOfRangeError: ``t_s`` is outside the kept history.
        """
        finite("t_s", t_s, "s")
        times = self._times
        if not times or not times[0] <= t_s <= times[-1]:
            low = times[0] if times else math.nan
            high = times[-1] if times else math.nan
            raise OutOfRangeError("t_s", t_s, low, high, "s")
        i = bisect_left(times, t_s)
        x, y, theta, ds, dtheta = self._states[i]
        if times[i] == t_s:
            return Pose(x, y, wrap_angle(theta))
        x0, y0, theta0, _, _ = self._states[i - 1]
        fraction = (t_s - times[i - 1]) / (times[i] - times[i - 1])
        h = 0.5 * fraction * dtheta
        chord = fraction * ds * _sinc(h)
        mid = theta0 + h
        return Pose(
            x0 + chord * math.cos(mid),
            y0 + chord * math.sin(mid),
            wrap_angle(theta0 + fraction * dtheta),
        )

    def _propagated(
        self,
        d_left_m: float,
        d_right_m: float,
        *,
        ds: float,
        h: float,
        sinc_h: float,
        dx: float,
        dy: float,
        cos_mid: float,
        sin_mid: float,
    ) -> tuple[float, float, float, float, float, float]:
        """The covariance after one arc step: ``F Σ Fᵀ + G Q Gᵀ``."""
        a, b, c, d, e, f = self._cov
        # F = I + [[0, 0, -dy], [0, 0, dx], [0, 0, 0]]: heading error swings the step.
        p, q = -dy, dx
        a, b, c, d, e = (
            a + 2.0 * p * c + p * p * f,
            b + p * e + q * c + p * q * f,
            c + p * f,
            d + 2.0 * q * e + q * q * f,
            e + q * f,
        )
        # G = ∂(x, y, θ)/∂(dl, dr) through ds and dθ.
        half_dsinc = 0.5 * _sinc_derivative(h)
        gx_ds = sinc_h * cos_mid
        gy_ds = sinc_h * sin_mid
        gx_dth = ds * (half_dsinc * cos_mid - 0.5 * sinc_h * sin_mid)
        gy_dth = ds * (half_dsinc * sin_mid + 0.5 * sinc_h * cos_mid)
        inv_b = 1.0 / self.wheel_separation_m
        for var, sign in (
            (self.noise.k_left_m * abs(d_left_m), -1.0),
            (self.noise.k_right_m * abs(d_right_m), 1.0),
        ):
            jx = 0.5 * gx_ds + sign * inv_b * gx_dth
            jy = 0.5 * gy_ds + sign * inv_b * gy_dth
            jt = sign * inv_b
            a += var * jx * jx
            b += var * jx * jy
            c += var * jx * jt
            d += var * jy * jy
            e += var * jy * jt
            f += var * jt * jt
        return (a, b, c, d, e, f)


def integrate_batch(
    d_left_m: npt.ArrayLike,
    d_right_m: npt.ArrayLike,
    wheel_separation_m: float,
    *,
    start: Pose | None = None,
    wrap_yaw: bool = True,
) -> npt.NDArray[np.float64]:
    """Integrate a log of wheel increments at once, exactly as :class:`Odometry` does.

    Vectorised: the heading is a cumulative sum, each step's arc displacement is computed
    for all steps at once (series for small turns), then positions are cumulative sums.
    Summation runs in the same order as the streaming integrator, so both agree to
    rounding (~1e-12 m after 10⁶ steps).

    Args:
        d_left_m: Left wheel increments, metres, forward positive (length N).
        d_right_m: Right wheel increments, metres, forward positive (length N).
        wheel_separation_m: Distance between the wheels, metres.
        start: Pose before the first increment (default the origin). Not in the output.
        wrap_yaw: Wrap the yaw column to ``(-π, π]`` (default) or leave it unwrapped.

    Returns:
        N×3 float64 array; row ``i`` is ``(x, y, yaw)`` after increment ``i``.

    Raises:
        InvalidArgumentError: The inputs are not 1-D of equal length, hold NaN or inf, or
            are so extreme that a pose would not be a finite number.
    """
    b = positive("wheel_separation_m", wheel_separation_m, "m")
    start = start if start is not None else Pose()
    given: object = start  # typed, but callers may pass a tuple
    if not isinstance(given, Pose):
        raise InvalidArgumentError(f"start must be a Pose, not {type(given).__name__}")
    dl = _as_increments("d_left_m", d_left_m)
    dr = _as_increments("d_right_m", d_right_m)
    if dl.shape != dr.shape:
        raise InvalidArgumentError(f"d_left_m has {dl.size} increments but d_right_m has {dr.size}")
    # Extreme but finite inputs may overflow; the result is checked as a whole below.
    with np.errstate(over="ignore", invalid="ignore"):
        n = dl.size
        ds = 0.5 * (dl + dr)
        dtheta = (dr - dl) / b
        # Prepending the start makes cumsum add in the streaming order: (θ0 + a) + b, ...
        theta = np.empty(n + 1)
        theta[0] = start.yaw
        theta[1:] = dtheta
        np.cumsum(theta, out=theta)
        h = 0.5 * dtheta
        mid = theta[:-1] + h
        chord = ds * _sinc_array(h)
        out = np.empty((n, 3))
        steps = np.empty(n + 1)
        steps[0] = start.x
        np.multiply(chord, np.cos(mid), out=steps[1:])
        out[:, 0] = np.cumsum(steps)[1:]
        steps[0] = start.y
        np.multiply(chord, np.sin(mid), out=steps[1:])
        out[:, 1] = np.cumsum(steps)[1:]
        out[:, 2] = _wrap_array(theta[1:]) if wrap_yaw else theta[1:]
    return _check_batch(out)


def _check_batch(out: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """``out`` if every pose in it is finite, else the first step that overflowed."""
    bad = np.flatnonzero(~np.all(np.isfinite(out), axis=1))
    if bad.size:
        raise InvalidArgumentError(
            f"the pose after increment {int(bad[0])} is not a finite number: the increments "
            f"or wheel_separation_m are too extreme to integrate"
        )
    return out


def wrap_angle(angle_rad: float) -> float:
    """``angle_rad`` wrapped to ``(-π, π]``; angles already inside are returned as is.

    Raises:
        InvalidArgumentError: ``angle_rad`` is not a number, NaN or infinite.
    """
    if type(angle_rad) is float and -math.pi < angle_rad <= math.pi:
        return angle_rad  # a float inside (NaN is not): nothing to check or wrap
    finite("angle_rad", angle_rad, "rad")
    if -math.pi < angle_rad <= math.pi:
        return angle_rad
    return math.pi - (math.pi - angle_rad) % _TWO_PI


def _sinc(h: float) -> float:
    """``sin(h) / h``, by its series near zero."""
    if abs(h) < _SERIES_BELOW:
        h2 = h * h
        return 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0 * (1.0 - h2 / 42.0))
    return math.sin(h) / h


def _sinc_array(h: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """:func:`_sinc` over an array, with the same series and threshold."""
    small = np.abs(h) < _SERIES_BELOW
    h2 = h * h
    series = 1.0 - h2 / 6.0 * (1.0 - h2 / 20.0 * (1.0 - h2 / 42.0))
    safe = np.where(small, 1.0, h)
    return np.where(small, series, np.sin(safe) / safe)


def _sinc_derivative(h: float) -> float:
    """``d/dh sin(h)/h = (h cos h - sin h) / h²``, by its series near zero."""
    if abs(h) < _SERIES_BELOW:
        h2 = h * h
        return -h / 3.0 * (1.0 - h2 / 10.0 * (1.0 - h2 / 28.0 * (1.0 - h2 / 54.0)))
    return (h * math.cos(h) - math.sin(h)) / (h * h)


def _wrap_array(angle_rad: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """:func:`wrap_angle` over an array."""
    inside = (angle_rad > -math.pi) & (angle_rad <= math.pi)
    return np.where(inside, angle_rad, math.pi - np.mod(math.pi - angle_rad, _TWO_PI))


def _as_increments(name: str, values: npt.ArrayLike) -> npt.NDArray[np.float64]:
    """``values`` as a 1-D float64 array of finite numbers, or a clear error."""
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InvalidArgumentError(f"{name} must be numbers in metres: {exc}") from None
    if array.ndim != 1:
        raise InvalidArgumentError(f"{name} must be 1-D, got shape {array.shape}")
    bad = np.flatnonzero(~np.isfinite(array))
    if bad.size:
        i = int(bad[0])
        raise InvalidArgumentError(f"{name}[{i}]={float(array[i])!r} m is not a finite number")
    return array
