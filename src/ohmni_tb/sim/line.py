"""The simulated line: wire timing, device turnaround, collisions, faults and dispatch.

:class:`SimLine` plays every simulated device on one half-duplex 8N1 line. The host's end
(:class:`~ohmni_tb.sim.transport.SimTransport`, or a pseudo-terminal through
:meth:`SimLine.serve`) hands it the bytes the host writes with :meth:`SimLine.host_write`
and gets the devices' bytes back through the callback given to :meth:`SimLine.attach`.
Nothing runs in between: the line works out at once what happens on the wire and when,
and asks the event loop to hand each reply over at its time. The rules:

* a byte takes ``10 / baudrate`` seconds (86.8 µs at 115200). The host's bytes go on the
  wire when they are written, behind the host's own earlier bytes;
* a device sees each packet when *that packet's* last byte has arrived — a write of three
  requests is three moments — and answers ``turnaround_s`` later, or once the line is
  quiet if someone else is still talking then (the replies of a batch queue one behind
  the other, and behind the rest of the batch);
* the host sees a reply when its last byte has left the device (or, with a USB latency
  set, when the adapter passes it on: see below);
* two devices answering the same packet collide: their bytes AND together (the dominant
  level wins) and arrive garbled;
* the host's UART does not listen before it talks: host bytes that reach the line while
  a reply is on it collide with the reply the same way, both ways garbled, and are
  counted in :attr:`LineStats.host_collisions`;
* a device's decoder gives up an incomplete frame when no byte has arrived for the
  HerkuleX packet garbage check period (:data:`~ohmni_tb.sim.servo.GARBAGE_TIMEOUT_S`,
  201.6 ms; the boards are assumed to do the same), checked at the next bytes and by a
  timer, so the device the frame names flags it on time.

Served on a transport (:meth:`SimLine.serve`, the pseudo-terminal of ``ohmni sim
--pty``), the line takes the host's bytes no more than :data:`HOST_BUFFER_BYTES` ahead of
the wire and then stops reading until the wire catches up, so a host that writes faster
than the wire waits in its writes as it would on a real adapter; junk outside any frame
is skipped in bulk, so a flood of it costs little CPU.

With ``realtime=False`` nothing waits for the clock: replies are handed over on the next
pass of the event loop, the host's bytes queue behind whatever the line carries (there
are no host collisions), and the simulated time runs ahead of the loop's clock by the
traffic's wire time.

**USB latency.** A real host reads the line through a USB serial adapter, which holds
received bytes until its latency timer expires or until a USB packet's payload (62 bytes)
is full. With ``usb_latency_s`` set, bytes for the host are held the same way: released
on a grid of that period counted from the line's start, or as soon as 62 are waiting —
so a reply may reach the host in two pieces, and two short replies in one.

Faults are set on :attr:`SimLine.faults` at any time: drop or corrupt a share of the
bytes in either direction, make devices silent, or pull the cable (nothing passes) and
put it back. Time comes from the event loop's clock, so under a virtual-time loop a test
runs hours of bus traffic in milliseconds, and every time above is exact.
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Final, Protocol, runtime_checkable

from ohmni_tb.errors import OutOfRangeError, StateError, TransportClosedError, TransportError
from ohmni_tb.protocol import (
    BROADCAST_ID,
    Command,
    Packet,
    PacketDecoder,
    RejectReason,
    encode_packet,
)
from ohmni_tb.protocol.jog import I_JOG_TAG_SIZE, S_JOG_TAG_SIZE
from ohmni_tb.protocol.timing import BITS_PER_BYTE, DEFAULT_BAUDRATE
from ohmni_tb.sim.device import SimDevice
from ohmni_tb.sim.servo import GARBAGE_TIMEOUT_S
from ohmni_tb.transport.base import Transport

__all__ = [
    "DEFAULT_TURNAROUND_S",
    "MAX_USB_LATENCY_S",
    "USB_PACKET_PAYLOAD",
    "HostReceiver",
    "LineFaults",
    "LineStats",
    "LineTap",
    "SimLine",
]

_log = logging.getLogger(__name__)

#: A HerkuleX servo's reply delay is undocumented; captures of similar firmware show a few
#: hundred microseconds between the request's stop bit and the reply's start bit.
DEFAULT_TURNAROUND_S: Final = 0.0005
#: Bytes of one USB packet from an FTDI adapter to the host: 64 less two status bytes.
USB_PACKET_PAYLOAD: Final = 62
#: The adapter's latency timer goes up to 255 ms; the simulator offers 0..32 ms, the
#: range a host would use on this bus (the default of Linux's ftdi_sio is 16 ms).
MAX_USB_LATENCY_S: Final = 0.032

#: How far the host's bytes may run ahead of the wire before a served transport stops
#: taking them: the host's transmit buffer (Linux's USB serial drivers queue a page, the
#: adapter a few hundred bytes more). A host that writes faster than the wire waits in its
#: write, as it would on the robot.
HOST_BUFFER_BYTES: Final = 4096

#: Receives the bytes the line hands to the host.
HostReceiver = Callable[[bytes], None]
#: Sees the bytes at the host's end of the line: ``tap(sent, data, t_s)``
#: (:meth:`SimLine.add_tap`).
LineTap = Callable[[bool, bytes, float], None]

_HEADER: Final = b"\xff\xff"
_MIN_FRAME: Final = 7
#: Commands after which a device may answer to another id (so the routing is rebuilt).
_ID_CHANGING: Final = frozenset(
    {Command.RAM_WRITE, Command.EEP_WRITE, Command.REBOOT, Command.ROLLBACK}
)
#: Float slack when comparing a byte's arrival with a timer tick of the same time.
_EPS_S: Final = 1e-12


@dataclass(slots=True)
class LineFaults:
    """Faults injected on the line; change them at any time.

    Attributes:
        drop_rate: Probability that a byte is lost (each direction, each byte).
        corrupt_rate: Probability that a byte arrives with one bit flipped.
        silent: Device ids that never answer (a dead board), though they still act.
        unplugged: The cable is out: no byte passes either way.
    """

    drop_rate: float = 0.0
    corrupt_rate: float = 0.0
    silent: set[int] = field(default_factory=set)
    unplugged: bool = False


@dataclass(slots=True)
class LineStats:
    """What the line carried.

    Attributes:
        bytes_to_devices: Bytes the devices received.
        bytes_to_host: Bytes the host received.
        packets: Packets the devices decoded.
        replies: Replies the devices sent (colliding replies count once).
        collisions: Packets answered by more than one device at once.
        host_collisions: Host writes that reached the line while a reply was on it.
        expired: Incomplete frames the devices gave up after the garbage timeout.
        dropped_bytes: Bytes lost to faults.
        corrupted_bytes: Bytes garbled by faults.
        busy_s: Time the line was carrying bytes.
        host_waits: Times :meth:`SimLine.serve` stopped taking the host's bytes because
            they ran more than :data:`HOST_BUFFER_BYTES` ahead of the wire (nothing is
            lost: the host's writes wait, as they do on a real adapter).
    """

    bytes_to_devices: int = 0
    bytes_to_host: int = 0
    packets: int = 0
    replies: int = 0
    collisions: int = 0
    host_collisions: int = 0
    expired: int = 0
    dropped_bytes: int = 0
    corrupted_bytes: int = 0
    busy_s: float = 0.0
    host_waits: int = 0


@runtime_checkable
class _Pausable(Protocol):
    """A transport that can stop reading (its peer's writes then wait), as asyncio's do."""

    def pause_reading(self) -> None: ...

    def resume_reading(self) -> None: ...


class _Reply:
    """A reply on (or queued for) the wire. ``wire`` is garbled in place by collisions."""

    __slots__ = ("end_s", "start_s", "wire")

    def __init__(self, start_s: float, end_s: float, wire: bytearray) -> None:
        self.start_s = start_s
        self.end_s = end_s
        self.wire = wire


class _Chunk:
    """Bytes handed to the host together: runs ``(reply, first index, count)`` of replies."""

    __slots__ = ("done", "due_s", "handle", "parts", "size")

    def __init__(self, due_s: float) -> None:
        self.due_s = due_s
        self.parts: list[tuple[_Reply, int, int]] = []
        self.size = 0
        self.handle: asyncio.Handle | None = None
        self.done = False


class SimLine:
    """Every simulated device on one line (see the module docstring for the rules).

    Args:
        devices: The virtual firmware on the line.
        baudrate: Line speed; sets each byte's wire time.
        turnaround_s: Delay between a request's end and its reply's start.
        seed: Seed for the fault generator, so a faulty run can be repeated.
        realtime: Hand each reply over when its last byte would arrive. With ``False``
            replies come on the next pass of the loop and the simulated time runs ahead of
            the clock by the wire time of the traffic (never behind it): bus traffic as
            fast as the CPU allows, for throughput tests. Under
            :func:`~ohmni_tb.sim.clock.run_virtual` both are exact.
        usb_latency_s: The host adapter's latency timer (0: off, bytes reach the host as
            they leave the line), up to :data:`MAX_USB_LATENCY_S`.

    Raises:
        OutOfRangeError: ``usb_latency_s`` is out of range.
    """

    def __init__(
        self,
        devices: Iterable[SimDevice],
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        turnaround_s: float = DEFAULT_TURNAROUND_S,
        seed: int = 0,
        realtime: bool = True,
        usb_latency_s: float = 0.0,
    ) -> None:
        if not 0.0 <= usb_latency_s <= MAX_USB_LATENCY_S:
            raise OutOfRangeError("usb_latency_s", usb_latency_s, 0.0, MAX_USB_LATENCY_S, "s")
        self.devices: list[SimDevice] = list(devices)
        self.baudrate = baudrate
        self.byte_s = BITS_PER_BYTE / baudrate
        self.turnaround_s = turnaround_s
        self.realtime = realtime
        self.usb_latency_s = usb_latency_s
        self.faults = LineFaults()
        self.stats = LineStats()
        self._rng = random.Random(seed)
        self._decoder = PacketDecoder(on_reject=self._on_reject)
        # Line time is loop time minus _t0; _now_s is the latest time the devices were
        # taken to (or the clock was read at), so it never goes back.
        self._loop: asyncio.AbstractEventLoop | None = None
        self._t0 = 0.0
        self._now_s = 0.0
        self._line_free_at = 0.0
        self._host_free_at = 0.0
        self._last_rx_s = 0.0
        self._event_s = 0.0
        self._deliver: HostReceiver | None = None
        self._on_wire: deque[_Reply] = deque()
        self._chunks: deque[_Chunk] = deque()
        self._open: _Chunk | None = None
        self._expiry: asyncio.TimerHandle | None = None
        self._by_sid: dict[int, list[SimDevice]] = {}
        self._anywhere: list[SimDevice] = []
        self._routed: list[SimDevice] = []
        self._taps: list[LineTap] = []
        self._tap_s = 0.0

    # -- clock -------------------------------------------------------------------------

    def now_s(self) -> float:
        """Simulated time: seconds since the line started serving (never goes back)."""
        loop = self._loop
        if loop is not None:
            elapsed = loop.time() - self._t0
            self._now_s = max(self._now_s, elapsed)
        return self._now_s

    def power_cycle(self) -> None:
        """Cycle the robot's power: every device reloads and forgets latched faults."""
        now = self.now_s()
        for device in self.devices:
            device.power_cycle(now)
        self._route_table()

    # -- the host's end ------------------------------------------------------------------

    @property
    def attached(self) -> bool:
        """Whether a host is connected (a transport, or a served pseudo-terminal)."""
        return self._deliver is not None

    def attach(self, deliver: HostReceiver) -> None:
        """Connect the host: from now on the devices' bytes go to ``deliver``.

        ``deliver`` is called from the event loop, never from inside :meth:`host_write`.
        The line keeps its time across hosts: a host that connects after another one left
        finds the devices where they were.

        Raises:
            StateError: Another host is connected (detach it first).
        """
        if self._deliver is not None:
            raise StateError("the simulated line already has a host connected")
        loop = asyncio.get_running_loop()
        if self._loop is None:
            self._t0 = loop.time()
        elif loop is not self._loop:
            # A new event loop (a new clock): carry the line's time over.
            self._t0 = loop.time() - self._now_s
        self._loop = loop
        self._deliver = deliver
        if self._decoder.pending:
            self._arm_expiry()

    def detach(self) -> None:
        """Disconnect the host: what was on its way to it is lost, nothing stays scheduled."""
        self._deliver = None
        for chunk in self._chunks:
            if chunk.handle is not None:
                chunk.handle.cancel()
        self._chunks.clear()
        self._open = None
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    def add_tap(self, tap: LineTap) -> Callable[[], None]:
        """Call ``tap(sent, data, t_s)`` with the bytes at the host's end of the line, at
        the line's time (:meth:`now_s`): each write of the host as it wrote it (``sent``
        true; before the line's faults, when it was written) and each chunk handed to the
        host (when it was handed over, after the faults) — what a program wrapping the
        host's serial port sees, on a clock that never goes back. Returns the function
        that removes it. A tap that raises is logged and removed; it never disturbs the
        line.
        """
        self._taps.append(tap)

        def remove() -> None:
            if tap in self._taps:
                self._taps.remove(tap)

        return remove

    def host_write(self, data: bytes) -> None:
        """The host writes ``data`` now: put it on the wire and let the devices act on it.

        Raises:
            StateError: No host is connected.
        """
        loop = self._loop
        if self._deliver is None or loop is None:
            raise StateError("no host is connected to the simulated line")
        if not data:
            return
        if self._taps:
            # When the host wrote: the loop's time on the line's clock, or, while the
            # simulated time runs ahead of the loop, when the bytes go on the wire.
            elapsed = loop.time() - self._t0
            if not self.realtime:
                elapsed = max(elapsed, self._line_free_at)
            self._tapped(True, data, elapsed)
        if self.faults.unplugged:
            self.stats.dropped_bytes += len(data)
            return
        data = self._apply_faults(data)
        if not data:
            return
        byte_s = self.byte_s
        elapsed = loop.time() - self._t0
        n = len(data)
        if self.realtime:
            start = max(elapsed, self._host_free_at)
            end = start + n * byte_s
            self.stats.busy_s += end - start
            if self._on_wire:
                data = self._meet_replies(data, start, end)
        else:
            # Simulated time runs ahead of the clock: the bytes wait for the line.
            start = max(elapsed, self._line_free_at)
            end = start + n * byte_s
            self.stats.busy_s += end - start
        self._host_free_at = end
        self._line_free_at = max(self._line_free_at, end)
        self.stats.bytes_to_devices += n
        decoder = self._decoder
        if decoder.pending and start + byte_s - self._last_rx_s >= GARBAGE_TIMEOUT_S - _EPS_S:
            self._expire(self._last_rx_s + GARBAGE_TIMEOUT_S)
        self._last_rx_s = end
        self._feed(data, start)
        if decoder.pending:
            self._arm_expiry()
        elif self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    async def serve(self, transport: Transport) -> None:
        """Play the devices on ``transport`` (read in pull mode) until it closes.

        For a transport whose other end is the host, such as a pseudo-terminal. In real
        time the host's bytes are taken no further than :data:`HOST_BUFFER_BYTES` ahead
        of the wire: beyond that the line waits for the wire to catch up, with the
        transport's reading paused if it can pause (the host's writes then wait, as they
        wait for a real adapter), so a flood costs neither memory nor a busy loop.

        Raises:
            StateError: Another host is connected.
        """

        def deliver(chunk: bytes) -> None:
            try:
                transport.write_nowait(chunk)
            except TransportError as exc:
                _log.debug("host end went away before %d bytes: %s", len(chunk), exc)

        self.attach(deliver)
        loop = asyncio.get_running_loop()
        pausable = transport if isinstance(transport, _Pausable) else None
        headroom_s = HOST_BUFFER_BYTES * self.byte_s
        try:
            while True:
                ahead_s = self._host_free_at - (loop.time() - self._t0) - headroom_s
                if self.realtime and ahead_s > 0:
                    self.stats.host_waits += 1
                    if pausable is not None:
                        pausable.pause_reading()
                    try:
                        await asyncio.sleep(ahead_s)
                    finally:
                        if pausable is not None:
                            pausable.resume_reading()
                try:
                    data = await transport.read()
                except TransportClosedError:
                    return
                self.host_write(data)
        finally:
            self.detach()

    # -- bytes to the devices ------------------------------------------------------------

    def _feed(self, data: bytes, start_s: float) -> None:
        """Decode ``data`` (on the wire from ``start_s``) packet by packet, each at its end.

        A whole clean frame is fed in one piece, and so is a run of junk outside any frame
        (no ``FF``, nothing held: the decoder only counts it); anything else byte by byte,
        so that every packet (and every rejected frame) is seen when its own last byte
        arrives.
        """
        decoder = self._decoder
        byte_s = self.byte_s
        n = len(data)
        pos = 0
        while pos < n:
            stop = pos + 1
            if not decoder.pending and data[pos] != 0xFF:
                stop = data.find(0xFF, pos)
                if stop < 0:
                    stop = n
            elif not decoder.pending and n - pos >= _MIN_FRAME and data[pos + 1] == 0xFF:
                size = data[pos + 2]
                # No FF FF inside: nothing else can start, let alone end, within the frame.
                if (
                    size >= _MIN_FRAME
                    and pos + size <= n
                    and data.find(_HEADER, pos + 1, pos + size) < 0
                ):
                    stop = pos + size
            at_s = start_s + stop * byte_s
            self._event_s = at_s
            packets = decoder.feed(data[pos:stop] if pos or stop < n else data)
            for packet in packets:
                self._dispatch(packet, at_s)
            pos = stop

    def _expire(self, at_s: float) -> None:
        """The quiet time ran out at ``at_s``: the devices give up the frame they hold."""
        self._event_s = at_s
        for packet in self._decoder.expire():
            self._dispatch(packet, at_s)

    def _arm_expiry(self) -> None:
        loop = self._loop
        if loop is None:
            return
        if self._expiry is not None:
            self._expiry.cancel()
        self._expiry = loop.call_at(
            self._t0 + self._last_rx_s + GARBAGE_TIMEOUT_S, self._on_expiry_timer
        )

    def _on_expiry_timer(self) -> None:
        self._expiry = None
        if self._decoder.pending:
            self._expire(self._last_rx_s + GARBAGE_TIMEOUT_S)

    def _on_reject(self, reason: RejectReason, frame: bytes) -> None:
        if reason is RejectReason.EXPIRED:
            self.stats.expired += 1
        at_s = max(self._event_s, self._now_s)
        self._now_s = at_s
        for device in self.devices:
            device.on_rejected(reason, frame, at_s)

    # -- the devices -------------------------------------------------------------------

    def _route_table(self) -> None:
        """Index the devices by the id they answer to now."""
        by_sid: dict[int, list[SimDevice]] = {}
        anywhere: list[SimDevice] = []
        for device in self.devices:
            sid = getattr(device, "sid", None)
            if isinstance(sid, int):
                by_sid.setdefault(sid, []).append(device)
            else:
                anywhere.append(device)
        self._by_sid = by_sid
        self._anywhere = anywhere
        self._routed = list(self.devices)

    def _concerned(self, packet: Packet) -> list[SimDevice]:
        """The devices a packet is for.

        A jog made of whole tags concerns the ids its tags name, plus its own id unless
        that is broadcast: the wheel command is a broadcast jog naming the two drive
        boards, and a servo acts on a jog only where a tag names it. Any other packet
        concerns its id, or every device when broadcast (a broken jog too, which the
        devices flag).
        """
        if self._routed != self.devices:
            self._route_table()
        sid = packet.sid
        cmd = packet.cmd
        if cmd == Command.S_JOG or cmd == Command.I_JOG:  # noqa: PLR1714 - two ints, no set
            data = packet.data
            if cmd == Command.S_JOG:
                whole = len(data) > 1 and (len(data) - 1) % S_JOG_TAG_SIZE == 0
                # Each tag: jog word (2), SET, id; after the shared playtime byte.
                named = data[4::S_JOG_TAG_SIZE] if whole else b""
            else:
                whole = len(data) > 0 and len(data) % I_JOG_TAG_SIZE == 0
                # Each tag: jog word (2), SET, id, playtime.
                named = data[3::I_JOG_TAG_SIZE] if whole else b""
            if named:
                wanted = set(named)
                if sid != BROADCAST_ID:
                    wanted.add(sid)
                anywhere = self._anywhere
                return [
                    d for d in self.devices if d in anywhere or getattr(d, "sid", None) in wanted
                ]
        if sid == BROADCAST_ID:
            return self.devices
        addressed = self._by_sid.get(sid)
        if not self._anywhere:
            return addressed or []
        return [d for d in self.devices if d in self._anywhere or (addressed and d in addressed)]

    def _dispatch(self, packet: Packet, at_s: float) -> None:
        """The devices ``packet`` concerns act on it at ``at_s``; a reply goes on the wire."""
        self.stats.packets += 1
        at_s = max(at_s, self._now_s)
        self._now_s = at_s
        silent = self.faults.silent
        replies: list[bytes] = []
        for device in self._concerned(packet):
            device.advance(at_s)
            answer = device.handle(packet, at_s)
            if answer is not None and answer.sid not in silent:
                replies.append(encode_packet(answer))
        if packet.cmd in _ID_CHANGING:
            self._route_table()
        if not replies:
            return
        if len(replies) > 1:
            self.stats.collisions += 1
        wire = _collide(replies)
        start = max(at_s + self.turnaround_s, self._line_free_at)
        end = start + len(wire) * self.byte_s
        self._line_free_at = end
        self.stats.busy_s += end - start
        self.stats.replies += 1
        reply = _Reply(start, end, bytearray(wire))
        if self.realtime:
            self._on_wire.append(reply)
        else:
            self._now_s = max(self._now_s, end)
        self._plan([(reply, 0, len(wire))])

    # -- the host meets the replies ----------------------------------------------------

    def _meet_replies(self, data: bytes, start: float, end: float) -> bytes:
        """Host bytes on ``[start, end)``: collide with a reply under way, defer the rest.

        A device does not start a reply while the line is busy, so replies that have not
        begun wait until the host's bytes are through; the one already on the line is hit.
        """
        on_wire = self._on_wire
        while on_wire and on_wire[0].end_s <= start + _EPS_S:
            on_wire.popleft()
        if not on_wire:
            return data
        first = on_wire[0]
        if first.start_s <= start + _EPS_S:
            data = self._garble(data, start, first)
            self.stats.host_collisions += 1
            self.stats.busy_s -= min(end, first.end_s) - start
            shifted = list(on_wire)[1:]
        else:
            shifted = list(on_wire)
        free = end
        moved: list[_Reply] = []
        for reply in shifted:
            if reply.start_s >= free - _EPS_S:
                break
            delay = free - reply.start_s
            reply.start_s += delay
            reply.end_s += delay
            free = reply.end_s
            moved.append(reply)
        if moved:
            self._line_free_at = max(self._line_free_at, free)
            self._replan(moved[0])
        return data

    def _garble(self, data: bytes, start: float, reply: _Reply) -> bytes:
        """AND the host's bytes with the reply's bytes they overlap in time, both ways."""
        host = bytearray(data)
        theirs = bytes(reply.wire)
        offset = (start - reply.start_s) / self.byte_s
        for i, mine in enumerate(data):
            pos = i + offset
            first = math.floor(pos)
            for j in (first, first + 1) if pos - first > 1e-9 else (first,):
                if 0 <= j < len(theirs):
                    host[i] &= theirs[j]
                    reply.wire[j] &= mine
        return bytes(host)

    # -- bytes to the host -------------------------------------------------------------

    def _plan(self, runs: Sequence[tuple[_Reply, int, int]]) -> None:
        """Put reply bytes on their way to the host: decide which chunks they go in, when."""
        loop = self._loop
        if loop is None or self._deliver is None:
            return
        latency = self.usb_latency_s
        touched: list[_Chunk] = []
        if not latency:
            for run in runs:
                chunk = _Chunk(run[0].end_s)
                chunk.parts.append(run)
                chunk.size = run[2]
                self._chunks.append(chunk)
                touched.append(chunk)
        else:
            byte_s = self.byte_s
            for reply, first, count in runs:
                index, stop = first, first + count
                while index < stop:
                    arrival = reply.start_s + (index + 1) * byte_s
                    open_chunk = self._open
                    if open_chunk is not None and arrival <= open_chunk.due_s + _EPS_S:
                        chunk = open_chunk
                    else:
                        # The adapter's buffer was empty: the next tick of its timer.
                        tick = math.ceil(arrival / latency - 1e-9) * latency
                        chunk = _Chunk(max(tick, arrival))
                        self._open = chunk
                        self._chunks.append(chunk)
                    by_tick = math.floor((chunk.due_s + _EPS_S - reply.start_s) / byte_s) - index
                    take = min(USB_PACKET_PAYLOAD - chunk.size, stop - index, max(1, by_tick))
                    chunk.parts.append((reply, index, take))
                    chunk.size += take
                    index += take
                    if chunk.size >= USB_PACKET_PAYLOAD:
                        # A full USB packet leaves at once, without waiting for the tick.
                        chunk.due_s = reply.start_s + index * byte_s
                        self._open = None
                    if not touched or touched[-1] is not chunk:
                        touched.append(chunk)
        for chunk in touched:
            if chunk.handle is not None:
                chunk.handle.cancel()
            if self.realtime:
                chunk.handle = loop.call_at(self._t0 + chunk.due_s, self._hand_over, chunk)
            else:
                chunk.handle = loop.call_soon(self._hand_over, chunk)

    def _replan(self, moved: _Reply) -> None:
        """Replies from ``moved`` on start later now: plan their way to the host again.

        The adapter's state depends only on the arrivals since its buffer was last empty,
        so the chunks from the first one holding a moved byte are planned afresh.
        """
        chunks = self._chunks
        index = next(
            (i for i, chunk in enumerate(chunks) if any(p[0] is moved for p in chunk.parts)),
            None,
        )
        if index is None:
            return
        redo = [chunks.pop() for _ in range(len(chunks) - index)][::-1]
        runs: list[tuple[_Reply, int, int]] = []
        for chunk in redo:
            if chunk.handle is not None:
                chunk.handle.cancel()
            for reply, first, count in chunk.parts:
                if runs and runs[-1][0] is reply and runs[-1][1] + runs[-1][2] == first:
                    runs[-1] = (reply, runs[-1][1], runs[-1][2] + count)
                else:
                    runs.append((reply, first, count))
        self._open = None
        self._plan(runs)

    def _hand_over(self, target: _Chunk) -> None:
        """Hand ``target`` to the host, and any chunk before it that is still waiting."""
        if target.done:
            return
        chunks = self._chunks
        while chunks:
            chunk = chunks.popleft()
            chunk.done = True
            if chunk.handle is not None and chunk is not target:
                chunk.handle.cancel()
            chunk.handle = None
            if chunk is self._open:
                self._open = None
            parts = chunk.parts
            if len(parts) == 1 and parts[0][1] == 0 and parts[0][2] == len(parts[0][0].wire):
                data = bytes(parts[0][0].wire)
            else:
                data = b"".join(bytes(r.wire[i : i + n]) for r, i, n in parts)
            data = self._apply_faults(data)
            deliver = self._deliver
            if data and deliver is not None:
                self.stats.bytes_to_host += len(data)
                deliver(data)
                if self._taps:
                    # When the host got them: their time, or later if the loop was late.
                    loop = self._loop
                    late_s = chunk.due_s if loop is None else loop.time() - self._t0
                    self._tapped(False, data, max(chunk.due_s, late_s))
            if chunk is target:
                return

    def _tapped(self, sent: bool, data: bytes, t_s: float) -> None:
        # The times a tap sees never go back, as a monotonic clock's at the host.
        t_s = self._tap_s = max(t_s, self._tap_s)
        for tap in list(self._taps):
            try:
                tap(sent, data, t_s)
            except Exception:
                _log.exception("a line tap failed: removed")
                self._taps.remove(tap)

    # -- faults ------------------------------------------------------------------------

    def _apply_faults(self, data: bytes) -> bytes:
        faults = self.faults
        if faults.unplugged:
            self.stats.dropped_bytes += len(data)
            return b""
        if not faults.drop_rate and not faults.corrupt_rate:
            return data
        out = bytearray()
        rng = self._rng
        for byte in data:
            if rng.random() < faults.drop_rate:
                self.stats.dropped_bytes += 1
                continue
            if rng.random() < faults.corrupt_rate:
                self.stats.corrupted_bytes += 1
                out.append(byte ^ (1 << rng.randrange(8)))
            else:
                out.append(byte)
        return bytes(out)


def _collide(frames: Sequence[bytes]) -> bytes:
    """Two drivers on one line: the dominant (low) level wins, so bytes AND together."""
    if len(frames) == 1:
        return frames[0]
    length = max(len(f) for f in frames)
    out = bytearray(b"\xff" * length)
    for f in frames:
        for i, b in enumerate(f):
            out[i] &= b
    return bytes(out)
