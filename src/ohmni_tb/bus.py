"""The async bus engine: prioritised, deadline-aware, wire-timed slots on one half-duplex line.

The line's rules live in the sans-IO :class:`~ohmni_tb.protocol.connection.BusConnection`
(matching, wire timing, holds, breaker, statistics); this module is the thin shell that
drives it from the event loop. It runs no task of its own: received bytes arrive through
the transport's readiness callback, and one ``loop.call_at`` timer wakes it when the
line frees or a reply window closes::

    async with Bus(await open_transport("/dev/ttyUSB0")) as bus:
        reply = await bus.read(0, 59, 4)                    # left wheel count
        left, right, _ = await bus.transact(                # one atomic slot
            [read_count(0), read_count(1), wheel_command(200, 200)],
            priority=10, deadline=loop.time() + 0.005,
        )

What it promises:

* **Slots.** :meth:`Bus.transact` sends its packets back to back with nothing else in
  between. Waiting slots go highest ``priority`` first, in order of arrival within a
  priority; one that has waited ``max_wait_s`` goes next whatever its priority, so nothing
  starves. A slot that cannot start before its ``deadline`` is dropped with
  :class:`~ohmni_tb.errors.DeadlineMissedError`; retries of its reads go only while the
  deadline allows. A slot queued with ``not_before`` waits for that time without holding
  anything else up, and starts from whatever wakes the bus then.
* **Wire-timed and pipelined.** The next request goes when the previous transaction's
  time on the wire is up by the cost model (:mod:`ohmni_tb.protocol.timing`), not when
  the host has read the reply: an adapter's latency delays replies, not the rate. A reply
  seen sooner frees the line sooner (``reply_guard_s`` after it), and the next request
  is written from the reply's own callback; while the replies come that promptly, a
  request waits for its reply rather than talk over a late one
  (:class:`~ohmni_tb.protocol.connection.BusConnection`). A reply answers only a request
  it fits and could have answered by then; a late or duplicate reply is counted, never
  delivered. Replies are stamped as they are read and requests as they are written, to
  the microsecond, whatever the loop (:func:`~ohmni_tb.eventloop.line_clock`).
* **Silent devices cost little.** A device that stopped answering trips a breaker:
  requests to it fail fast with :class:`~ohmni_tb.errors.DeviceUnavailableError`, with a
  probe a second, until it answers.
* **Stops jump the queue.** :meth:`Bus.send_now` waits only for the transaction on the
  wire; :meth:`Bus.aclose` writes its ``final`` packets (the wheel stop) before the port
  closes, even when the closing task is cancelled.
* **A lost link is reported** (requests fail with :class:`~ohmni_tb.errors.TransportError`,
  :meth:`Bus.wait_lost` returns) and :meth:`Bus.reconnect` reopens the port on the same
  Bus, with backoff, keeping its statistics. :meth:`Bus.release` closes the port on
  purpose, so another program can open it, until :meth:`Bus.reconnect` takes it back.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass, fields
from types import TracebackType
from typing import Self, cast

from ohmni_tb._checks import check_seconds, integer
from ohmni_tb.errors import (
    BusClosedError,
    BusTimeoutError,
    DeadlineMissedError,
    DeviceUnavailableError,
    InvalidArgumentError,
    OutOfRangeError,
    StateError,
    TransportError,
)
from ohmni_tb.eventloop import MILLISECOND_S, LineClock, line_clock, timer_resolution_s
from ohmni_tb.protocol import (
    BROADCAST_ID,
    MAX_PACKET_SIZE,
    Command,
    Memory,
    Packet,
    ReadReply,
    StatusReply,
    read_request,
    write_request,
)
from ohmni_tb.protocol.connection import (
    DEFAULT_BREAKER_QUIET_S,
    DEFAULT_BREAKER_TIMEOUTS,
    DEFAULT_CAUTION_S,
    DEFAULT_PROBE_INTERVAL_S,
    DEFAULT_TIMEOUT_S,
    BreakerState,
    BusConnection,
    ConnectionStats,
    DeviceStats,
    Event,
    Exchange,
    MissingReason,
    ReplyMissing,
    ReplyPacket,
    ReplyReceived,
    StrayPacket,
    is_idempotent,
    percentile,
)
from ohmni_tb.protocol.timing import (
    DEFAULT_GUARD_S,
    DEFAULT_TURNAROUND_S,
    reply_size_range,
    transaction_cost_s,
)
from ohmni_tb.transport import Transport, open_transport

__all__ = [
    "DEFAULT_CLOSE_TIMEOUT_S",
    "DEFAULT_GUARD_S",
    "DEFAULT_MAX_WAIT_S",
    "DEFAULT_RETRIES",
    "DEFAULT_STALL_S",
    "DEFAULT_TIMEOUT_S",
    "DEFAULT_TURNAROUND_S",
    "BreakerState",
    "Bus",
    "BusStats",
    "DeviceStats",
    "ReplyPacket",
    "Slot",
    "Tap",
    "transaction_cost_s",
]

_log = logging.getLogger(__name__)

#: A bus tap (:meth:`Bus.add_tap`): (sent, the bytes, loop time).
Tap = Callable[[bool, bytes, float], None]

#: Extra attempts for reads and STAT; writes are never repeated blindly.
DEFAULT_RETRIES = 2
#: A waiting slot older than this goes next, whatever its priority.
DEFAULT_MAX_WAIT_S = 0.5
#: Bytes that stay queued in the port this long mean the other end is not reading.
DEFAULT_STALL_S = 0.5
#: How long :meth:`Bus.aclose` may take to put its final packets on the wire.
DEFAULT_CLOSE_TIMEOUT_S = 0.5
#: Queue-wait samples kept for the percentiles.
_WAIT_WINDOW = 1024
#: While bytes wait in the port, look again this often.
_BACKLOG_POLL_S = 0.001
#: On a loop whose timers wait in whole milliseconds, the last this long of a wait for the
#: line is slept inline rather than left to the timer (Bus._wait_inline).
_INLINE_WAIT_MAX_S = MILLISECOND_S
#: A wait for the line this short is waited out in the loop on any real clock: shorter
#: than what a pass of the event loop and its wake-up cost (Bus._wait_inline).
_SPIN_S = 0.00005
_EPS = 1e-9

#: Opens a fresh transport for :meth:`Bus.reconnect`.
Reopen = Callable[[], Awaitable[Transport]]


@dataclass(frozen=True, slots=True)
class BusStats(ConnectionStats):
    """Counters for the whole bus (a snapshot): the line's, and the scheduler's.

    Every field of :class:`~ohmni_tb.protocol.connection.ConnectionStats` (bytes, echoes,
    unmatched, cautions, wire utilisation, the decoder's and each device's counters…),
    and:

    Attributes:
        slots: Slots started.
        queue_wait_p50_s: Median wait from submission to the slot's start, or ``None``.
        queue_wait_p99_s: 99th percentile of the same, or ``None``.
        deadline_misses: Slots dropped (and retries not sent) because of their deadline.
        promoted: Slots sent ahead of their priority after waiting ``max_wait_s``.
        refused: Requests not sent because the device's breaker was open.
        twins: Requests of a slot not sent because an identical request sent ahead of
            them (a stop's own read) was outstanding or held: their replies could not be
            told apart. Their results are ``None``.
        link_losses: Times the link was lost.
        reconnects: Times it was reopened.
    """

    slots: int
    queue_wait_p50_s: float | None
    queue_wait_p99_s: float | None
    deadline_misses: int
    promoted: int
    refused: int
    twins: int
    link_losses: int
    reconnects: int


class Slot:
    """One atomic slot: its packets, and what became of each (:meth:`Bus.submit`).

    Public attributes: :attr:`future` (resolves to one reply or ``None`` per packet, as
    :meth:`Bus.transact` returns, or to its exception), :attr:`started_at` (the loop time
    its first packet was written, ``None`` until then), :attr:`packets`, and, once it
    has completed (:attr:`finished`), :attr:`results` (one reply or ``None`` per packet)
    or :attr:`error`; :attr:`tag` holds whatever the submitter attached. A slot that has
    completed can be queued again with :meth:`Bus.resubmit`.
    """

    __slots__ = (
        "_error",
        "_future",
        "_loop",
        "_owner",
        "active",
        "attempts",
        "cancelled",
        "deadline",
        "exchanges",
        "expect",
        "finished",
        "given",
        "on_done",
        "packets",
        "priority",
        "probe",
        "refused",
        "remaining",
        "results",
        "retries",
        "seq",
        "started",
        "started_at",
        "submitted_at",
        "tag",
        "timeout_s",
    )

    def __init__(
        self,
        packets: list[Packet],
        expect: list[bool],
        *,
        priority: int,
        deadline: float | None,
        retries: int,
        timeout_s: float | None,
        seq: int,
        submitted_at: float,
        loop: asyncio.AbstractEventLoop,
        owner: object = None,
    ) -> None:
        self.packets = packets
        self.expect = expect
        self.priority = priority
        self.deadline = deadline
        self.retries = retries
        self.timeout_s = timeout_s
        self.seq = seq
        self.submitted_at = submitted_at
        self._loop = loop
        self._owner = owner  # the bus it runs on
        # Made when first asked for (Slot.future): a stream's slots, which report
        # through on_done, never need one.
        self._future: asyncio.Future[list[ReplyPacket | None]] | None = None
        self._error: BaseException | None = None
        self.results: list[ReplyPacket | None] = [None] * len(packets)
        self.attempts = [0] * len(packets)
        self.refused: list[float | None] = [None] * len(packets)
        self.exchanges: list[Exchange] = []
        self.remaining = len(packets)
        self.started = False
        self.started_at: float | None = None
        self.on_done: Callable[[Slot], None] | None = None
        #: Withdrawn (Bus.cancel, or its future cancelled).
        self.cancelled = False
        #: Completed, failed or withdrawn: nothing more happens to it.
        self.finished = False
        self.tag: object = None
        #: The sequence it was submitted as (resubmit() keeps it when passed again).
        self.given: Sequence[Packet] = ()
        #: Sent to its devices even while their breakers are open (transact's probe).
        self.probe = False
        # The bus's set of slots whose callers still wait; this slot leaves it when done.
        self.active: set[Slot] | None = None

    @property
    def future(self) -> asyncio.Future[list[ReplyPacket | None]]:
        """Resolves to :attr:`results`, or to :attr:`error`; cancelled when withdrawn."""
        future = self._future
        if future is None:
            future = self._future = self._loop.create_future()
            if self.finished:
                if self.cancelled:
                    future.cancel()
                elif self._error is not None:
                    future.set_exception(self._error)
                else:
                    future.set_result(self.results)
        return future

    @property
    def error(self) -> BaseException | None:
        """Why it failed (:class:`~ohmni_tb.errors.DeadlineMissedError`, a lost link…),
        or ``None``."""
        return self._error

    def replace_unsent(self, index: int, packet: Packet) -> None:
        """Put ``packet`` in place of packet ``index``, which must expect no reply, before
        the slot starts: a scheduler updating a queued command to the newest value.

        Raises:
            StateError: The slot has started (or finished).
            InvalidArgumentError: Packet ``index`` waits for a reply, or ``packet`` is
                not of the same command and id (its reply would be judged differently).
        """
        if self.started or self.remaining <= 0:
            raise StateError("the slot has started: its packets can no longer change")
        old = self.packets[index]
        if self.expect[index] or (old.sid, old.cmd) != (packet.sid, packet.cmd):
            raise InvalidArgumentError(
                f"only a packet that waits for no reply can be replaced, by one of the same "
                f"command and id: {old!r} by {packet!r}"
            )
        self.packets[index] = packet

    def settle(self, index: int, result: ReplyPacket | None) -> None:
        if self.finished:
            return
        self.results[index] = result
        self.remaining -= 1
        if self.remaining <= 0:
            # _finish() and _notify(), written out: every cycle of every stream ends here.
            self.finished = True
            active = self.active
            if active is not None:
                active.discard(self)
                self.active = None
            self.exchanges = []
            future = self._future
            if future is not None and not future.done():
                future.set_result(self.results)
            on_done = self.on_done
            if on_done is not None:
                self.on_done = None
                try:
                    on_done(self)
                except Exception:
                    _log.exception("a slot's on_done callback failed")

    def fail(self, exc: BaseException) -> None:
        self.remaining = 0
        if self.finished:
            return
        self._finish()
        self._error = exc
        future = self._future
        if future is not None and not future.done():
            future.set_exception(exc)
        self._notify()

    def withdraw(self) -> None:
        """Mark it withdrawn: finished, its future (if any) cancelled, no callback."""
        self.cancelled = True
        self.on_done = None
        if not self.finished:
            self._finish()
        future = self._future
        if future is not None and not future.done():
            future.cancel()

    def _notify(self) -> None:
        on_done = self.on_done
        if on_done is None:
            return
        self.on_done = None
        try:
            on_done(self)
        except Exception:
            _log.exception("a slot's on_done callback failed")

    def _finish(self) -> None:
        self.finished = True
        if self.active is not None:
            self.active.discard(self)
            self.active = None
        # Each exchange's token points back at this slot: a finished slot lets go of its
        # exchanges, so the pair is freed at once instead of by the cycle collector
        # (~150 slots a second under the Robot's schedule; its full collections paused
        # the loop for one or two control periods).
        self.exchanges = []


class _Part:
    """Packets of a slot to send back to back: the whole slot first, then single retries."""

    __slots__ = ("indices", "pos", "ready_at", "seq", "slot", "submitted_at", "urgents")

    def __init__(
        self,
        slot: Slot,
        indices: list[int],
        *,
        seq: int,
        submitted_at: float,
        ready_at: float = -math.inf,
    ) -> None:
        self.slot = slot
        self.indices = indices
        self.pos = 0
        self.seq = seq
        #: The bus's count of urgent packets sent, when it was chosen to go.
        self.urgents = 0
        # Waiting (for promotion and the queue-wait figure) counts from when it may start.
        self.submitted_at = max(submitted_at, ready_at)
        #: It may not start before this loop time (a cycle queued ahead of its due time).
        self.ready_at = ready_at


class _Urgent:
    __slots__ = ("future", "packet")

    def __init__(self, packet: Packet, future: asyncio.Future[None] | None) -> None:
        self.packet = packet
        self.future = future


class Bus:
    """Prioritised, wire-timed request/reply slots on one shared line (module docstring).

    Use it as an async context manager: it starts receiving on entry and closes the
    transport on exit. :meth:`open` builds one from a URL that it can also reopen.

    Args:
        transport: The byte link. The bus closes it on :meth:`aclose`.
        timeout_s: How long past a reply's latest time on the wire it is still waited
            for: the adapter's and the host's receive latency.
        retries: Extra attempts for reads and STAT.
        guard_s: Quiet between transactions, by the cost model.
        reply_guard_s: Quiet after a reply is seen before the next request goes: its
            sender's line-driver turnaround (``None``: ``guard_s``).
        turnaround_s: The longest a device takes to start its reply (per device:
            :meth:`set_turnaround`).
        max_packet_size: The largest packet sent or accepted (223 HerkuleX, 64 Ohmni).
        commands: Command codes the receiver accepts; the nine HerkuleX ones by default.
        pipelined: Send on the wire's timing (default), or wait until each reply is seen
            or missing (request at a time).
        max_wait_s: A slot waiting this long goes next, whatever its priority.
        breaker_timeouts: Missing replies in a row before a device may be presumed gone.
        breaker_quiet_s: How long those misses must span, from the first one's send.
        probe_interval_s: How often a presumed-gone device is probed, once the probes
            have backed off from the first, 0.125 s after the breaker opened.
        caution_s: After junk on the line, how long requests go one at a time (0: never).
        stall_s: Bytes queued in the port for this long fail the link.
        close_timeout_s: The most :meth:`aclose` waits to put its final packets out.
        reopen: How :meth:`reconnect` opens a fresh transport.

    Raises:
        OutOfRangeError: A setting is out of range; the message names it.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        guard_s: float = DEFAULT_GUARD_S,
        reply_guard_s: float | None = None,
        turnaround_s: float = DEFAULT_TURNAROUND_S,
        max_packet_size: int = MAX_PACKET_SIZE,
        commands: Iterable[int] | None = None,
        pipelined: bool = True,
        max_wait_s: float = DEFAULT_MAX_WAIT_S,
        breaker_timeouts: int = DEFAULT_BREAKER_TIMEOUTS,
        breaker_quiet_s: float = DEFAULT_BREAKER_QUIET_S,
        probe_interval_s: float = DEFAULT_PROBE_INTERVAL_S,
        caution_s: float = DEFAULT_CAUTION_S,
        stall_s: float = DEFAULT_STALL_S,
        close_timeout_s: float = DEFAULT_CLOSE_TIMEOUT_S,
        reopen: Reopen | None = None,
    ) -> None:
        integer("retries", retries, 0, 10)
        check_seconds("max_wait_s", max_wait_s, 0.0, 3600.0)
        check_seconds("stall_s", stall_s, 0.001, 60.0)
        check_seconds("close_timeout_s", close_timeout_s, 0.0, 60.0)
        self._conn = BusConnection(
            baudrate=transport.baudrate,
            turnaround_s=turnaround_s,
            guard_s=guard_s,
            reply_guard_s=reply_guard_s,
            timeout_s=timeout_s,
            max_packet_size=max_packet_size,
            commands=commands,
            pipelined=pipelined,
            breaker_timeouts=breaker_timeouts,
            breaker_quiet_s=breaker_quiet_s,
            probe_interval_s=probe_interval_s,
            caution_s=caution_s,
        )
        self._transport = transport
        self.retries = retries
        self.max_wait_s = float(max_wait_s)
        self.stall_s = float(stall_s)
        self.close_timeout_s = float(close_timeout_s)
        self._reopen = reopen
        self._loop: asyncio.AbstractEventLoop | None = None
        # The line's time (ohmni_tb.eventloop.line_clock): chosen for the loop at start.
        self._clock: LineClock | None = None
        self._now: Callable[[], float] = _not_started
        # The longest wait for the line slept inline rather than on a timer (coarse loops).
        self._inline_wait_s = 0.0
        self._waiting: list[_Part] = []
        # Every slot whose caller still waits, wherever its packets are.
        self._active: set[Slot] = set()
        self._current: _Part | None = None
        self._urgent: deque[_Urgent] = deque()
        self._urgent_done: asyncio.Future[None] | None = None
        self._wake: asyncio.TimerHandle | None = None
        self._wake_at = math.inf
        # The reply timeouts' own timer (_arm_expiry).
        self._expiry: asyncio.TimerHandle | None = None
        self._expiry_at = math.inf
        self._pumping = False
        self._again = False
        self._seq = 0
        self._started = False
        self._closing = False
        self._closed = False
        self._failure: TransportError | None = None
        self._lost: asyncio.Event | None = None
        self._taps: list[Tap] = []
        #: Tuples of packets already found encodable, by id (the tuple is kept, so the
        #: id is not reused), with which of them wait for a reply under the ACK policies
        #: of that version: a stream's same reads every cycle are checked once.
        self._checked: dict[int, tuple[tuple[Packet, ...], list[bool], int]] = {}
        # Bytes may wait in the port since the last write (its backlog is looked at then).
        self._backlogged = False
        self._stall_since: float | None = None
        self._waits: deque[float] = deque(maxlen=_WAIT_WINDOW)
        self._slots = 0
        self._deadline_misses = 0
        self._promoted = 0
        self._refused = 0
        self._twins = 0
        # Urgent packets sent (send_now): a slot under way checks for twins only after one.
        self._urgents_sent = 0
        self._link_losses = 0
        self._reconnects = 0

    @classmethod
    async def open(cls, url: str, **settings: object) -> Bus:
        """Open the transport ``url`` names and a Bus on it that can :meth:`reconnect`.

        ``settings`` are the constructor's keyword arguments.

        Raises:
            ConfigError: The URL is invalid.
            TransportError: The port cannot be opened.
        """

        async def reopen() -> Transport:
            return await open_transport(url)

        return cls(await reopen(), reopen=reopen, **settings)  # type: ignore[arg-type]  # checked by the constructor

    # -- lifecycle -------------------------------------------------------------------

    async def __aenter__(self) -> Self:
        self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    def start(self) -> None:
        """Start receiving (done by ``async with``). Idempotent.

        Raises:
            BusClosedError: The bus was closed.
        """
        if self._closed or self._closing:
            raise BusClosedError("the bus is closed")
        if self._started:
            return
        self._loop = asyncio.get_running_loop()
        self._clock = clock = line_clock(self._loop)
        self._now = clock.now
        coarse = timer_resolution_s(self._loop) >= MILLISECOND_S
        # Waits it may make in the loop (_wait_inline): never on virtual time, whose
        # clock only moves when the loop waits.
        real = clock.now is time.monotonic
        self._inline_wait_s = _INLINE_WAIT_MAX_S if coarse and real else _SPIN_S if real else 0.0
        self._conn.clock_resolution_s = clock.resolution_s
        self._lost = asyncio.Event()
        self._transport.start_receiving(self._on_data, self._on_lost)
        self._started = True

    async def aclose(self, final: Sequence[Packet] = ()) -> None:
        """Write ``final`` packets, then close the transport. Idempotent.

        The final packets (the wheel stop) go out as soon as the transaction on the wire
        ends, ahead of anything queued, which fails with
        :class:`~ohmni_tb.errors.BusClosedError`. They are written even if the caller is
        cancelled meanwhile (the cancellation is raised afterwards), within
        ``close_timeout_s``; one that cannot be written is logged as a warning.

        Raises:
            OutOfRangeError: A final packet cannot be encoded; nothing was done.
        """
        for packet in final:
            self._conn.frame(packet)
        if self._closed or self._closing:
            return
        self._closing = True
        closing = BusClosedError("the bus was closed")
        self._fail_all(closing)
        cancelled: asyncio.CancelledError | None = None
        try:
            if final and self._started and self._failure is None:
                loop = asyncio.get_running_loop()
                for packet in final:
                    self._urgent.append(_Urgent(packet, None))
                self._pump()
                deadline = loop.time() + self.close_timeout_s
                while (self._urgent or self._transport.backlog) and self._failure is None:
                    left = deadline - loop.time()
                    if left <= 0:
                        break
                    try:
                        # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a
                        # cancellation that arrives as the inner wait completes.
                        async with asyncio.timeout(left):
                            await asyncio.shield(self._progress())
                    except TimeoutError:
                        break
                    except asyncio.CancelledError as exc:
                        # The stop must still reach the wheels; the caller hears of its
                        # cancellation once it has.
                        cancelled = exc
                if self._urgent or self._transport.backlog:
                    _log.warning(
                        "bus closing: %d final packet(s) and %d queued bytes not sent "
                        "within %.3f s",
                        len(self._urgent),
                        self._transport.backlog,
                        self.close_timeout_s,
                    )
        finally:
            self._closed = True
            for urgent in self._urgent:
                if urgent.future is not None and not urgent.future.done():
                    urgent.future.set_exception(closing)
            self._urgent.clear()
            self._cancel_wake()
            for exchange in self._conn.pending():
                self._conn.abandon(exchange)
            try:
                await self._transport.aclose()
            except asyncio.CancelledError as exc:
                cancelled = exc
                await self._transport.aclose()
        if cancelled is not None:
            raise cancelled

    @property
    def closed(self) -> bool:
        """Whether the bus was closed."""
        return self._closed

    @property
    def connected(self) -> bool:
        """Whether the link is up (started, not lost, not closed)."""
        return self._started and not self._closed and self._failure is None

    @property
    def transport(self) -> Transport:
        """The byte link underneath (a new one after :meth:`reconnect`)."""
        return self._transport

    @property
    def connection(self) -> BusConnection:
        """The sans-IO line state this bus drives."""
        return self._conn

    @property
    def clock(self) -> LineClock:
        """The clock the bus keeps the line's time with, in the loop's time base
        (:func:`~ohmni_tb.eventloop.line_clock`): its stamps, and timers that never fire
        early.

        Raises:
            BusClosedError: The bus is not started.
        """
        if self._clock is None:
            raise BusClosedError("the bus is not started: use `async with Bus(...)`")
        return self._clock

    async def wait_lost(self) -> TransportError:
        """Wait until the link is lost and return why (at once if it is lost now).

        Raises:
            BusClosedError: The bus is closed or not started.
        """
        if self._failure is not None:
            return self._failure
        if self._closed or self._lost is None:
            raise BusClosedError("the bus is closed or not started")
        await self._lost.wait()
        return self._lost_reason()

    @property
    def can_reconnect(self) -> bool:
        """Whether :meth:`reconnect` can reopen the port (the bus was given a way to)."""
        return self._reopen is not None

    @property
    def reopen(self) -> Reopen | None:
        """How :meth:`reconnect` opens a fresh transport (``None``: it cannot)."""
        return self._reopen

    @reopen.setter
    def reopen(self, reopen: Reopen | None) -> None:
        # Another port from the next reconnect() on (Robot.connect).
        self._reopen = reopen

    async def release(self) -> None:
        """Close the port but keep the Bus, so another program can open it; :meth:`reconnect`
        takes it back. Idempotent.

        Nothing is sent first (stop the wheels before: :func:`~ohmni_tb.safety.stop_wheels`).
        Slots still waiting fail with :class:`~ohmni_tb.errors.TransportError`, and so do
        requests until :meth:`reconnect` returns; :meth:`wait_lost` returns. Unlike a lost
        link it is not counted in ``link_losses``. It returns once the transport is closed:
        for a serial port, its file descriptor and its exclusive lock are released.

        Raises:
            StateError: The bus cannot reopen its port (use :meth:`open` or ``reopen=``):
                nothing was done.
            BusClosedError: The bus is closed.
        """
        if self._reopen is None:
            raise StateError(
                "this bus cannot reopen its port, so it cannot release it: create it with "
                "Bus.open(url) or Bus(transport, reopen=...)"
            )
        if self._shutting():
            raise BusClosedError("the bus is closed")
        if self._failure is None:
            self._link_down(TransportError("the port was released to another program"), loss=False)
        await self._transport.aclose()

    def _lost_reason(self) -> TransportError:
        if self._failure is None:
            raise BusClosedError("the bus was closed")
        return self._failure

    def _shutting(self) -> bool:
        return self._closed or self._closing

    async def reconnect(
        self,
        *,
        attempts: int | None = None,
        backoff_s: float = 0.1,
        max_backoff_s: float = 5.0,
    ) -> None:
        """Close the transport and open a fresh one, retrying with a doubling backoff.

        Statistics, ACK policies and turnaround budgets carry over; requests can be sent
        again once it returns.

        Args:
            attempts: Give up after this many failed opens (``None``: keep trying).
            backoff_s: The first wait between attempts.
            max_backoff_s: The longest wait.

        Raises:
            StateError: The bus has no way to reopen (use :meth:`open` or ``reopen=``).
            BusClosedError: The bus is closed.
            TransportError: ``attempts`` opens failed; the last error.
        """
        if self._reopen is None:
            raise StateError(
                "this bus cannot reopen its port: create it with Bus.open(url) or "
                "Bus(transport, reopen=...)"
            )
        if self._closed or self._closing:
            raise BusClosedError("the bus is closed")
        if attempts is not None and (not isinstance(attempts, int) or attempts < 1):
            raise OutOfRangeError("attempts", attempts, 1, math.inf)
        check_seconds("backoff_s", backoff_s, 0.0, 3600.0)
        check_seconds("max_backoff_s", max_backoff_s, 0.0, 3600.0)
        if self._failure is None:
            self._on_lost(TransportError("reconnect requested"))
        await self._transport.aclose()
        delay = backoff_s
        failures = 0
        while True:
            try:
                transport = await self._reopen()
                break
            except TransportError as exc:
                failures += 1
                if attempts is not None and failures >= attempts:
                    raise
                _log.info("reopen failed (%s); again in %.2f s", exc, delay)
                await asyncio.sleep(delay)
                delay = min(max(delay * 2, 0.001), max_backoff_s)
        if self._shutting():
            await transport.aclose()
            raise BusClosedError("the bus was closed while reconnecting")
        self._transport = transport
        if transport.baudrate != self._conn.baudrate:
            _log.warning(
                "reopened at %s baud, not %s: keeping the old timing",
                transport.baudrate,
                self._conn.baudrate,
            )
        self._failure = None
        self._stall_since = None
        self._backlogged = False
        self._lost = asyncio.Event()
        transport.start_receiving(self._on_data, self._on_lost)
        self._reconnects += 1
        _log.info("bus reconnected on %r", transport)

    # -- configuration ---------------------------------------------------------------

    @property
    def timeout_s(self) -> float:
        """The default reply timeout (past the reply's latest wire time)."""
        return self._conn.timeout_s

    @property
    def guard_s(self) -> float:
        """Quiet between transactions."""
        return self._conn.guard_s

    def ack_policy(self, sid: int) -> int:
        """The ACK policy the bus assumes for ``sid`` (HerkuleX default: 1, reads only)."""
        return self._conn.ack_policy(sid)

    def set_ack_policy(self, sid: int, policy: int) -> None:
        """Tell the bus which ACK policy device ``sid`` runs, so it knows what answers.

        Raises:
            OutOfRangeError: ``policy`` is not 0, 1 or 2.
        """
        self._conn.set_ack_policy(sid, policy)

    def set_turnaround(self, sid: int, turnaround_s: float | None) -> None:
        """Give a slow device its own turnaround budget (``None``: the default).

        Raises:
            OutOfRangeError: Not 0..1 s.
        """
        self._conn.set_turnaround(sid, turnaround_s)

    def cost_s(self, packet: Packet) -> float:
        """Line time ``packet`` and its reply take on this bus, by the cost model."""
        return transaction_cost_s(
            packet,
            baudrate=self._conn.baudrate or 1_000_000_000,
            turnaround_s=self._conn.turnaround(packet.sid),
            guard_s=self._conn.guard_s,
            expect_reply=self._conn.expects_reply(packet),
            max_packet_size=self._conn.max_packet_size,
        )

    # -- requests --------------------------------------------------------------------

    async def transact(
        self,
        packets: Sequence[Packet],
        *,
        priority: int = 0,
        deadline: float | None = None,
        retries: int | None = None,
        timeout_s: float | None = None,
        not_before: float | None = None,
        probe: bool = False,
    ) -> list[ReplyPacket | None]:
        """Send ``packets`` as one atomic slot and return each one's reply.

        Args:
            packets: The requests, sent back to back with nothing else in between.
            priority: Higher goes first among waiting slots.
            deadline: An absolute ``loop.time()``: the slot is dropped if it cannot start
                by then, and reads are retried only while it allows.
            retries: Extra attempts for the reads and STATs of this slot.
            timeout_s: Reply timeout for this slot.
            not_before: An absolute ``loop.time()`` before which the slot does not start:
                queued ahead of its due time, it goes from whatever wakes the bus then
                (the reply in flight, the line freeing) instead of from a timer of the
                caller's; its waiting counts from then.
            probe: Send the requests even to a device the bus presumes gone (its
                breaker open), for an answer that matters more than the line's time:
                :func:`~ohmni_tb.safety.stop_wheels` reads the wheel counts so.

        Returns:
            One entry per packet: its reply, or ``None`` when it gets none (no reply
            expected, no reply in time, or its device's breaker is open).

        Raises:
            OutOfRangeError: A packet cannot be encoded; nothing was sent.
            InvalidArgumentError: No packets, a STAT to broadcast, or two requests whose
                replies could not be told apart; nothing was sent.
            DeadlineMissedError: The slot could not start before ``deadline``.
            BusClosedError: The bus is closed.
            TransportError: The link is lost.
        """
        if probe is not True and probe is not False:
            raise InvalidArgumentError(f"probe must be True or False, not {probe!r}")
        slot = self._submit(
            packets,
            None,
            priority=priority,
            deadline=deadline,
            retries=retries,
            timeout_s=timeout_s,
            not_before=not_before,
            probe=probe,
        )
        return await self._await(slot)

    def submit(
        self,
        packets: Sequence[Packet],
        *,
        priority: int = 0,
        deadline: float | None = None,
        retries: int | None = None,
        timeout_s: float | None = None,
        on_done: Callable[[Slot], None] | None = None,
        not_before: float | None = None,
        tag: object = None,
    ) -> Slot:
        """Queue ``packets`` as one atomic slot and return at once: :meth:`transact`
        without a task.

        For schedulers that start many slots a second from timer callbacks: attach a
        done-callback to ``slot.future`` instead of awaiting a coroutine per slot, or pass
        ``on_done``, called with the slot the moment it completes (its future done), from
        inside the bus — no pass of the event loop in between, so it must not block.
        Cancelling the future, or :meth:`cancel`, withdraws the slot (what has gone out
        stays out). A stream that sends the same packets every cycle can pass the same
        tuple each time: the bus checks that its packets encode (and that their replies
        fit) the first time only; once its slot has completed, :meth:`resubmit` queues
        that slot again. ``tag`` is set as :attr:`Slot.tag` before anything can complete.

        Raises:
            OhmniError: The same as :meth:`transact`, except that
                :class:`DeadlineMissedError` and a lost link come through the future.
        """
        slot = self._submit(
            packets,
            None,
            priority=priority,
            deadline=deadline,
            retries=retries,
            timeout_s=timeout_s,
            on_done=on_done,
            not_before=not_before,
            tag=tag,
        )
        if on_done is None and not slot.finished:
            slot.future.add_done_callback(self._withdraw_if_cancelled(slot))
        return slot

    def resubmit(
        self,
        slot: Slot,
        packets: Sequence[Packet] | None = None,
        *,
        deadline: float | None = None,
        not_before: float | None = None,
        on_done: Callable[[Slot], None] | None = None,
        tag: object = None,
    ) -> Slot:
        """Queue a slot from :meth:`submit` that has completed once more, as a new slot:
        a stream's next cycle, without making one.

        It keeps its priority, retries and timeout; it goes with its packets as they
        were submitted (or ``packets``), a fresh ``deadline`` and ``not_before``,
        ``on_done`` and ``tag``, and starts over (its results, start time and future
        are new). Returns ``slot``.

        Raises:
            StateError: The slot has not completed, or is another bus's.
            OhmniError: The same as :meth:`submit` for ``packets``, ``deadline`` and
                ``not_before``.
        """
        if not slot.finished or slot._owner is not self:
            raise StateError("only a slot of this bus that has completed can be queued again")
        given = slot.given if packets is None else packets
        wants = slot.expect if given is slot.given else self._wants(given, None)
        for name, value in (("deadline", deadline), ("not_before", not_before)):
            # A float that is finite (x - x is 0.0 for those only): no call for the others.
            if value is not None and (type(value) is not float or value - value != 0.0):
                _check_loop_time(name, value)
        if self._closed or self._closing or self._failure is not None:
            self._check_usable()
        now = self._now()
        count = len(given)
        slot.given = given
        slot.packets = list(given)
        slot.expect = wants
        slot.deadline = deadline
        self._seq += 1
        slot.seq = self._seq
        slot.submitted_at = now
        slot._future = None
        slot._error = None
        slot.results = [None] * count
        slot.attempts = [0] * count
        slot.refused = [None] * count
        slot.exchanges = []
        slot.remaining = count
        slot.started = False
        slot.started_at = None
        slot.cancelled = False
        slot.finished = False
        slot.on_done = on_done
        slot.tag = tag
        slot.active = self._active
        self._active.add(slot)
        ready_at = -math.inf if not_before is None else not_before
        self._waiting.append(
            _Part(slot, list(range(count)), seq=slot.seq, submitted_at=now, ready_at=ready_at)
        )
        self._pump()
        return slot

    def cancel(self, slot: Slot) -> None:
        """Withdraw a slot from :meth:`submit` (what has gone out stays out)."""
        if slot.finished:
            return
        self._cancel(slot)

    def _withdraw_if_cancelled(
        self, slot: Slot
    ) -> Callable[[asyncio.Future[list[ReplyPacket | None]]], None]:
        def done(future: asyncio.Future[list[ReplyPacket | None]]) -> None:
            if future.cancelled() and not slot.cancelled and future is slot._future:
                self._cancel(slot)

        return done

    async def request(
        self,
        packet: Packet,
        *,
        expect_reply: bool | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
        priority: int = 0,
        deadline: float | None = None,
    ) -> ReplyPacket | None:
        """Send one request and return its reply, or ``None`` when none is expected.

        Args:
            packet: The request.
            expect_reply: Override whether to wait for a reply; by default
                :func:`~ohmni_tb.protocol.reply_expected` decides from the command, the
                sid and the device's ACK policy. A broadcast never waits.
            timeout_s: Reply timeout for this request.
            retries: Extra attempts for this request (reads and STAT only).
            priority: As for :meth:`transact`.
            deadline: As for :meth:`transact`.

        Raises:
            OutOfRangeError: The packet cannot be encoded; nothing was sent.
            InvalidArgumentError: A STAT to broadcast (every device would answer at once).
            BusTimeoutError: No reply after every attempt.
            DeviceUnavailableError: The device stopped answering; the request was not sent.
            DeadlineMissedError: It could not start before ``deadline``.
            BusClosedError: The bus is closed.
            TransportError: The link failed.
        """
        slot = self._submit(
            [packet],
            None if expect_reply is None else [expect_reply],
            priority=priority,
            deadline=deadline,
            retries=retries,
            timeout_s=timeout_s,
            fail_fast=True,
        )
        reply = (await self._await(slot))[0]
        if reply is None and slot.expect[0]:
            self._raise_missing(slot, 0)
        return reply

    async def send(self, packet: Packet) -> None:
        """Send a request that gets no reply (a jog, a write under ACK policy 0/1)."""
        await self.request(packet, expect_reply=False)

    async def send_now(self, packet: Packet) -> None:
        """Send ``packet`` ahead of everything queued: the stop path.

        It waits only for the transaction on the wire to end, not for waiting slots or
        retries, and jumps into the middle of an atomic slot if one is being sent. It
        returns once the bytes are handed to the port; a reply it gets is not waited for
        (it is counted). Once called, the packet goes out even if the caller is cancelled.

        Raises:
            OutOfRangeError: The packet cannot be encoded; nothing was sent.
            BusClosedError: The bus is closed.
            TransportError: The link is lost.
        """
        self._conn.frame(packet)
        self._check_usable()
        future: asyncio.Future[None] = self._loop_().create_future()
        self._urgent.append(_Urgent(packet, future))
        self._pump()
        await asyncio.shield(future)

    async def read(
        self, sid: int, addr: int, length: int, memory: Memory = Memory.RAM
    ) -> ReadReply:
        """Read ``length`` bytes at ``addr`` of device ``sid``.

        Raises:
            OutOfRangeError: A bad sid or addr, or a length whose reply would not fit
                ``max_packet_size``; nothing was sent.
            MalformedReplyError: The reply's layout does not fit the request.
            BusTimeoutError: No reply after every attempt.
        """
        return await self.query(read_request(sid, addr, length, memory))

    async def query(self, request: Packet) -> ReadReply:
        """Send a read request built by a codec and return its parsed reply.

        ``parse_count(await bus.query(read_count(0)))`` reads the left wheel count.

        Raises:
            InvalidArgumentError: ``request`` is not a read to one device (RAM_READ or
                EEP_READ, not broadcast).
            MalformedReplyError: The reply's layout does not fit the request.
            BusTimeoutError: No reply after every attempt.
        """
        if request.cmd not in (Command.RAM_READ, Command.EEP_READ):
            raise InvalidArgumentError(f"query() takes a read request, not {request!r}")
        if request.sid == BROADCAST_ID:
            raise InvalidArgumentError(
                "query() of broadcast (0xFE): no device answers a broadcast read"
            )
        reply = await self.request(request, expect_reply=True)
        if reply is None:  # pragma: no cover - expect_reply=True returns a packet or raises
            raise InvalidArgumentError(f"no reply to {request!r}")
        return ReadReply.parse(reply)

    async def write(
        self, sid: int, addr: int, data: bytes, memory: Memory = Memory.RAM
    ) -> StatusReply | None:
        """Write ``data`` at ``addr`` of device ``sid``; the status reply under ACK policy 2."""
        reply = await self.request(write_request(sid, addr, data, memory))
        return None if reply is None else StatusReply.parse(reply)

    # -- statistics ------------------------------------------------------------------

    @property
    def stats(self) -> BusStats:
        """A snapshot of every counter."""
        now = self._now() if self._loop is not None else 0.0
        line = self._conn.stats(now)
        waits = sorted(self._waits)
        return BusStats(
            **{f.name: getattr(line, f.name) for f in fields(ConnectionStats)},
            slots=self._slots,
            queue_wait_p50_s=percentile(waits, 0.50),
            queue_wait_p99_s=percentile(waits, 0.99),
            deadline_misses=self._deadline_misses,
            promoted=self._promoted,
            refused=self._refused,
            twins=self._twins,
            link_losses=self._link_losses,
            reconnects=self._reconnects,
        )

    # -- submission ------------------------------------------------------------------

    def _loop_(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise BusClosedError("the bus is not started: use `async with Bus(...)`")
        return self._loop

    def _check_usable(self) -> None:
        if self._closed or self._closing:
            raise BusClosedError("the bus is closed")
        if not self._started:
            raise BusClosedError("the bus is not started: use `async with Bus(...)`")
        if self._failure is not None:
            raise TransportError(
                f"the bus link failed: {self._failure}; call reconnect()"
            ) from self._failure

    def _submit(
        self,
        packets: Sequence[Packet],
        expect: list[bool] | None,
        *,
        priority: int,
        deadline: float | None,
        retries: int | None,
        timeout_s: float | None,
        fail_fast: bool = False,
        on_done: Callable[[Slot], None] | None = None,
        not_before: float | None = None,
        tag: object = None,
        probe: bool = False,
    ) -> Slot:
        conn = self._conn
        given = packets
        if not given:
            raise InvalidArgumentError("transact() needs at least one packet")
        if isinstance(priority, bool) or not isinstance(priority, int):
            raise InvalidArgumentError(f"priority must be an int, not {priority!r}")
        extra = self.retries if retries is None else retries
        integer("retries", extra, 0, 10)
        if timeout_s is not None:
            check_seconds("timeout_s", timeout_s, 0.0005, 10.0)
        _check_loop_time("deadline", deadline)
        _check_loop_time("not_before", not_before)
        wants = self._wants(given, expect)
        self._check_usable()
        now = self._now()
        slot = Slot(
            list(given),
            wants,
            priority=priority,
            deadline=deadline,
            retries=extra,
            timeout_s=timeout_s,
            seq=self._next_seq(),
            submitted_at=now,
            loop=self._loop_(),
            owner=self,
        )
        slot.given = given
        slot.probe = probe
        if fail_fast and wants[0]:
            # A request to a device known to be gone fails at once (a probe may still go).
            first = slot.packets[0]
            retry_in = conn.refusal(first.sid, now)
            if retry_in is not None:
                self._refused += 1
                raise DeviceUnavailableError(
                    sid=first.sid,
                    cmd=first.cmd,
                    silent_s=conn.silent_for(first.sid, now),
                    retry_in_s=retry_in,
                )
        # Before the pump below, which may already settle it (a deadline it cannot meet).
        slot.on_done = on_done
        slot.tag = tag
        slot.active = self._active
        self._active.add(slot)
        ready_at = -math.inf if not_before is None else float(not_before)
        self._waiting.append(
            _Part(
                slot,
                list(range(len(given))),
                seq=slot.seq,
                submitted_at=now,
                ready_at=ready_at,
            )
        )
        self._pump()
        return slot

    def _wants(self, given: Sequence[Packet], expect: list[bool] | None) -> list[bool]:
        """Check ``given`` can go as one slot; return which packets wait for a reply.

        A tuple seen before is not checked again (a stream's same packets every cycle).

        Raises:
            OutOfRangeError: A packet cannot be encoded, or a read's reply would not fit.
            InvalidArgumentError: A STAT to broadcast, or two replies that look alike.
        """
        tupled = type(given) is tuple and expect is None
        version = self._conn.policy_version
        if tupled:
            known = self._checked.get(id(given))
            if known is not None and known[0] is given and known[2] == version:
                return known[1]
        conn = self._conn
        wants: list[bool] = []
        keys: set[tuple[int, int, bytes]] = set()
        for i, packet in enumerate(given):
            conn.frame(packet)  # raises OutOfRangeError before anything is queued
            _check_reply_fits(packet, conn.max_packet_size)
            if packet.sid == BROADCAST_ID:
                if packet.cmd == Command.STAT:
                    raise InvalidArgumentError(
                        "STAT to broadcast (0xFE): every device would answer at once"
                    )
                wants.append(False)
                continue
            want = conn.expects_reply(packet) if expect is None else bool(expect[i])
            wants.append(want)
            if want:
                key = (packet.sid, packet.cmd, packet.data[:1])
                if key in keys:
                    raise InvalidArgumentError(
                        f"one slot cannot wait for two replies that look alike: {packet!r}"
                    )
                keys.add(key)
        if tupled:
            if len(self._checked) >= _CHECKED_MAX:
                self._checked.clear()
            self._checked[id(given)] = (cast(tuple[Packet, ...], given), wants, version)
        return wants

    async def _await(self, slot: Slot) -> list[ReplyPacket | None]:
        try:
            return await slot.future
        except asyncio.CancelledError:
            self._cancel(slot)
            raise

    def _raise_missing(self, slot: Slot, index: int) -> None:
        packet = slot.packets[index]
        retry_in = slot.refused[index]
        if retry_in is not None:
            now = self._now()
            raise DeviceUnavailableError(
                sid=packet.sid,
                cmd=packet.cmd,
                silent_s=self._conn.silent_for(packet.sid, now),
                retry_in_s=retry_in,
            )
        timeout = self._conn.timeout_s if slot.timeout_s is None else slot.timeout_s
        raise BusTimeoutError(
            sid=packet.sid, cmd=packet.cmd, attempts=max(1, slot.attempts[index]), timeout_s=timeout
        )

    def _cancel(self, slot: Slot) -> None:
        for exchange in slot.exchanges:
            if not exchange.done:
                self._conn.abandon(exchange)
        slot.withdraw()  # finished: lets go of its exchanges (Slot._finish)
        self._active.discard(slot)
        self._waiting = [p for p in self._waiting if p.slot is not slot]
        if self._current is not None and self._current.slot is slot:
            self._current = None
        self._pump()

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _fail_all(self, error: BaseException) -> None:
        self._waiting.clear()
        self._current = None
        for slot in list(self._active):
            slot.fail(error)
        self._active.clear()

    # -- the engine ------------------------------------------------------------------

    def add_tap(self, tap: Tap) -> Callable[[], None]:
        """Call ``tap(sent, data, t_s)`` with every chunk of bytes written to the port
        (``sent`` true) or read from it, as it happens, with the loop's time; across
        reconnections. Returns the function that removes it. A tap that raises is
        logged and removed; it never disturbs the bus.

        The bytes a ``ohmni record --raw`` recording keeps, for ``ohmni bus monitor``.
        """
        self._taps.append(tap)

        def remove() -> None:
            with contextlib.suppress(ValueError):
                self._taps.remove(tap)

        return remove

    def _tapped(self, sent: bool, data: bytes, t_s: float) -> None:
        for tap in list(self._taps):
            try:
                tap(sent, data, t_s)
            except Exception:
                _log.exception("a bus tap failed: removed")
                self._taps.remove(tap)

    def _on_data(self, data: bytes) -> None:
        if self._closed or self._loop is None:
            return
        # Stamped as it is read: the line's clock, whatever the loop's own resolution.
        now = self._now()
        if self._taps:
            self._tapped(False, data, now)
        events = self._conn.receive_data(data, now)
        if events:
            # The slots these settle may queue more (a stream's next cycle): their
            # submissions wait for the one pass below instead of each making its own,
            # and the next request goes from here, the reply's own callback.
            pumping, self._pumping = self._pumping, True
            try:
                self._handle(events)
            finally:
                self._pumping = pumping
        self._pump()

    def _on_lost(self, exc: TransportError) -> None:
        self._link_down(exc, loss=True)

    def _link_down(self, exc: TransportError, *, loss: bool) -> None:
        """The link is down (lost, or released when not ``loss``): fail what waits."""
        if self._failure is not None or self._closed:
            return
        now = self._now() if self._loop is not None else 0.0
        self._failure = exc
        if loss:
            self._link_losses += 1
            if not self._closing:
                _log.warning("bus link lost: %s", exc)
        self._conn.link_lost(now)
        error = TransportError(f"the bus link was lost: {exc}" if loss else str(exc))
        error.__cause__ = exc
        self._fail_all(error)
        for slot_exchange in list(self._urgent):
            if slot_exchange.future is not None and not slot_exchange.future.done():
                slot_exchange.future.set_exception(error)
        self._urgent.clear()
        self._resolve_progress()
        if self._lost is not None:
            self._lost.set()

    def _on_wake(self) -> None:
        self._wake = None
        self._wake_at = math.inf
        self._pump()

    def _cancel_wake(self) -> None:
        if self._wake is not None:
            self._wake.cancel()
            self._wake = None
            self._wake_at = math.inf
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None
            self._expiry_at = math.inf

    def _on_expiry(self) -> None:
        self._expiry = None
        self._expiry_at = math.inf
        self._pump()

    def _arm_expiry(self, when: float | None) -> None:
        """Make the reply-timeout timer fire by ``when`` (the connection's next deadline).

        A timer of its own, apart from the line's: a reply's timeout is set for every
        request and almost never needed, so the one set for an earlier request is left
        to fire (it finds nothing due, and sets the next) rather than moved for each.
        """
        if self._closed or when is None:
            return
        if self._expiry is not None:
            if self._expiry_at <= when + _EPS:
                return
            self._expiry.cancel()
        self._expiry_at = when
        clock = self._clock
        assert clock is not None  # armed only once started
        self._expiry = clock.call_at(when, self._on_expiry)

    def _arm(self, when: float) -> None:
        """Make the one timer fire at ``when`` (``inf``: not at all).

        ``when`` is the whole of what the engine waits for. A timer set for later is
        moved; one set for sooner is left, and looks again when it fires.
        """
        if self._closed:
            return
        if self._wake is not None:
            if self._wake_at <= when + _EPS:
                # It fires no later than needed, and looks again then: moving it would
                # cost more than that look (a reply's timeout, set for each request and
                # mostly not needed, is always later than the one before).
                return
            self._cancel_wake()
        if when == math.inf:
            return
        self._wake_at = when
        clock = self._clock
        assert clock is not None  # armed only once started
        self._wake = clock.call_at(when, self._on_wake)

    def _progress(self) -> asyncio.Future[None]:
        if self._urgent_done is None or self._urgent_done.done():
            self._urgent_done = self._loop_().create_future()
        return self._urgent_done

    def _resolve_progress(self) -> None:
        if self._urgent_done is not None and not self._urgent_done.done():
            self._urgent_done.set_result(None)

    def _pump(self) -> None:
        """Send whatever may go now; arm the timer for the next thing that may."""
        if self._pumping:
            self._again = True
            return
        loop = self._loop
        if loop is None or self._closed:
            return
        self._pumping = True
        try:
            while True:
                self._again = False
                self._run(self._now())
                if not self._again:
                    break
        finally:
            self._pumping = False

    def _run(self, now: float) -> None:
        conn = self._conn
        if now + _EPS >= conn.poll_at:
            events = conn.poll(now)
            if events:
                self._handle(events)
        # What those events queued, the loop below sees: no second pass for it.
        self._again = False
        wake = math.inf
        while self._failure is None and not self._closed:
            backlog = self._transport.backlog if self._backlogged else 0
            if backlog:
                # The port has not taken the last bytes: the wire model is off until it
                # does, and a port that never does has lost its peer.
                if self._stall_since is None:
                    self._stall_since = now
                elif now - self._stall_since >= self.stall_s:
                    self._on_lost(
                        TransportError(
                            f"{self._transport!r}: {backlog} bytes not sent after "
                            f"{now - self._stall_since:.2f} s (is the other end reading?)"
                        )
                    )
                    return
                wake = min(wake, now + _BACKLOG_POLL_S)
                break
            self._backlogged = False
            self._stall_since = None
            if self._urgent:
                line_at = conn.urgent_free_at
                if now + _EPS < line_at:
                    if line_at - now <= self._inline_wait_s:
                        now = self._wait_inline(line_at)
                        continue
                    wake = min(wake, line_at - self._inline_wait_s)
                    break
                self._send_urgent(self._urgent.popleft(), now)
                if not self._urgent:
                    self._resolve_progress()
                continue
            if self._closing:
                break
            if now + _EPS < conn.free_at:
                # Choose only when the line is free: a slot that arrives meanwhile with a
                # higher priority must still be able to go first. With nothing waiting
                # there is nothing to wake for; a new slot pumps by itself.
                line_at = conn.free_at
                next_at = math.inf
                if self._current is not None:
                    next_at = line_at  # its next packet
                if self._waiting and line_at != math.inf:
                    # The scan counts the line's freeing for the parts that may go then,
                    # not for a cycle queued ahead of its time (it has a time of its own).
                    # While the line waits for a reply, the reply (or its timeout) pumps
                    # next, and the scan is done then: nothing can start before.
                    next_at = min(next_at, self._scan(now, choose=False)[1])
                if next_at <= line_at + _EPS:
                    # Something goes when the line frees: on a loop with millisecond
                    # timers, the last of the wait is slept (_wait_inline); the last
                    # few tens of microseconds (of the guard after a reply) on any.
                    if line_at - now <= self._inline_wait_s:
                        now = self._wait_inline(line_at)
                        continue
                    next_at = min(next_at, line_at - self._inline_wait_s)
                wake = min(wake, next_at)
                break
            part = self._current
            if part is None:
                part, next_at = self._scan(now, choose=True)
                if part is None:
                    wake = min(wake, next_at)
                    break
            self._send_next(part, now)
        # The soonest a reply's timeout (or a half frame) can be due: a lower bound, so a
        # timer set for it may find nothing due, and set the next.
        deadline = conn.poll_at
        # The timers are moved only when they would fire too late (_arm, _arm_expiry):
        # most passes leave them as they are, without the calls.
        if deadline != math.inf and (self._expiry is None or deadline + _EPS < self._expiry_at):
            self._arm_expiry(deadline)
        if self._wake is None or wake + _EPS < self._wake_at:
            self._arm(wake)

    def _wait_inline(self, until: float) -> float:
        """Wait until ``until`` in the loop's own time and return the time then.

        A wait of a few tens of microseconds (``_SPIN_S``: the last of the guard after a
        reply, when the reply's own callback is ready to send) is waited out: a timer
        would cost a pass of the event loop, its wake-up included, which takes longer
        than that. On a loop whose timers wait in whole milliseconds the last
        millisecond of a wait is slept (``_inline_wait_s``): its timer is set that much
        before the line frees. On a timer alone each request would start up to a
        millisecond late, and a schedule that books the line to 81 % does not have a
        millisecond per transaction to spare; the loop's other work waits that
        fraction instead.
        """
        now = self._now
        left = until - now()
        if left > _SPIN_S:
            time.sleep(left)
        while now() < until:
            pass
        return now()

    def _scan(self, now: float, *, choose: bool) -> tuple[_Part | None, float]:
        """One pass over the waiting parts.

        Drops the parts that can no longer start before their deadlines; with ``choose``
        (the line is free), starts and returns the best part that may go now (holds
        respected; promoted after ``max_wait_s``, then priority, then first come); and
        says when the timer must next look (a hold ends, a deadline passes, a part is
        promoted) for when none may go.
        """
        conn = self._conn
        free_at = conn.free_at
        if free_at == math.inf:
            # Request at a time (caution): the line frees when the reply in flight comes
            # or goes missing, which is not known yet; judge then.
            free_at = now
        start_at = max(now, free_at)
        soon = now + _EPS
        # When the line frees, for a part that may go then (free_at: inf while cautious,
        # when a reply event frees it instead).
        frees_at = conn.free_at
        max_wait = self.max_wait_s
        best: _Part | None = None
        best_key: tuple[bool, int, int] | None = None
        wake = math.inf
        gone: list[_Part] = []
        for part in self._waiting:
            slot = part.slot
            if slot.finished:
                gone.append(part)
                continue
            deadline = slot.deadline
            if deadline is not None:
                if start_at > deadline + _EPS:
                    gone.append(part)
                    self._miss_deadline(part, start_at)
                    continue
                wake = min(wake, deadline + 2 * _EPS)
            if part.ready_at > start_at + _EPS:
                # Not yet due: its own time wakes the bus, unless the line is busy
                # then (the freeing that follows starts it).
                wake = min(wake, part.ready_at)
                continue
            if not choose:
                wake = min(wake, frees_at)
            blocked = -math.inf
            expect, packets = slot.expect, slot.packets
            for i in part.indices:
                if expect[i]:
                    until = conn.blocked_until(packets[i], now)
                    blocked = max(blocked, until)
            promote_at = part.submitted_at + max_wait
            if blocked > soon:
                if blocked < math.inf:
                    # A hold ends then (an outstanding twin resolves by an event).
                    wake = min(wake, blocked)
            elif choose:
                key = (promote_at <= now, slot.priority, -part.seq)
                if best_key is None or key > best_key:
                    best, best_key = part, key
            if promote_at > now:
                wake = min(wake, promote_at)
        if gone:
            # A settled slot's callback may have changed the list meanwhile: filter the
            # list as it is now, and look again.
            dropped = {id(part) for part in gone}
            self._waiting = [part for part in self._waiting if id(part) not in dropped]
            self._again = True
        if best is None or best_key is None or best.slot.finished:
            return None, max(wake, now)
        self._waiting.remove(best)
        if best_key[0] and any(p.slot.priority > best.slot.priority for p in self._waiting):
            self._promoted += 1
        slot = best.slot
        if not slot.started:
            slot.started = True
            slot.started_at = now
            self._slots += 1
            self._waits.append(now - best.submitted_at)
        best.urgents = self._urgents_sent
        self._current = best
        return best, now

    def _miss_deadline(self, part: _Part, start_at: float) -> None:
        slot = part.slot
        self._deadline_misses += 1
        if not slot.started:
            assert slot.deadline is not None
            slot.fail(DeadlineMissedError(deadline=slot.deadline, late_s=start_at - slot.deadline))
            return
        for index in part.indices:
            slot.settle(index, None)

    def _send_next(self, part: _Part, now: float) -> None:
        slot = part.slot
        index = part.indices[part.pos]
        part.pos += 1
        if part.pos >= len(part.indices):
            self._current = None
        packet = slot.packets[index]
        expect = slot.expect[index]
        if expect:
            retry_in = None if slot.probe else self._conn.refusal(packet.sid, now)
            if retry_in is not None:
                self._refused += 1
                slot.refused[index] = retry_in
                slot.settle(index, None)
                return
            if part.urgents != self._urgents_sent and (
                self._conn.blocked_until(packet, now) > now + _EPS
            ):
                # An urgent twin went in the middle of this slot (the scan checked the
                # slot's packets when it chose it): this one's reply would be taken for
                # the twin's, or the twin's for this one's.
                self._twins += 1
                slot.settle(index, None)
                return
        attempt = slot.attempts[index]
        slot.attempts[index] = attempt + 1
        exchange = self._conn.send(
            packet,
            self._now(),
            expect_reply=expect,
            timeout_s=slot.timeout_s,
            attempt=attempt,
            # Its slot, which packet, and which cycle of a slot sent again (resubmit).
            token=(slot, index, slot.seq),
        )
        if not self._write(exchange):
            return
        if expect:
            slot.exchanges.append(exchange)
        else:
            slot.settle(index, None)

    def _send_urgent(self, urgent: _Urgent, now: float) -> None:
        self._urgents_sent += 1
        conn = self._conn
        packet = urgent.packet
        expect = conn.expects_reply(packet)
        if expect and conn.blocked_until(packet, now) > now + _EPS:
            # Its reply could not be told from another's: send it and ignore the answer.
            expect = False
        exchange = conn.send(packet, self._now(), expect_reply=expect, urgent=True)
        if expect:
            conn.abandon(exchange)
        if self._write(exchange) and urgent.future is not None and not urgent.future.done():
            urgent.future.set_result(None)

    def _write(self, exchange: Exchange) -> bool:
        """Write ``exchange``'s frame; tell the connection when the write returned.

        The exchange was registered, with the time just before, so that no reply can
        arrive unexpected; the time just after bounds when the bytes left.
        """
        transport = self._transport
        try:
            transport.write_nowait(exchange.frame)
        except TransportError as exc:
            self._on_lost(exc)
            return False
        now = self._now()
        self._conn.written(exchange, now)
        if transport.backlog:
            self._backlogged = True
        if self._taps:
            self._tapped(True, exchange.frame, now)
        return True

    def _handle(self, events: list[Event]) -> None:
        for event in events:
            # Exact types, tested without a call (the events are final classes).
            if event.__class__ is ReplyReceived:
                token: tuple[Slot, int, int] = event.exchange.token  # type: ignore[assignment]  # _send_next sets it
                slot, index, seq = token
                if slot.seq == seq:  # not a reply of the slot's previous cycle
                    slot.settle(index, event.reply)
            elif isinstance(event, ReplyMissing):
                self._missing(event)
            elif isinstance(event, StrayPacket):
                _log.debug("%s: %r", event.kind.value, event.packet)

    def _missing(self, event: ReplyMissing) -> None:
        token = event.exchange.token
        if not isinstance(token, tuple):
            return
        slot, index, seq = token
        assert isinstance(slot, Slot)
        if slot.finished or slot.seq != seq:
            return
        packet = slot.packets[index]
        now = self._now()
        may_retry = (
            event.reason is not MissingReason.LINK_LOST
            and is_idempotent(packet)
            and slot.attempts[index] <= slot.retries
            and (slot.deadline is None or now <= slot.deadline)
            and not self._closing
        )
        if not may_retry:
            slot.settle(index, None)
            return
        self._waiting.append(_Part(slot, [index], seq=self._next_seq(), submitted_at=now))


def _not_started() -> float:
    raise BusClosedError("the bus is not started: use `async with Bus(...)`")


#: Packet tuples remembered as checked (``Bus._checked``); more, and it starts over.
_CHECKED_MAX = 64


def _check_loop_time(name: str, value: float | None) -> None:
    """``value`` is ``None`` or a finite ``loop.time()`` (an int or a float, not a bool)."""
    if value is not None and (
        isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value)
    ):
        raise InvalidArgumentError(f"{name} must be a loop.time() value, not {value!r}")


def _check_reply_fits(packet: Packet, max_packet_size: int) -> None:
    """Refuse a read whose reply would be larger than the receiver accepts.

    The receiver drops such a reply as a bad size, so the read could only time out.

    Raises:
        OutOfRangeError: Names ``length`` and the lengths whose reply fits.
    """
    if packet.cmd not in (Command.RAM_READ, Command.EEP_READ) or len(packet.data) < 2:
        return
    length = packet.data[1]
    smallest, _ = reply_size_range(packet, max_packet_size=max_packet_size)
    if smallest <= max_packet_size:
        return
    error = OutOfRangeError("length", length, 0, max_packet_size - (smallest - length), "bytes")
    error.args = (f"{error}: its reply must fit max_packet_size={max_packet_size}; nothing sent",)
    raise error
