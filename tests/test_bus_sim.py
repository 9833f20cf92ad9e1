"""The bus engine on the simulated robot, in virtual time: the issue's scenarios end to end.

A slow device, a corrupted line, silent servos, an adapter that holds replies 16 ms,
the stop on close, a pulled USB cable — each against ``sim://``, whose line is
byte-timed and counts a request that lands on a reply.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import pytest

from ohmni_tb.bus import Bus, BusStats
from ohmni_tb.errors import BusTimeoutError, DeadlineMissedError, TransportError
from ohmni_tb.protocol import ReadReply, read_request
from ohmni_tb.protocol.connection import BreakerState
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import parse_count, read_count, wheel_command
from ohmni_tb.sim.clock import VirtualClockLoop, run_virtual
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import Transport, open_transport
from ohmni_tb.transport.base import LostHandler, Receiver

T = TypeVar("T")


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


async def sim(query: str = "") -> SimTransport:
    transport = await open_transport(f"sim://?{query}")
    assert isinstance(transport, SimTransport)
    return transport


def count(reply: Any) -> int:
    return parse_count(ReadReply.parse(reply))


async def schedule(bus: Bus, seconds: float) -> dict[str, int]:
    """tb_control's schedule, staggered; returns the cycles that got their replies."""
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    done = {"wheels": 0, "servos": 0, "core": 0}

    async def stream(name: str, hz: float, phase_s: float, slot: Callable[[float], Any]) -> None:
        k = 0
        tasks = []
        while (due := t0 + phase_s + k / hz) < t0 + seconds:
            await asyncio.sleep(max(0.0, due - loop.time()))
            tasks.append(asyncio.ensure_future(slot(due)))
            k += 1
        for ok in await asyncio.gather(*tasks):
            done[name] += bool(ok)

    async def wheels(due: float) -> bool:
        try:
            replies = await bus.transact(
                [read_count(0), read_count(1), wheel_command(200, 200)],
                priority=10,
                deadline=due + 0.010,
            )
        except DeadlineMissedError:
            return False
        return replies[0] is not None and replies[1] is not None

    def servo(sid: int) -> Callable[[float], Any]:
        async def read(due: float) -> bool:
            try:
                [reply] = await bus.transact(
                    [read_request(sid, 48, 12)], priority=5, deadline=due + 1 / 30
                )
            except DeadlineMissedError:
                return False
            return reply is not None

        return read

    async def core(due: float) -> bool:
        [reply] = await bus.transact([read_status()], priority=1, deadline=due + 0.1)
        return reply is not None

    await asyncio.gather(
        stream("wheels", 50, 0.0, wheels),
        *(stream("servos", 30, 0.010 + k / 90, servo(sid)) for k, sid in enumerate((3, 11, 12))),
        stream("core", 10, 0.013, core),
    )
    return done


@pytest.mark.parametrize("usb_ms", [0, 1, 16])
def test_the_full_schedule_keeps_every_rate_whatever_the_adapter_latency(usb_ms: int) -> None:
    async def main() -> tuple[dict[str, int], BusStats, int]:
        transport = await sim(f"usb_latency_ms={usb_ms}")
        async with Bus(transport) as bus:
            done = await schedule(bus, 2.0)
            stats = bus.stats
        return done, stats, transport.line.stats.host_collisions

    done, stats, collisions = virtual(main)
    assert done == {"wheels": 100, "servos": 180, "core": 20}
    assert collisions == 0
    assert stats.unmatched == 0
    assert stats.deadline_misses == 0


def test_silent_servos_cost_the_schedule_nothing() -> None:
    async def main() -> tuple[dict[str, int], BusStats]:
        async with Bus(await sim("silent=11,12")) as bus:
            done = await schedule(bus, 3.0)
            stats = bus.stats
        return done, stats

    done, stats = virtual(main)
    assert done["wheels"] == 150
    assert done["core"] == 30
    assert done["servos"] == 90  # the neck's, every cycle; the silent ones none
    for sid in (11, 12):
        assert stats.devices[sid].breaker is not BreakerState.CLOSED
        # Probed about once a second after the breaker opened, not 30 times a second.
        assert stats.devices[sid].requests <= 15
    assert stats.refused > 100


def test_a_device_slower_than_its_budget_times_out_and_never_answers_the_next_read() -> None:
    async def main() -> tuple[list[int], int, BusStats]:
        async with Bus(await sim("turnaround_us=30000"), breaker_timeouts=1000) as bus:
            timeouts = 0
            for _ in range(20):
                try:
                    await bus.request(read_count(0))
                except BusTimeoutError:
                    timeouts += 1
            # Given its own budget, the same device is read, and the robot moves between
            # reads: every count is new.
            bus.set_turnaround(0, 0.035)
            await bus.send(wheel_command(300, 300))
            await asyncio.sleep(0.5)
            counts = [count(await bus.request(read_count(0))) for _ in range(20)]
            stats = bus.stats
        return counts, timeouts, stats

    counts, timeouts, stats = virtual(main)
    assert timeouts == 20
    assert stats.devices[0].late > 0
    assert counts == sorted(counts)
    assert len(set(counts)) == len(counts)


def test_a_corrupting_line_never_returns_a_reply_twice() -> None:
    """Driving at speed, every count read 3 ms apart differs: a repeat would be stale."""

    async def main() -> tuple[list[int], int, BusStats]:
        transport = await sim("corrupt=0.002&seed=3")
        async with Bus(transport, breaker_timeouts=1000) as bus:
            transport.line.faults.corrupt_rate = 0.0
            await bus.send(wheel_command(600, 600))
            await asyncio.sleep(1.0)
            transport.line.faults.corrupt_rate = 0.002
            counts: list[int] = []
            timeouts = 0
            for _ in range(1500):
                try:
                    counts.append(count(await bus.request(read_count(0))))
                except BusTimeoutError:
                    timeouts += 1
            stats = bus.stats
        return counts, timeouts, stats

    counts, timeouts, stats = virtual(main)
    assert len(counts) + timeouts == 1500
    assert len(counts) > 1400
    assert len(set(counts)) == len(counts)
    assert stats.decoder.checksum_errors + stats.decoder.bad_headers > 0


def test_the_final_stop_reaches_the_wheels_while_the_bus_closes() -> None:
    async def main() -> tuple[float, float, list[BaseException]]:
        transport = await sim()
        robot = transport.robot
        assert robot is not None
        bus = Bus(transport)
        bus.start()
        await bus.send(wheel_command(500, 500))
        await asyncio.sleep(1.0)
        moving = robot.wheel_speeds_mps()[0]
        queued = [asyncio.ensure_future(bus.read(sid, 48, 12)) for sid in (3, 11, 12)]
        await asyncio.sleep(0)
        await bus.aclose(final=[wheel_command(0, 0)])
        errors = [r for r in await asyncio.gather(*queued, return_exceptions=True) if r]
        robot.attach_clock(lambda: 3.0)  # the line is closed: read the robot a second on
        return (
            moving,
            robot.wheel_speeds_mps()[0],
            [e for e in errors if isinstance(e, BaseException)],
        )

    moving, after, errors = virtual(main)
    assert moving > 0.3
    assert after == 0.0
    assert len(errors) >= 2


def test_a_pulled_usb_cable_is_reported_and_reconnect_finds_the_same_robot() -> None:
    async def main() -> tuple[int, int, BusStats]:
        transport = await sim()
        line, robot = transport.line, transport.robot

        async def reopen() -> Transport:
            return SimTransport(line, robot=robot)

        async with Bus(transport, reopen=reopen) as bus:
            await bus.send(wheel_command(300, 300))
            await asyncio.sleep(0.5)
            before = count(await bus.request(read_count(0)))
            transport.unplug_usb()
            lost = await bus.wait_lost()
            assert "unplugged" in str(lost)
            with pytest.raises(TransportError):
                await bus.request(read_count(0))
            await asyncio.sleep(0.2)
            await bus.reconnect()
            after = count(await bus.request(read_count(0)))
            stats = bus.stats
        return before, after, stats

    before, after, stats = virtual(main)
    assert after > before  # the robot kept driving; the new link reads the same boards
    assert (stats.link_losses, stats.reconnects) == (1, 1)


class Stalling(Transport):
    """Passes bytes on, but every few writes the process "stalls" before the bytes leave:
    the virtual clock jumps inside the write, as when the host is descheduled there."""

    def __init__(self, inner: SimTransport, every: int, stall_s: float) -> None:
        self.inner = inner
        self.baudrate = inner.baudrate
        self.every = every
        self.stall_s = stall_s
        self.writes = 0

    @property
    def closed(self) -> bool:
        return self.inner.closed

    def write_nowait(self, data: bytes) -> None:
        self.writes += 1
        if self.writes % self.every == 0:
            loop = asyncio.get_running_loop()
            assert isinstance(loop, VirtualClockLoop)
            loop.advance(self.stall_s)
        self.inner.write_nowait(data)

    async def read(self) -> bytes:
        return await self.inner.read()

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        self.inner.start_receiving(on_data, on_lost)

    async def aclose(self) -> None:
        await self.inner.aclose()


def test_a_host_stalled_inside_a_write_never_talks_over_a_reply() -> None:
    async def main() -> tuple[dict[str, int], int, int]:
        transport = await sim("usb_latency_ms=1")
        stalling = Stalling(transport, every=7, stall_s=0.0015)
        async with Bus(stalling) as bus:
            done = await schedule(bus, 2.0)
        return done, stalling.writes, transport.line.stats.host_collisions

    done, writes, collisions = virtual(main)
    assert collisions == 0
    assert writes > 450
    assert done["wheels"] >= 95
