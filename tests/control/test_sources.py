"""Command sources (sans-IO): the highest live source drives, a lower one is refused and
changes nothing, a source lapses its timeout after its last command taken, a goal holds
its source live; the table's text is read with each bad entry named."""

from __future__ import annotations

import math

import pytest

from ohmni_tb.control.sources import (
    DEFAULT_SOURCES,
    CommandSource,
    SourceMux,
    claimable_beyond_loopback,
    format_sources,
    parse_sources,
)
from ohmni_tb.errors import InvalidArgumentError


def mux() -> SourceMux:
    return SourceMux(DEFAULT_SOURCES)


def test_the_default_table_is_safety_local_remote_autonomy_with_their_timeouts() -> None:
    assert [(s.name, s.timeout_s) for s in DEFAULT_SOURCES] == [
        ("safety", 0.5),
        ("local", 0.5),
        ("remote", 0.5),
        ("autonomy", 1.0),
    ]
    assert format_sources(DEFAULT_SOURCES) == (
        "safety:0.5",
        "local:0.5",
        "remote:0.5",
        "autonomy:1",
    )


def test_a_higher_source_overrides_a_lower_one_until_it_lapses() -> None:
    sources = mux()
    assert sources.active(0.0) is None
    assert sources.take("remote", 0.0) is None
    assert sources.active(0.1) == "remote"
    assert sources.take("local", 0.2) is None  # higher: taken at once
    assert sources.active(0.2) == "local"
    # The lower one is refused, named the source in its way, and nothing changes: its
    # refused command does not keep it live.
    assert sources.take("remote", 0.3) == "local"
    assert sources.take("remote", 0.65) == "local"
    assert sources.lapses_at("local") == pytest.approx(0.7)
    assert sources.active(0.69) == "local"
    # local lapses 0.5 s after its last command; remote's last taken one was at 0.0.
    assert sources.active(0.7) is None
    assert sources.take("remote", 0.71) is None
    assert sources.active(0.71) == "remote"


def test_a_lower_source_still_live_drives_again_when_the_higher_lapses() -> None:
    sources = mux()
    sources.take("autonomy", 0.0)  # live until 1.0
    sources.take("local", 0.1)  # until 0.6
    assert sources.active(0.5) == "local"
    assert sources.active(0.6) == "autonomy"
    assert sources.active(1.0) is None


def test_a_command_of_the_source_that_drives_keeps_it_live() -> None:
    sources = mux()
    for tick in range(20):  # 10 Hz for 2 s
        assert sources.take("local", tick * 0.1) is None
        assert sources.take("autonomy", tick * 0.1 + 0.05) == "local"
    assert sources.active(2.3) == "local"
    assert sources.active(2.401) is None  # 0.5 s after the last, at 1.9 s


def test_a_held_source_stays_live_and_lapses_its_timeout_after_release() -> None:
    sources = mux()
    sources.hold("remote")
    assert sources.active(100.0) == "remote"
    assert math.isinf(sources.lapses_at("remote"))
    assert sources.take("autonomy", 100.0) == "remote"
    assert sources.take("local", 100.0) is None  # a higher one still takes over
    sources.release("remote", 100.0)
    assert sources.active(100.4) == "local"
    assert sources.blocker("autonomy", 100.4) == "local"
    assert sources.active(100.5) is None  # both lapsed 0.5 s after


def test_the_order_is_the_priority() -> None:
    sources = SourceMux(parse_sources("autonomy:1,remote:0.5,local:0.5"))
    assert sources.take("local", 0.0) is None
    assert sources.take("autonomy", 0.1) is None  # first in this table: the highest
    assert sources.take("local", 0.2) == "autonomy"
    assert sources.outranks("autonomy", "local")


def test_an_unknown_source_is_refused_naming_the_sources() -> None:
    with pytest.raises(InvalidArgumentError) as raised:
        mux().check_name("operator")
    assert str(raised.value) == (
        "source='operator' is not a command source: allowed safety, local, remote, autonomy"
    )
    with pytest.raises(InvalidArgumentError, match="source=3 is not"):
        mux().check_name(3)


def test_beyond_loopback_a_client_may_claim_remote_and_below_only() -> None:
    table = parse_sources("safety:0.5,local:0.5,operator:0.5,remote:0.5,nav:2,autonomy:1")
    allowed = [s.name for s in table if claimable_beyond_loopback(table, s.name)]
    assert allowed == ["remote", "nav", "autonomy"]
    assert not claimable_beyond_loopback(table, "nobody")


@pytest.mark.parametrize(
    ("text", "said"),
    [
        (
            "local:0.5,remote:0.5",
            "command_sources lacks autonomy: the table needs local, remote, autonomy",
        ),
        ("local:soon,remote:1,autonomy:1", "entry 1 'local:soon': 'soon' is not a number"),
        ("local:0.5,Remote:1,autonomy:1", "entry 2 'Remote:1': 'Remote' is not a source name"),
        ("local:0.5,remote:0.01,autonomy:1", "the timeout 0.01 s is out of range: allowed"),
        ("local:0.5,remote:nan,autonomy:1", "the timeout nan s is out of range"),
        ("local:0.5,remote,autonomy:1", "entry 2 'remote' is not name:seconds"),
        ("local:0.5,local:1,remote:1,autonomy:1", "entry 2 'local' repeats a source"),
        (",".join(f"s{n}:1" for n in range(17)), "has 17 entries: at most 16"),
    ],
)
def test_a_bad_table_is_refused_naming_the_entry(text: str, said: str) -> None:
    with pytest.raises(ValueError, match=r"^command_sources") as raised:
        parse_sources(text)
    assert said in str(raised.value)


def test_rows_and_entries_read_the_same() -> None:
    rows = (CommandSource("local", 0.25), CommandSource("remote", 2), CommandSource("autonomy", 1))
    assert parse_sources(rows) == parse_sources(["local:0.25", "remote:2", "autonomy:1"])
    assert format_sources(parse_sources(" local : 0.25 , remote:2,autonomy:1")) == (
        "local:0.25",
        "remote:2",
        "autonomy:1",
    )
