"""The byte-stream contract every transport keeps.

A transport moves bytes and nothing else (framing lives in :mod:`ohmni_tb.protocol`). It
offers two ways to receive, and one owner picks one of them:

* **pull**: ``await transport.read()`` returns the next chunk — simple, for tools and
  scripts;
* **push**: ``transport.start_receiving(on_data, on_lost)`` hands every chunk to
  ``on_data`` straight from the event loop's readiness callback, with no task in
  between. The :class:`~ohmni_tb.bus.Bus` uses this: at 250 transactions a second, a task
  wake-up per read is most of the cost of a transaction.

Sending never blocks the caller: :meth:`Transport.write_nowait` queues the bytes and
returns; :attr:`Transport.backlog` says how many are still queued, so an owner can tell a
port that does not drain (a peer that stopped reading) from a slow one, and
:meth:`Transport.write` waits for the queue to empty, under a timeout.
"""

from __future__ import annotations

import abc
import asyncio
from collections import deque
from collections.abc import Callable
from types import TracebackType
from typing import Self

from ohmni_tb.errors import StateError, TransportClosedError, TransportError

__all__ = ["DEFAULT_WRITE_TIMEOUT_S", "LostHandler", "ReceiveBuffer", "Receiver", "Transport"]

#: Called with each chunk of received bytes, from the event loop (never re-entrantly from
#: inside the owner's own ``write_nowait``).
Receiver = Callable[[bytes], None]
#: Called once when the link is lost (peer gone, cable pulled, I/O error) — not after the
#: owner's own :meth:`Transport.aclose`.
LostHandler = Callable[[TransportError], None]

#: How long :meth:`Transport.write` waits for its bytes to leave. A bus frame takes a few
#: milliseconds at 115200 baud; a second means the peer is not reading.
DEFAULT_WRITE_TIMEOUT_S = 1.0


class Transport(abc.ABC):
    """A bidirectional byte stream: a serial port, an in-memory pipe, a simulated line.

    Transports are async context managers, and :meth:`aclose` may be called any number of
    times.

    Attributes:
        baudrate: Bits per second on the wire when the transport has one (serial, the
            simulated line), else ``None``. The bus times its slots with it.
    """

    baudrate: int | None = None

    @abc.abstractmethod
    def write_nowait(self, data: bytes) -> None:
        """Queue ``data`` for sending and return at once; order is kept.

        Raises:
            TransportClosedError: The transport is closed or its peer went away.
            TransportError: The link failed.
        """

    @property
    def backlog(self) -> int:
        """Bytes accepted by :meth:`write_nowait` that have not left for the peer yet."""
        return 0

    async def drain(self) -> None:
        """Wait until :attr:`backlog` is zero (a transport that holds nothing returns)."""
        return

    async def write(self, data: bytes, *, timeout_s: float = DEFAULT_WRITE_TIMEOUT_S) -> None:
        """Send ``data`` whole and wait until it has left.

        Raises:
            TransportClosedError: The transport is closed.
            TransportError: The write failed, or the bytes did not leave within
                ``timeout_s`` (the peer is not reading).
        """
        self.write_nowait(data)
        if not self.backlog:
            return
        try:
            async with asyncio.timeout(timeout_s):
                await self.drain()
        except TimeoutError:
            raise TransportError(
                f"{self!r}: {self.backlog} bytes not sent after {timeout_s:g} s "
                f"(is the other end reading?)"
            ) from None

    @abc.abstractmethod
    async def read(self) -> bytes:
        """Wait for bytes and return what has arrived (at least one byte).

        A transport may hand the bytes over in the chunks they arrived in, so one frame can
        take several reads; framing is the decoder's business.

        Raises:
            TransportClosedError: The transport was closed, or the peer went away, and
                nothing is left to read.
            TransportError: The read failed.
            StateError: :meth:`start_receiving` was called: bytes go to its callback.
        """

    @abc.abstractmethod
    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        """Hand every received chunk to ``on_data`` from now on, instead of :meth:`read`.

        Bytes already received and not read are handed over first, in order. ``on_lost``
        is called once if the link is lost; it is not called after :meth:`aclose`.

        Raises:
            StateError: Receiving was already started.
            TransportClosedError: The transport is closed.
        """

    @abc.abstractmethod
    async def aclose(self) -> None:
        """Close the transport; a second call does nothing. Pending reads then raise."""

    @property
    @abc.abstractmethod
    def closed(self) -> bool:
        """Whether :meth:`aclose` was called or the link was lost."""

    @property
    def can_reopen(self) -> bool:
        """Whether :meth:`reopen` can open this link again (a serial port, a simulated
        line); ``False`` for a transport that cannot (an in-memory pipe)."""
        return False

    async def reopen(self) -> Transport:
        """Open the same link again, as a new transport: after a lost link, or after the
        port was handed to another program. This one is left as it is (close it first).

        Raises:
            StateError: This transport cannot be reopened (:attr:`can_reopen` is false).
            TransportError: The link cannot be opened now (another program holds the
                port, the adapter is unplugged).
        """
        raise StateError(f"{self!r} cannot be reopened: it was not opened from a port")

    @property
    def simulated(self) -> object | None:
        """The simulated robot behind this link (its ground truth, for tests and tools),
        or ``None`` on a real one."""
        return None

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()


class ReceiveBuffer:
    """The receive side of a transport, in either mode: one place for the rules.

    A transport calls :meth:`deliver` with each chunk it gets and :meth:`lose` when the
    link goes; its :meth:`Transport.read` and :meth:`Transport.start_receiving` delegate
    here. In push mode a chunk goes straight to the receiver; in pull mode it waits in a
    queue for :meth:`read`.

    Args:
        name: How errors name the transport.
    """

    __slots__ = ("_chunks", "_closed", "_lost", "_name", "_on_data", "_on_lost", "_ready")

    def __init__(self, name: str) -> None:
        self._name = name
        self._chunks: deque[bytes] = deque()
        self._ready: asyncio.Event | None = None
        self._on_data: Receiver | None = None
        self._on_lost: LostHandler | None = None
        self._lost: TransportError | None = None
        self._closed = False

    @property
    def pushing(self) -> bool:
        """Whether a receiver was installed."""
        return self._on_data is not None

    def deliver(self, chunk: bytes) -> None:
        """A chunk arrived: hand it to the receiver, or queue it for :meth:`read`."""
        if self._closed or not chunk:
            return
        on_data = self._on_data
        if on_data is not None:
            on_data(chunk)
            return
        self._chunks.append(chunk)
        if self._ready is not None:
            self._ready.set()

    def lose(self, exc: TransportError) -> None:
        """The link is gone: wake a reader, or tell the receiver once."""
        if self._closed or self._lost is not None:
            return
        self._lost = exc
        if self._ready is not None:
            self._ready.set()
        on_lost = self._on_lost
        if on_lost is not None:
            on_lost(exc)

    def close(self) -> None:
        """The owner closed the transport: drop what is queued, wake a reader, stay quiet."""
        self._closed = True
        self._chunks.clear()
        self._on_data = None
        self._on_lost = None
        if self._ready is not None:
            self._ready.set()

    def start(self, on_data: Receiver, on_lost: LostHandler) -> None:
        """Install the receiver (see :meth:`Transport.start_receiving`)."""
        if self._closed:
            raise TransportClosedError(f"{self._name} is closed")
        if self._on_data is not None:
            raise StateError(f"{self._name}: receiving was already started")
        self._on_data = on_data
        self._on_lost = on_lost
        while self._chunks and self._on_data is not None:
            on_data(self._chunks.popleft())
        if self._lost is not None:
            on_lost(self._lost)

    async def read(self) -> bytes:
        """Pull mode: the next chunk (see :meth:`Transport.read`)."""
        if self._on_data is not None:
            raise StateError(f"{self._name}: bytes go to the receiver set by start_receiving")
        while not self._chunks:
            if self._closed:
                raise TransportClosedError(f"{self._name} is closed")
            lost = self._lost
            if lost is not None:
                # A fresh error each time: re-raising one instance would grow its traceback.
                raise type(lost)(str(lost)) from lost.__cause__
            if self._ready is None:
                self._ready = asyncio.Event()
            self._ready.clear()
            await self._ready.wait()
        return self._chunks.popleft()
