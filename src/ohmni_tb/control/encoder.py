"""Wheel encoders: unwrap the board's counters, convert ticks to metres, estimate speed.

A drive board reports two counters of the same motor encoder:

- RAM 59, the accumulated count, int32: wraps from 2**31 - 1 to -2**31 after ~24 km.
- RAM 58, the motor position, 14 bits 0..16383: wraps every motor turn (~10.7 mm of
  travel). Unwrapping it is only unambiguous while the wheel moves less than half a motor
  turn (8192 ticks, ~87 ms at 1 m/s) between two *good* reads, so after a few failed reads
  at speed it silently loses turns; prefer the int32 count.

Both unwrap the same way: the step between two reads is taken modulo the counter's range
and mapped into ``[-range/2, range/2)``. The right wheel counts mirrored; a mirrored
:class:`EncoderConfig` negates it so that forward is positive on both wheels.

A failed read is never a sample: pass ``None`` and nothing changes, so the next good read
carries the whole motion since the last good one, and the speed estimate does not see a
fake stop.

A read can also be wrong and still pass the bus's 7-bit checksum (a flipped bit): a
:class:`CountFilter` in front of the encoder rejects a count no wheel can reach from the
last one, and counts it.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

from ohmni_tb._checks import (
    FLOAT_MAX,
    finite,
    finite_result,
    integer,
    non_negative,
    positive,
    whole,
)
from ohmni_tb.control.defaults import DEFAULT_TICKS_PER_REV, DEFAULT_WHEEL_RADIUS_M
from ohmni_tb.errors import InvalidArgumentError

__all__ = [
    "COUNT_BITS",
    "COUNT_SLACK_M",
    "MOTOR_POSITION_BITS",
    "REBASE_AFTER",
    "CountFilter",
    "CountVerdict",
    "EncoderConfig",
    "Unwrapper",
    "VelocityEstimator",
    "WheelEncoder",
    "WheelSample",
    "unwrap_delta",
]

#: Width of the accumulated wheel count (RAM 59, int32 LE).
COUNT_BITS = 32
#: Width of the motor position (RAM 58, 0..16383: one motor turn).
MOTOR_POSITION_BITS = 14
#: The widest counter unwrapped.
MAX_COUNTER_BITS = 64
#: Largest continuous count a speed estimate takes (a 64-bit counter's range).
_MAX_COUNT = 1 << 63
#: Closest two samples may be: a speed over less is a division by rounding noise.
MIN_SAMPLE_SPACING_S = 1e-9
#: What a plausible read may roll beyond the fastest wheel in the time between two reads:
#: a couple of millimetres of timing noise and the count's own step.
COUNT_SLACK_M = 0.002
#: Implausible reads in a row after which the count really moved (a board reset) and is
#: taken as a new origin.
REBASE_AFTER = 3


def unwrap_delta(previous: int, current: int, bits: int) -> int:
    """The signed step between two reads of a ``bits``-wide wrapping counter.

    Args:
        previous: The earlier raw reading.
        current: The later raw reading.
        bits: The counter's width.

    Returns:
        ``current - previous`` modulo ``2**bits``, in ``[-2**(bits-1), 2**(bits-1))``.

    Raises:
        InvalidArgumentError: A reading is not an int.
        OutOfRangeError: ``bits`` is not 2..64.
    """
    whole("previous", previous)
    whole("current", current)
    integer("bits", bits, 2, MAX_COUNTER_BITS)
    return _unwrap(previous, current, bits)


def _unwrap(previous: int, current: int, bits: int) -> int:
    """:func:`unwrap_delta` of readings and a width already checked."""
    modulus = 1 << bits
    half = modulus >> 1
    return (current - previous + half) % modulus - half


class Unwrapper:
    """Turns readings of a wrapping counter into a continuous count.

    Args:
        bits: The counter's width (32 for the wheel count, 14 for the motor position).
        signed: Whether raw readings are two's complement (the int32 count) or unsigned.
    """

    def __init__(self, bits: int = COUNT_BITS, *, signed: bool = True) -> None:
        self.bits = integer("bits", bits, 2, MAX_COUNTER_BITS)
        self.low = -(1 << (bits - 1)) if signed else 0
        self.high = self.low + (1 << bits) - 1
        self._raw: int | None = None
        self._count = 0

    @classmethod
    def for_count(cls) -> Unwrapper:
        """An unwrapper for the int32 accumulated wheel count (RAM 59)."""
        return cls(COUNT_BITS, signed=True)

    @classmethod
    def for_motor_position(cls) -> Unwrapper:
        """An unwrapper for the 14-bit motor position (RAM 58)."""
        return cls(MOTOR_POSITION_BITS, signed=False)

    @property
    def count(self) -> int:
        """The continuous count: the first reading plus every unwrapped step since."""
        return self._count

    def update(self, raw: int) -> int:
        """Feed one good reading; returns the continuous count.

        Raises:
            OutOfRangeError: ``raw`` does not fit the counter.
        """
        if type(raw) is not int or not self.low <= raw <= self.high:
            integer("raw", raw, self.low, self.high, "ticks")  # raises, naming the range
        if self._raw is None:
            self._count = raw
        else:
            self._count += _unwrap(self._raw, raw, self.bits)
        self._raw = raw
        return self._count

    def reset(self) -> None:
        """Forget the history; the next reading starts the count again."""
        self._raw = None
        self._count = 0


@dataclass(frozen=True, slots=True)
class EncoderConfig:
    """How a wheel's counter maps to distance.

    Attributes:
        ticks_per_rev: Ticks per wheel turn (default 16384 × 30/11 ≈ 44,684, inferred).
        wheel_radius_m: Wheel radius (default 0.0760 m).
        mirrored: The counter runs backwards when the wheel drives forward (the right
            wheel of the Ohmni).
        counter_bits: Width of the counter read (32 for RAM 59, 14 for RAM 58).
        counter_signed: Whether the counter is two's complement.
    """

    ticks_per_rev: float = DEFAULT_TICKS_PER_REV
    wheel_radius_m: float = DEFAULT_WHEEL_RADIUS_M
    mirrored: bool = False
    counter_bits: int = COUNT_BITS
    counter_signed: bool = True

    def __post_init__(self) -> None:
        positive("ticks_per_rev", self.ticks_per_rev, "ticks")
        positive("wheel_radius_m", self.wheel_radius_m, "m")
        for name in ("mirrored", "counter_signed"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidArgumentError(f"{name} must be a bool, not {getattr(self, name)!r}")
        integer("counter_bits", self.counter_bits, 2, MAX_COUNTER_BITS)
        per_tick = self.metres_per_tick
        if not (math.isfinite(per_tick) and per_tick > 0.0):
            raise InvalidArgumentError(
                f"wheel_radius_m={self.wheel_radius_m!r} m and ticks_per_rev="
                f"{self.ticks_per_rev!r} give {per_tick!r} m a tick: not a usable scale"
            )

    @classmethod
    def left(cls, wheel_radius_m: float = DEFAULT_WHEEL_RADIUS_M) -> EncoderConfig:
        """The Ohmni's left wheel on its int32 count."""
        return cls(wheel_radius_m=wheel_radius_m)

    @classmethod
    def right(cls, wheel_radius_m: float = DEFAULT_WHEEL_RADIUS_M) -> EncoderConfig:
        """The Ohmni's right wheel on its int32 count (mirrored)."""
        return cls(wheel_radius_m=wheel_radius_m, mirrored=True)

    @property
    def metres_per_tick(self) -> float:
        """Distance a wheel rolls per tick (≈10.7 µm by default)."""
        return 2.0 * math.pi * self.wheel_radius_m / self.ticks_per_rev

    def ticks_to_m(self, ticks: float) -> float:
        """Distance rolled for ``ticks`` (forward-positive ticks, mirroring applied).

        Raises:
            InvalidArgumentError: Not a number, NaN or infinite.
            OutOfRangeError: The distance would not be a finite number.
        """
        per_tick = self.metres_per_tick
        limit = FLOAT_MAX / max(per_tick, 1.0)
        return finite_result(
            finite("ticks", ticks, "ticks") * per_tick, "ticks", ticks, -limit, limit, unit="ticks"
        )

    def m_to_ticks(self, distance_m: float) -> float:
        """Ticks for a rolled distance (forward-positive ticks, mirroring applied).

        Raises:
            InvalidArgumentError: Not a number, NaN or infinite.
            OutOfRangeError: The tick count would not be a finite number.
        """
        per_tick = self.metres_per_tick
        limit = FLOAT_MAX * min(per_tick, 1.0)
        return finite_result(
            finite("distance_m", distance_m, "m") / per_tick,
            "distance_m",
            distance_m,
            -limit,
            limit,
            unit="m",
        )


class VelocityEstimator:
    """Speed of a tick counter that stays useful down to a tick every few samples.

    At speed it divides the ticks counted over the last ``window_s`` by the time they
    took. When the window holds fewer than ``min_ticks`` ticks, that ratio jumps between
    zero and one tick per window, so it switches to the time between the last two count
    changes, bounded by one tick over the time since the last change (had the wheel kept
    its speed, the next tick would have come by now). It reports zero once no tick has
    come for ``stop_after_s``.

    Args:
        window_s: Length of the counting window (default 0.1 s, 5 samples at 50 Hz).
        min_ticks: Ticks in the window from which the window rate is trusted.
        stop_after_s: Time without a tick after which the speed is zero.
    """

    def __init__(
        self, *, window_s: float = 0.1, min_ticks: int = 4, stop_after_s: float = 0.5
    ) -> None:
        self.window_s = positive("window_s", window_s, "s")
        self.min_ticks = integer("min_ticks", min_ticks, 1)
        self.stop_after_s = positive("stop_after_s", stop_after_s, "s")
        self._samples: deque[tuple[float, int]] = deque()
        self._last_change: tuple[float, int] | None = None
        self._prev_change: tuple[float, int] | None = None
        self._rate = 0.0

    @property
    def rate(self) -> float:
        """The latest estimate, ticks/s."""
        return self._rate

    def update(self, count: int, t_s: float) -> float:
        """Add a sample of the continuous count; returns the speed estimate in ticks/s.

        Raises:
            InvalidArgumentError: ``t_s`` is not finite or not after the previous sample
                (by at least a nanosecond), or ``count`` is not an int.
            OutOfRangeError: ``count`` is beyond ±2**63.
        """
        if type(count) is not int or not -_MAX_COUNT <= count <= _MAX_COUNT:
            integer("count", count, -_MAX_COUNT, _MAX_COUNT, "ticks")
        if type(t_s) is not float or t_s - t_s:  # a finite float passes without a call
            finite("t_s", t_s, "s")
        samples = self._samples
        if samples:
            last_t, last_count = samples[-1]
            if not t_s - last_t >= MIN_SAMPLE_SPACING_S:
                raise InvalidArgumentError(
                    f"t_s={t_s!r} s is not after the previous sample at {last_t!r} s"
                )
            if count != last_count:
                self._prev_change = self._last_change
                self._last_change = (t_s, count)
        else:
            # The first sample counts as a change: a wheel that starts after standing a
            # long time gets a small first estimate instead of none.
            self._last_change = (t_s, count)
        samples.append((t_s, count))
        # Keep the newest sample at or before the window start, so the window is full.
        while len(samples) > 2 and samples[1][0] <= t_s - self.window_s:
            samples.popleft()
        self._rate = self._estimate(t_s, count)
        return self._rate

    def reset(self) -> None:
        """Forget every sample."""
        self._samples.clear()
        self._last_change = None
        self._prev_change = None
        self._rate = 0.0

    def _estimate(self, t_s: float, count: int) -> float:
        """The estimate after a sample at ``t_s``."""
        first_t, first_count = self._samples[0]
        ticks = count - first_count
        if abs(ticks) >= self.min_ticks:
            return ticks / (t_s - first_t)
        last = self._last_change
        prev = self._prev_change
        if last is None or prev is None or t_s - last[0] > self.stop_after_s:
            return 0.0
        edge_rate = (last[1] - prev[1]) / (last[0] - prev[0])
        since_s = t_s - last[0]
        if since_s > 0.0 and abs(edge_rate) * since_s > 1.0:
            return math.copysign(1.0 / since_s, edge_rate)
        return edge_rate


@dataclass(frozen=True, slots=True)
class WheelSample:
    """One good encoder reading, converted.

    Attributes:
        t_s: Time of the reading.
        count: Continuous tick count, forward positive, since the first reading.
        position_m: Distance rolled since the first reading, forward positive.
        delta_m: Distance rolled since the previous good reading (0 for the first).
        velocity_mps: Rim speed estimate.
    """

    t_s: float
    count: int
    position_m: float
    delta_m: float
    velocity_mps: float


class WheelEncoder:
    """One wheel: unwrap, un-mirror, convert to metres and estimate speed.

    Args:
        config: The wheel's counter and geometry (default: left wheel, int32 count).
        velocity: The speed estimator (default :class:`VelocityEstimator`).
    """

    def __init__(
        self, config: EncoderConfig | None = None, velocity: VelocityEstimator | None = None
    ) -> None:
        self.config = config if config is not None else EncoderConfig()
        self._unwrapper = Unwrapper(self.config.counter_bits, signed=self.config.counter_signed)
        self._velocity = velocity if velocity is not None else VelocityEstimator()
        self._origin: int | None = None
        self._last: WheelSample | None = None

    @property
    def last(self) -> WheelSample | None:
        """The latest good sample."""
        return self._last

    def update(self, raw: int | None, t_s: float) -> WheelSample | None:
        """Feed one read of the counter.

        Args:
            raw: The raw counter value, or None when the read failed.
            t_s: Time of the read.

        Returns:
            The converted sample, or None for a failed read (nothing changes).

        Raises:
            OutOfRangeError: ``raw`` does not fit the counter.
            InvalidArgumentError: ``t_s`` is not finite or not after the previous read.
        """
        if type(t_s) is not float or t_s - t_s:  # a finite float passes without a call
            finite("t_s", t_s, "s")
        if raw is None:
            return None
        if self._last is not None and t_s <= self._last.t_s:
            raise InvalidArgumentError(
                f"t_s={t_s!r} s is not after the previous read at {self._last.t_s!r} s"
            )
        unwrapped = self._unwrapper.update(raw)
        if self._origin is None:
            self._origin = unwrapped
        count = unwrapped - self._origin
        if self.config.mirrored:
            count = -count
        metres_per_tick = self.config.metres_per_tick
        previous = 0 if self._last is None else self._last.count
        self._last = WheelSample(
            t_s=float(t_s),
            count=count,
            position_m=count * metres_per_tick,
            delta_m=(count - previous) * metres_per_tick,
            velocity_mps=self._velocity.update(count, t_s) * metres_per_tick,
        )
        return self._last

    def reset(self) -> None:
        """Forget every reading; the next one is a new origin."""
        self._unwrapper.reset()
        self._velocity.reset()
        self._origin = None
        self._last = None


class CountVerdict(enum.Enum):
    """What :meth:`CountFilter.check` makes of one read."""

    #: Plausible: :meth:`CountFilter.take` it.
    TAKE = "take"
    #: A step no wheel can make since the last read taken: rejected (counted).
    IMPLAUSIBLE = "implausible"
    #: The last of :data:`REBASE_AFTER` implausible reads in a row (counted): the count
    #: really moved, and the encoder starts again from it.
    REBASED = "rebased"
    #: Not after the last read taken: ignored.
    STALE = "stale"


class CountFilter:
    """One wheel's count reads, checked before its encoder takes them (sans-IO).

    A read whose step from the last one taken is more than a wheel at ``max_mps`` rolls
    in the time between them (plus ``slack_m``) is rejected: a bit flipped past the bus's
    7-bit checksum would otherwise hand odometry a jump of metres. After ``rebase_after``
    such reads in a row the count did move (the board reset): the encoder is reset and
    starts from that read.

    Checking and taking are two steps, so a caller that needs both wheels of one tick
    (odometry) takes both reads or neither.

    Args:
        encoder: The wheel's encoder, fed by :meth:`take`.
        max_mps: The fastest a wheel can roll, m/s.
        slack_m: What a read may exceed that by.
        rebase_after: Implausible reads in a row before the count is a new origin.

    Attributes:
        encoder: The wheel's encoder.
        rejected: Reads rejected as implausible, rebases included.
    """

    def __init__(
        self,
        encoder: WheelEncoder,
        max_mps: float,
        *,
        slack_m: float = COUNT_SLACK_M,
        rebase_after: int = REBASE_AFTER,
    ) -> None:
        self.encoder = encoder
        self.max_mps = positive("max_mps", max_mps, "m/s")
        self.slack_m = non_negative("slack_m", slack_m, "m")
        self.rebase_after = integer("rebase_after", rebase_after, 1)
        self.rejected = 0
        self._in_row = 0
        self._raw: int | None = None
        self._t_s: float | None = None

    @property
    def last_raw(self) -> int | None:
        """The last raw count taken (or rebased on)."""
        return self._raw

    def check(self, raw: int, t_s: float) -> CountVerdict:
        """Judge the read ``raw`` at ``t_s`` against the last one taken.

        On :attr:`CountVerdict.REBASED` the encoder has been reset and has taken ``raw``
        as its new origin; nothing is to be taken.

        Raises:
            InvalidArgumentError: ``raw`` is not an int, or ``t_s`` not a finite number.
            OutOfRangeError: ``raw`` does not fit the counter (a rebase on it).
        """
        if type(raw) is not int:
            whole("raw", raw)
        if type(t_s) is not float or t_s - t_s:  # a finite float passes without a call
            finite("t_s", t_s, "s")
        last_raw, last_t = self._raw, self._t_s
        if last_t is None or last_raw is None:
            return CountVerdict.TAKE
        if t_s <= last_t:
            return CountVerdict.STALE
        ticks = abs(_unwrap(last_raw, raw, self.encoder.config.counter_bits))
        if ticks * self.encoder.config.metres_per_tick <= self.max_mps * (t_s - last_t) + (
            self.slack_m
        ):
            return CountVerdict.TAKE
        self.rejected += 1
        self._in_row += 1
        if self._in_row < self.rebase_after:
            return CountVerdict.IMPLAUSIBLE
        self.encoder.reset()
        self.encoder.update(raw, t_s)
        self._raw, self._t_s, self._in_row = raw, t_s, 0
        return CountVerdict.REBASED

    def take(self, raw: int, t_s: float) -> WheelSample:
        """Feed a read :meth:`check` found plausible to the encoder; its sample.

        Raises:
            InvalidArgumentError: ``raw`` is not an int, or ``t_s`` is not after the
                previous read.
            OutOfRangeError: ``raw`` does not fit the counter.
        """
        if type(raw) is not int:
            whole("raw", raw)
        sample = self.encoder.update(raw, t_s)
        self._in_row = 0
        self._raw, self._t_s = raw, t_s
        assert sample is not None  # a read, not a failed one: always a sample
        return sample

    def reset(self) -> None:
        """Forget the reads taken and the encoder's history."""
        self.encoder.reset()
        self._raw = self._t_s = None
        self._in_row = 0
