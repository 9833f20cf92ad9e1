"""Reopening a link is the transport's job: ``Transport.reopen()`` opens the same link
again as a new transport (a serial port with its settings, the simulated robot as it
was), or says that it cannot."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import pytest
from serial.tools import list_ports as serial_ports

from ohmni_tb.bus import Bus
from ohmni_tb.errors import StateError, TransportError
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import parse_count, read_count, wheel_command
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.transport import MemoryTransport, SerialTransport, open_transport
from ohmni_tb.transport.ports import BUS_USB_ID, ROBOT_BUS_LINK


async def left_count(bus: Bus) -> int:
    return parse_count(await bus.query(read_count(DeviceId.LEFT_DRIVE)))


def test_a_simulated_line_reopens_to_the_robot_as_it_was() -> None:
    async def main() -> tuple[int, int, int]:
        first = await open_transport("sim://?count_offset=5000")
        assert first.can_reopen
        robot = first.simulated
        assert isinstance(robot, SimRobot)
        with pytest.raises(StateError, match="already has a host"):
            await first.reopen()  # still plugged in
        async with Bus(first) as bus:
            at_open = await left_count(bus)
            await bus.request(wheel_command(300, 300), expect_reply=False)
            await asyncio.sleep(0.5)
            await bus.request(wheel_command(0, 0), expect_reply=False)
            await asyncio.sleep(1.0)
            moved = await left_count(bus)
        again = await first.reopen()
        assert again is not first
        assert again.simulated is robot
        async with Bus(again) as bus:
            return at_open, moved, await left_count(bus)

    at_open, moved, after = run_virtual(main())
    assert at_open == 5000
    assert moved > 5000 + 1000
    assert after == moved


async def test_an_in_memory_pipe_cannot_reopen_and_says_so() -> None:
    host, device = MemoryTransport.pair("pipe")
    assert not host.can_reopen
    assert host.simulated is None
    with pytest.raises(StateError, match="cannot be reopened"):
        await host.reopen()
    await host.aclose()
    await device.aclose()


@contextmanager
def open_pty() -> Iterator[str]:
    """A pseudo-terminal's slave path (its master side held open meanwhile)."""
    master, slave = os.openpty()
    try:
        yield os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


async def test_a_serial_port_reopens_with_its_settings() -> None:
    with open_pty() as path:
        first = await SerialTransport.open(path, 57_600, low_latency=False)
        assert first.can_reopen
        assert first.simulated is None
        await first.aclose()
        again = await first.reopen()
        try:
            assert isinstance(again, SerialTransport)
            assert (again.port, again.baudrate) == (path, 57_600)
            assert not again.closed
            # Exclusive, as it was opened: a second opener is refused.
            with pytest.raises(TransportError, match=path):
                await SerialTransport.open(path)
        finally:
            await again.aclose()


@dataclass
class FakePort:
    device: str
    description: str = "FT230X Basic UART"
    vid: int | None = BUS_USB_ID[0]
    pid: int | None = BUS_USB_ID[1]
    serial_number: str | None = None


async def test_the_auto_port_is_looked_for_again_when_reopened(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Unplugged and plugged back, an adapter may come back under another name.
    real_exists = os.path.exists
    monkeypatch.setattr(os.path, "exists", lambda p: p != ROBOT_BUS_LINK and real_exists(p))
    with open_pty() as before, open_pty() as after:
        monkeypatch.setattr(serial_ports, "comports", lambda: [FakePort(before)])
        first = await open_transport("auto")
        assert isinstance(first, SerialTransport)
        assert first.port == before
        await first.aclose()
        monkeypatch.setattr(serial_ports, "comports", lambda: [FakePort(after)])
        again = await first.reopen()
        assert isinstance(again, SerialTransport)
        assert again.port == after
        await again.aclose()
