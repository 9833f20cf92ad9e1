"""An in-memory byte pipe with fault injection, for tests and the simulator.

:meth:`MemoryTransport.pair` returns two connected ends. Each end can carry a
*manipulator*: a function that receives every chunk that end writes and returns what the
peer receives, as a sequence of ``bytes`` chunks (delivered separately, so a write can be
split) and ``float`` delays in seconds (applied before the chunks after them). Returning
nothing drops the write; returning changed bytes corrupts it. Order is always kept::

    host, device = MemoryTransport.pair()
    host.set_manipulator(split(1))            # the peer gets one byte per read
    device.set_manipulator(corrupt_byte(3))   # flip bits in the 4th byte the device sends
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable

from ohmni_tb.errors import TransportClosedError
from ohmni_tb.transport.base import LostHandler, ReceiveBuffer, Receiver, Transport

__all__ = [
    "Manipulator",
    "MemoryTransport",
    "corrupt_byte",
    "delay",
    "drop_bytes",
    "split",
]

#: Receives a written chunk; returns what the peer gets: bytes chunks and float delays (s).
Manipulator = Callable[[bytes], Iterable[bytes | float]]


class MemoryTransport(Transport):
    """One end of an in-memory byte pipe. Make connected ends with :meth:`pair`.

    What one end writes reaches the other on the next pass of the event loop (never
    inside the writer's own call), in order, through the manipulator if one is set.
    :meth:`set_stalled` makes the peer stop taking bytes, like a device that does not
    read: written bytes then wait in :attr:`backlog`.
    """

    def __init__(self, name: str = "memory", *, baudrate: int | None = None) -> None:
        self.name = name
        self.baudrate = baudrate
        self._peer: MemoryTransport | None = None
        self._rx = ReceiveBuffer(name)
        self._closed = False
        self._manipulator: Manipulator | None = None
        # Delayed chunks must not overtake each other: each is due no earlier than the last.
        self._last_due = 0.0
        self._timers: set[asyncio.TimerHandle] = set()
        self._stalled: list[bytes] | None = None
        self._drained: asyncio.Event | None = None
        self.bytes_written = 0
        self.bytes_read = 0

    @classmethod
    def pair(
        cls, name: str = "memory", *, baudrate: int | None = None
    ) -> tuple[MemoryTransport, MemoryTransport]:
        """Two connected ends: what one writes, the other reads."""
        a = cls(f"{name}[a]", baudrate=baudrate)
        b = cls(f"{name}[b]", baudrate=baudrate)
        a._peer, b._peer = b, a
        return a, b

    @classmethod
    def loopback(cls, name: str = "loopback") -> MemoryTransport:
        """One end whose writes come back to its own reads."""
        t = cls(name)
        t._peer = t
        return t

    def set_manipulator(self, manipulator: Manipulator | None) -> None:
        """Alter what this end writes from now on (``None`` restores a clean line)."""
        self._manipulator = manipulator

    def set_stalled(self, stalled: bool) -> None:
        """Hold what this end writes from now on (``True``), or let it all go (``False``)."""
        if stalled:
            if self._stalled is None:
                self._stalled = []
            return
        held, self._stalled = self._stalled, None
        for chunk in held or ():
            self._send(chunk)
        if self._drained is not None:
            self._drained.set()

    @property
    def closed(self) -> bool:
        peer = self._peer
        return self._closed or (peer is not None and peer is not self and peer._closed)

    @property
    def backlog(self) -> int:
        return sum(map(len, self._stalled)) if self._stalled else 0

    async def drain(self) -> None:
        while self.backlog and not self._closed:
            if self._drained is None:
                self._drained = asyncio.Event()
            self._drained.clear()
            await self._drained.wait()

    def write_nowait(self, data: bytes) -> None:
        if self._closed:
            raise TransportClosedError(f"{self.name} is closed")
        peer = self._peer
        if peer is None or peer._closed:
            raise TransportClosedError(f"{self.name}: the other end is closed")
        self.bytes_written += len(data)
        if self._stalled is not None:
            self._stalled.append(bytes(data))
            return
        self._send(bytes(data))

    def _send(self, data: bytes) -> None:
        peer = self._peer
        if peer is None:
            return
        items: Iterable[bytes | float] = (
            (data,) if self._manipulator is None else self._manipulator(data)
        )
        loop = asyncio.get_running_loop()
        now = loop.time()
        if self._timers:
            self._timers = {t for t in self._timers if t.when() > now}
        wait_s = 0.0
        for item in items:
            if isinstance(item, float):
                wait_s += item
                continue
            due = max(now + wait_s, self._last_due)
            self._last_due = due
            if due <= now:
                # Next pass of the loop, as a socket would: never inside the writer's call.
                loop.call_soon(self._deliver_later, peer, bytes(item))
            else:
                handle = loop.call_at(due, self._deliver_later, peer, bytes(item))
                self._timers.add(handle)

    def _deliver_later(self, peer: MemoryTransport, chunk: bytes) -> None:
        # Bytes already on their way arrive even if the writer closes meanwhile.
        if not peer._closed and chunk:
            peer.bytes_read += len(chunk)
            peer._rx.deliver(chunk)

    async def read(self) -> bytes:
        """Return the next chunk delivered: one write, or one piece of a split write."""
        return await self._rx.read()

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        self._rx.start(on_data, on_lost)

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        for handle in self._timers:
            handle.cancel()
        self._timers.clear()
        self._stalled = None
        if self._drained is not None:
            self._drained.set()
        self._rx.close()
        peer = self._peer
        if peer is not None and peer is not self:
            # The other end sees the link go — after the bytes already on their way, as
            # a socket's peer reads what was sent before the close.
            asyncio.get_running_loop().call_soon(
                peer._rx.lose, TransportClosedError(f"{peer.name}: the other end closed")
            )

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<MemoryTransport {self.name} {state}>"


def split(size: int) -> Manipulator:
    """Deliver every write in chunks of ``size`` bytes."""
    if size < 1:
        raise ValueError(f"size={size} must be at least 1")

    def manipulate(data: bytes) -> list[bytes | float]:
        return [data[i : i + size] for i in range(0, len(data), size)]

    return manipulate


def delay(seconds: float) -> Manipulator:
    """Deliver every write ``seconds`` late (order kept)."""

    def manipulate(data: bytes) -> list[bytes | float]:
        return [seconds, data]

    return manipulate


def drop_bytes(count: int, *, skip: int = 0) -> Manipulator:
    """Drop ``count`` bytes of the stream after the first ``skip`` bytes, then pass all."""
    state = {"pos": 0}

    def manipulate(data: bytes) -> list[bytes | float]:
        start, state["pos"] = state["pos"], state["pos"] + len(data)
        kept = bytes(b for i, b in enumerate(data, start) if not skip <= i < skip + count)
        return [kept] if kept else []

    return manipulate


def corrupt_byte(index: int, *, xor: int = 0x01) -> Manipulator:
    """XOR the byte at stream offset ``index`` with ``xor`` (once), pass everything else."""
    state = {"pos": 0}

    def manipulate(data: bytes) -> list[bytes | float]:
        start, state["pos"] = state["pos"], state["pos"] + len(data)
        if start <= index < start + len(data):
            buf = bytearray(data)
            buf[index - start] ^= xor
            data = bytes(buf)
        return [data]

    return manipulate
