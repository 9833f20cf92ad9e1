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
works on any loop; :func:`timer_resolution_s` says what its timers get, and the Robot
logs a warning, once, when it opens a serial port on a millisecond loop.
"""

from __future__ import annotations

import asyncio
import select
import selectors
import sys
from collections.abc import Coroutine
from typing import Any, TypeVar

__all__ = ["PreciseEpollSelector", "new_event_loop", "run", "timer_resolution_s"]

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
            self._precise = self.fileno() < _FD_SETSIZE

        @property
        def precise(self) -> bool:
            """Whether its waits keep sub-millisecond time."""
            return self._precise

        def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
            if self._precise and timeout is not None and timeout > 0:
                # Only the wait: the events are read below, by epoll, as always.
                select.select([self.fileno()], [], [], timeout)
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
    Linux, ``epoll`` or ``poll``), 0.0 for a finer one (:class:`PreciseEpollSelector`,
    ``select``, ``kqueue``) and for any other loop (uvloop, a virtual-time loop): the
    figure is about the selector, and for those it is not known to be coarse.
    """
    if loop is None:
        loop = asyncio.get_running_loop()
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
