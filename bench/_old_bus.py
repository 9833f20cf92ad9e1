"""The bus engine as it was before the wire-timed rewrite, kept to measure against.

``bench/schedule.py`` runs it side by side with :class:`ohmni_tb.bus.Bus` on the same
schedule. It is today's request-at-a-time design verbatim (a FIFO lock, a reader task,
one request in flight until its reply is read), on the transports' pull mode. Not used
by the library.

The original module docstring follows.

The async half-duplex request/response engine over a :class:`Transport`.

Every device shares one line, so the bus sends one request at a time and waits for its
reply before the next. A reply is matched to its request by sid, reply code
(``cmd | 0x40``) and, for reads, register address; anything else that arrives — a late
reply to a request that timed out, an echo of our own bytes — is counted and dropped,
never handed to the next request::

    async with Bus(await open_transport("/dev/ttyUSB0")) as bus:
        reply = await bus.read(0, 59, 4)          # left wheel count
        print(int.from_bytes(reply.data, "little", signed=True))

Timing on the wire: the reply timeout starts when the request has been written and is
stretched by the request's and reply's own wire time at the transport's baud rate, so it
means "device turnaround plus link latency" at any baud rate. A timed-out request has
already waited its whole reply window; after a *cancelled* one the bus keeps quiet for one
more reply window before the next request, so a late reply cannot collide with it on the
line (and a late reply that does arrive is counted, never delivered).
"""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from types import TracebackType
from typing import Self

from ohmni_tb.errors import (
    BusClosedError,
    BusTimeoutError,
    InvalidArgumentError,
    OutOfRangeError,
    TransportError,
)
from ohmni_tb.protocol import (
    BROADCAST_ID,
    MAX_PACKET_SIZE,
    AckPolicy,
    Command,
    DecoderStats,
    Memory,
    Packet,
    PacketDecoder,
    ReadReply,
    StatusReply,
    encode_packet,
    read_request,
    reply_expected,
    reply_matches,
    write_request,
)
from ohmni_tb.protocol.framing import HEADER_SIZE
from ohmni_tb.transport import Transport

__all__ = [
    "DEFAULT_GAP_S",
    "DEFAULT_RETRIES",
    "DEFAULT_TIMEOUT_S",
    "BusStats",
    "DeviceStats",
    "OldBus",
]

_log = logging.getLogger(__name__)

#: Device turnaround plus link latency allowed per attempt. The FTDI adapter alone may
#: hold received bytes 16 ms unless its latency timer is lowered (docs/hardware.md).
DEFAULT_TIMEOUT_S = 0.025
#: Extra attempts for reads and STAT; writes are never repeated blindly.
DEFAULT_RETRIES = 2
#: Quiet time between the end of one transaction and the next request. The vendor's
#: driver warns that back-to-back requests conflict; HerkuleX drivers leave 1-3 ms.
DEFAULT_GAP_S = 0.001
#: Bits per byte on an 8N1 line: start + 8 data + stop.
_BITS_PER_BYTE = 10
#: Latency samples kept per device for the percentiles.
_LATENCY_WINDOW = 1024
#: A read reply is a header plus addr, len, the bytes and two status bytes.
_READ_REPLY_OVERHEAD = HEADER_SIZE + 2 + 2
_STATUS_REPLY_SIZE = HEADER_SIZE + 2

_IDEMPOTENT = frozenset({Command.RAM_READ, Command.EEP_READ, Command.STAT})


@dataclass(frozen=True, slots=True)
class DeviceStats:
    """Counters for one device id.

    Attributes:
        sid: The device id.
        requests: Requests written (each retry counts).
        replies: Replies matched to a request.
        timeouts: Attempts that got no reply in time.
        retries: Attempts after the first.
        unmatched: Replies from this id that answered nothing pending (late, duplicate).
        latency_p50_s: Median request-written → reply-received time, or ``None``.
        latency_p99_s: 99th percentile of the same, or ``None``.
    """

    sid: int
    requests: int
    replies: int
    timeouts: int
    retries: int
    unmatched: int
    latency_p50_s: float | None
    latency_p99_s: float | None


@dataclass(frozen=True, slots=True)
class BusStats:
    """Counters for the whole bus.

    Attributes:
        bytes_out: Bytes written.
        echoes: Copies of our own requests read back (a line that echoes).
        unmatched: Packets received that answered nothing pending, all devices.
        decoder: The receive decoder's counters (junk, checksum errors…).
        devices: Per-device counters by sid.
    """

    bytes_out: int
    echoes: int
    unmatched: int
    decoder: DecoderStats
    devices: dict[int, DeviceStats]


class _DeviceCounters:
    __slots__ = ("latencies", "replies", "requests", "retries", "timeouts", "unmatched")

    def __init__(self) -> None:
        self.requests = 0
        self.replies = 0
        self.timeouts = 0
        self.retries = 0
        self.unmatched = 0
        self.latencies: deque[float] = deque(maxlen=_LATENCY_WINDOW)

    def snapshot(self, sid: int) -> DeviceStats:
        lat = sorted(self.latencies)
        return DeviceStats(
            sid=sid,
            requests=self.requests,
            replies=self.replies,
            timeouts=self.timeouts,
            retries=self.retries,
            unmatched=self.unmatched,
            latency_p50_s=_percentile(lat, 0.50),
            latency_p99_s=_percentile(lat, 0.99),
        )


class OldBus:
    """One request in flight on a shared half-duplex line.

    Use it as an async context manager; it starts a reader task on entry and stops it,
    and closes the transport, on exit.

    Args:
        transport: The byte link. The bus closes it on :meth:`aclose`.
        timeout_s: Per-attempt reply timeout, beyond the wire time of the bytes.
        retries: Extra attempts for reads and STAT after a timeout.
        gap_s: Quiet time before each request.
        max_packet_size: The largest packet sent or accepted (223 HerkuleX, 64 Ohmni).
        commands: Command codes the receiver accepts (requests and replies); the nine
            HerkuleX commands by default. Widen it if a capture shows a board using more.
    """

    def __init__(
        self,
        transport: Transport,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        gap_s: float = DEFAULT_GAP_S,
        max_packet_size: int = MAX_PACKET_SIZE,
        commands: Iterable[int] | None = None,
    ) -> None:
        _check_seconds("timeout_s", timeout_s, 0.0005, 10.0)
        _check_seconds("gap_s", gap_s, 0.0, 1.0)
        if not isinstance(retries, int) or not 0 <= retries <= 10:
            raise OutOfRangeError("retries", retries, 0, 10)
        self._transport = transport
        self.timeout_s = timeout_s
        self.retries = retries
        self.gap_s = gap_s
        self._max_size = max_packet_size
        self._decoder = PacketDecoder(max_size=max_packet_size, commands=commands)
        self._lock = asyncio.Lock()
        self._pending: tuple[Packet, asyncio.Future[Packet]] | None = None
        self._last_sent: Packet | None = None
        self._quiet_until = 0.0
        self._reader: asyncio.Task[None] | None = None
        self._failure: BaseException | None = None
        self._closed = False
        self._ack_policy: dict[int, int] = {}
        self._devices: dict[int, _DeviceCounters] = {}
        self._bytes_out = 0
        self._echoes = 0
        self._unmatched = 0

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
        """Start the reader task (done by ``async with``). Idempotent.

        Raises:
            BusClosedError: The bus was closed.
        """
        if self._closed:
            raise BusClosedError("the bus is closed")
        if self._reader is None:
            self._reader = asyncio.create_task(self._read_loop(), name="ohmni-bus-reader")

    async def aclose(self) -> None:
        """Stop the reader and close the transport. Idempotent."""
        if self._closed:
            return
        self._closed = True
        reader, self._reader = self._reader, None
        try:
            if reader is not None:
                reader.cancel()
                # wait() does not re-raise the reader's own cancellation, while a
                # cancellation of the caller still propagates.
                await asyncio.wait({reader})
        finally:
            # Even when the caller is cancelled mid-close, the port is released.
            if self._pending is not None and not self._pending[1].done():
                self._pending[1].set_exception(BusClosedError("the bus was closed"))
            await self._transport.aclose()

    @property
    def closed(self) -> bool:
        """Whether the bus was closed."""
        return self._closed

    @property
    def transport(self) -> Transport:
        """The byte link underneath."""
        return self._transport

    # -- configuration ---------------------------------------------------------------

    def ack_policy(self, sid: int) -> int:
        """The ACK policy the bus assumes for ``sid`` (HerkuleX default: 1, reads only)."""
        return self._ack_policy.get(sid, AckPolicy.READS)

    def set_ack_policy(self, sid: int, policy: int) -> None:
        """Tell the bus which ACK policy device ``sid`` runs, so it knows what answers.

        Raises:
            OutOfRangeError: ``policy`` is not 0, 1 or 2.
        """
        if policy not in (0, 1, 2):
            raise OutOfRangeError("ack policy", policy, 0, 2)
        self._ack_policy[sid] = int(policy)

    # -- requests --------------------------------------------------------------------

    async def request(
        self,
        packet: Packet,
        *,
        expect_reply: bool | None = None,
        timeout_s: float | None = None,
        retries: int | None = None,
    ) -> Packet | None:
        """Send one request and return its reply, or ``None`` when none is expected.

        Args:
            packet: The request.
            expect_reply: Override whether to wait for a reply; by default
                :func:`~ohmni_tb.protocol.reply_expected` decides from the command, the
                sid and the device's ACK policy. A broadcast never waits.
            timeout_s: Per-attempt timeout for this request.
            retries: Extra attempts for this request (reads and STAT only).

        Raises:
            OutOfRangeError: The packet cannot be encoded; nothing was sent.
            InvalidArgumentError: A STAT to broadcast (every device would answer at once).
            BusTimeoutError: No reply after every attempt.
            BusClosedError: The bus is closed.
            TransportError: The link failed.
        """
        frame = encode_packet(packet, max_size=self._max_size)
        if packet.sid == BROADCAST_ID:
            if packet.cmd == Command.STAT:
                raise InvalidArgumentError(
                    "STAT to broadcast (0xFE): every device would answer at once"
                )
            expect_reply = False
        elif expect_reply is None:
            expect_reply = reply_expected(packet.cmd, packet.sid, self.ack_policy(packet.sid))
        timeout = self.timeout_s if timeout_s is None else timeout_s
        _check_seconds("timeout_s", timeout, 0.0005, 10.0)
        extra = self.retries if retries is None else retries
        if not isinstance(extra, int) or not 0 <= extra <= 10:
            raise OutOfRangeError("retries", extra, 0, 10)
        attempts = 1 + (extra if packet.cmd in _IDEMPOTENT else 0)
        counters = self._counters(packet.sid)
        async with self._lock:
            self._check_usable()
            for attempt in range(attempts):
                if attempt:
                    counters.retries += 1
                reply = await self._transact(packet, frame, expect_reply, timeout, counters)
                if reply is not None or not expect_reply:
                    return reply
        raise BusTimeoutError(sid=packet.sid, cmd=packet.cmd, attempts=attempts, timeout_s=timeout)

    async def send(self, packet: Packet) -> None:
        """Send a request that gets no reply (a jog, a write under ACK policy 0/1)."""
        await self.request(packet, expect_reply=False)

    async def read(
        self, sid: int, addr: int, length: int, memory: Memory = Memory.RAM
    ) -> ReadReply:
        """Read ``length`` bytes at ``addr`` of device ``sid``.

        Raises:
            MalformedReplyError: The reply's layout does not fit the request.
            BusTimeoutError: No reply after every attempt.
        """
        return await self.query(read_request(sid, addr, length, memory))

    async def query(self, request: Packet) -> ReadReply:
        """Send a read request built by a codec and return its parsed reply.

        ``parse_count(await bus.query(read_count(0)))`` reads the left wheel count.

        Raises:
            InvalidArgumentError: ``request`` is not a RAM_READ or EEP_READ.
            MalformedReplyError: The reply's layout does not fit the request.
            BusTimeoutError: No reply after every attempt.
        """
        if request.cmd not in (Command.RAM_READ, Command.EEP_READ):
            raise InvalidArgumentError(f"query() takes a read request, not {request!r}")
        reply = await self.request(request, expect_reply=True)
        assert reply is not None  # expect_reply=True returns a packet or raises
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
        return BusStats(
            bytes_out=self._bytes_out,
            echoes=self._echoes,
            unmatched=self._unmatched,
            decoder=self._decoder.stats,
            devices={sid: c.snapshot(sid) for sid, c in sorted(self._devices.items())},
        )

    # -- private ---------------------------------------------------------------------

    def _counters(self, sid: int) -> _DeviceCounters:
        counters = self._devices.get(sid)
        if counters is None:
            counters = self._devices[sid] = _DeviceCounters()
        return counters

    def _check_usable(self) -> None:
        if self._closed:
            raise BusClosedError("the bus is closed")
        if self._failure is not None:
            raise TransportError(f"the bus link failed: {self._failure}") from self._failure
        if self._reader is None:
            raise BusClosedError("the bus is not started: use `async with Bus(...)`")

    def _wire_s(self, nbytes: int) -> float:
        baud = self._transport.baudrate
        return 0.0 if not baud else nbytes * _BITS_PER_BYTE / baud

    async def _transact(
        self,
        packet: Packet,
        frame: bytes,
        expect_reply: bool,
        timeout_s: float,
        counters: _DeviceCounters,
    ) -> Packet | None:
        """One attempt: wait for quiet, write, wait for the reply. ``None`` on timeout."""
        loop = asyncio.get_running_loop()
        quiet_s = self._quiet_until - loop.time()
        if quiet_s > 0:
            await asyncio.sleep(quiet_s)
        self._check_usable()
        future: asyncio.Future[Packet] = loop.create_future()
        # Registered before the write, with no await between, so a fast reply is never
        # mistaken for an unmatched one.
        if expect_reply:
            self._pending = (packet, future)
        sent_at = loop.time()
        done = False
        try:
            await self._transport.write(frame)
            self._bytes_out += len(frame)
            self._last_sent = packet
            counters.requests += 1
            request_wire_s = self._wire_s(len(frame))
            if not expect_reply:
                done = True
                self._quiet_until = loop.time() + request_wire_s + self.gap_s
                return None
            budget = request_wire_s + self._wire_s(_reply_size(packet)) + timeout_s
            try:
                async with asyncio.timeout(budget):
                    reply = await future
            except TimeoutError:
                counters.timeouts += 1
                # A frame cut short will not be completed now; rescan what is held.
                self._route(self._decoder.expire())
                done = True
                self._quiet_until = loop.time() + self.gap_s
                _log.debug(
                    "timeout: sid %d cmd 0x%02X after %.1f ms", packet.sid, packet.cmd, budget * 1e3
                )
                return None
            received_at = loop.time()
            counters.replies += 1
            counters.latencies.append(received_at - sent_at)
            done = True
            self._quiet_until = received_at + self.gap_s
            return reply
        finally:
            if expect_reply:
                self._pending = None
            if not done:
                # Cancelled or failed mid-transaction: the device may still answer, so
                # keep the line quiet for one reply window before the next request.
                self._quiet_until = max(self._quiet_until, sent_at + timeout_s + self.gap_s)

    async def _read_loop(self) -> None:
        transport = self._transport
        try:
            while True:
                data = await transport.read()
                self._route(self._decoder.feed(data))
        except TransportError as exc:
            self._fail(exc)
            if not self._closed:
                _log.warning("bus link failed: %s", exc)
        except Exception as exc:
            # A bug must not leave requests waiting for a reader that is gone.
            self._fail(exc)
            _log.exception("bus reader crashed")

    def _fail(self, exc: BaseException) -> None:
        self._failure = exc
        pending = self._pending
        if pending is not None and not pending[1].done():
            pending[1].set_exception(exc)

    def _route(self, packets: list[Packet]) -> None:
        for packet in packets:
            pending = self._pending
            if pending is not None and not pending[1].done() and reply_matches(pending[0], packet):
                pending[1].set_result(packet)
            elif not packet.is_reply and packet == self._last_sent:
                self._echoes += 1
            else:
                self._unmatched += 1
                self._counters(packet.sid).unmatched += 1
                _log.debug("unmatched packet dropped: %r", packet)


def _reply_size(request: Packet) -> int:
    if request.cmd in (Command.RAM_READ, Command.EEP_READ) and len(request.data) >= 2:
        return _READ_REPLY_OVERHEAD + request.data[1]
    return _STATUS_REPLY_SIZE


def _percentile(sorted_values: list[float], q: float) -> float | None:
    if not sorted_values:
        return None
    index = min(len(sorted_values) - 1, max(0, round(q * (len(sorted_values) - 1))))
    return sorted_values[index]


def _check_seconds(name: str, value: float, low: float, high: float) -> None:
    if not isinstance(value, int | float) or not low <= value <= high:
        raise OutOfRangeError(name, value, low, high, "s")
