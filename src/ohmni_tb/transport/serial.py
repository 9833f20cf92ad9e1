"""A serial port as a :class:`Transport`, on pyserial-asyncio-fast's asyncio Protocol API.

pyserial-asyncio-fast drives the port from the event loop's readiness callbacks instead of
blocking calls. This transport takes the bytes straight from that callback
(``data_received``) and hands them to the bus's receiver, with no task and no stream
buffer in between; writes go to the port at once and wait in its buffer only when the
device does not take them.

Closing never hangs on a peer that stopped reading: queued bytes get
``close_timeout_s`` to leave, then they are discarded and the port is closed (its file
descriptor and its exclusive lock released).
"""

from __future__ import annotations

import array
import asyncio
import contextlib
import errno
import fcntl
import functools
import logging
import os
import select
import termios

import serial
import serial_asyncio_fast

from ohmni_tb.errors import TransportClosedError, TransportError
from ohmni_tb.protocol.timing import DEFAULT_BAUDRATE
from ohmni_tb.transport.base import LostHandler, ReceiveBuffer, Receiver, Transport
from ohmni_tb.transport.ports import AUTO_PORT, resolve_port

__all__ = ["DEFAULT_BAUDRATE", "SerialTransport"]

_log = logging.getLogger(__name__)

#: How long aclose() lets queued bytes leave, then how long it waits for the port to close.
_CLOSE_TIMEOUT_S = 1.0


class _Protocol(asyncio.Protocol):
    """Forwards the port's callbacks to the transport that owns it."""

    def __init__(self, owner: SerialTransport) -> None:
        self._owner = owner

    def data_received(self, data: bytes) -> None:
        self._owner._rx.deliver(data)

    def pause_writing(self) -> None:
        self._owner._drained.clear()

    def resume_writing(self) -> None:
        self._owner._drained.set()

    def connection_lost(self, exc: Exception | None) -> None:
        self._owner._connection_lost(exc)


class SerialTransport(Transport):
    """A serial port. Open it with :meth:`open` (or ``open_transport("/dev/ttyUSB0")``)."""

    def __init__(
        self,
        *,
        port: str,
        baudrate: int,
        low_latency: bool = True,
        exclusive: bool = True,
        asked: str | None = None,
    ) -> None:
        self.port = port
        self.baudrate = baudrate
        # What reopen() opens: the port as asked (``auto`` is looked for again: the
        # adapter may come back under another name), with the same settings.
        self._asked = port if asked is None else asked
        self._asked_baudrate = baudrate
        self._low_latency = low_latency
        self._exclusive = exclusive
        self._rx = ReceiveBuffer(f"serial port {port}")
        self._serial: _TtyTransport | None = None
        self._closed = False
        self._gone: asyncio.Future[None] | None = None
        # Set while the port's write buffer is empty (the protocol's flow control).
        self._drained = asyncio.Event()
        self._drained.set()

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
            port: The device path, e.g. ``/dev/ttyUSB0``, or ``auto``: the bus adapter,
                found by its USB id (:func:`~ohmni_tb.transport.ports.resolve_port`), and
                found again by :meth:`reopen`.
            baudrate: Bits per second.
            low_latency: Ask the driver for low-latency mode (the FTDI adapter otherwise
                holds received bytes up to 16 ms). Ports that cannot (a pseudo-terminal)
                are used as they are; the refusal is logged at debug level.
            exclusive: Lock the port so a second process cannot open it too.

        Raises:
            TransportError: The port cannot be opened; the message names it.
            NoBusPortError: ``auto`` found no bus adapter (a :class:`TransportError`).
        """
        transport = cls(
            port=resolve_port(port) if port == AUTO_PORT else port,
            baudrate=baudrate,
            low_latency=low_latency,
            exclusive=exclusive,
            asked=port,
        )
        port = transport.port
        loop = asyncio.get_running_loop()
        transport._gone = loop.create_future()
        try:
            # Opening may block (the driver's own open); as pyserial-asyncio-fast's
            # create_serial_connection does, off the loop — then our transport class.
            device = await loop.run_in_executor(
                None,
                functools.partial(
                    serial.serial_for_url,
                    port,
                    baudrate=baudrate,
                    bytesize=serial.EIGHTBITS,
                    parity=serial.PARITY_NONE,
                    stopbits=serial.STOPBITS_ONE,
                    exclusive=exclusive,
                ),
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise TransportError(_open_error(port, exc)) from exc
        serial_transport = _TtyTransport(loop, _Protocol(transport), device)
        transport._serial = serial_transport
        # Told of every byte left waiting (high water 0), so drain() needs no polling.
        serial_transport.set_write_buffer_limits(high=0, low=0)
        if low_latency:
            transport._try_low_latency()
        return transport

    @property
    def can_reopen(self) -> bool:
        return True

    async def reopen(self) -> SerialTransport:
        """Open the same port again with the same settings (``auto``: the adapter found
        again), as a new transport (see :meth:`open`).

        Raises:
            TransportError: The port cannot be opened now; the message names it.
        """
        return await SerialTransport.open(
            self._asked,
            self._asked_baudrate,
            low_latency=self._low_latency,
            exclusive=self._exclusive,
        )

    def _try_low_latency(self) -> None:
        port = self._port()
        setter = getattr(port, "set_low_latency_mode", None)
        if setter is None:
            _log.debug("%s: no low-latency mode on this platform", self.port)
            return
        try:
            setter(True)
        except (OSError, ValueError, serial.SerialException) as exc:
            _log.debug("%s: low-latency mode refused: %s", self.port, exc)

    def _port(self) -> serial.Serial | None:
        if self._serial is None:
            return None
        port = self._serial.get_extra_info("serial")
        return port if isinstance(port, serial.Serial) else None

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def backlog(self) -> int:
        serial_transport = self._serial
        if serial_transport is None or self._closed or not serial_transport._write_buffer:
            return 0
        return serial_transport.get_write_buffer_size()

    async def drain(self) -> None:
        if self.backlog and not self._closed:
            await self._drained.wait()

    def write_nowait(self, data: bytes) -> None:
        serial_transport = self._serial
        if self._closed or serial_transport is None or serial_transport._closing:
            raise TransportClosedError(f"serial port {self.port} is closed")
        try:
            serial_transport.write(data)
        except (serial.SerialException, OSError) as exc:
            raise TransportError(f"write to {self.port} failed: {exc}") from exc

    async def read(self) -> bytes:
        return await self._rx.read()

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        self._rx.start(on_data, on_lost)
        if self._serial is not None and not self._closed:
            # Straight from the port's readiness callback to the receiver: the protocol
            # and the receive buffer would only hand each chunk on.
            self._serial._receiver = on_data

    def _connection_lost(self, exc: Exception | None) -> None:
        if self._gone is not None and not self._gone.done():
            self._gone.set_result(None)
        self._drained.set()
        if self._closed:
            return
        # Not our own close: the adapter was unplugged or the port failed.
        self._closed = True
        if self._serial is not None:
            self._serial._receiver = None
        reason = f": {exc}" if exc is not None else ""
        lost = TransportClosedError(f"serial port {self.port} was closed or unplugged{reason}")
        lost.__cause__ = exc
        self._rx.lose(lost)

    async def aclose(self) -> None:
        if self._closed and (self._serial is None or self._serial.is_closing()):
            await self._wait_gone()
            return
        self._closed = True
        self._rx.close()
        serial_transport = self._serial
        if serial_transport is None:
            return
        serial_transport._receiver = None
        if serial_transport.get_write_buffer_size():
            # Give queued bytes (a final stop) their wire time, no more.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                    await self._drained.wait()
        port = self._port()
        if port is not None and serial_transport.get_write_buffer_size():
            # A peer that does not read would hold a flushing close forever.
            with contextlib.suppress(OSError, serial.SerialException):
                port.reset_output_buffer()
        # abort() closes without the blocking flush of close(); the port is released
        # once connection_lost has run.
        serial_transport.abort()
        await self._wait_gone()

    async def _wait_gone(self) -> None:
        if self._gone is None or self._gone.done():
            return
        try:
            async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                await asyncio.shield(self._gone)
        except TimeoutError:
            _log.warning("%s: the port did not close within %.1f s", self.port, _CLOSE_TIMEOUT_S)

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"<SerialTransport {self.port} @{self.baudrate} {state}>"


#: Empty reads in a row, with no sign of a lost device, before the link counts as lost.
_MAX_SPURIOUS_EMPTY_READS = 64


class _TtyTransport(serial_asyncio_fast.SerialTransport):
    """pyserial-asyncio-fast's transport, telling a lost device from a spurious empty read.

    pyserial sets VMIN=0 VTIME=0, so a read on a tty returns 0 bytes both when nothing is
    there and when the other end is gone (a hung-up tty — an unplugged adapter, or a pty
    whose simulator exited — reads 0 forever), and pyserial's own read() calls any empty
    read after readiness "disconnected". Here the descriptor is asked instead: POLLHUP or
    POLLERR, TIOCINQ failing (EIO on a hung-up tty), or the device node gone or replaced
    mean lost, with a message that says so; anything else is a spurious wake-up.
    """

    _empty_reads = 0
    #: The owner's receiver, called with each chunk straight from _read_ready (else the
    #: protocol's data_received).
    _receiver: Receiver | None = None

    def write(self, data: bytes | bytearray | memoryview) -> None:
        # The library's write() checks, then calls _write_data(): here the usual case,
        # nothing queued and the port open, writes at once.
        device: serial.Serial | None = self._serial
        fd = None if device is None else device.fd
        if self._closing or self._write_buffer or fd is None:
            super().write(data)
            return
        try:
            n = os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self._write_failed(exc)
            return
        if n < len(data):
            self._write_buffer.append(data[n:])  # the rest when the port can take it
            self._maybe_pause_protocol()
            self._ensure_writer()

    def _write_failed(self, exc: OSError) -> None:
        """A write the port refused: the transport closes as the library closes it."""
        self._fatal_error(
            serial.SerialException(f"write failed: {exc}"), "Fatal write error on serial transport"
        )

    def _write_data(self, data: bytes | bytearray | memoryview) -> None:
        # The library's own goes through pyserial's write(), whose timeout bookkeeping is
        # most of its cost; the port is non-blocking, so one os.write() is the same write.
        device: serial.Serial | None = self._serial
        fd = None if device is None else device.fd
        if fd is None:  # closing
            super()._write_data(data)
            return
        try:
            n = os.write(fd, data)
        except (BlockingIOError, InterruptedError):
            n = 0
        except OSError as exc:
            self._write_failed(exc)
            return
        if n == len(data):
            if self._closing:
                self._close()
            return
        self._write_buffer.append(data[n:])  # the rest when the port can take it
        self._maybe_pause_protocol()
        self._ensure_writer()

    def _read_ready(self) -> None:
        device: serial.Serial | None = self._serial
        fd = None if device is None else device.fd
        if device is None or fd is None:  # closing
            return
        try:
            data = os.read(fd, self._max_read_size)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            self._close(exc=serial.SerialException(f"read failed: {exc}"))
            return
        if data:
            self._empty_reads = 0
            receiver = self._receiver
            if receiver is not None:
                receiver(data)
            else:
                self._protocol.data_received(data)
            return
        reason = _why_lost(fd, device.port)
        if reason is None:
            self._empty_reads += 1
            _log.debug("%s: spurious empty read #%d", device.port, self._empty_reads)
            if self._empty_reads < _MAX_SPURIOUS_EMPTY_READS:
                return
            reason = f"{self._empty_reads} empty reads in a row"
        self._close(
            exc=serial.SerialException(
                f"the other end hung up ({reason}): the adapter was unplugged, or the "
                f"program serving this pty exited"
            )
        )


def _why_lost(fd: int, path: str | None) -> str | None:
    """Why a tty that read 0 bytes is gone, or ``None`` if it still looks alive."""
    signs = []
    poller = select.poll()
    poller.register(fd, select.POLLIN)
    for _, events in poller.poll(0):
        if events & select.POLLHUP:
            signs.append("POLLHUP")
        if events & (select.POLLERR | select.POLLNVAL):
            signs.append("POLLERR")
    queued = array.array("i", [0])
    try:
        fcntl.ioctl(fd, termios.TIOCINQ, queued)
    except OSError as exc:
        signs.append(f"TIOCINQ: {errno.errorcode.get(exc.errno or 0, exc.errno)}")
    if path:
        try:
            if os.stat(path).st_rdev != os.fstat(fd).st_rdev:
                signs.append(f"{path} is another device now")
        except FileNotFoundError:
            signs.append(f"{path} removed")
        except OSError:
            pass
    return "; ".join(signs) or None


#: What to do about an errno when a port does not open.
_OPEN_HINTS = {
    errno.ENOENT: "no such device: `ohmni ports` lists the serial ports here, "
    "--port sim:// is the simulator",
    errno.ENODEV: "no such device: `ohmni ports` lists the serial ports here, "
    "--port sim:// is the simulator",
    errno.EACCES: "permission denied: add your user to the port's group "
    "(`ls -l` on the device shows it, often dialout) and log in again",
    errno.ENOTTY: "not a serial port",
    errno.EBUSY: "another program holds it (ohmni serve? the vendor's tb-node? "
    "`fuser` on the device tells)",
    errno.EAGAIN: "another program holds it (ohmni serve? the vendor's tb-node? "
    "`fuser` on the device tells)",
}


def _open_error(port: str, exc: BaseException) -> str:
    """One line on why ``port`` did not open and what to do: the errno's words once (the
    serial library repeats the port and the errno in its own message), and a hint."""
    code = getattr(exc, "errno", None)
    for inner in (exc.__cause__, exc.__context__):
        if isinstance(code, int) or inner is None:
            continue
        # An OSError's errno, or termios.error's (errno, text) arguments.
        code = getattr(inner, "errno", None) or next(iter(inner.args), None)
    if isinstance(code, int) and code in _OPEN_HINTS:
        return f"cannot open serial port {port!r}: {os.strerror(code)}; {_OPEN_HINTS[code]}"
    if isinstance(code, int):
        return f"cannot open serial port {port!r}: {os.strerror(code)}"
    return f"cannot open serial port {port!r}: {exc}"
