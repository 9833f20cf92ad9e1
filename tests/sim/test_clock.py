"""The virtual clock: timers jump, threads keep real time without spending virtual time."""

from __future__ import annotations

import asyncio
import time

from ohmni_tb.sim.clock import run_virtual


def test_a_sleep_takes_virtual_time_and_no_wall_time() -> None:
    async def main() -> float:
        loop = asyncio.get_running_loop()
        start = loop.time()
        await asyncio.sleep(600)
        return loop.time() - start

    wall = time.monotonic()
    assert run_virtual(main()) == 600
    assert time.monotonic() - wall < 5


def test_a_slow_thread_inside_a_short_virtual_timeout_is_waited_for() -> None:
    # Opening a serial port runs in a thread: however slow the machine, the clock must
    # not run on meanwhile, or a virtual timeout around the open expires at once.
    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                await asyncio.sleep(0.02)
                ticks += 1

        task = asyncio.create_task(ticker())
        start = loop.time()

        def slow_open() -> str:
            time.sleep(0.3)
            return "opened"

        async with asyncio.timeout(0.05):
            result = await asyncio.to_thread(slow_open)
        elapsed = loop.time() - start
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return result, elapsed

    result, elapsed = run_virtual(main())
    assert result == "opened"
    assert elapsed < 0.05


def test_the_clock_runs_on_once_the_thread_is_done() -> None:
    async def main() -> float:
        loop = asyncio.get_running_loop()
        await asyncio.to_thread(time.sleep, 0.01)
        start = loop.time()
        await asyncio.sleep(30)
        return loop.time() - start

    assert run_virtual(main()) == 30
