"""Encoders: counter unwrapping, ticks ↔ metres, mirroring, speed, failed reads."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.control import (
    DEFAULT_TICKS_PER_REV,
    EncoderConfig,
    Unwrapper,
    VelocityEstimator,
    WheelEncoder,
    unwrap_delta,
)
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

INT32_MAX = 2**31 - 1
INT32_MIN = -(2**31)


def test_motor_position_wraps_both_ways() -> None:
    assert unwrap_delta(16380, 3, 14) == 7
    assert unwrap_delta(3, 16380, 14) == -7
    # Half a turn is ambiguous; it is read as backwards.
    assert unwrap_delta(0, 8192, 14) == -8192
    assert unwrap_delta(0, 8191, 14) == 8191


def test_int32_count_overflow_is_unwrapped() -> None:
    unwrapper = Unwrapper.for_count()
    assert unwrapper.update(INT32_MAX - 10) == INT32_MAX - 10
    assert unwrapper.update(INT32_MIN + 4) == INT32_MAX + 5
    assert unwrapper.update(INT32_MAX) == INT32_MAX  # and back down through the wrap


@given(
    st.integers(0, 16383),
    st.lists(st.integers(-8192, 8191), max_size=60),
)
def test_unwrapped_motor_position_follows_the_true_count(start: int, steps: list[int]) -> None:
    unwrapper = Unwrapper.for_motor_position()
    true_count = start
    assert unwrapper.update(start) == start
    for step in steps:
        true_count += step
        assert unwrapper.update(true_count % 16384) == true_count


@given(st.integers(INT32_MIN, INT32_MAX), st.lists(st.integers(-(2**31), 2**31 - 1), max_size=30))
def test_unwrapped_int32_follows_the_true_count(start: int, steps: list[int]) -> None:
    unwrapper = Unwrapper.for_count()
    true_count = start
    unwrapper.update(start)
    for step in steps:
        true_count += step
        raw = (true_count - INT32_MIN) % 2**32 + INT32_MIN  # as the board's int32 reads
        assert unwrapper.update(raw) == true_count


def test_raw_values_outside_the_counter_are_rejected() -> None:
    with pytest.raises(OutOfRangeError, match="raw=16384"):
        Unwrapper.for_motor_position().update(16384)
    with pytest.raises(OutOfRangeError, match="raw=-1"):
        Unwrapper.for_motor_position().update(-1)
    with pytest.raises(OutOfRangeError, match="raw=2147483648"):
        Unwrapper.for_count().update(2**31)


def test_ticks_and_metres_from_ticks_per_turn_and_radius() -> None:
    config = EncoderConfig()
    turn_m = 2.0 * math.pi * 0.076
    assert config.ticks_to_m(DEFAULT_TICKS_PER_REV) == pytest.approx(turn_m)
    assert config.m_to_ticks(turn_m) == pytest.approx(DEFAULT_TICKS_PER_REV)
    assert 1e-3 / config.metres_per_tick == pytest.approx(93.58, abs=0.01)  # ticks per mm


def test_right_wheel_is_mirrored_to_forward_positive() -> None:
    right = WheelEncoder(EncoderConfig.right())
    right.update(1000, 0.0)
    sample = right.update(1000 - 44684, 0.02)  # one wheel turn, counted backwards
    assert sample is not None
    assert sample.count == 44684
    assert sample.position_m == pytest.approx(44684 * EncoderConfig().metres_per_tick)
    assert sample.delta_m == sample.position_m


def test_encoder_across_int32_overflow() -> None:
    left = WheelEncoder(EncoderConfig.left())
    first = left.update(INT32_MAX - 99, 0.0)
    assert first is not None
    assert (first.count, first.delta_m, first.velocity_mps) == (0, 0.0, 0.0)
    sample = left.update(INT32_MIN + 100, 0.02)
    assert sample is not None
    assert sample.count == 200
    assert sample.delta_m == pytest.approx(200 * EncoderConfig().metres_per_tick)


def test_failed_read_is_never_a_sample() -> None:
    encoder = WheelEncoder()
    encoder.update(0, 0.00)
    encoder.update(200, 0.02)
    assert encoder.update(None, 0.04) is None
    assert encoder.last is not None
    assert encoder.last.t_s == 0.02
    sample = encoder.update(600, 0.06)
    assert sample is not None
    # The good read carries both intervals; the speed never dipped to zero.
    assert sample.delta_m == pytest.approx(400 * EncoderConfig().metres_per_tick)
    assert sample.velocity_mps == pytest.approx(10_000 * EncoderConfig().metres_per_tick)


def test_motor_position_encoder_wraps_every_motor_turn() -> None:
    config = EncoderConfig(counter_bits=14, counter_signed=False)
    encoder = WheelEncoder(config)
    position = 0
    for k in range(50):
        sample = encoder.update(position % 16384, k * 0.02)
        position += 5000
    assert sample is not None
    assert sample.count == 49 * 5000


def test_velocity_at_speed_is_ticks_over_the_window() -> None:
    estimator = VelocityEstimator()
    rate = 9_876.5  # ticks/s, ~0.1 m/s
    estimates = [estimator.update(math.floor(rate * k * 0.02), k * 0.02) for k in range(50)]
    for estimate in estimates[5:]:
        assert abs(estimate - rate) <= 1.0 / 0.1  # one tick over the 0.1 s window


def test_velocity_at_a_tick_every_fifteen_samples_stays_useful() -> None:
    # One tick every 0.3 s (3.33 ticks/s): a 0.1 s window would read 0 or 10 ticks/s.
    estimator = VelocityEstimator()
    estimates = [estimator.update(k // 15, k * 0.02) for k in range(91)]
    for estimate in estimates[30:]:
        assert estimate == pytest.approx(1.0 / 0.3)


def test_velocity_decays_after_the_last_tick_and_reaches_zero() -> None:
    estimator = VelocityEstimator(stop_after_s=0.5)
    for k in range(31):
        estimator.update(k // 15, k * 0.02)  # ticks at 0.3 s and 0.6 s
    # Stopped at count 2: after 0.3 s without a tick the estimate falls as 1 / t.
    assert estimator.update(2, 1.0) == pytest.approx(1.0 / 0.4)
    assert estimator.update(2, 1.05) == pytest.approx(1.0 / 0.45)
    assert estimator.update(2, 1.2) == 0.0  # no tick for 0.6 s > stop_after_s


def test_velocity_estimator_rejects_time_going_backwards() -> None:
    estimator = VelocityEstimator()
    estimator.update(0, 1.0)
    with pytest.raises(InvalidArgumentError, match=r"t_s=1\.0"):
        estimator.update(1, 1.0)
    with pytest.raises(InvalidArgumentError, match="t_s=nan"):
        estimator.update(1, math.nan)


def test_reset_starts_a_new_origin() -> None:
    encoder = WheelEncoder()
    encoder.update(500, 0.0)
    encoder.update(900, 0.02)
    encoder.reset()
    sample = encoder.update(100, 0.04)
    assert sample is not None
    assert sample.count == 0
    assert encoder.update(150, 0.06) is not None


def test_bad_config_is_rejected_by_name() -> None:
    with pytest.raises(InvalidArgumentError, match="ticks_per_rev=0"):
        EncoderConfig(ticks_per_rev=0)
    with pytest.raises(InvalidArgumentError, match="wheel_radius_m=nan"):
        EncoderConfig(wheel_radius_m=math.nan)
    with pytest.raises(InvalidArgumentError, match="min_ticks=0"):
        VelocityEstimator(min_ticks=0)
