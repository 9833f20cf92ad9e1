"""The sans-IO bus engine: wire timing, in-order matching, holds, breaker — no event loop.

Every test drives :class:`BusConnection` with explicit times, the way the async shell
does, and feeds the replies whole, in halves, or a byte at a time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TypeVar

import pytest

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, StateError
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Packet,
    encode_packet,
    read_request,
    write_request,
)
from ohmni_tb.protocol.connection import (
    BreakerState,
    BusConnection,
    Event,
    MissingReason,
    ReplyMatcher,
    ReplyMissing,
    ReplyPacket,
    ReplyReceived,
    StrayKind,
    StrayPacket,
)
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.protocol.timing import (
    DEFAULT_GUARD_S,
    DEFAULT_TURNAROUND_S,
    reply_size_range,
    transaction_cost_s,
    wire_time_s,
)

BAUD = 115_200
BYTE_S = 10 / BAUD
GUARD = DEFAULT_GUARD_S
TURN = DEFAULT_TURNAROUND_S
TIMEOUT = 0.025


def conn(**kwargs: object) -> BusConnection:
    settings: dict[str, object] = {"baudrate": BAUD, "timeout_s": TIMEOUT}
    settings.update(kwargs)
    return BusConnection(**settings)  # type: ignore[arg-type]  # test settings, checked at run time


def read_reply(sid: int, addr: int, value: bytes) -> Packet:
    return Packet(sid, Command.RAM_READ | REPLY_FLAG, bytes([addr, len(value)]) + value + b"\0\0")


def count_reply(sid: int, count: int) -> Packet:
    return read_reply(sid, 59, count.to_bytes(4, "little", signed=True))


Feeder = Callable[[BusConnection, bytes, float], list[Event]]


def whole(c: BusConnection, data: bytes, now: float) -> list[Event]:
    return c.receive_data(data, now)


def halves(c: BusConnection, data: bytes, now: float) -> list[Event]:
    mid = len(data) // 2
    return c.receive_data(data[:mid], now) + c.receive_data(data[mid:], now)


def bytewise(c: BusConnection, data: bytes, now: float) -> list[Event]:
    events: list[Event] = []
    for i in range(len(data)):
        events += c.receive_data(data[i : i + 1], now)
    return events


FEEDERS = pytest.mark.parametrize(
    "feed", [whole, halves, bytewise], ids=["whole", "halves", "bytes"]
)


E = TypeVar("E", ReplyReceived, ReplyMissing, StrayPacket)


def only(events: list[Event], kind: type[E]) -> list[E]:
    return [e for e in events if isinstance(e, kind)]


# -- the cost model ------------------------------------------------------------------------


def test_cost_model_adds_request_turnaround_reply_and_guard() -> None:
    # A wheel-count read: 9-byte request, 15-byte reply.
    expected = 24 * BYTE_S + TURN + GUARD
    assert transaction_cost_s(read_count(0)) == pytest.approx(expected, abs=1e-12)
    assert wire_time_s(24) == pytest.approx(24 * BYTE_S)
    # The wheel command is a broadcast: no reply, no turnaround.
    assert transaction_cost_s(wheel_command(0, 0)) == pytest.approx(
        wheel_command(0, 0).size * BYTE_S + GUARD
    )
    # A write is answered only under ACK policy 2.
    write = write_request(3, 52, b"\x60")
    assert transaction_cost_s(write) == pytest.approx(write.size * BYTE_S + GUARD)
    assert transaction_cost_s(write, ack_policy=2) == pytest.approx(
        (write.size + 9) * BYTE_S + TURN + GUARD
    )
    # At 9600 baud the same read takes twelve times the wire time.
    slow = transaction_cost_s(read_count(0), baudrate=9600, turnaround_s=0.0, guard_s=0.0)
    assert slow == pytest.approx(24 * 10 / 9600)


def test_a_length_zero_read_budgets_the_largest_reply() -> None:
    tag = read_request(20, 0xF1, 0)
    assert reply_size_range(tag, max_packet_size=64) == (11, 64)
    assert transaction_cost_s(tag, max_packet_size=64) == pytest.approx(
        (9 + 64) * BYTE_S + TURN + GUARD
    )


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"baudrate": 0}, "baudrate"),
        ({"turnaround_s": -1e-3}, "turnaround_s"),
        ({"guard_s": math.nan}, "guard_s"),
        ({"turnaround_s": math.inf}, "turnaround_s"),
    ],
)
def test_cost_model_refuses_bad_settings(kwargs: dict[str, float], name: str) -> None:
    with pytest.raises(OutOfRangeError) as info:
        transaction_cost_s(read_count(0), **kwargs)  # type: ignore[arg-type]  # checked at run time
    assert info.value.name == name


# -- wire timing ---------------------------------------------------------------------------


@FEEDERS
def test_a_read_holds_the_line_for_its_budget_and_delivers_its_times(feed: Feeder) -> None:
    c = conn()
    exchange = c.send(read_count(0), 1.0)
    assert exchange.frame == encode_packet(read_count(0))
    window_end = 1.0 + 24 * BYTE_S + TURN
    assert c.free_at == pytest.approx(window_end + GUARD)
    assert exchange.expires_at == pytest.approx(window_end + TIMEOUT)
    # The device answers after 0.5 ms; its reply is complete 0.5 ms + 24 bytes later.
    arrive = 1.0 + 24 * BYTE_S + 0.0005
    events = feed(c, encode_packet(count_reply(0, 1234)), arrive)
    [received] = only(events, ReplyReceived)
    assert isinstance(received, ReplyReceived)
    assert received.exchange is exchange
    assert received.reply == count_reply(0, 1234)
    assert isinstance(received.reply, ReplyPacket)
    assert (received.reply.sent_at, received.reply.received_at) == (1.0, arrive)
    # Seen, and nothing sent after it: the line is free a guard later, before the budget.
    assert c.free_at == pytest.approx(arrive + GUARD)
    stats = c.stats(arrive)
    assert (stats.devices[0].requests, stats.devices[0].replies) == (1, 1)
    assert stats.devices[0].latency_p50_s == pytest.approx(arrive - 1.0)
    assert stats.wire_busy_s == pytest.approx(24 * BYTE_S)


def test_after_a_reply_seen_the_line_frees_by_its_own_guard_and_the_model_keeps_its() -> None:
    c = conn(reply_guard_s=3 * BYTE_S / 10)  # three bit times
    exchange = c.send(read_count(0), 1.0)
    assert c.free_at == pytest.approx(exchange.window_end_s + GUARD)  # the model's
    seen = exchange.reply_earliest_s + 0.0002
    only(c.receive_data(encode_packet(count_reply(0, 1)), seen), ReplyReceived)
    assert c.free_at == pytest.approx(seen + 3 * BYTE_S / 10)
    command = wheel_command(10, 10)
    write = c.send(command, c.free_at)
    assert c.free_at == pytest.approx(write.wire_end_s + GUARD)  # no reply: the model's
    assert conn().reply_guard_s == GUARD  # not told: the guard


def test_the_line_is_refused_before_it_is_free() -> None:
    c = conn()
    c.send(read_count(0), 0.0)
    with pytest.raises(StateError, match="busy"):
        c.send(read_count(1), c.free_at - 1e-4)
    c.send(read_count(1), c.free_at)


def test_a_broadcast_holds_the_line_for_its_own_bytes_only() -> None:
    c = conn()
    packet = wheel_command(100, 100)
    exchange = c.send(packet, 0.0)
    assert not exchange.expect_reply
    assert exchange.done
    assert c.free_at == pytest.approx(packet.size * BYTE_S + GUARD)
    assert c.next_deadline() is None
    with pytest.raises(InvalidArgumentError, match="broadcast"):
        c.send(Packet(BROADCAST_ID, Command.STAT), c.free_at)


def test_pipelined_replies_seen_late_are_matched_in_order() -> None:
    # A USB adapter holds the replies and hands them over together, 16 ms later: the
    # requests still went at the wire's pace.
    c = conn()
    sent = []
    t = 0.0
    for sid in (0, 1, 20):
        request = read_count(sid) if sid < 2 else read_request(20, 0xA0, 18)
        sent.append(c.send(request, t))
        t = c.free_at
    assert t < 0.012  # three transactions, each a few ms on the wire
    burst = (
        encode_packet(count_reply(0, 10))
        + encode_packet(count_reply(1, -10))
        + encode_packet(read_reply(20, 0xA0, bytes(18)))
    )
    events = c.receive_data(burst, 0.016)
    received = only(events, ReplyReceived)
    assert [e.exchange for e in received] == sent
    assert c.outstanding == 0


def test_unpipelined_waits_for_each_reply() -> None:
    c = conn(pipelined=False)
    c.send(read_count(0), 0.0)
    assert c.free_at == math.inf
    c.receive_data(encode_packet(count_reply(0, 1)), 0.004)
    assert c.free_at == pytest.approx(0.004 + GUARD)


def test_a_link_without_a_baud_rate_is_not_pipelined() -> None:
    c = BusConnection(baudrate=None)
    exchange = c.send(read_count(0), 0.0)
    assert c.free_at == math.inf
    # No wire time to add: the turnaround budget and the timeout.
    assert exchange.expires_at == pytest.approx(c.turnaround_s + c.timeout_s)


# -- a clock in whole milliseconds ---------------------------------------------------------


def _ms(t: float) -> float:
    """What a clock in whole milliseconds (uvloop's loop.time()) reads at ``t``."""
    return math.floor(t * 1000 + 1e-9) / 1000


def _on_a_millisecond_clock(c: BusConnection, count: int) -> tuple[int, int, float]:
    """Reads on a true timeline, stamped by a clock in whole milliseconds: the device
    answers 0.5 ms after each request. Returns the replies taken, those refused as
    early, and the shortest true quiet between a reply's end and the next request."""
    true_t = 0.0104
    taken = early = 0
    quiet = math.inf
    reply_end = -math.inf
    for k in range(count):
        request = read_count(k % 2)
        # The owner waits until its own clock says the line is free (and the request's
        # look-alike answered or given up), then sends.
        while True:
            stamp = _ms(true_t)
            c.poll(stamp)
            if stamp + 1e-12 >= max(c.free_at, c.blocked_until(request, stamp)):
                break
            true_t = stamp + 0.001
        quiet = min(quiet, true_t - reply_end)
        exchange = c.send(request, stamp)
        reply_end = true_t + (request.size + 15) * BYTE_S + 0.0005
        for event in c.receive_data(encode_packet(count_reply(k % 2, k)), _ms(reply_end)):
            taken += isinstance(event, ReplyReceived)
            early += isinstance(event, StrayPacket) and event.kind is StrayKind.EARLY
        # The owner comes back a little later; an unanswered request is waited out.
        true_t = reply_end + 0.000137 * (k % 7)
        if not exchange.done:
            true_t = max(true_t, exchange.expires_at)
    return taken, early, quiet


def test_a_clock_in_whole_milliseconds_takes_every_reply_and_keeps_the_guard() -> None:
    # Told its clock's step, the connection allows for stamps up to a step behind.
    c = conn(clock_resolution_s=0.001)
    taken, early, quiet = _on_a_millisecond_clock(c, 200)
    assert (taken, early) == (200, 0)
    assert quiet >= GUARD  # never talked over the end of a reply
    stats = c.stats(10.0)
    assert sum(d.timeouts for d in stats.devices.values()) == 0
    # Not told, it takes good replies for another request's, come too early.
    taken, early, _ = _on_a_millisecond_clock(conn(), 200)
    assert early == 200
    assert taken == 0


def test_a_coarse_clock_widens_the_windows_by_its_step_and_nothing_else() -> None:
    exact, coarse = conn(), conn(clock_resolution_s=0.001)
    a, b = exact.send(read_count(0), 1.0), coarse.send(read_count(0), 1.0)
    assert b.reply_earliest_s == a.reply_earliest_s  # a lower bound stays one
    assert b.wire_end_s == pytest.approx(a.wire_end_s + 0.001)
    assert b.window_end_s == pytest.approx(a.window_end_s + 0.001)
    assert b.expires_at == pytest.approx(a.expires_at + 0.001)
    assert coarse.free_at == pytest.approx(exact.free_at + 0.001)
    # A reply stamped half a step before it could have been complete is still taken...
    early_stamp = a.reply_earliest_s - 0.0005
    assert only(coarse.receive_data(encode_packet(count_reply(0, 1)), early_stamp), ReplyReceived)
    assert only(exact.receive_data(encode_packet(count_reply(0, 1)), early_stamp), StrayPacket)
    # ... and the line frees a guard after the latest the reply can really have come.
    assert coarse.free_at == pytest.approx(early_stamp + 0.001 + GUARD)


@pytest.mark.parametrize("bad", [-0.001, 0.5, math.nan])
def test_a_clock_resolution_out_of_range_is_refused(bad: float) -> None:
    with pytest.raises(OutOfRangeError, match="clock_resolution_s"):
        conn(clock_resolution_s=bad)


# -- which reply answers which request -----------------------------------------------------


def test_a_reply_before_its_request_could_be_answered_is_early_not_taken() -> None:
    c = conn()
    exchange = c.send(read_count(0), 1.0)
    # The same bytes, arriving 1 ms after the request went: its own 9 bytes and a 15-byte
    # reply need 2.1 ms, so this is another request's reply that merely looks the same.
    events = c.receive_data(encode_packet(count_reply(0, 7)), 1.001)
    [stray] = only(events, StrayPacket)
    assert isinstance(stray, StrayPacket)
    assert stray.kind is StrayKind.EARLY
    assert not only(events, ReplyReceived)
    assert not exchange.done
    stats = c.stats(1.001).devices[0]
    assert (stats.early, stats.unmatched, stats.replies) == (1, 1, 0)


def test_a_later_reply_means_the_earlier_ones_are_missing() -> None:
    c = conn()
    first = c.send(read_count(0), 0.0)
    second = c.send(read_count(1), c.free_at)
    events = c.receive_data(encode_packet(count_reply(1, 5)), 0.01)
    missing = only(events, ReplyMissing)
    assert [(e.exchange, e.reason) for e in missing] == [(first, MissingReason.OVERTAKEN)]
    assert [e.exchange for e in only(events, ReplyReceived)] == [second]
    assert c.stats(0.01).devices[0].timeouts == 1


def test_an_identical_request_waits_while_one_is_outstanding() -> None:
    c = conn()
    c.send(read_count(0), 0.0)
    assert c.blocked_until(read_count(0), c.free_at) == math.inf
    with pytest.raises(StateError, match="identical"):
        c.send(read_count(0), c.free_at)
    # Another register of the same device is not alike.
    assert c.blocked_until(read_request(0, 58, 2), c.free_at) == -math.inf


def test_after_a_timeout_an_identical_request_is_held_and_a_late_reply_is_counted() -> None:
    c = conn()
    first = c.send(read_count(0), 0.0)
    assert c.poll(first.expires_at - 1e-6) == []
    [missing] = c.poll(first.expires_at)
    assert isinstance(missing, ReplyMissing)
    assert missing.reason is MissingReason.TIMEOUT
    hold_until = c.blocked_until(read_count(0), first.expires_at)
    assert hold_until == pytest.approx(first.expires_at + first.expires_at - first.wire_end_s)
    # The slow device answers at last: recognised as late, and it may have more queued,
    # so the hold runs one window from this reply.
    late_at = first.expires_at + 0.005
    [stray] = c.receive_data(encode_packet(count_reply(0, 1)), late_at)
    assert isinstance(stray, StrayPacket)
    assert stray.kind is StrayKind.LATE
    window = TURN + 15 * BYTE_S + GUARD + TIMEOUT
    until = c.blocked_until(read_count(0), late_at)
    assert until == pytest.approx(max(hold_until, late_at + window))
    second = c.send(read_count(0), until)
    # The next reply belongs to the second request: held one reply slot, then delivered.
    arrive = second.reply_earliest_s
    assert c.receive_data(encode_packet(count_reply(0, 2)), arrive) == []
    deadline = c.next_deadline()
    assert deadline is not None
    [received] = c.poll(deadline)
    assert isinstance(received, ReplyReceived)
    assert received.exchange is second
    stats = c.stats(late_at).devices[0]
    assert (stats.late, stats.timeouts, stats.replies) == (1, 1, 1)


def test_a_reply_to_nothing_is_counted_unmatched() -> None:
    c = conn()
    [stray] = c.receive_data(encode_packet(count_reply(1, 1)), 0.0)
    assert isinstance(stray, StrayPacket)
    assert stray.kind is StrayKind.UNMATCHED
    assert c.stats(0.0).unmatched == 1
    assert c.stats(0.0).devices[1].unmatched == 1


def test_an_abandoned_request_still_holds_the_line_and_its_reply_is_counted() -> None:
    c = conn()
    exchange = c.send(read_count(0), 0.0)
    c.abandon(exchange)
    assert c.free_at > 0.003
    [stray] = c.receive_data(encode_packet(count_reply(0, 1)), 0.003)
    assert isinstance(stray, StrayPacket)
    assert stray.kind is StrayKind.ABANDONED
    assert c.stats(0.003).abandoned == 1
    assert c.stats(0.003).unmatched == 0


def test_echoes_and_foreign_requests_are_told_apart() -> None:
    c = conn()
    c.send(read_count(0), 0.0)
    [echo] = c.receive_data(encode_packet(read_count(0)), 0.001)
    assert isinstance(echo, StrayPacket)
    assert echo.kind is StrayKind.ECHO
    free_before = c.free_at
    [foreign] = c.receive_data(encode_packet(read_request(20, 0xA0, 18)), 0.002)
    assert isinstance(foreign, StrayPacket)
    assert foreign.kind is StrayKind.FOREIGN_REQUEST
    # Another master's request will be answered: keep off the line for its reply.
    assert c.free_at >= 0.002 + (7 + 4 + 18) * BYTE_S
    assert c.free_at >= free_before
    stats = c.stats(0.002)
    assert (stats.echoes, stats.foreign_requests) == (1, 1)


def test_a_half_frame_is_given_up_after_a_quiet_timeout() -> None:
    c = conn()
    frame = encode_packet(count_reply(0, 1))
    assert c.receive_data(frame[:-3], 0.0) == []
    assert c.next_deadline() == pytest.approx(TIMEOUT)
    assert c.poll(TIMEOUT - 1e-6) == []
    c.poll(TIMEOUT)
    assert c.stats(TIMEOUT).decoder.expired == 1
    assert c.stats(TIMEOUT).decoder.bytes_pending == 0


# -- breaker ------------------------------------------------------------------------------


def silence(c: BusConnection, sid: int, t: float, times: int) -> float:
    """Send ``times`` reads to a silent ``sid``, each timing out; return the time after."""
    for _ in range(times):
        t = max(t, c.free_at, c.blocked_until(read_request(sid, 48, 12), t))
        exchange = c.send(read_request(sid, 48, 12), t)
        t = exchange.expires_at
        c.poll(t)
    return t


def test_breaker_opens_after_silence_probes_and_closes_on_a_reply() -> None:
    c = conn(breaker_timeouts=3, breaker_quiet_s=0.05, probe_interval_s=1.0)
    t = silence(c, 11, 0.0, 3)
    assert t >= 0.05
    assert c.stats(t).devices[11].breaker is BreakerState.OPEN
    # The first probe is due soon: a burst of noise may have tripped it.
    assert c.refusal(11, t) == pytest.approx(0.125)
    # Other devices are not affected.
    assert c.refusal(3, t) is None
    # While a probe is out, the rest are refused.
    t += 0.125
    assert c.refusal(11, t) is None
    probe = c.send(read_request(11, 48, 12), t)
    assert c.stats(t).devices[11].breaker is BreakerState.PROBING
    assert c.refusal(11, t + 0.001) is not None
    # It answers (after its silence the reply is held one reply slot): closed again.
    c.receive_data(encode_packet(read_reply(11, 48, bytes(12))), probe.wire_end_s + 0.003)
    deadline = c.next_deadline()
    assert deadline is not None
    c.poll(deadline)
    assert c.stats(t).devices[11].breaker is BreakerState.CLOSED
    assert c.refusal(11, t + 0.01) is None


def test_probes_of_a_dead_device_back_off_to_the_probe_interval() -> None:
    c = conn(breaker_timeouts=1, breaker_quiet_s=0.0, probe_interval_s=1.0)
    t = silence(c, 12, 0.0, 1)
    gaps = []
    for _ in range(7):
        wait = c.refusal(12, t)
        assert wait is not None
        gaps.append(round(wait, 6))
        # Each probe goes when due and times out; the gap counts from when it went.
        sent = t + wait
        t = silence(c, 12, sent, 1)
        assert c.stats(t).devices[12].breaker is BreakerState.OPEN
        t = sent
    assert gaps == [0.125, 0.25, 0.5, 1.0, 1.0, 1.0, 1.0]
    assert c.stats(t).devices[12].probes == 7


def test_breaker_needs_silence_as_well_as_timeouts() -> None:
    c = conn(breaker_timeouts=3, breaker_quiet_s=10.0)
    exchange = c.send(read_request(0, 48, 12), 0.0)
    c.receive_data(encode_packet(read_reply(0, 48, bytes(12))), exchange.reply_earliest_s)
    t = silence(c, 0, exchange.reply_earliest_s, 5)
    # Five misses in a row, but it answered less than 10 s ago: a noisy line, not a
    # dead board.
    assert c.stats(t).devices[0].breaker is BreakerState.CLOSED


def test_silence_counts_from_the_first_miss_not_from_an_idle_devices_last_reply() -> None:
    c = conn(breaker_timeouts=3, breaker_quiet_s=0.25)
    exchange = c.send(read_count(0), 0.0)
    c.receive_data(encode_packet(count_reply(0, 1)), exchange.reply_earliest_s)
    # Nobody asks for a minute; then three reads in a row go missing within 0.1 s.
    t = silence(c, 0, 60.0, 3)
    assert t - 60.0 < 0.25
    assert c.stats(t).devices[0].breaker is BreakerState.CLOSED
    assert c.refusal(0, t) is None
    # Missing on and on until the misses span 0.25 s: now it is presumed gone.
    while c.stats(t).devices[0].breaker is BreakerState.CLOSED:
        t = silence(c, 0, t, 1)
    assert t - 60.0 >= 0.25
    assert c.stats(t).devices[0].consecutive_timeouts >= 4


def test_a_failed_probe_reopens_the_breaker() -> None:
    c = conn(breaker_timeouts=1, breaker_quiet_s=0.0, probe_interval_s=0.5)
    t = silence(c, 12, 0.0, 1)
    assert c.stats(t).devices[12].breaker is BreakerState.OPEN
    probe_at = t + 0.125
    t = silence(c, 12, probe_at, 1)
    assert c.stats(t).devices[12].breaker is BreakerState.OPEN
    # The next probe is due twice the first gap after the failed one went.
    assert c.refusal(12, t) == pytest.approx(probe_at + 0.25 - t)


# -- a prompt line waits for its replies ---------------------------------------------------


def _answered(c: BusConnection, count: int, t: float, *, late_s: float = -0.0004) -> float:
    """``count`` reads of both wheel counts, each reply seen ``late_s`` after the line
    was free by the model (negative: before); returns the time after the last."""
    for k in range(count):
        exchange = c.send(read_count(k % 2), t)
        seen = exchange.window_end_s + GUARD + late_s
        [got] = only(c.receive_data(encode_packet(count_reply(k % 2, k)), seen), ReplyReceived)
        assert got.exchange is exchange
        t = max(c.free_at, seen)
    return t


def test_a_prompt_line_waits_for_a_late_reply_instead_of_talking_over_it() -> None:
    c = conn()
    t = _answered(c, 15, 0.0)
    before = c.prompt  # not yet: 16 replies tell
    t = _answered(c, 1, t)
    assert (before, c.prompt) == (False, True)
    exchange = c.send(read_count(0), t)
    model = exchange.window_end_s + GUARD
    # The reply is late (its host was busy): the line stays taken past the model's time...
    assert c.free_at == math.inf
    assert c.urgent_free_at == pytest.approx(model)  # a stop still goes on the model
    with pytest.raises(StateError, match="busy"):
        c.send(read_count(1), model + 0.003)
    # ... until it comes, 3 ms late: a guard after it, the next request may go.
    late = model + 0.003
    [got] = only(c.receive_data(encode_packet(count_reply(0, 7)), late), ReplyReceived)
    assert got.exchange is exchange
    assert c.free_at == pytest.approx(late + GUARD)


def test_a_stop_on_a_prompt_line_goes_on_the_models_time() -> None:
    c = conn()
    exchange = c.send(read_count(0), _answered(c, 16, 0.0))
    model = exchange.window_end_s + GUARD
    with pytest.raises(StateError, match="busy"):
        c.send(wheel_command(0, 0), model - 0.0001, urgent=True)
    stop = c.send(wheel_command(0, 0), model, urgent=True)
    assert stop.sent_at == model


def test_a_prompt_line_waits_out_a_missing_reply_then_goes_on_the_model_for_that_device() -> None:
    c = conn()
    t = _answered(c, 16, 0.0)
    silent = c.send(read_request(3, 0x30, 2), t)
    assert c.free_at == math.inf
    [missing] = only(c.poll(silent.expires_at), ReplyMissing)
    assert missing.exchange is silent
    assert c.free_at == pytest.approx(silent.expires_at + GUARD)
    # A miss in the last 16: the line goes on the model's time again, for every device.
    assert not c.prompt
    again = c.send(read_request(3, 0x31, 2), c.free_at)
    assert c.free_at == pytest.approx(again.window_end_s + GUARD)


def test_replies_an_adapter_holds_keep_the_line_on_the_models_time() -> None:
    # Replies seen after the line was free by the model, as a rule: a USB adapter's
    # latency timer holds them, and waiting for each would cost its latency every time.
    c = conn()
    t = 0.0
    for k in range(40):
        exchange = c.send(read_count(k % 2), t)
        assert c.free_at == pytest.approx(exchange.window_end_s + GUARD)
        seen = exchange.window_end_s + GUARD + 0.004
        only(c.receive_data(encode_packet(count_reply(k % 2, k)), seen), ReplyReceived)
        t = exchange.window_end_s + GUARD
    assert not c.prompt
    # A few late replies among prompt ones leave it prompt.
    t = _answered(c, 12, t + 0.1)
    t = _answered(c, 4, t, late_s=0.002)
    assert c.prompt


def test_an_unpipelined_or_cautious_line_is_unchanged_by_promptness() -> None:
    u = conn(pipelined=False)
    for k in range(20):
        exchange = u.send(read_count(k % 2), k * 0.01)
        assert u.free_at == math.inf
        assert u.urgent_free_at == math.inf
        u.receive_data(encode_packet(count_reply(k % 2, k)), exchange.window_end_s)


# -- junk makes the line cautious ------------------------------------------------------


def garbled(packet: Packet) -> bytes:
    """A reply hit by a collision: its bytes ANDed with another's, the checksum broken."""
    frame = bytearray(encode_packet(packet))
    frame[-1] &= 0x0F
    frame[5] &= 0x0F
    return bytes(frame)


@FEEDERS
def test_after_junk_each_request_waits_for_its_reply_then_pipelining_resumes(
    feed: Feeder,
) -> None:
    c = conn(caution_s=0.1)
    first = c.send(read_count(0), 0.0)
    assert c.free_at == pytest.approx(first.window_end_s + GUARD)  # pipelined
    # The reply comes back garbled (a collision): the decoder discards it.
    assert only(feed(c, garbled(count_reply(0, 1)), first.reply_earliest_s), ReplyReceived) == []
    assert c.stats(first.reply_earliest_s).cautious
    assert c.stats(first.reply_earliest_s).cautions == 1
    t = c.free_at
    second = c.send(read_count(1), t)
    # Request at a time: the line stays taken until the reply is seen...
    assert c.free_at == math.inf
    assert c.blocked_until(read_count(0), second.window_end_s + 1.0) == math.inf
    events = feed(c, encode_packet(count_reply(1, 5)), second.window_end_s + 0.004)
    [got] = only(events, ReplyReceived)
    assert got.exchange is second
    assert c.free_at == pytest.approx(second.window_end_s + 0.004 + GUARD)
    # ... or missing: the timeout frees it.
    c.poll(first.expires_at)
    third = c.send(read_count(0), max(c.free_at, c.blocked_until(read_count(0), c.free_at)))
    assert c.free_at == math.inf
    [missing] = only(c.poll(third.expires_at), ReplyMissing)
    assert missing.exchange is third
    assert c.free_at == pytest.approx(third.expires_at + GUARD)
    # Once caution_s has passed with no more junk, requests pipeline again.
    later = max(c.free_at, 0.1 + first.reply_earliest_s)
    fourth = c.send(read_count(1), later)
    assert c.free_at == pytest.approx(fourth.window_end_s + GUARD)
    assert not c.stats(later).cautious
    assert c.stats(later).cautions == 1


def test_more_junk_extends_the_caution_and_a_stale_half_frame_counts_as_junk() -> None:
    c = conn(caution_s=0.1)
    c.receive_data(b"\x00\x13", 0.0)
    assert c.stats(0.05).cautious
    c.receive_data(b"\x00", 0.08)
    assert c.stats(0.15).cautious  # extended to 0.18
    assert c.stats(0.19).cautions == 1  # one spell, extended
    assert not c.stats(0.19).cautious
    # A half frame that never completes is junk too, found when it expires.
    c.receive_data(encode_packet(count_reply(0, 1))[:-3], 1.0)
    assert not c.stats(1.0).cautious
    c.poll(1.0 + TIMEOUT)
    assert c.stats(1.0 + TIMEOUT).cautious
    assert c.stats(1.0 + TIMEOUT).cautions == 2


def test_caution_off_or_unpipelined_changes_nothing() -> None:
    c = conn(caution_s=0.0)
    c.receive_data(b"\x00\x13\x37", 0.0)
    exchange = c.send(read_count(0), 0.0)
    assert c.free_at == pytest.approx(exchange.window_end_s + GUARD)
    assert c.stats(0.0).cautions == 0
    u = conn(pipelined=False)
    u.receive_data(b"\x00\x13\x37", 0.0)
    assert u.stats(0.0).cautions == 0


# -- settings and odds ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"baudrate": 0}, "baudrate"),
        ({"timeout_s": 0.0}, "timeout_s"),
        ({"guard_s": -1.0}, "guard_s"),
        ({"reply_guard_s": -1.0}, "reply_guard_s"),
        ({"reply_guard_s": math.inf}, "reply_guard_s"),
        ({"turnaround_s": math.nan}, "turnaround_s"),
        ({"breaker_timeouts": 0}, "breaker_timeouts"),
        ({"probe_interval_s": 0.0}, "probe_interval_s"),
        ({"caution_s": -0.1}, "caution_s"),
    ],
)
def test_settings_are_checked(kwargs: dict[str, object], name: str) -> None:
    with pytest.raises(OutOfRangeError) as info:
        conn(**kwargs)
    assert info.value.name == name


def test_per_device_turnaround_widens_only_its_window() -> None:
    c = conn()
    c.set_turnaround(3, 0.030)
    assert c.turnaround(3) == 0.030
    assert c.turnaround(0) == TURN
    slow = c.send(read_request(3, 48, 2), 0.0)
    assert slow.window_end_s == pytest.approx(slow.wire_end_s + 0.030 + 13 * BYTE_S)
    c.set_turnaround(3, None)
    assert c.turnaround(3) == TURN
    with pytest.raises(OutOfRangeError, match="turnaround_s"):
        c.set_turnaround(3, 2.0)


def test_frames_of_repeated_requests_are_encoded_once() -> None:
    c = conn()
    assert c.frame(read_count(0)) is c.frame(read_count(0))
    with pytest.raises(OutOfRangeError, match="size"):
        BusConnection(max_packet_size=64).frame(Packet(3, Command.RAM_WRITE, bytes(58)))


def test_link_lost_makes_every_outstanding_request_missing() -> None:
    c = conn()
    a = c.send(read_count(0), 0.0)
    b = c.send(read_count(1), c.free_at)
    events = c.link_lost(0.004)
    assert len(events) == 2
    assert [(e.exchange, e.reason) for e in only(events, ReplyMissing)] == [
        (a, MissingReason.LINK_LOST),
        (b, MissingReason.LINK_LOST),
    ]
    assert c.outstanding == 0
    assert c.free_at == 0.004


def test_reply_packet_compares_as_its_packet() -> None:
    reply = ReplyPacket(0, 0x44, b"\x3b\x04", sent_at=1.0, received_at=2.0)
    plain = Packet(0, 0x44, b"\x3b\x04")
    assert reply == plain
    assert plain == reply
    assert hash(reply) == hash(plain)


def test_reply_matcher_pairs_in_order_and_stays_bounded() -> None:
    matcher: ReplyMatcher[str] = ReplyMatcher(limit=2)
    assert matcher.add(read_count(0), "a") == []
    assert matcher.add(read_count(1), "b") == []
    assert matcher.add(read_request(20, 0xA0, 18), "c") == ["a"]
    item, overtaken = matcher.match(count_reply(0, 1))
    assert (item, overtaken) == (None, [])
    item, overtaken = matcher.match(read_reply(20, 0xA0, bytes(18)))
    assert (item, overtaken) == ("c", ["b"])
    assert len(matcher) == 0


# -- after trouble: confirm before delivering ----------------------------------------------


def troubled(c: BusConnection) -> float:
    """Make the left wheel count's look suspect (one read goes missing); return the time."""
    first = c.send(read_count(0), 0.0)
    c.poll(first.expires_at)
    return c.blocked_until(read_count(0), first.expires_at)


def test_a_healthy_key_is_delivered_at_once() -> None:
    c = conn()
    exchange = c.send(read_count(0), 0.0)
    [received] = c.receive_data(encode_packet(count_reply(0, 1)), exchange.reply_earliest_s)
    assert isinstance(received, ReplyReceived)


def test_after_trouble_a_reply_is_delivered_once_no_twin_follows() -> None:
    c = conn()
    t = troubled(c)
    exchange = c.send(read_count(0), t)
    arrive = exchange.reply_earliest_s + 0.0005
    assert c.receive_data(encode_packet(count_reply(0, 2)), arrive) == []
    confirm_at = c.next_deadline()
    assert confirm_at is not None
    assert confirm_at == pytest.approx(arrive + TURN + 15 * BYTE_S + GUARD)
    [received] = c.poll(confirm_at)
    assert isinstance(received, ReplyReceived)
    assert received.reply.received_at == arrive
    # Confirmed: the next read of it is delivered at once again.
    again = c.send(read_count(0), c.free_at)
    [now] = c.receive_data(encode_packet(count_reply(0, 3)), again.reply_earliest_s)
    assert isinstance(now, ReplyReceived)


def test_a_burst_of_lookalike_replies_is_ambiguous_not_guessed() -> None:
    # A device that swallowed earlier requests behind a corrupted size byte answers them
    # all when the newest completes the frame: the first of the burst comes exactly when
    # the newest's own reply would.
    c = conn()
    t = troubled(c)
    exchange = c.send(read_count(0), t)
    arrive = exchange.reply_earliest_s
    events = c.receive_data(encode_packet(count_reply(0, 2)), arrive)
    events += c.receive_data(encode_packet(count_reply(0, 3)), arrive + 15 * BYTE_S)
    assert not only(events, ReplyReceived)
    [missing] = only(events, ReplyMissing)
    assert (missing.exchange, missing.reason) == (exchange, MissingReason.AMBIGUOUS)
    assert [e.kind for e in only(events, StrayPacket)] == [StrayKind.TWIN]
    # More of the burst extends the hold on an identical request.
    later = arrive + 2 * 15 * BYTE_S
    c.receive_data(encode_packet(count_reply(0, 4)), later)
    assert c.blocked_until(read_count(0), later) > later + TIMEOUT
    assert c.stats(later).ambiguous == 1


def test_junk_in_the_confirm_window_makes_the_held_reply_ambiguous() -> None:
    c = conn()
    t = troubled(c)
    exchange = c.send(read_count(0), t)
    arrive = exchange.reply_earliest_s
    assert c.receive_data(encode_packet(count_reply(0, 2)), arrive) == []
    # A twin whose command byte was hit by the checksum's blind bit: the decoder drops it.
    twin = bytearray(encode_packet(count_reply(0, 3)))
    twin[4] ^= 0x04
    [missing] = c.receive_data(bytes(twin), arrive + 0.001)
    assert isinstance(missing, ReplyMissing)
    assert missing.reason is MissingReason.AMBIGUOUS


def test_a_lookalike_before_any_reply_could_come_taints_the_request() -> None:
    c = conn()
    exchange = c.send(read_count(0), 0.0)
    [early] = c.receive_data(encode_packet(count_reply(0, 1)), 0.001)
    assert isinstance(early, StrayPacket)
    events = c.receive_data(encode_packet(count_reply(0, 2)), exchange.reply_earliest_s)
    [missing] = only(events, ReplyMissing)
    assert missing.reason is MissingReason.AMBIGUOUS
    assert not only(events, ReplyReceived)


def test_a_later_requests_reply_confirms_a_held_one() -> None:
    c = conn()
    t = troubled(c)
    first = c.send(read_count(0), t)
    assert c.receive_data(encode_packet(count_reply(0, 2)), first.reply_earliest_s) == []
    second = c.send(read_count(1), c.free_at)
    events = c.receive_data(encode_packet(count_reply(1, 9)), second.reply_earliest_s)
    assert [e.exchange for e in only(events, ReplyReceived)] == [first, second]


def test_a_write_that_returned_late_moves_the_window_not_the_earliest_reply() -> None:
    c = conn()
    exchange = c.send(read_count(0), 1.0)
    earliest, window, free = exchange.reply_earliest_s, exchange.window_end_s, c.free_at
    # The process was descheduled inside the write: it returned 2 ms later.
    c.written(exchange, 1.002)
    assert exchange.reply_earliest_s == earliest  # a reply can still come that early
    assert exchange.window_end_s == pytest.approx(window + 0.002)
    assert c.free_at == pytest.approx(free + 0.002)
    # A write that returned at once changes nothing.
    other = c.send(read_count(1), c.free_at)
    before = (other.window_end_s, c.free_at)
    c.written(other, other.sent_at)
    assert (other.window_end_s, c.free_at) == before
