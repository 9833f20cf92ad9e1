"""The half-duplex line's rules as a state machine: bytes and ``now`` in, events out.

:class:`BusConnection` is the bus master's side of the Ohmni line without any I/O, in the
manner of h11's ``Connection``: the owner asks it when the line is free
(:attr:`~BusConnection.free_at`), hands it a request to :meth:`~BusConnection.send` and
writes the bytes it returns, feeds it what the port received
(:meth:`~BusConnection.receive_data`) and calls :meth:`~BusConnection.poll` when
:meth:`~BusConnection.next_deadline` comes. Events come back: a reply with its times, a
reply that is missing, and every packet that answered nothing, by kind. It never reads a
clock, so every rule below is tested without an event loop::

    conn = BusConnection(baudrate=115200)
    exchange = conn.send(read_request(0, 59, 4), now=0.0)
    port.write(exchange.frame)
    ...
    for event in conn.receive_data(received, now=0.0031):
        ...                                   # ReplyReceived(exchange, reply)

The rules:

* **Wire-timed slots.** A request holds the line for its own bytes, the device's
  turnaround budget, its reply's bytes and a guard (:mod:`ohmni_tb.protocol.timing`).
  The next request may go when that time is up by the model, even if the host has not
  seen the reply yet: a USB adapter's latency then delays the delivery of replies, not
  the rate. Once a reply is seen and nothing was sent after it, the line is free
  ``reply_guard_s`` later (the guard unless told otherwise), whatever the budget said:
  the reply's sender has finished, and only needs to turn its line driver around.
* **A prompt line waits for a late reply.** While the last 16 requests were all answered
  and over a quarter of their replies reached the host before the line was free by the
  model (no adapter holds them: one whose latency timer is 16 ms hands over nearly every
  reply later), a reply later than that is its device's lateness, or the host's (a
  simulator its host did not schedule in time, a host busy elsewhere): a request to a
  device that answered its last one then holds the line until its reply is seen or
  missing, as request at a time, instead of the next one talking over a reply still on
  the wire. The reply frees the line a guard after it is seen, as always, so a reply in
  time costs nothing more. While replies come late as a rule (three quarters of them or
  more: a USB adapter's latency timer holds them), or go missing (a noisy line: waiting
  out each would cost a timeout), and for a device whose last request went unanswered,
  requests go on the model's time. A stop (:attr:`~BusConnection.urgent_free_at`) goes
  on the model's time whatever the line.
* **Junk makes the line cautious.** The model is only as good as the timing it assumes:
  a device that answers later than its budget, or a host whose bytes reach the wire later
  than it wrote them, makes the next request talk over a reply, and a collision leaves
  garbled bytes. So after junk on the line (bytes the decoder discarded), each request
  waits for its reply or its timeout before the next goes (request at a time) for
  ``caution_s``; every more junk extends it. A clean line never pays for it.
* **In-order matching.** Replies come back in the order the requests went out, so a
  reply answers the oldest outstanding request it fits (sid, reply code, address and
  length — :func:`~ohmni_tb.protocol.reply_matches`); earlier requests still waiting are
  missing by then (their replies would have come first).
* **Time tells replies apart.** HerkuleX replies carry no sequence number. A reply that
  arrives before its request could have been answered (request and reply bytes on the
  wire) is not its answer: it is counted as *early* and dropped. Two requests whose
  replies would look alike are never outstanding together, and after one goes missing an
  identical request waits one more reply window (a *hold*), in which a late reply is
  recognised and counted as *late* instead of being taken as the new request's; every
  stray reply of that look extends the hold by a window.
* **Trouble makes a key suspect.** A device that swallowed several requests behind a
  corrupted size byte may answer them all at once, and the first of that burst arrives
  exactly when the newest request's own reply would. So after a miss or a stray on a
  key, its next reply is delivered only once one reply window has passed on a clean
  line: a twin, another stray from that device, junk or a half frame in that window make
  the request *ambiguous* — missing, retried, never guessed — and so does a look-alike
  that came before its reply could. A confirmed reply clears the suspicion, so a healthy
  line never waits.
* **Breaker.** After ``breaker_timeouts`` missing replies in a row, spanning at least
  ``breaker_quiet_s`` from when the first of them was sent, a device is presumed gone:
  :meth:`~BusConnection.refusal` says to fail requests to it at once, except probes: the
  first 0.125 s after it opened, then at doubling gaps up to one every
  ``probe_interval_s``; its first reply closes the breaker.
* **A coarse clock is allowed for.** Every ``now`` may be up to ``clock_resolution_s``
  earlier than the truth (a clock that counts whole milliseconds reads up to one behind):
  a reply is early only when it came more than that before its request could have been
  answered, and every time the line is held (a request's reply window, the guard after a
  reply, a hold) ends that much later. With an exact clock (the default, 0) nothing moves.
* **Nothing dropped silently.** Echoes of our own requests, other masters' requests,
  early, late, unmatched replies and replies to abandoned requests are each counted, per
  device where there is one, beside the decoder's own counters.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from ohmni_tb._checks import check_seconds, integer
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, StateError
from ohmni_tb.protocol.framing import (
    BROADCAST_ID,
    HEADER_SIZE,
    MAX_PACKET_SIZE,
    REPLY_FLAG,
    Command,
    DecoderStats,
    Packet,
    PacketDecoder,
    encode_packet,
)
from ohmni_tb.protocol.messages import AckPolicy, _reply_expected, reply_matches
from ohmni_tb.protocol.timing import (
    BITS_PER_BYTE,
    DEFAULT_GUARD_S,
    DEFAULT_TURNAROUND_S,
    reply_size_range,
)

__all__ = [
    "DEFAULT_BREAKER_QUIET_S",
    "DEFAULT_BREAKER_TIMEOUTS",
    "DEFAULT_CAUTION_S",
    "DEFAULT_PROBE_INTERVAL_S",
    "DEFAULT_TIMEOUT_S",
    "BreakerState",
    "BusConnection",
    "ConnectionStats",
    "DeviceStats",
    "Event",
    "Exchange",
    "MissingReason",
    "ReplyMatcher",
    "ReplyMissing",
    "ReplyPacket",
    "ReplyReceived",
    "StrayKind",
    "StrayPacket",
    "is_idempotent",
]

#: How long after a reply's latest wire time the host still waits for it: the USB
#: adapter's latency timer (16 ms unless lowered, docs/hardware.md) plus event-loop delay.
DEFAULT_TIMEOUT_S = 0.025
#: Missing replies in a row before a device may be presumed gone...
DEFAULT_BREAKER_TIMEOUTS = 3
#: ...and it must also have been silent this long, so a burst of noise on a healthy
#: wheel board (read at 50 Hz) does not cut its feedback for a second.
DEFAULT_BREAKER_QUIET_S = 0.25
#: A presumed-gone device is probed this often, once the probes have backed off...
DEFAULT_PROBE_INTERVAL_S = 1.0
#: ...from a first probe this soon after the breaker opens, the gap doubling each time:
#: a breaker tripped by a burst of noise closes again within a few slots, and a dead
#: device costs a handful of extra probes before they reach ``probe_interval_s``.
_FIRST_PROBE_S = 0.125
#: After junk on the line, requests go one at a time for this long.
DEFAULT_CAUTION_S = 0.25
#: Latency samples kept per device for the percentiles.
_LATENCY_WINDOW = 1024
#: Requests remembered to recognise their echoes.
_RECENT_SENT = 8
#: Frames remembered ready-encoded (periodic requests repeat; each is encoded once).
_FRAME_CACHE_SIZE = 512
#: Requests behind a prompt line: it is prompt while all of the last ones were answered
#: and fewer than three quarters of their replies came after it was free by the model.
_PROMPT_WINDOW = 16
_HELD_AS_A_RULE = 12
#: Window of the sliding figures (utilisation, transactions per second).
_RATE_WINDOW_S = 1.0
#: Holds kept before expired ones are swept (corrupted addresses make new keys).
_MAX_HOLDS = 64
#: Float slack when comparing model times.
_EPS = 1e-9

#: A request's outcome, for a prompt line (0: answered in time).
_LATE = 1
_MISSED = 2

_IDEMPOTENT = frozenset({Command.RAM_READ, Command.EEP_READ, Command.STAT})
_READS = frozenset({Command.RAM_READ, Command.EEP_READ})


def is_idempotent(packet: Packet) -> bool:
    """Whether sending ``packet`` twice does no harm (reads and STAT): only those are retried."""
    return packet.cmd in _IDEMPOTENT


@dataclass(frozen=True, slots=True, eq=False, repr=False)
class ReplyPacket(Packet):
    """A reply as the bus delivers it: the packet, and when its request went and it came.

    It compares equal to, and prints as, a plain :class:`~ohmni_tb.protocol.Packet` with
    the same content.

    Attributes:
        sent_at: When the request was handed to the port (``loop.time()`` seconds).
        received_at: When the reply's last byte was decoded.
    """

    sent_at: float = 0.0
    received_at: float = 0.0


class BreakerState(enum.Enum):
    """Whether requests to a device go out."""

    #: The device answers: requests go.
    CLOSED = "closed"
    #: Presumed gone: requests fail fast until the next probe is due.
    OPEN = "open"
    #: A probe is on its way; the rest fail fast until it is answered or missing.
    PROBING = "probing"


class MissingReason(enum.Enum):
    """Why a reply will not come."""

    TIMEOUT = "no reply within its window"
    OVERTAKEN = "a later request was answered first"
    AMBIGUOUS = "two replies came that it could not tell apart"
    LINK_LOST = "the link was lost"


class StrayKind(enum.Enum):
    """What a packet that answered nothing was."""

    ECHO = "our own request, echoed"
    FOREIGN_REQUEST = "a request we did not send"
    EARLY = "a reply before its request could have been answered"
    LATE = "a reply after its request went missing"
    ABANDONED = "the reply to a request nobody waits for any more"
    TWIN = "a second reply fitting a request that already had one"
    UNMATCHED = "a reply to no request"


class _State(enum.Enum):
    PENDING = "pending"
    ANSWERED = "answered"
    MISSING = "missing"
    SENT = "sent"


@dataclass(eq=False, slots=True)
class Exchange:
    """One request on the line and what came of it. Times are the owner's clock (s).

    Attributes:
        packet: The request.
        frame: Its bytes, to write.
        expect_reply: Whether a reply is waited for.
        attempt: 0 for the first try, then 1, 2… for retries.
        sent_at: When it was handed to the port.
        wire_end_s: When its last byte has left, by the model.
        reply_earliest_s: The earliest its reply can be complete.
        window_end_s: The latest its reply's last byte can be on the wire.
        expires_at: When it goes missing if no reply has been seen.
        token: Whatever the owner attached.
        reply: The reply, once received.
        received_at: When it was received.
        abandoned: The owner no longer waits for the reply (it still holds the line).
    """

    packet: Packet
    frame: bytes
    expect_reply: bool
    attempt: int
    sent_at: float
    wire_end_s: float
    reply_earliest_s: float
    window_end_s: float
    expires_at: float
    token: object = None
    reply: Packet | None = None
    received_at: float | None = None
    abandoned: bool = False
    missing: MissingReason | None = None
    _state: _State = _State.PENDING
    # A reply held back until no look-alike twin follows it (after trouble on its key).
    _held_reply: Packet | None = None
    _held_at: float = 0.0
    _confirm_at: float = math.inf
    # A look-alike came before any reply could: whatever answers next is ambiguous.
    _tainted: bool = False
    # What its reply looks like (_reply_key), and its device's counters.
    _key: tuple[int, int, int] = field(default=(-1, -1, -1), repr=False)
    _device: _Device | None = field(default=None, repr=False)

    @property
    def done(self) -> bool:
        """Whether it is answered, missing, or was never going to be answered."""
        return self._state is not _State.PENDING


@dataclass(frozen=True, slots=True)
class ReplyReceived:
    """``exchange`` got its reply."""

    exchange: Exchange
    reply: ReplyPacket


@dataclass(frozen=True, slots=True)
class ReplyMissing:
    """``exchange`` will get no reply."""

    exchange: Exchange
    reason: MissingReason


@dataclass(frozen=True, slots=True)
class StrayPacket:
    """A packet that answered nothing we wait for (counted in the stats)."""

    packet: Packet
    at: float
    kind: StrayKind


Event = ReplyReceived | ReplyMissing | StrayPacket


@dataclass(frozen=True, slots=True)
class DeviceStats:
    """Counters for one device id.

    Attributes:
        sid: The device id.
        requests: Requests sent (each retry counts).
        replies: Replies matched to a request.
        timeouts: Attempts that got no reply (in time, or before a later one was answered).
        retries: Attempts after the first.
        unmatched: Replies from this id that answered nothing waiting: early + late +
            unmatched (abandoned replies are counted apart).
        late: Replies that came after their request had gone missing.
        early: Replies that came before the request they fit could have been answered.
        abandoned: Replies to requests their sender gave up (cancelled).
        latency_p50_s: Median request-sent → reply-received time, or ``None``.
        latency_p99_s: 99th percentile of the same, or ``None``.
        last_reply_at: When the last good reply came, or ``None``.
        consecutive_timeouts: Missing replies since the last good one.
        breaker: Whether requests to it go out.
        probes: Requests let through to it while its breaker was open.
    """

    sid: int
    requests: int
    replies: int
    timeouts: int
    retries: int
    unmatched: int
    late: int
    early: int
    abandoned: int
    latency_p50_s: float | None
    latency_p99_s: float | None
    last_reply_at: float | None
    consecutive_timeouts: int
    breaker: BreakerState
    probes: int


@dataclass(frozen=True, slots=True)
class ConnectionStats:
    """Counters of a :class:`BusConnection`.

    Attributes:
        bytes_out: Bytes sent.
        bytes_in: Bytes received.
        echoes: Copies of our own requests read back.
        foreign_requests: Requests seen that we did not send (another master, a glitch).
        unmatched: Replies that answered nothing waiting, all devices (early, late,
            unmatched).
        abandoned: Replies to requests their sender gave up.
        ambiguous: Requests given up because two look-alike replies came.
        cautions: Times junk on the line made the connection send request at a time
            (``caution_s``; more junk meanwhile extends the spell, not the count).
        cautious: Whether it does so now.
        wire_busy_s: Line time carried: every byte sent and received, at the baud rate.
        wire_utilisation: Share of the last second the line carried bytes.
        reserved_utilisation: Share of the last second the cost model reserved
            (bytes plus turnaround budgets and guards).
        transactions_per_s: Replies received in the last second.
        decoder: The receive decoder's counters.
        devices: Per-device counters by sid.
    """

    bytes_out: int
    bytes_in: int
    echoes: int
    foreign_requests: int
    unmatched: int
    abandoned: int
    ambiguous: int
    cautions: int
    cautious: bool
    wire_busy_s: float
    wire_utilisation: float
    reserved_utilisation: float
    transactions_per_s: float
    decoder: DecoderStats
    devices: dict[int, DeviceStats]


T = TypeVar("T")


class ReplyMatcher(Generic[T]):
    """Outstanding requests in the order they went out, and which one a reply answers.

    The one copy of the pairing rule, shared by the bus engine and the bus monitor:
    a reply answers the oldest outstanding request it fits (and that ``accept`` allows),
    and every request before that one has been overtaken. Each request carries an
    ``item`` of the owner's (an exchange, a time).

    Args:
        limit: The most requests kept; adding one more drops the oldest (returned by
            :meth:`add`), so a capture of requests without replies stays bounded.
    """

    __slots__ = ("_limit", "_pending")

    def __init__(self, limit: int | None = None) -> None:
        self._pending: deque[tuple[Packet, T]] = deque()
        self._limit = limit

    def __len__(self) -> int:
        return len(self._pending)

    def __iter__(self) -> Iterator[T]:
        return (item for _, item in self._pending)

    def add(self, request: Packet, item: T) -> list[T]:
        """Add an outstanding request; return what fell off the end (over the limit)."""
        self._pending.append((request, item))
        dropped: list[T] = []
        while self._limit is not None and len(self._pending) > self._limit:
            dropped.append(self._pending.popleft()[1])
        return dropped

    def find(self, reply: Packet) -> T | None:
        """The item of the oldest request ``reply`` fits, without removing anything."""
        for request, item in self._pending:
            if reply_matches(request, reply):
                return item
        return None

    def match(
        self, reply: Packet, accept: Callable[[T], bool] | None = None
    ) -> tuple[T | None, list[T]]:
        """Pair ``reply`` with the oldest request it fits.

        Returns:
            The item it answers (removed) and the items of the requests before it
            (removed: overtaken); or ``None`` and ``[]`` when it fits none, or when the
            one it fits is refused by ``accept`` (then nothing is removed).
        """
        for index, (request, item) in enumerate(self._pending):
            if reply_matches(request, reply):
                if accept is not None and not accept(item):
                    return None, []
                overtaken = [self._pending.popleft()[1] for _ in range(index)]
                self._pending.popleft()
                return item, overtaken
        return None, []

    def remove_where(self, predicate: Callable[[T], bool]) -> list[T]:
        """Remove and return the items for which ``predicate`` holds, in order."""
        if not any(predicate(item) for _, item in self._pending):
            return []
        kept: deque[tuple[Packet, T]] = deque()
        removed: list[T] = []
        for entry in self._pending:
            (removed.append(entry[1]) if predicate(entry[1]) else kept.append(entry))
        self._pending = kept
        return removed

    def clear(self) -> list[T]:
        """Remove and return every item."""
        items = [item for _, item in self._pending]
        self._pending.clear()
        return items


#: A packet sent, with what the connection works out from it once (_packet_info): its
#: frame, the look of its reply (_reply_key), and its reply's smallest and largest size.
_PacketInfo = tuple[Packet, bytes, tuple[int, int, int], int, int]

#: Makes an Exchange without its generated __init__: every field is set by send().
_new_exchange = object.__new__
_new = object.__new__
# The slots of a ReplyPacket and a ReplyReceived, set directly (_answer).
_set_reply_sid: Callable[[Packet, int], None] = Packet.__dict__["sid"].__set__
_set_reply_cmd: Callable[[Packet, int], None] = Packet.__dict__["cmd"].__set__
_set_reply_data: Callable[[Packet, bytes], None] = Packet.__dict__["data"].__set__
_set_sent_at: Callable[[ReplyPacket, float], None] = ReplyPacket.__dict__["sent_at"].__set__
_set_received_at: Callable[[ReplyPacket, float], None] = ReplyPacket.__dict__["received_at"].__set__
_set_event_exchange: Callable[[ReplyReceived, Exchange], None] = ReplyReceived.__dict__[
    "exchange"
].__set__
_set_event_reply: Callable[[ReplyReceived, ReplyPacket], None] = ReplyReceived.__dict__[
    "reply"
].__set__


def _reply_key(packet: Packet) -> tuple[int, int, int]:
    """What makes two replies look alike: sid, request code and (for reads) address."""
    base = packet.cmd & ~REPLY_FLAG
    addr = packet.data[0] if base in _READS and packet.data else -1
    return packet.sid, base, addr


class _Device:
    __slots__ = (
        "abandoned",
        "breaker",
        "consecutive",
        "early",
        "first_miss_at",
        "last_reply_at",
        "late",
        "latencies",
        "next_probe_at",
        "probe_gap",
        "probes",
        "replies",
        "requests",
        "retries",
        "timeouts",
        "turnaround_s",
        "unmatched",
    )

    def __init__(self) -> None:
        self.requests = 0
        self.replies = 0
        self.timeouts = 0
        self.retries = 0
        self.unmatched = 0
        self.late = 0
        self.early = 0
        self.abandoned = 0
        self.latencies: deque[float] = deque(maxlen=_LATENCY_WINDOW)
        self.last_reply_at: float | None = None
        self.consecutive = 0
        self.first_miss_at = 0.0
        self.breaker = BreakerState.CLOSED
        self.next_probe_at = 0.0
        self.probe_gap = 0.0
        self.probes = 0
        self.turnaround_s: float | None = None

    def snapshot(self, sid: int) -> DeviceStats:
        lat = sorted(self.latencies)
        return DeviceStats(
            sid=sid,
            requests=self.requests,
            replies=self.replies,
            timeouts=self.timeouts,
            retries=self.retries,
            unmatched=self.unmatched,
            late=self.late,
            early=self.early,
            abandoned=self.abandoned,
            latency_p50_s=percentile(lat, 0.50),
            latency_p99_s=percentile(lat, 0.99),
            last_reply_at=self.last_reply_at,
            consecutive_timeouts=self.consecutive,
            breaker=self.breaker,
            probes=self.probes,
        )


@dataclass(slots=True)
class _Window:
    """Sums of (time, amount) over the last ``_RATE_WINDOW_S``."""

    entries: deque[tuple[float, float]] = field(default_factory=deque)
    total: float = 0.0

    def add(self, at: float, amount: float) -> None:
        self.entries.append((at, amount))
        self.total += amount

    def over(self, now: float) -> float:
        entries = self.entries
        while entries and entries[0][0] <= now - _RATE_WINDOW_S:
            self.total -= entries.popleft()[1]
        if not entries:
            self.total = 0.0
        return max(0.0, self.total)


class BusConnection:
    """The bus master's half-duplex rules, sans-IO (see the module docstring).

    Args:
        baudrate: Line speed; ``None`` for a link without one (then nothing is
            pipelined: the next request waits for the reply or its timeout).
        turnaround_s: Default device turnaround budget (:meth:`set_turnaround` per device).
        guard_s: Quiet between transactions, by the cost model.
        reply_guard_s: Quiet after a reply the owner has seen before the next request:
            the time its sender takes to turn its line driver around (``None``: the
            guard). A few bit times are enough for a device; the cost model keeps
            ``guard_s``.
        timeout_s: How long past a reply's latest wire time it is still waited for.
        max_packet_size: The largest packet sent or accepted; a length-0 read budgets it.
        commands: Command codes the decoder accepts (default: the nine HerkuleX ones).
        pipelined: Send on the model's timing (``True``) or only after the reply is seen
            or missing (``False``: request at a time, the way most drivers work).
        breaker_timeouts: Missing replies in a row before the breaker may open.
        breaker_quiet_s: How long the misses must span as well (from the first missed
            request's send), before it opens.
        probe_interval_s: How often an open breaker lets a probe through once the
            probes have backed off (the first goes 0.125 s after it opens).
        caution_s: How long junk on the line makes a pipelined connection wait for each
            reply before the next request (0: never).
        clock_resolution_s: How much earlier than the truth the owner's ``now`` may be
            (its clock's step: 0.001 for one in whole milliseconds; 0: exact).

    Attributes:
        free_at: When the next request may start (``inf`` while waiting for a reply: a
            prompt line, a cautious one, or one not pipelined). Read it; the connection
            keeps it (an attribute, not a property: the owner reads it on every pass).
        urgent_free_at: When a stop may start (:meth:`send` with ``urgent``): the
            model's time, also while a prompt line waits for a reply (``inf`` only while
            cautious or not pipelined).
        poll_at: No :meth:`poll` has work to do before this time: an owner polls when it
            comes (a lower bound, made exact by each :meth:`poll` that works and by
            :meth:`next_deadline`).

    Raises:
        OutOfRangeError: A setting is out of range; the message names it.
    """

    def __init__(
        self,
        *,
        baudrate: int | None = None,
        turnaround_s: float = DEFAULT_TURNAROUND_S,
        guard_s: float = DEFAULT_GUARD_S,
        reply_guard_s: float | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        max_packet_size: int = MAX_PACKET_SIZE,
        commands: Iterable[int] | None = None,
        pipelined: bool = True,
        breaker_timeouts: int = DEFAULT_BREAKER_TIMEOUTS,
        breaker_quiet_s: float = DEFAULT_BREAKER_QUIET_S,
        probe_interval_s: float = DEFAULT_PROBE_INTERVAL_S,
        caution_s: float = DEFAULT_CAUTION_S,
        clock_resolution_s: float = 0.0,
    ) -> None:
        if baudrate is not None and (
            isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0
        ):
            raise OutOfRangeError("baudrate", baudrate, 1, 4_000_000, "baud")
        check_seconds("turnaround_s", turnaround_s, 0.0, 1.0)
        check_seconds("guard_s", guard_s, 0.0, 1.0)
        if reply_guard_s is not None:
            check_seconds("reply_guard_s", reply_guard_s, 0.0, 1.0)
        check_seconds("timeout_s", timeout_s, 0.0005, 10.0)
        check_seconds("breaker_quiet_s", breaker_quiet_s, 0.0, 3600.0)
        check_seconds("probe_interval_s", probe_interval_s, 0.001, 3600.0)
        check_seconds("caution_s", caution_s, 0.0, 60.0)
        check_seconds("clock_resolution_s", clock_resolution_s, 0.0, 0.1)
        integer("breaker_timeouts", breaker_timeouts, 1, 1000)
        self.baudrate = baudrate
        self.byte_s = 0.0 if baudrate is None else BITS_PER_BYTE / baudrate
        self.turnaround_s = float(turnaround_s)
        self.guard_s = float(guard_s)
        self.reply_guard_s = self.guard_s if reply_guard_s is None else float(reply_guard_s)
        self.timeout_s = float(timeout_s)
        self.max_packet_size = max_packet_size
        self.pipelined = bool(pipelined) and baudrate is not None
        self.breaker_timeouts = breaker_timeouts
        self.breaker_quiet_s = float(breaker_quiet_s)
        self.probe_interval_s = float(probe_interval_s)
        self.caution_s = float(caution_s)
        self.clock_resolution_s = float(clock_resolution_s)
        self._decoder = PacketDecoder(max_size=max_packet_size, commands=commands)
        self._outstanding: ReplyMatcher[Exchange] = ReplyMatcher()
        self._keys: dict[tuple[int, int, int], Exchange] = {}
        self._holds: dict[tuple[int, int, int], float] = {}
        self._suspect: set[tuple[int, int, int]] = set()
        self._recent: deque[Packet] = deque(maxlen=_RECENT_SENT)
        self._info: dict[int, _PacketInfo] = {}
        self._frames: dict[Packet, bytes] = {}
        self._ack_policy: dict[int, int] = {}
        #: Counts the changes of ACK policy (what :meth:`expects_reply` says may change).
        self.policy_version = 0
        self._devices: dict[int, _Device] = {}
        self.free_at = -math.inf
        self.poll_at = math.inf
        # When a stop may go: the model's time, even while a prompt line waits for a reply.
        self.urgent_free_at = -math.inf
        # The last requests' outcomes: whether each reply was seen after the line was free
        # by the model, or missing; and how many of each among them.
        self._outcomes: deque[int] = deque(maxlen=_PROMPT_WINDOW)
        self._late_count = 0
        self._miss_count = 0
        self._prompt = False
        self._cautious_until = -math.inf
        self._cautions = 0
        self._last: Exchange | None = None
        self._last_rx_at = -math.inf
        self._bytes_out = 0
        self._bytes_in = 0
        self._echoes = 0
        self._foreign = 0
        self._unmatched = 0
        self._abandoned = 0
        self._ambiguous = 0
        self._busy_s = 0.0
        self._busy = _Window()
        self._reserved = _Window()
        self._answers = _Window()

    # -- configuration ---------------------------------------------------------------

    def ack_policy(self, sid: int) -> int:
        """The ACK policy assumed for ``sid`` (HerkuleX default: 1, reads only)."""
        return self._ack_policy.get(sid, AckPolicy.READS)

    def set_ack_policy(self, sid: int, policy: int) -> None:
        """Tell the connection which ACK policy device ``sid`` runs, so it knows what answers.

        Raises:
            OutOfRangeError: ``policy`` is not 0, 1 or 2.
        """
        if isinstance(policy, bool) or policy not in (0, 1, 2):
            raise OutOfRangeError("ack policy", policy, 0, 2)
        self._ack_policy[sid] = int(policy)
        self.policy_version += 1

    def turnaround(self, sid: int) -> float:
        """The turnaround budget of device ``sid``."""
        device = self._devices.get(sid)
        if device is None or device.turnaround_s is None:
            return self.turnaround_s
        return device.turnaround_s

    def set_turnaround(self, sid: int, turnaround_s: float | None) -> None:
        """Give device ``sid`` its own turnaround budget (``None``: back to the default).

        Raises:
            OutOfRangeError: Not 0..1 s.
        """
        if turnaround_s is not None:
            check_seconds("turnaround_s", turnaround_s, 0.0, 1.0)
            turnaround_s = float(turnaround_s)
        self._device(sid).turnaround_s = turnaround_s

    def expects_reply(self, packet: Packet) -> bool:
        """Whether ``packet`` gets a reply under the ACK policy known for its device."""
        sid = packet.sid
        if sid == BROADCAST_ID:
            return False
        return _reply_expected(packet.cmd, sid, self._ack_policy.get(sid, AckPolicy.READS))

    # -- the line ---------------------------------------------------------------------

    @property
    def prompt(self) -> bool:
        """Whether the line is prompt: requests to devices that answer wait for their
        replies (module docstring)."""
        return self._prompt

    @property
    def outstanding(self) -> int:
        """Requests waiting for their replies (abandoned ones included)."""
        return len(self._outstanding)

    def pending(self) -> list[Exchange]:
        """The exchanges still waiting for replies, oldest first."""
        return list(self._outstanding)

    def blocked_until(self, packet: Packet, now: float) -> float:
        """When ``packet`` may be sent as far as look-alike replies go.

        ``-inf`` when it may go now; ``inf`` while an identical request is outstanding
        (it resolves by an event); else the end of the hold after an identical request
        went missing.
        """
        keys, holds = self._keys, self._holds
        if not keys and not holds:
            return -math.inf  # nothing outstanding or held: the common case
        if not self.expects_reply(packet):
            return -math.inf
        key = self._packet_info(packet)[2]
        if key in keys:
            return math.inf
        until = holds.get(key)
        if until is None:
            return -math.inf
        if until <= now + _EPS:
            del self._holds[key]
            return -math.inf
        return until

    def refusal(self, sid: int, now: float) -> float | None:
        """``None`` if requests to ``sid`` may go; else seconds until its next probe may."""
        device = self._devices.get(sid)
        if device is None or device.breaker is BreakerState.CLOSED:
            return None
        if device.breaker is BreakerState.OPEN and now + _EPS >= device.next_probe_at:
            return None
        return max(0.0, device.next_probe_at - now)

    def silent_for(self, sid: int, now: float) -> float | None:
        """Seconds since ``sid`` last answered, or ``None`` if it never did."""
        device = self._devices.get(sid)
        if device is None or device.last_reply_at is None:
            return None
        return now - device.last_reply_at

    def frame(self, packet: Packet) -> bytes:
        """``packet``'s bytes, encoded once for requests that repeat.

        Raises:
            OutOfRangeError: The packet cannot be encoded (bad sid, command or size).
        """
        return self._packet_info(packet)[1]

    def _packet_info(self, packet: Packet) -> _PacketInfo:
        """``packet`` with its frame, reply key and reply sizes, worked out once for a
        packet object sent again (a stream's requests are the same objects every cycle).

        Raises:
            OutOfRangeError: The packet cannot be encoded (bad sid, command or size).
        """
        info = self._info.get(id(packet))
        if info is not None and info[0] is packet:
            return info
        # An equal packet seen before shares its frame: encoded once per content.
        frame = self._frames.get(packet)
        if frame is None:
            frame = encode_packet(packet, max_size=self.max_packet_size)
            if len(self._frames) >= _FRAME_CACHE_SIZE:
                self._frames.clear()
            self._frames[packet] = frame
        smallest, largest = reply_size_range(packet, max_packet_size=self.max_packet_size)
        info = (packet, frame, _reply_key(packet), smallest, largest)
        if len(self._info) >= _FRAME_CACHE_SIZE:
            self._info.clear()
        # Keyed by identity, the packet kept in the entry: its id is not reused meanwhile.
        self._info[id(packet)] = info
        return info

    def send(
        self,
        packet: Packet,
        now: float,
        *,
        expect_reply: bool | None = None,
        timeout_s: float | None = None,
        attempt: int = 0,
        token: object = None,
        urgent: bool = False,
    ) -> Exchange:
        """Start a transaction now: return the exchange, whose ``frame`` the owner writes.

        Args:
            packet: The request.
            now: The owner's clock.
            expect_reply: Override whether a reply is waited for (``None``: the ACK
                policy decides; a broadcast never waits).
            timeout_s: This request's own timeout (past its reply's latest wire time).
            attempt: 0 for a first try; more for a retry (counted).
            token: Anything the owner wants back with the events.
            urgent: A stop: it may go at :attr:`urgent_free_at` (the model's time)
                rather than :attr:`free_at`.

        Raises:
            OutOfRangeError: The packet cannot be encoded; nothing changed.
            InvalidArgumentError: A STAT to broadcast (every device would answer at once).
            StateError: The line is not free yet, or an identical request is
                outstanding or held (see :meth:`blocked_until`).
        """
        _, frame, key, smallest, largest = self._packet_info(packet)
        sid = packet.sid
        if sid == BROADCAST_ID:
            if packet.cmd == Command.STAT:
                raise InvalidArgumentError(
                    "STAT to broadcast (0xFE): every device would answer at once"
                )
            expect_reply = False
        elif expect_reply is None:
            expect_reply = self.expects_reply(packet)
        free = self.urgent_free_at if urgent else self.free_at
        if now + _EPS < free:
            raise StateError(f"the line is busy for {free - now:.6f} s more")
        if timeout_s is None:
            timeout = self.timeout_s
        else:
            check_seconds("timeout_s", timeout_s, 0.0005, 10.0)
            timeout = timeout_s
        holds = self._holds
        if expect_reply and (
            key in self._keys or (holds and holds.get(key, -math.inf) > now + _EPS)
        ):
            raise StateError(f"an identical request is outstanding or held: {packet!r}")
        byte_s = self.byte_s
        size = len(frame)
        wire_s = size * byte_s
        # A coarse clock may read behind: the bytes may have gone that much later.
        wire_end = now + self.clock_resolution_s + wire_s
        device = self._devices.get(sid)
        if device is None:
            device = self._device(sid)
        device.requests += 1
        if attempt:
            device.retries += 1
        self._bytes_out += size
        if wire_s:
            self._busy_s += wire_s
            busy = self._busy
            busy.entries.append((now, wire_s))
            busy.total += wire_s
        exchange = _new_exchange(Exchange)
        exchange.packet = packet
        exchange.frame = frame
        exchange.attempt = attempt
        exchange.sent_at = now
        exchange.wire_end_s = wire_end
        exchange.token = token
        exchange.reply = None
        exchange.received_at = None
        exchange.abandoned = False
        exchange.missing = None
        exchange._held_reply = None
        exchange._held_at = 0.0
        exchange._confirm_at = math.inf
        exchange._tainted = False
        exchange._key = key
        exchange._device = device
        if expect_reply:
            turnaround = device.turnaround_s
            window_end = (
                wire_end
                + (self.turnaround_s if turnaround is None else turnaround)
                + largest * byte_s
            )
            exchange.expect_reply = True
            exchange.reply_earliest_s = now + (size + smallest) * byte_s
            exchange.window_end_s = window_end
            exchange.expires_at = window_end + timeout
            exchange._state = _State.PENDING
            self._outstanding._pending.append((packet, exchange))
            self._keys[key] = exchange
            if holds:
                holds.pop(key, None)
            self.poll_at = min(self.poll_at, exchange.expires_at)
            if device.breaker is BreakerState.OPEN:
                device.breaker = BreakerState.PROBING
                device.probe_gap = min(2.0 * device.probe_gap, self.probe_interval_s)
                device.next_probe_at = now + device.probe_gap
                device.probes += 1
            pipelined = self.pipelined and now + _EPS >= self._cautious_until
            urgent_free_at = free_at = window_end + self.guard_s if pipelined else math.inf
            if pipelined and self._prompt and device.consecutive == 0:
                # A prompt line waits for a device that answers (it may be late).
                free_at = math.inf
            reserved_s = window_end - now + self.guard_s
        else:
            exchange.expect_reply = False
            exchange.reply_earliest_s = wire_end
            exchange.window_end_s = wire_end
            exchange.expires_at = wire_end
            exchange._state = _State.SENT
            urgent_free_at = free_at = wire_end + self.guard_s
            reserved_s = wire_end - now + self.guard_s
        reserved = self._reserved
        reserved.entries.append((now, reserved_s))
        reserved.total += reserved_s
        self.free_at = free_at
        self.urgent_free_at = urgent_free_at
        self._last = exchange
        self._recent.append(packet)
        return exchange

    def written(self, exchange: Exchange, at: float) -> None:
        """The write of ``exchange``'s frame returned at ``at``: its bytes left by then.

        ``send`` was given the time just before the write, which bounds the reply's
        earliest arrival; a write that returned later (the process was descheduled in
        between) moves the latest end of the request, of its reply window and of the
        line's busy time to match — or a reply still on the wire could be talked over.
        """
        delta = at - exchange.sent_at
        if delta <= 0:
            return
        exchange.wire_end_s += delta
        exchange.window_end_s += delta
        exchange.expires_at += delta
        if exchange is self._last:
            end = exchange.window_end_s if exchange.expect_reply else exchange.wire_end_s
            if self.free_at != math.inf:
                self.free_at = max(self.free_at, end + self.guard_s)
            if self.urgent_free_at != math.inf:
                self.urgent_free_at = max(self.urgent_free_at, end + self.guard_s)

    def abandon(self, exchange: Exchange) -> None:
        """The owner no longer waits for ``exchange``'s reply (its time on the line stays)."""
        exchange.abandoned = True

    def receive_data(self, data: bytes, now: float) -> list[Event]:
        """Feed received bytes; return what they complete."""
        self._bytes_in += len(data)
        self._last_rx_at = now
        events: list[Event] = []
        decoder = self._decoder
        # The decoder's own counters, read without its properties' calls (a read a reply).
        discarded = decoder._discarded
        pending = self._outstanding._pending
        for packet in decoder.feed(data):
            if pending and packet.cmd & REPLY_FLAG and not self._suspect:
                # The common case, the oldest request's reply on a clean line: what
                # _route would conclude, without its general search.
                request, exchange = pending[0]
                if (
                    exchange._held_reply is None
                    and not exchange._tainted
                    and now + self.clock_resolution_s + _EPS >= exchange.reply_earliest_s
                    and reply_matches(request, packet)
                ):
                    pending.popleft()
                    wire_s = (HEADER_SIZE + len(packet.data)) * self.byte_s
                    self._busy_s += wire_s
                    busy = self._busy
                    busy.entries.append((now, wire_s))
                    busy.total += wire_s
                    self._answer(exchange, packet, now, events)
                    continue
            self._route(packet, now, events)
        if decoder._discarded != discarded:
            self._junk(now, events)
        if decoder._buf:  # feed() leaves the bytes of a half frame, from position 0
            # A half frame: given up a timeout after its last byte (poll).
            self.poll_at = min(self.poll_at, now + self.timeout_s)
        return events

    def next_deadline(self) -> float | None:
        """When :meth:`poll` next has something to do (a reply window, a half frame)."""
        deadline = math.inf
        for _, exchange in self._outstanding._pending:
            if exchange._held_reply is not None:
                deadline = min(deadline, exchange._confirm_at)
            else:
                deadline = min(deadline, exchange.expires_at)
        if self._decoder._buf:  # a half frame held (feed() leaves it from position 0)
            deadline = min(deadline, self._last_rx_at + self.timeout_s)
        self.poll_at = deadline  # exact, so also the soonest poll() has work
        return None if deadline == math.inf else deadline

    def poll(self, now: float) -> list[Event]:
        """Give up what ``now`` has made hopeless: half frames, then overdue replies."""
        events: list[Event] = []
        if now + _EPS < self.poll_at:
            return events  # nothing is due before then: the common case
        try:
            self._poll(now, events)
        finally:
            self.next_deadline()
        return events

    def _poll(self, now: float, events: list[Event]) -> None:
        if not self._outstanding._pending and not self._decoder.pending:
            return
        if self._decoder.pending and now + _EPS >= self._last_rx_at + self.timeout_s:
            # Nothing arrived for a whole timeout: the rest of this frame is not coming.
            discarded = self._decoder.discarded
            for packet in self._decoder.expire():
                self._route(packet, now, events)
            if self._decoder.discarded != discarded:
                self._junk(now, events)
        for exchange in self._outstanding.remove_where(
            lambda e: (e._confirm_at if e._held_reply is not None else e.expires_at) <= now + _EPS
        ):
            held = exchange._held_reply
            if held is not None and self._decoder.pending:
                # A frame is still arriving: wait for it, or for it to expire.
                self._outstanding.add(exchange.packet, exchange)
                exchange._confirm_at = self._last_rx_at + self.timeout_s
                continue
            if held is not None:
                # No twin came within a reply window: the held reply is its answer.
                self._suspect.discard(_reply_key(exchange.packet))
                self._answer(exchange, held, exchange._held_at, events)
            else:
                self._miss(exchange, MissingReason.TIMEOUT, now, events)
        if len(self._holds) > _MAX_HOLDS:
            self._holds = {k: t for k, t in self._holds.items() if t > now}

    def link_lost(self, now: float) -> list[Event]:
        """The port went away: every outstanding request is missing; the line starts over."""
        events: list[Event] = []
        for exchange in self._outstanding.clear():
            self._keys.pop(_reply_key(exchange.packet), None)
            exchange._state = _State.MISSING
            exchange.missing = MissingReason.LINK_LOST
            if not exchange.abandoned:
                events.append(ReplyMissing(exchange, MissingReason.LINK_LOST))
        self._decoder.reset()
        self._holds.clear()
        self._suspect.clear()
        self.free_at = self.urgent_free_at = now
        self._last = None
        return events

    # -- statistics ------------------------------------------------------------------

    def stats(self, now: float) -> ConnectionStats:
        """A snapshot of every counter; the sliding figures end at ``now``."""
        return ConnectionStats(
            bytes_out=self._bytes_out,
            bytes_in=self._bytes_in,
            echoes=self._echoes,
            foreign_requests=self._foreign,
            unmatched=self._unmatched,
            abandoned=self._abandoned,
            ambiguous=self._ambiguous,
            cautions=self._cautions,
            cautious=now + _EPS < self._cautious_until,
            wire_busy_s=self._busy_s,
            wire_utilisation=self._busy.over(now) / _RATE_WINDOW_S,
            reserved_utilisation=self._reserved.over(now) / _RATE_WINDOW_S,
            transactions_per_s=self._answers.over(now) / _RATE_WINDOW_S,
            decoder=self._decoder.stats,
            devices={sid: d.snapshot(sid) for sid, d in sorted(self._devices.items())},
        )

    # -- private ---------------------------------------------------------------------

    def _device(self, sid: int) -> _Device:
        device = self._devices.get(sid)
        if device is None:
            device = self._devices[sid] = _Device()
        return device

    def _note_busy(self, at: float, seconds: float) -> None:
        if seconds:
            self._busy_s += seconds
            self._busy.add(at, seconds)

    def _route(self, packet: Packet, now: float, events: list[Event]) -> None:
        if not packet.is_reply:
            if packet in self._recent:
                self._echoes += 1
                events.append(StrayPacket(packet, now, StrayKind.ECHO))
                return
            # Someone else is talking; whoever it asked may answer, so keep off the line
            # for one reply window.
            self._foreign += 1
            _, largest = reply_size_range(packet, max_packet_size=self.max_packet_size)
            busy_until = (
                now
                + self.clock_resolution_s
                + self.turnaround_s
                + largest * self.byte_s
                + self.guard_s
            )
            self.free_at = max(self.free_at, busy_until)
            self.urgent_free_at = max(self.urgent_free_at, busy_until)
            events.append(StrayPacket(packet, now, StrayKind.FOREIGN_REQUEST))
            return
        self._note_busy(now, packet.size * self.byte_s)
        key = _reply_key(packet)
        exchange = self._outstanding.find(packet)
        if exchange is not None:
            if exchange._held_reply is not None:
                # A twin: one of the two is another request's, and nothing says which.
                self._outstanding.remove_where(lambda e: e is exchange)
                self._ambiguous += 1
                self._stray(packet, now, StrayKind.TWIN, events)
                self._miss(exchange, MissingReason.AMBIGUOUS, now, events)
                return
            if now + self.clock_resolution_s + _EPS < exchange.reply_earliest_s:
                # Its request's bytes and its own could not both have crossed the line
                # yet: this is another request's reply that merely looks the same, and
                # more of those may queue ahead of its own.
                exchange._tainted = True
                self._stray(packet, now, StrayKind.EARLY, events)
                return
            if exchange._tainted:
                self._outstanding.remove_where(lambda e: e is exchange)
                self._ambiguous += 1
                self._stray(packet, now, StrayKind.TWIN, events)
                self._miss(exchange, MissingReason.AMBIGUOUS, now, events)
                return
            matched, overtaken = self._outstanding.match(packet)
            assert matched is exchange  # find() and match() walk the same queue
            for earlier in overtaken:
                if earlier._held_reply is not None:
                    # The line moved on to later requests without a twin: confirmed.
                    self._suspect.discard(_reply_key(earlier.packet))
                    self._answer(earlier, earlier._held_reply, earlier._held_at, events)
                else:
                    self._miss(earlier, MissingReason.OVERTAKEN, now, events)
            if key in self._suspect:
                # Keep it outstanding, its reply held, for one reply window.
                self._outstanding.add(exchange.packet, exchange)
                exchange._held_reply = packet
                exchange._held_at = now
                exchange._confirm_at = (
                    now + self.clock_resolution_s + self._window_s(packet.sid, packet.size)
                )
                self.poll_at = min(self.poll_at, exchange._confirm_at)
                return
            self._answer(exchange, packet, now, events)
            return
        self._stray(
            packet, now, StrayKind.LATE if key in self._holds else StrayKind.UNMATCHED, events
        )
        self._void_held(packet.sid, now, events)

    def _junk(self, now: float, events: list[Event]) -> None:
        """Bytes were discarded: a collision, noise, a half frame. Be careful for a while."""
        # A held reply's twin may be in the junk.
        self._void_held(None, now, events)
        if self.pipelined and self.caution_s:
            if now + _EPS >= self._cautious_until:
                self._cautions += 1
            self._cautious_until = now + self.caution_s

    def _void_held(self, sid: int | None, now: float, events: list[Event]) -> None:
        """The line was not clean: held replies (of device ``sid``, or all) are ambiguous."""
        voided = self._outstanding.remove_where(
            lambda e: e._held_reply is not None and (sid is None or e.packet.sid == sid)
        )
        for exchange in voided:
            self._ambiguous += 1
            self._miss(exchange, MissingReason.AMBIGUOUS, now, events)

    def _window_s(self, sid: int, reply_size: int) -> float:
        """How long a device's look-alike answer may still follow: one reply slot."""
        return self.turnaround(sid) + reply_size * self.byte_s + self.guard_s

    def _stray(self, packet: Packet, now: float, kind: StrayKind, events: list[Event]) -> None:
        key = _reply_key(packet)
        # Its sender may have more of these queued: its look stays suspect and held.
        self._suspect.add(key)
        hold = (
            now + self.clock_resolution_s + self._window_s(packet.sid, packet.size) + self.timeout_s
        )
        self._holds[key] = max(self._holds.get(key, -math.inf), hold)
        device = self._device(packet.sid)
        device.unmatched += 1
        self._unmatched += 1
        if kind is StrayKind.LATE:
            device.late += 1
        elif kind is StrayKind.EARLY:
            device.early += 1
        events.append(StrayPacket(packet, now, kind))

    def _answer(self, exchange: Exchange, packet: Packet, now: float, events: list[Event]) -> None:
        self._keys.pop(exchange._key, None)
        exchange._state = _State.ANSWERED
        exchange.reply = packet
        exchange.received_at = now
        device = exchange._device
        if device is None:  # pragma: no cover - send() gives every exchange its device
            device = self._device(exchange.packet.sid)
        device.replies += 1
        device.latencies.append(now - exchange.sent_at)
        device.last_reply_at = now
        device.consecutive = 0
        device.breaker = BreakerState.CLOSED
        answers = self._answers
        answers.entries.append((now, 1.0))
        answers.total += 1.0
        late = now > exchange.window_end_s + self.guard_s + _EPS
        if late or not self._prompt:
            self._note_outcome(_LATE if late else 0)
        else:
            # In time on a prompt line: the window moves on by an answer in time.
            window = self._outcomes
            gone = window[0]
            if gone:
                self._late_count -= gone == _LATE
                self._miss_count -= gone == _MISSED
                self._prompt = not self._miss_count and self._late_count < _HELD_AS_A_RULE
            window.append(0)
        if exchange is self._last:
            # The reply is in, so the line went quiet no later than now, whatever the
            # budget said.
            quiet = now + self.clock_resolution_s + self.reply_guard_s
            self.free_at = min(self.free_at, quiet)
            self.urgent_free_at = min(self.urgent_free_at, quiet)
        if exchange.abandoned:
            device.abandoned += 1
            self._abandoned += 1
            events.append(StrayPacket(packet, now, StrayKind.ABANDONED))
            return
        # Built through the slots, as the decoder builds packets: the frozen dataclasses'
        # __init__ sets each field by name, which takes a Python call and twice as long.
        reply = _new(ReplyPacket)
        _set_reply_sid(reply, packet.sid)
        _set_reply_cmd(reply, packet.cmd)
        _set_reply_data(reply, packet.data)
        _set_sent_at(reply, exchange.sent_at)
        _set_received_at(reply, now)
        event = _new(ReplyReceived)
        _set_event_exchange(event, exchange)
        _set_event_reply(event, reply)
        events.append(event)

    def _note_outcome(self, outcome: int) -> None:
        """A request was answered in time (0), late (``_LATE``) or not (``_MISSED``)."""
        window = self._outcomes
        if len(window) == _PROMPT_WINDOW:
            gone = window[0]
            self._late_count -= gone == _LATE
            self._miss_count -= gone == _MISSED
        window.append(outcome)
        self._late_count += outcome == _LATE
        self._miss_count += outcome == _MISSED
        self._prompt = (
            len(window) == _PROMPT_WINDOW
            and not self._miss_count
            and self._late_count < _HELD_AS_A_RULE
        )

    def _miss(
        self, exchange: Exchange, reason: MissingReason, now: float, events: list[Event]
    ) -> None:
        key = _reply_key(exchange.packet)
        self._keys.pop(key, None)
        # A device slower than its budget may still answer: an identical request waits
        # one more window, in which that answer is recognised as late.
        hold = now + self.clock_resolution_s + (exchange.expires_at - exchange.wire_end_s)
        self._holds[key] = max(self._holds.get(key, -math.inf), hold)
        self._suspect.add(key)
        exchange._state = _State.MISSING
        exchange.missing = reason
        self._note_outcome(_MISSED)
        device = self._device(exchange.packet.sid)
        device.timeouts += 1
        if device.consecutive == 0:
            device.first_miss_at = exchange.sent_at
        device.consecutive += 1
        if device.breaker is BreakerState.PROBING:
            device.breaker = BreakerState.OPEN
        elif (
            device.breaker is BreakerState.CLOSED
            and device.consecutive >= self.breaker_timeouts
            # Silent while it was being asked: from the first request of this run of
            # misses, not from its last reply (a device nobody asked for a minute is
            # not a minute silent).
            and now - device.first_miss_at >= self.breaker_quiet_s
        ):
            device.breaker = BreakerState.OPEN
            device.probe_gap = min(_FIRST_PROBE_S, self.probe_interval_s)
            device.next_probe_at = now + device.probe_gap
        if exchange is self._last:
            if self.free_at == math.inf:
                self.free_at = now + self.clock_resolution_s + self.guard_s
            if self.urgent_free_at == math.inf:
                self.urgent_free_at = now + self.clock_resolution_s + self.guard_s
        if not exchange.abandoned:
            events.append(ReplyMissing(exchange, reason))


def percentile(sorted_values: list[float], q: float) -> float | None:
    """The ``q`` quantile of already sorted values (nearest rank), or ``None`` if empty."""
    if not sorted_values:
        return None
    index = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[index]
