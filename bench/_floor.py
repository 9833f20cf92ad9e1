"""The floor under the Robot's CPU: a minimal bus master running the Robot's schedule.

It is what any program that polls these devices at these rates must do, and nothing
more: the pty opened raw (``os.open``, locked like a serial port, so a second process on
the line is refused instead of halving what each one reads), ``loop.add_reader``, one
timer per stream on absolute deadlines, the request bytes written with ``os.write``, the
next request written from the reply's readable callback, replies counted by their
length, not parsed. No bus engine, no pairing, no samples. Its CPU is the floor the
Robot's is measured against (``bench/robot.py``), on the same loop and the same
``ohmni sim --pty``.

The schedule is the Robot's on the default simulator: every 20 ms a wheel command and
both wheel-count reads, servos 3, 11 and 12 at 30 Hz (RAM 48..59, their phases spread
over the period), the core board's status at 10 Hz. A stream whose cycle is still
waiting for the line when the next is due skips that cycle (counted); a reply that does
not come within 25 ms is a timeout (counted): the bytes waiting to be read are flushed, so
that what is left of the late reply is not counted toward the next one, and the line
moves on.
"""

from __future__ import annotations

import asyncio
import errno
import fcntl
import os
import termios
import tty
from collections import deque
from dataclasses import dataclass, field

from ohmni_tb.protocol import Packet, encode_packet, read_request
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.protocol.timing import reply_size_range

__all__ = ["FloorMaster", "FloorStream", "close_locked", "open_locked", "robot_schedule"]

#: A reply not complete this long after its request went is given up (the bus's own
#: default timeout, and then some: the floor has no wire model to be exact with).
REPLY_TIMEOUT_S = 0.025


@dataclass
class FloorStream:
    """One stream of the schedule: its requests, each with the size of its reply (0: none)."""

    name: str
    hz: float
    phase_s: float
    requests: list[tuple[bytes, int]]
    cycles: int = 0
    skipped: int = 0
    timeouts: int = 0
    #: A cycle of it is queued or on the line.
    busy: bool = field(default=False, repr=False)


def _request(packet: Packet, *, reply: bool = True) -> tuple[bytes, int]:
    return encode_packet(packet), reply_size_range(packet)[0] if reply else 0


def robot_schedule() -> list[FloorStream]:
    """The Robot's schedule on the default simulator (phases as ``robot.feedback``)."""
    servos = [
        FloorStream(
            f"servo {sid}",
            30.0,
            0.010 + k / 30.0 / 3,
            [_request(read_request(sid, 48, 12))],
        )
        for k, sid in enumerate((3, 11, 12))
    ]
    return [
        FloorStream(
            "wheels",
            50.0,
            0.0,
            [
                _request(wheel_command(0, 0), reply=False),
                _request(read_count(0)),
                _request(read_count(1)),
            ],
        ),
        *servos,
        FloorStream("core", 10.0, 0.013, [_request(read_status())]),
    ]


def open_locked(path: str) -> int:
    """Open the pty ``path`` raw and non-blocking, locked as a serial port is.

    Raises:
        OSError: Another process holds the line (``EBUSY``), or it cannot be opened.
    """
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        # pyserial's exclusive=True: an advisory lock every serial program here takes.
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        # And the terminal's own: further opens fail with EBUSY (root excepted).
        fcntl.ioctl(fd, termios.TIOCEXCL)
        tty.setraw(fd)
    except BlockingIOError:
        os.close(fd)
        raise OSError(errno.EBUSY, f"{path} is in use by another process") from None
    except BaseException:
        os.close(fd)
        raise
    return fd


def close_locked(fd: int) -> None:
    """Close a descriptor from :func:`open_locked`, the terminal's exclusive mode lifted
    first (the simulator keeps the pty open, so the mode would outlive the descriptor)."""
    try:
        fcntl.ioctl(fd, termios.TIOCNXCL)
    finally:
        os.close(fd)


class FloorMaster:
    """Runs :func:`robot_schedule` on a locked pty from the running loop (module docstring)."""

    def __init__(self, path: str) -> None:
        self.streams = robot_schedule()
        self._fd = open_locked(path)
        self._loop = asyncio.get_running_loop()
        self._queue: deque[tuple[FloorStream, int]] = deque()
        # The request on the line: its stream, its index, the reply bytes still due, when.
        self._current: FloorStream | None = None
        self._index = 0
        self._due_bytes = 0
        self._sent_at = 0.0
        self.replies = 0
        self.junk_bytes = 0
        self._timers: list[asyncio.TimerHandle] = []
        self._running = False

    def start(self) -> None:
        """Start every stream's timer and the reader."""
        self._running = True
        self._loop.add_reader(self._fd, self._readable)
        t0 = self._loop.time() + 0.005
        for stream in self.streams:
            self._every(stream, t0 + stream.phase_s, 1.0 / stream.hz)

    def close(self) -> None:
        """Stop the timers and the reader; close the pty."""
        self._running = False
        for timer in self._timers:
            timer.cancel()
        self._loop.remove_reader(self._fd)
        close_locked(self._fd)

    def _every(self, stream: FloorStream, first: float, period: float) -> None:
        loop = self._loop
        k = 0
        slot = len(self._timers)
        self._timers.append(loop.call_at(first, lambda: None))

        def fire() -> None:
            nonlocal k
            if not self._running:
                return
            k += 1
            self._timers[slot] = loop.call_at(first + k * period, fire)
            self._due(stream)

        self._timers[slot].cancel()
        self._timers[slot] = loop.call_at(first, fire)

    def _due(self, stream: FloorStream) -> None:
        current = self._current
        if current is not None and self._loop.time() - self._sent_at > REPLY_TIMEOUT_S:
            # The reply is not coming (a collision garbled it, or the simulator's process
            # was not scheduled): what has come of it goes, and the line moves on.
            current.timeouts += 1
            termios.tcflush(self._fd, termios.TCIFLUSH)
            self._finish(current)
        if stream.busy:
            stream.skipped += 1
            return
        stream.busy = True
        self._queue.append((stream, 0))
        if self._current is None:
            self._send()

    def _send(self) -> None:
        """Write queued requests until one waits for a reply."""
        while self._queue:
            stream, index = self._queue.popleft()
            frame, reply = stream.requests[index]
            os.write(self._fd, frame)
            if index + 1 < len(stream.requests):
                self._queue.appendleft((stream, index + 1))
            if reply:
                self._current, self._index, self._due_bytes = stream, index, reply
                self._sent_at = self._loop.time()
                return
            if index + 1 == len(stream.requests):
                stream.cycles += 1
                stream.busy = False
        self._current = None

    def _finish(self, stream: FloorStream) -> None:
        self._current = None
        if self._queue and self._queue[0][0] is stream:
            return  # the rest of its cycle goes next
        stream.busy = False

    def _readable(self) -> None:
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return  # another reader took the bytes (the lock should prevent that)
        stream = self._current
        if stream is None:
            self.junk_bytes += len(data)
            return
        self._due_bytes -= len(data)
        if self._due_bytes > 0:
            return
        self.junk_bytes -= self._due_bytes
        self.replies += 1
        if self._index + 1 == len(stream.requests):
            stream.cycles += 1
        self._finish(stream)
        self._send()
