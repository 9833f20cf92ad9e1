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
from ohmni_tb.transport import Transport

__all__ = ["PtyTransport", "open_pty_pair"]

_READ_CHUNK = 4096


class PtyTransport(Transport):
    """The master side of a pseudo-terminal as a transport (the simulator's end).

    The slave side stays open here too, so a client that closes and reopens the device
    does not end the session.
    """

    def __init__(self, master_fd: int, slave_fd: int, *, baudrate: int | None = None) -> None:
        self.master_fd = master_fd
        self.slave_fd = slave_fd
        self.path = os.ttyname(slave_fd)
        self.baudrate = baudrate
        self._closed = False
        self._ready = asyncio.Event()
        self._loop = asyncio.get_running_loop()
        os.set_blocking(master_fd, False)
        self._loop.add_reader(master_fd, self._ready.set)

    @property
    def closed(self) -> bool:
        return self._closed

    async def read(self) -> bytes:
        while True:
            if self._closed:
                raise TransportClosedError(f"pty {self.path} is closed")
            try:
                data = os.read(self.master_fd, _READ_CHUNK)
            except BlockingIOError:
                self._ready.clear()
                await self._ready.wait()
                continue
            except OSError as exc:
                raise TransportError(f"pty {self.path}: read failed: {exc}") from exc
            if data:
                return data
            self._ready.clear()
            await self._ready.wait()

    async def write(self, data: bytes) -> None:
        if self._closed:
            raise TransportClosedError(f"pty {self.path} is closed")
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master_fd, view)
            except BlockingIOError:
                await asyncio.sleep(0.001)
                continue
            except OSError as exc:
                raise TransportError(f"pty {self.path}: write failed: {exc}") from exc
            view = view[n:]

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._ready.set()
        self._loop.remove_reader(self.master_fd)
        for fd in (self.master_fd, self.slave_fd):
            with contextlib.suppress(OSError):
                os.close(fd)


def open_pty_pair(baudrate: int | None = None) -> PtyTransport:
    """A new pseudo-terminal in raw mode (no echo, no line editing), master side wrapped."""
    master_fd, slave_fd = os.openpty()
    # Raw mode on the slave: the line discipline must pass binary frames untouched.
    tty.setraw(slave_fd)
    return PtyTransport(master_fd, slave_fd, baudrate=baudrate)
