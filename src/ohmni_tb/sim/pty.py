"""Serve the simulated robot on a pseudo-terminal, so any serial program can drive it.

``ohmni sim --pty`` prints the device path (e.g. ``/dev/pts/5``) and serves until
stopped; open that path at 115200 8N1 with pyserial, minicom, or ``ohmni --port``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tty

from ohmni_tb.errors import TransportClosedError, TransportError
from ohmni_tb.transport.base import LostHandler, ReceiveBuffer, Receiver, Transport

__all__ = ["PtyTransport", "open_pty_pair"]

_READ_CHUNK = 4096


class PtyTransport(Transport):
    """The master side of a pseudo-terminal as a transport (the simulator's end).

    The slave side stays open here too, so a client that closes and reopens the device
    does not end the session. Bytes are read as soon as the loop sees them (for
    :meth:`read` or a receiver), up to 4 KiB a pass, unless reading is paused
    (:meth:`pause_reading`: the bytes then wait in the terminal, and once its buffer is
    full the client's writes wait too); writes the terminal cannot take at once wait in
    :attr:`backlog` and go out when it can.
    """

    def __init__(self, master_fd: int, slave_fd: int, *, baudrate: int | None = None) -> None:
        self.master_fd = master_fd
        self.slave_fd = slave_fd
        self.path = os.ttyname(slave_fd)
        self.baudrate = baudrate
        self._closed = False
        self._lost = False
        self._paused = False
        self._rx = ReceiveBuffer(f"pty {self.path}")
        self._out = bytearray()
        self._writing = False
        self._drained: asyncio.Event | None = None
        self._loop = asyncio.get_running_loop()
        os.set_blocking(master_fd, False)
        self._loop.add_reader(master_fd, self._on_readable)

    @property
    def closed(self) -> bool:
        return self._closed or self._lost

    @property
    def backlog(self) -> int:
        return len(self._out)

    @property
    def reading_paused(self) -> bool:
        """Whether :meth:`pause_reading` is in force."""
        return self._paused

    def pause_reading(self) -> None:
        """Stop reading the terminal until :meth:`resume_reading`."""
        if self._paused or self.closed:
            return
        self._paused = True
        self._loop.remove_reader(self.master_fd)

    def resume_reading(self) -> None:
        """Read the terminal again after :meth:`pause_reading`."""
        if not self._paused:
            return
        self._paused = False
        if not self.closed:
            self._loop.add_reader(self.master_fd, self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = os.read(self.master_fd, _READ_CHUNK)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(TransportError(f"pty {self.path}: read failed: {exc}"))
            return
        if data:
            self._rx.deliver(data)

    def _fail(self, exc: TransportError) -> None:
        if self._lost or self._closed:
            return
        self._lost = True
        if not self._paused:
            self._loop.remove_reader(self.master_fd)
        self._stop_writing()
        self._out.clear()
        self._rx.lose(exc)

    def write_nowait(self, data: bytes) -> None:
        if self._closed:
            raise TransportClosedError(f"pty {self.path} is closed")
        if self._lost:
            raise TransportError(f"pty {self.path}: the link failed")
        if self._out:
            self._out += data
            return
        try:
            sent = os.write(self.master_fd, data)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            raise TransportError(f"pty {self.path}: write failed: {exc}") from exc
        if sent < len(data):
            self._out += data[sent:]
            self._writing = True
            self._loop.add_writer(self.master_fd, self._on_writable)

    def _on_writable(self) -> None:
        try:
            sent = os.write(self.master_fd, self._out)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(TransportError(f"pty {self.path}: write failed: {exc}"))
            return
        del self._out[:sent]
        if not self._out:
            self._stop_writing()

    def _stop_writing(self) -> None:
        if self._writing:
            self._writing = False
            self._loop.remove_writer(self.master_fd)
        if self._drained is not None:
            self._drained.set()

    async def drain(self) -> None:
        while self._out and not self.closed:
            if self._drained is None:
                self._drained = asyncio.Event()
            self._drained.clear()
            await self._drained.wait()

    async def read(self) -> bytes:
        return await self._rx.read()

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        self._rx.start(on_data, on_lost)

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        if not self._lost and not self._paused:
            self._loop.remove_reader(self.master_fd)
        self._stop_writing()
        self._out.clear()
        self._rx.close()
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)


def open_pty_pair(baudrate: int | None = None) -> PtyTransport:
    """A new pseudo-terminal in raw mode (no echo, no line editing), master side wrapped."""
    master_fd, slave_fd = os.openpty()
    # Raw mode on the slave: the line discipline must pass binary frames untouched.
    tty.setraw(slave_fd)
    return PtyTransport(master_fd, slave_fd, baudrate=baudrate)
