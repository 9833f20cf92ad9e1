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
is due and nothing is ready it blocks for real.
"""

from __future__ import annotations

import asyncio
import selectors
from collections.abc import Coroutine
from typing import Any, TypeVar

__all__ = ["VirtualClockLoop", "run_virtual"]

T = TypeVar("T")


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

    def time(self) -> float:
        return self._virtual_s

    def advance(self, seconds: float) -> None:
        """Move the clock forward (the loop does this itself when it would wait)."""
        self._virtual_s += seconds


def run_virtual(main: Coroutine[Any, Any, T], *, debug: bool = False) -> T:
    """Run ``main`` to completion on a fresh :class:`VirtualClockLoop`, like asyncio.run."""
    with asyncio.Runner(debug=debug, loop_factory=VirtualClockLoop) as runner:
        return runner.run(main)
