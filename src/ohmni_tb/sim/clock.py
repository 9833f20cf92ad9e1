"""Virtual time for the simulator: an event loop whose clock jumps instead of waiting.

Under :func:`run_virtual`, ``asyncio.sleep(10)`` returns at once with ``loop.time()`` ten
seconds later, and everything scheduled in between runs in order. The simulated line and
the bus take their time from the loop, so a test drives the robot for minutes in
milliseconds, deterministically::

    from ohmni_tb.sim.clock import run_virtual

    async def main() -> None:
        async with Bus(await open_transport("sim://")) as bus:
            ...

    run_virtual(main())

The loop still polls real file descriptors (without blocking while timers are due), so a
pseudo-terminal or a thread calling ``call_soon_threadsafe`` keeps working; when nothing
is due and nothing is ready it blocks for real. While a job it handed to an executor
(``asyncio.to_thread``, ``run_in_executor``: opening a serial port, say) is running, the
clock stands still and the loop waits for it for real: a thread takes no virtual time, so
a virtual timeout around it cannot expire however slow the machine is.
"""

from __future__ import annotations

import asyncio
import selectors
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

__all__ = ["VirtualClockLoop", "run_virtual"]

T = TypeVar("T")

#: While an executor job runs, the longest real wait before the loop looks again.
_THREAD_POLL_S = 0.05


class _JumpingSelector(selectors.DefaultSelector):
    """Polls without blocking; a wait for a timer becomes a jump of the virtual clock."""

    #: Timers fire exactly when due (ohmni_tb.eventloop.timer_resolution_s).
    precise = True

    def __init__(self) -> None:
        super().__init__()
        self.loop: VirtualClockLoop | None = None

    def select(self, timeout: float | None = None) -> list[tuple[selectors.SelectorKey, int]]:
        ready = super().select(0)
        if ready or timeout is None:
            return ready if ready or timeout == 0 else super().select(None)
        if timeout > 0 and self.loop is not None:
            if self.loop.threads_busy:
                # The thread's result wakes the loop through its self-pipe.
                return super().select(min(timeout, _THREAD_POLL_S))
            self.loop.advance(timeout)
        return ready


class VirtualClockLoop(asyncio.SelectorEventLoop):
    """An event loop on virtual time (see the module docstring)."""

    def __init__(self, start_s: float = 0.0) -> None:
        selector = _JumpingSelector()
        super().__init__(selector)
        selector.loop = self
        self._virtual_s = start_s
        # Timers due within this window run together; virtual time is exact, so none.
        self._clock_resolution = 1e-9
        #: Executor jobs started and not yet finished: the clock stands still meanwhile.
        self.threads_busy = 0

    def run_in_executor(  # type: ignore[override]  # same call; typeshed's overloads
        self, executor: Any, func: Callable[..., T], *args: Any
    ) -> asyncio.Future[T]:
        future = super().run_in_executor(executor, func, *args)
        self.threads_busy += 1
        future.add_done_callback(self._thread_done)
        return future

    def _thread_done(self, _future: asyncio.Future[Any]) -> None:
        self.threads_busy -= 1

    def time(self) -> float:
        return self._virtual_s

    def advance(self, seconds: float) -> None:
        """Move the clock forward (the loop does this itself when it would wait)."""
        self._virtual_s += seconds


def run_virtual(main: Coroutine[Any, Any, T], *, debug: bool = False) -> T:
    """Run ``main`` to completion on a fresh :class:`VirtualClockLoop`, like asyncio.run."""
    with asyncio.Runner(debug=debug, loop_factory=VirtualClockLoop) as runner:
        return runner.run(main)
