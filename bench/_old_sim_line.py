"""The simulated line as it was before the per-packet, task-free rewrite, kept to measure.

``bench/sim_cpu.py`` runs the same load on this line (served by a task over an in-memory
pipe, as it used to be) and on the current one, side by side. This is the project's own
previous ``ohmni_tb.sim.line.SimLine`` with only the host-end class, the URL factory and
unused imports taken out. Do not optimise it: its value is being the reference.
"""

from __future__ import annotations

import asyncio
import logging
import random
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from ohmni_tb.errors import TransportClosedError
from ohmni_tb.protocol import Packet, PacketDecoder, RejectReason, encode_packet
from ohmni_tb.sim.device import SimDevice
from ohmni_tb.transport import DEFAULT_BAUDRATE, Transport

__all__ = ["OldSimLine"]

_log = logging.getLogger(__name__)

#: A HerkuleX servo's reply delay is undocumented; captures of similar firmware show a few
#: hundred microseconds between the request's stop bit and the reply's start bit.
DEFAULT_TURNAROUND_S = 0.0005
_BITS_PER_BYTE = 10


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
        replies: Replies sent.
        collisions: Packets answered by more than one device at once.
        dropped_bytes: Bytes lost to faults.
        corrupted_bytes: Bytes garbled by faults.
        busy_s: Time the line was carrying bytes.
    """

    bytes_to_devices: int = 0
    bytes_to_host: int = 0
    packets: int = 0
    replies: int = 0
    collisions: int = 0
    dropped_bytes: int = 0
    corrupted_bytes: int = 0
    busy_s: float = 0.0


class OldSimLine:
    """Every simulated device on one line, served over a byte transport.

    Args:
        devices: The virtual firmware on the line.
        baudrate: Line speed; sets each byte's wire time.
        turnaround_s: Delay between a request's end and its reply's start.
        seed: Seed for the fault generator, so a faulty run can be repeated.
        realtime: Deliver each reply when its last byte would arrive. With ``False`` replies
            come at once and the simulated time runs ahead of the clock by the wire time
            of the traffic (never behind it): bus traffic as fast as the CPU allows, for
            throughput tests. Under :func:`~ohmni_tb.sim.clock.run_virtual` both are exact.
    """

    def __init__(
        self,
        devices: Iterable[SimDevice],
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        turnaround_s: float = DEFAULT_TURNAROUND_S,
        seed: int = 0,
        realtime: bool = True,
    ) -> None:
        self.devices: list[SimDevice] = list(devices)
        self.baudrate = baudrate
        self.byte_s = _BITS_PER_BYTE / baudrate
        self.turnaround_s = turnaround_s
        self.realtime = realtime
        self.faults = LineFaults()
        self.stats = LineStats()
        self._rng = random.Random(seed)
        self._t0: float | None = None
        self._line_free_at = 0.0
        self._decoder = PacketDecoder(on_reject=self._on_reject)
        self._now_s = 0.0

    def now_s(self) -> float:
        """Simulated time: seconds since the line started serving (never goes back)."""
        return max(self._elapsed_s(), self._now_s)

    def _elapsed_s(self) -> float:
        """Loop time since the line started serving."""
        loop = asyncio.get_running_loop()
        if self._t0 is None:
            self._t0 = loop.time()
        return loop.time() - self._t0

    def power_cycle(self) -> None:
        """Cycle the robot's power: every device reloads and forgets latched faults."""
        now = self.now_s()
        for device in self.devices:
            device.power_cycle(now)

    async def serve(self, transport: Transport) -> None:
        """Play the devices on ``transport`` until it closes."""
        self._elapsed_s()
        while True:
            try:
                data = await transport.read()
            except TransportClosedError:
                return
            await self._carry_to_devices(transport, data)

    async def _carry_to_devices(self, transport: Transport, data: bytes) -> None:
        data = self._apply_faults(data)
        if not data:
            return
        # The bytes occupy the line after whatever is on it now.
        start = max(self._elapsed_s(), self._line_free_at)
        end = start + len(data) * self.byte_s
        self._line_free_at = end
        self.stats.busy_s += end - start
        self.stats.bytes_to_devices += len(data)
        # The devices act at the moment the last byte arrives. Nothing can reach them
        # before then (the line is busy), so there is no need to wait for it in real time:
        # the one wait is for the reply, which keeps real-time runs close to the model.
        self._now_s = max(self._now_s, end)
        for packet in self._decoder.feed(data):
            self.stats.packets += 1
            await self._dispatch(transport, packet, end)

    async def _dispatch(self, transport: Transport, packet: Packet, at_s: float) -> None:
        replies: list[bytes] = []
        for device in self.devices:
            device.advance(at_s)
            reply = device.handle(packet, at_s)
            if reply is not None and reply.sid not in self.faults.silent:
                replies.append(encode_packet(reply))
        if not replies:
            return
        if len(replies) > 1:
            self.stats.collisions += 1
        wire = _collide(replies)
        start = max(at_s + self.turnaround_s, self._line_free_at)
        end = start + len(wire) * self.byte_s
        self._line_free_at = end
        self.stats.busy_s += end - start
        wait_s = end - self._elapsed_s()
        if self.realtime and wait_s > 0:
            await asyncio.sleep(wait_s)
        # The line was busy until the reply's last byte, whether or not we waited for it.
        self._now_s = max(self._now_s, end)
        wire = self._apply_faults(wire)
        if not wire:
            return
        self.stats.replies += 1
        self.stats.bytes_to_host += len(wire)
        try:
            await transport.write(wire)
        except TransportClosedError:
            _log.debug("host went away before a reply of %d bytes", len(wire))

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

    def _on_reject(self, reason: RejectReason, frame: bytes) -> None:
        for device in self.devices:
            device.on_rejected(reason, frame, self._now_s)


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
