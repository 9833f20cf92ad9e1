"""The wheel-count plausibility filter: a count no wheel can reach is rejected, counted,
and after a few in a row taken as a new origin (sans-IO, time as an argument)."""

from __future__ import annotations

import math

import pytest

from ohmni_tb.control.encoder import (
    COUNT_SLACK_M,
    REBASE_AFTER,
    CountFilter,
    CountVerdict,
    EncoderConfig,
    WheelEncoder,
)
from ohmni_tb.errors import InvalidArgumentError

MAX_MPS = 3.0
PERIOD_S = 0.02
CONFIG = EncoderConfig()
#: Ticks a wheel at MAX_MPS rolls in one period, plus the slack.
LIMIT_TICKS = (MAX_MPS * PERIOD_S + COUNT_SLACK_M) / CONFIG.metres_per_tick


def new_filter(config: EncoderConfig = CONFIG) -> CountFilter:
    return CountFilter(WheelEncoder(config), MAX_MPS)


def feed(counts: CountFilter, raw: int, t_s: float) -> CountVerdict:
    """Check a read and take it when it is plausible, as a caller with one wheel does."""
    verdict = counts.check(raw, t_s)
    if verdict is CountVerdict.TAKE:
        counts.take(raw, t_s)
    return verdict


def test_plausible_reads_reach_the_encoder() -> None:
    counts = new_filter()
    assert feed(counts, 1000, 0.0) is CountVerdict.TAKE
    assert feed(counts, 1500, PERIOD_S) is CountVerdict.TAKE
    last = counts.encoder.last
    assert last is not None
    assert last.count == 500
    assert last.delta_m == pytest.approx(500 * CONFIG.metres_per_tick)
    assert counts.last_raw == 1500
    assert counts.rejected == 0


def test_the_limit_is_the_fastest_wheel_over_the_time_between_reads() -> None:
    at_limit = math.floor(LIMIT_TICKS)
    counts = new_filter()
    feed(counts, 0, 0.0)
    assert counts.check(at_limit, PERIOD_S) is CountVerdict.TAKE
    assert counts.check(-at_limit, PERIOD_S) is CountVerdict.TAKE  # backwards too
    assert counts.check(at_limit + 2, PERIOD_S) is CountVerdict.IMPLAUSIBLE
    # Twice the time between the reads: twice the distance is plausible.
    assert counts.check(2 * at_limit - 200, 2 * PERIOD_S) is CountVerdict.TAKE


def test_a_flipped_bit_is_rejected_and_counted_and_the_next_good_read_carries_the_motion() -> None:
    counts = new_filter()
    feed(counts, 10_000, 0.0)
    assert feed(counts, 10_000 ^ (1 << 20), PERIOD_S) is CountVerdict.IMPLAUSIBLE
    assert counts.rejected == 1
    last = counts.encoder.last
    assert last is not None
    assert last.count == 0  # the encoder never saw the bad read
    assert feed(counts, 10_400, 2 * PERIOD_S) is CountVerdict.TAKE
    last = counts.encoder.last
    assert last is not None
    assert last.count == 400
    assert last.delta_m == pytest.approx(400 * CONFIG.metres_per_tick)


def test_a_count_that_really_jumped_becomes_a_new_origin_after_a_few_reads() -> None:
    counts = new_filter()
    feed(counts, 5_000, 0.0)
    feed(counts, 5_300, PERIOD_S)
    verdicts = [feed(counts, 9_000_000 + i, (2 + i) * PERIOD_S) for i in range(REBASE_AFTER)]
    assert verdicts == [CountVerdict.IMPLAUSIBLE] * (REBASE_AFTER - 1) + [CountVerdict.REBASED]
    assert counts.rejected == REBASE_AFTER
    # The encoder starts again from the count it was rebased on: no jump reaches it.
    last = counts.encoder.last
    assert last is not None
    assert (last.count, last.delta_m) == (0, 0.0)
    assert counts.last_raw == 9_000_000 + REBASE_AFTER - 1
    assert feed(counts, 9_000_100, (2 + REBASE_AFTER) * PERIOD_S) is CountVerdict.TAKE
    last = counts.encoder.last
    assert last is not None
    assert last.count == 100 - (REBASE_AFTER - 1)


def test_a_good_read_between_bad_ones_restarts_the_run() -> None:
    counts = new_filter()
    feed(counts, 0, 0.0)
    t = PERIOD_S
    for _ in range(3):
        for _ in range(REBASE_AFTER - 1):
            assert feed(counts, 1 << 24, t) is CountVerdict.IMPLAUSIBLE
            t += PERIOD_S
        assert feed(counts, 10, t) is CountVerdict.TAKE
        t += PERIOD_S
    assert counts.rejected == 3 * (REBASE_AFTER - 1)


def test_a_read_not_after_the_last_one_taken_is_stale_and_not_counted() -> None:
    counts = new_filter()
    feed(counts, 100, 1.0)
    assert counts.check(10**9, 1.0) is CountVerdict.STALE
    assert counts.check(100, 0.5) is CountVerdict.STALE
    assert counts.rejected == 0


def test_the_int32_count_wrapping_is_a_small_step() -> None:
    counts = new_filter()
    feed(counts, 2**31 - 100, 0.0)
    assert feed(counts, -(2**31) + 100, PERIOD_S) is CountVerdict.TAKE
    last = counts.encoder.last
    assert last is not None
    assert last.count == 200


def test_the_mirrored_wheel_is_judged_on_the_size_of_its_step() -> None:
    counts = new_filter(EncoderConfig.right())
    feed(counts, 0, 0.0)
    assert feed(counts, -1000, PERIOD_S) is CountVerdict.TAKE
    last = counts.encoder.last
    assert last is not None
    assert last.count == 1000  # forward, un-mirrored


def test_reset_forgets_the_reads_taken() -> None:
    counts = new_filter()
    feed(counts, 0, 0.0)
    feed(counts, 100, PERIOD_S)
    counts.reset()
    assert counts.last_raw is None
    assert counts.encoder.last is None
    assert counts.check(10**8, 2 * PERIOD_S) is CountVerdict.TAKE  # nothing to compare


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_mps": 0.0}, "max_mps=0.0 m/s must be > 0"),
        ({"max_mps": math.nan}, "max_mps=nan"),
        ({"max_mps": 3.0, "slack_m": math.inf}, "slack_m=inf m"),
        ({"max_mps": 3.0, "slack_m": -0.001}, "slack_m=-0.001 m"),
        ({"max_mps": 3.0, "rebase_after": 0}, "rebase_after=0 must be an integer >= 1"),
    ],
)
def test_bad_settings_are_refused_by_name(kwargs: dict[str, float], message: str) -> None:
    with pytest.raises(InvalidArgumentError, match=message):
        CountFilter(WheelEncoder(), **kwargs)  # type: ignore[arg-type]  # the bad values
