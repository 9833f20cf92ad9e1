"""The byte-stream contract every transport keeps."""

from __future__ import annotations

import abc
from types import TracebackType
from typing import Self

__all__ = ["Transport"]


class Transport(abc.ABC):
    """A bidirectional byte stream: a serial port, an in-memory pipe, a simulated line.

    Transports move bytes only; framing lives in :mod:`ohmni_tb.protocol`. They are async
    context managers, and :meth:`aclose` may be called any number of times.

    Attributes:
        baudrate: Bits per second on the wire when the transport has one (serial, the
            simulated line), else ``None``. The bus uses it to add a request's own wire
            time to its reply timeout.
    """

    baudrate: int | None = None

    @abc.abstractmethod
    async def write(self, data: bytes) -> None:
        """Send ``data`` whole.

        Raises:
            TransportClosedError: The transport is closed.
            TransportError: The write failed.
        """

    @abc.abstractmethod
    async def read(self) -> bytes:
        """Wait for bytes and return what has arrived (at least one byte).

        A transport may hand the bytes over in the chunks they arrived in, so one frame can
        take several reads; framing is the decoder's business.

        Raises:
            TransportClosedError: The transport was closed, or the peer went away, and
                nothing is left to read.
            TransportError: The read failed.
        """

    @abc.abstractmethod
    async def aclose(self) -> None:
        """Close the transport; a second call does nothing. Pending reads then raise."""

    @property
    @abc.abstractmethod
    def closed(self) -> bool:
        """Whether :meth:`aclose` was called or the link was lost."""

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()
