"""A serial port as a :class:`Transport`, on pyserial-asyncio-fast.

pyserial-asyncio-fast drives the port from the event loop's readiness callbacks instead of
blocking calls, so a 50 Hz control loop is never stalled by the port.
"""

from __future__ import annotations

import asyncio
import logging

import serial
import serial_asyncio_fast

from ohmni_tb.errors import TransportClosedError, TransportError
from ohmni_tb.transport.base import Transport

__all__ = ["DEFAULT_BAUDRATE", "SerialTransport"]

_log = logging.getLogger(__name__)

#: The Ohmni bus runs at 115200 8N1.
DEFAULT_BAUDRATE = 115_200
#: Largest chunk taken from the stream reader per read().
_READ_CHUNK = 4096
#: How long aclose() waits for the port to flush and close.
_CLOSE_TIMEOUT_S = 1.0


class SerialTransport(Transport):
    """A serial port. Open it with :meth:`open` (or ``open_transport("/dev/ttyUSB0")``)."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        port: str,
        baudrate: int,
    ) -> None:
        self._reader = reader
        self._writer = writer
        self.port = port
        self.baudrate = baudrate
        self._closed = False

    @classmethod
    async def open(
        cls,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        *,
        low_latency: bool = True,
        exclusive: bool = True,
    ) -> SerialTransport:
        """Open ``port`` at ``baudrate`` 8N1.

        Args:
            port: The device path, e.g. ``/dev/ttyUSB0``.
            baudrate: Bits per second.
            low_latency: Ask the driver for low-latency mode (the FTDI adapter otherwise
                holds received bytes up to 16 ms). Ports that cannot (a pseudo-terminal)
                are used as they are; the refusal is logged at debug level.
            exclusive: Lock the port so a second process cannot open it too.

        Raises:
            TransportError: The port cannot be opened; the message names it.
        """
        try:
            reader, writer = await serial_asyncio_fast.open_serial_connection(
                url=port,
                baudrate=baudrate,
                bytesize=serial.EIGHTBITS,
                parity=serial.PARITY_NONE,
                stopbits=serial.STOPBITS_ONE,
                exclusive=exclusive,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(f"cannot open serial port {port!r}: {exc}") from exc
        transport = cls(reader, writer, port=port, baudrate=baudrate)
        if low_latency:
            transport._try_low_latency()
        return transport

    def _try_low_latency(self) -> None:
        port = self._writer.transport.get_extra_info("serial")
        setter = getattr(port, "set_low_latency_mode", None)
        if setter is None:
            _log.debug("%s: no low-latency mode on this platform", self.port)
            return
        try:
            setter(True)
        except (OSError, ValueError, serial.SerialException) as exc:
            _log.debug("%s: low-latency mode refused: %s", self.port, exc)

    @property
    def closed(self) -> bool:
        return self._closed

    async def write(self, data: bytes) -> None:
        if self._closed:
            raise TransportClosedError(f"serial port {self.port} is closed")
        try:
            self._writer.write(data)
            await self._writer.drain()
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"write to {self.port} failed: {exc}") from exc

    async def read(self) -> bytes:
        if self._closed:
            raise TransportClosedError(f"serial port {self.port} is closed")
        try:
            data = await self._reader.read(_READ_CHUNK)
        except (serial.SerialException, OSError) as exc:
            # An unplugged adapter fails every read from now on: the link is lost.
            self._closed = True
            raise TransportError(f"read from {self.port} failed: {exc}") from exc
        if not data:
            self._closed = True
            raise TransportClosedError(f"serial port {self.port} was closed or unplugged")
        return data

    async def aclose(self) -> None:
        if self._closed and self._writer.is_closing():
            return
        self._closed = True
        self._writer.close()
        try:
            async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                await self._writer.wait_closed()
        except (TimeoutError, serial.SerialException, OSError) as exc:
            # The port is going away regardless; a failed flush on close is not news.
            _log.debug("%s: close did not finish cleanly: %s", self.port, exc)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<SerialTransport {self.port} @{self.baudrate} {state}>"
