"""A Robot reopens its port through its transport (``Transport.reopen``): one opened on a
serial port it was handed, not by URL, hands the port over and takes it back too."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator

import pytest

from cli._helpers import needs_pty, sim_on_pty
from ohmni_tb.bus import Bus
from ohmni_tb.errors import TransportError
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import parse_count, read_count
from ohmni_tb.robot import Link, LocalRobot, Robot
from ohmni_tb.transport import SerialTransport


@pytest.fixture
def pty_path() -> Iterator[str]:
    """``ohmni sim --pty`` in its own process (started outside the test's event loop)."""
    with sim_on_pty() as (path, _proc):
        yield path


def link(robot: Robot) -> Link:
    """The Robot's link now (a call, so a type checker does not narrow it)."""
    return robot.state.link


@needs_pty
@pytest.mark.real_time  # a pseudo-terminal keeps real time
async def test_a_robot_on_an_injected_serial_port_releases_and_reclaims_it(
    pty_path: str,
) -> None:
    transport = await SerialTransport.open(pty_path)
    async with LocalRobot.open(transport) as robot:
        await robot.release_port()
        assert link(robot) is Link.RELEASED
        # The port is free: another program opens it and talks to the robot.
        async with await Bus.open(pty_path, timeout_s=1.0) as other:
            assert parse_count(await other.query(read_count(DeviceId.LEFT_DRIVE))) == 0
        await robot.reclaim_port()
        assert link(robot) is Link.CONNECTED
        encoder = robot.subscribe("wheel_encoder", maxlen=1000)
        await asyncio.sleep(1.0)
        # Real time on a shared machine: the stream is back, not a rate to the sample.
        assert encoder.pending >= 25
        # The Robot holds the port again, on a transport of its own opening.
        assert robot.bus.transport is not transport
        with pytest.raises(TransportError):
            await Bus.open(pty_path)
