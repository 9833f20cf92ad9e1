"""An asyncio event loop whose timers keep sub-millisecond time, for a line booked to 80 %.

On Linux, asyncio's default loop waits in ``epoll_wait``, whose timeout is whole
milliseconds: :mod:`selectors` rounds every wait *up* to the next millisecond, so a timer
due in 0.2 ms fires 1 ms later, and one due in 3.1 ms fires at 4. The bus sends the next
request of a slot when the previous reply has left the wire by the cost model — a timer
whenever the host does not see that reply at once, which is always behind an adapter
that holds bytes (the FTDI latency timer: 16 ms unless lowered, 1 ms when lowered). Each
such send then starts 0.5 ms late on average; at ~200 transactions a second that is a
tenth of the line, and a schedule the cost model books to 81 % no longer fits: the servo
streams fall to 23–26 Hz of 30 behind a 16 ms adapter (``bench/robot.py``).

:func:`new_event_loop` returns asyncio's own selector loop on
:class:`PreciseEpollSelector`, which waits on the epoll descriptor with :func:`select.select`
(microsecond timeouts, the kernel's timer slack of ~50 µs) and then collects the events
with a zero-timeout ``epoll_wait``: the same loop, the same scaling in descriptors, one
system call more per pass. :func:`run` is :func:`asyncio.run` on it. Where epoll does not
exist (macOS and the BSDs wait in kqueue with nanosecond timeouts; Windows' proactor
waits in milliseconds) :func:`new_event_loop` is asyncio's default.

``ohmni`` commands and ``ohmni serve`` run on it; a program that embeds the
:class:`~ohmni_tb.robot.Robot` gets it with ``ohmni_tb.run(main())`` in place of
``asyncio.run(main())`` (or ``asyncio.Runner(loop_factory=new_event_loop)``). The Robot
works on any loop: on one whose timers wait in whole milliseconds
(:func:`timer_resolution_s`: asyncio's default, uvloop) the bus sets its timer a
millisecond before the line frees and sleeps the rest in the loop, so the schedule keeps
its rates there too, at the cost of up to a millisecond of the loop's time per request
sent on a timer; the Robot logs a warning, once, when it opens a serial port on such a
loop.

Whatever the loop, the bus keeps the line's time with a :class:`LineClock`
(:func:`line_clock`): the moment a reply is read and a request written, to the
microsecond, in the loop's own time base. On asyncio's loops that is
:func:`time.monotonic`, which their ``time()`` already is; on uvloop, whose ``time()``
counts whole milliseconds of the same clock, it is :func:`time.monotonic` too (a reply
stamped up to a millisecond early looks as if it came before its request could have been
answered), and its timers, which libuv also counts in whole milliseconds and rounds to
the nearest, are set on the millisecond after their time so that none fires early. On a
loop that keeps a time of its own (the simulator's virtual time) it is that loop's
``time()``, exact.

A precise timer still fires late when every core is busy with other programs: the
kernel lets a waking time-shared process wait its turn. :func:`set_realtime` puts the
loop's thread in the ``SCHED_FIFO`` class, which runs the moment it wakes, ahead of
every time-shared process (``ohmni serve --rt-priority``; docs/hardware.md).
"""

from __future__ import annotations

import asyncio
import math
import os
import select
import selectors
import sys
import time
from collections.abc import Callable, Coroutine
from typing import Any, Final, TypeVar

from ohmni_tb._checks import integer
from ohmni_tb.errors import ConfigError

__all__ = [
    "DEFAULT_RT_PRIORITY",
    "LineClock",
    "PreciseEpollSelector",
    "line_clock",
    "new_event_loop",
    "realtime_priority",
    "run",
    "set_realtime",
    "timer_resolution_s",
]

_T = TypeVar("_T")

#: select(2) takes descriptors below this number only.
_FD_SETSIZE = 1024

#: The wait of a loop whose selector rounds its timeout up to whole milliseconds.
MILLISECOND_S = 0.001


if hasattr(selectors, "EpollSelector"):

    class PreciseEpollSelector(selectors.EpollSelector):
        """An epoll selector whose waits end within microseconds of their timeout.

        It waits with ``select(2)`` on the epoll descriptor itself (readable when any
        registered descriptor has an event), then reads the events with a zero
        timeout. Should the epoll descriptor ever be numbered beyond what ``select(2)``
        takes (a process with over a thousand files open before the loop was made), it
        waits as :class:`selectors.EpollSelector` does, in whole milliseconds.
        """

        def __init__(self) -> None:
            super().__init__()
            self._epoll_fd = self.fileno()
            self._precise = self._epoll_fd < _FD_SETSIZE

        @property
        def precise(self) -> bool:
            """Whether its waits keep sub-millisecond time."""
            return self._precise

        def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
            if self._precise and timeout is not None and timeout > 0:
                # Only the wait: the events are read below, by epoll, as always.
                select.select([self._epoll_fd], [], [], timeout)
                timeout = 0
            return super().select(timeout)

    def new_event_loop() -> asyncio.AbstractEventLoop:
        """A new asyncio selector loop on :class:`PreciseEpollSelector`."""
        return asyncio.SelectorEventLoop(PreciseEpollSelector())

else:  # pragma: no cover  # macOS, the BSDs, Windows: no epoll to make precise
    __all__.remove("PreciseEpollSelector")

    def new_event_loop() -> asyncio.AbstractEventLoop:
        """asyncio's default loop (its timers are as precise as that platform's)."""
        return asyncio.new_event_loop()


def run(main: Coroutine[Any, Any, _T], *, debug: bool | None = None) -> _T:
    """:func:`asyncio.run` on :func:`new_event_loop`: run ``main``, close the loop."""
    with asyncio.Runner(debug=debug, loop_factory=new_event_loop) as runner:
        return runner.run(main)


def timer_resolution_s(loop: asyncio.AbstractEventLoop | None = None) -> float:
    """How late ``loop``'s timers may fire from the way it waits, in seconds.

    0.001 for a selector loop that waits in whole milliseconds (asyncio's default on
    Linux, ``epoll`` or ``poll``) and for uvloop (libuv counts its timers in whole
    milliseconds); 0.0 for a finer one (:class:`PreciseEpollSelector`, ``select``,
    ``kqueue``) and for any other loop (a virtual-time loop, one not known to be coarse).
    """
    if loop is None:
        loop = asyncio.get_running_loop()
    if _is_uvloop(loop):
        return MILLISECOND_S
    selector = getattr(loop, "_selector", None)  # asyncio's selector loops keep it here
    if selector is None:
        return 0.0
    precise = getattr(selector, "precise", None)
    if precise is not None:
        return 0.0 if precise else MILLISECOND_S
    coarse = tuple(
        getattr(selectors, name)
        for name in ("EpollSelector", "PollSelector", "DevpollSelector")
        if hasattr(selectors, name)
    )
    if isinstance(selector, coarse) and sys.platform != "win32":
        return MILLISECOND_S
    return 0.0


class LineClock:
    """The time a bus keeps on one event loop (:func:`line_clock`; the module docstring).

    Attributes:
        now: Reads the time: seconds in the loop's own time base (what ``call_at`` takes).
        resolution_s: How much earlier than the truth :attr:`now` may read (0.0: exact to
            the microsecond; more only for a loop whose own coarse ``time()`` is the
            clock, as its ``_clock_resolution`` says).
        grid_s: The loop's timer grid, where its timers round to it (uvloop's whole
            milliseconds); :meth:`call_at` sets a timer on the grid step after its time.
    """

    __slots__ = ("_loop", "grid_s", "now", "resolution_s")

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        now: Callable[[], float],
        *,
        resolution_s: float = 0.0,
        grid_s: float = 0.0,
    ) -> None:
        self._loop = loop
        self.now = now
        self.resolution_s = resolution_s
        self.grid_s = grid_s

    def call_at(self, when: float, callback: Callable[[], object]) -> asyncio.TimerHandle:
        """``loop.call_at(when, callback)``, never firing before :attr:`now` reaches ``when``."""
        grid = self.grid_s
        if grid:
            # The next step of the grid at or after `when` (a nanosecond of float slack).
            when = math.ceil(when / grid - 1e-6) * grid
        return self._loop.call_at(when, callback)

    def __repr__(self) -> str:
        return (
            f"<LineClock {getattr(self.now, '__qualname__', self.now)} "
            f"resolution={self.resolution_s:g} s grid={self.grid_s:g} s>"
        )


def line_clock(loop: asyncio.AbstractEventLoop | None = None) -> LineClock:
    """The clock a bus keeps its line's time with on ``loop`` (the running one by default).

    :func:`time.monotonic` on asyncio's own loops (their ``time()``, read without the
    method call) and on a loop whose ``time()`` counts the same clock more coarsely
    (uvloop: whole milliseconds, and timers on that grid); the loop's own ``time()``
    on a loop that keeps a time of its own (a virtual clock), with the resolution it
    declares (asyncio's ``_clock_resolution``).
    """
    if loop is None:
        loop = asyncio.get_running_loop()
    if isinstance(loop, asyncio.BaseEventLoop):
        if type(loop).time is asyncio.BaseEventLoop.time:
            return LineClock(loop, time.monotonic)
        declared = getattr(loop, "_clock_resolution", 0.0)
        resolution = float(declared) if isinstance(declared, int | float) else 0.0
        # Finer than a microsecond is exact for a line of 87 µs bytes.
        return LineClock(loop, loop.time, resolution_s=resolution if resolution > 1e-6 else 0.0)
    grid = MILLISECOND_S if _is_uvloop(loop) else 0.0
    behind = time.monotonic() - loop.time()
    if 0.0 <= behind < 2 * MILLISECOND_S:
        # The same clock, truncated (libuv: whole milliseconds of CLOCK_MONOTONIC).
        return LineClock(loop, time.monotonic, grid_s=grid)
    return LineClock(loop, loop.time, resolution_s=grid, grid_s=grid)


def _is_uvloop(loop: asyncio.AbstractEventLoop) -> bool:
    return type(loop).__module__.split(".", 1)[0] in ("uvloop", "winloop")


#: ``ohmni serve --rt-priority``'s suggestion: above every time-shared process, below the
#: kernel's own real-time threads (threaded interrupt handlers run at 50).
DEFAULT_RT_PRIORITY: Final = 10


def set_realtime(priority: int = DEFAULT_RT_PRIORITY) -> None:
    """Run the calling thread under ``SCHED_FIFO`` at ``priority``; 0 puts it back.

    Call it from the thread that runs the event loop, before the loop starts: on Linux
    the class belongs to a thread, and threads started afterwards inherit it. The thread
    then runs the moment a timer or a reply wakes it, whatever time-shared programs keep
    the cores busy (with 50 daemon clients on the two cores of ``bench/daemon.py``'s host,
    the control slot's start p99 grew 2.5–4.2 ms time-shared, 0–0.5 ms at 10). A thread in
    this class that never sleeps would starve its core of time-shared work; the kernel
    keeps 5 % of every second for them (``/proc/sys/kernel/sched_rt_runtime_us``), and the
    event loop sleeps between its callbacks.

    Args:
        priority: 1..99 (higher runs first), or 0 for normal time sharing (``SCHED_OTHER``).

    Raises:
        OutOfRangeError: ``priority`` outside 0..99 (or the system's range).
        ConfigError: the system has no ``SCHED_FIFO`` (it is Linux's), or this process may
            not use it: that needs root, ``CAP_SYS_NICE``, or an ``RLIMIT_RTPRIO`` of at
            least ``priority`` (systemd's ``LimitRTPRIO=``, ``rtprio`` in
            /etc/security/limits.conf).
    """
    if not hasattr(os, "SCHED_FIFO") or not hasattr(os, "sched_setscheduler"):
        raise ConfigError(
            f"real-time scheduling (SCHED_FIFO) is Linux's; this system ({sys.platform}) "
            "has none: run without a real-time priority"
        )
    integer("priority", priority, 0, os.sched_get_priority_max(os.SCHED_FIFO))
    policy = os.SCHED_FIFO if priority else os.SCHED_OTHER
    try:
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except PermissionError:
        import resource  # noqa: PLC0415  # Unix's; only this refusal needs it

        which = getattr(resource, "RLIMIT_RTPRIO", None)  # Linux's
        limit = "" if which is None else f" (its RLIMIT_RTPRIO: {resource.getrlimit(which)[0]})"
        raise ConfigError(
            f"real-time priority {priority} refused to this process{limit}: run it as root, "
            "give it CAP_SYS_NICE, or raise RLIMIT_RTPRIO to the priority "
            "(systemd: LimitRTPRIO=; /etc/security/limits.conf: rtprio)"
        ) from None


def realtime_priority() -> int:
    """The calling thread's ``SCHED_FIFO``/``SCHED_RR`` priority; 0 when time-shared."""
    if not hasattr(os, "sched_getscheduler"):
        return 0
    if os.sched_getscheduler(0) not in (os.SCHED_FIFO, os.SCHED_RR):
        return 0
    return int(os.sched_getparam(0).sched_priority)
