"""Handing the serial port to another program through the daemon, and taking it back.

The robot is ``ohmni sim --pty`` in its own process, so "another program" really opens
the same device after the daemon let go of it.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator

import pytest
from typer.testing import CliRunner

from cli._helpers import needs_pty, sim_on_pty
from ohmni_tb import Robot
from ohmni_tb.bus import Bus
from ohmni_tb.cli import app
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import LeaseError, StateError, TransportError
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import parse_count, read_count
from ohmni_tb.robot import RobotStateSample, SampleStream

from ._serving import free_port, start_serving, stop_serving


@pytest.fixture
def pty_path() -> Iterator[str]:
    with sim_on_pty() as (path, _proc):
        yield path


async def link_becomes(
    client: RobotClient,
    states: SampleStream[RobotStateSample],
    link: str,
    timeout_s: float = 5.0,
) -> RobotStateSample:
    """The first ``robot_state`` sample with ``link`` (samples before it are skipped)."""
    async with asyncio.timeout(timeout_s):
        async for state in states:
            if state.link.value == link:
                sample: RobotStateSample = state
                return sample
    raise AssertionError(f"the subscription ended before the link was {link}")


@pytest.mark.real_time  # a pseudo-terminal keeps real time
@needs_pty
async def test_a_driver_hands_the_port_to_another_program_and_takes_it_back(
    pty_path: str,
) -> None:
    async with (
        Robot.open(pty_path) as robot,
        RobotServer(robot, port=0) as server,
        RobotClient.connect(server.url) as driver,
        RobotClient.connect(server.url) as reader,
        reader.subscribe("robot_state", maxlen=256) as states,
    ):
        # Without the lease: refused, and the daemon keeps the port.
        with pytest.raises(LeaseError):
            await reader.release_port()
        with pytest.raises(TransportError):
            await Bus.open(pty_path)
        await driver.acquire()
        await driver.release_port()
        released = await link_becomes(reader, states, "released")
        assert "port released to another program" in (released.event or "")
        # Every client sees it; drive commands are refused by the daemon's Robot.
        driver.drive(0.2, 0.0)
        with pytest.raises(StateError, match="released to another program"):
            await driver.confirm()
        # The other program opens the very device and talks to the robot.
        async with await Bus.open(pty_path, timeout_s=1.0) as other:
            assert parse_count(await other.query(read_count(DeviceId.LEFT_DRIVE))) == 0
        await driver.reclaim_port()
        await link_becomes(reader, states, "connected")
        # The daemon's streams run again, and it holds the port again.
        before = robot.stats().streams["wheel_encoder"].samples
        await asyncio.sleep(1.0)
        assert robot.stats().streams["wheel_encoder"].samples - before >= 25
        with pytest.raises(TransportError):
            await Bus.open(pty_path)


async def test_a_timed_hand_off_comes_back_by_itself(robot: Robot, server: RobotServer) -> None:
    async with (
        RobotClient.connect(server.url) as driver,
        driver.subscribe("robot_state", maxlen=256) as states,
    ):
        await driver.acquire()
        await driver.release_port(0.5)
        released = await link_becomes(driver, states, "released")
        assert "for 0.5 s" in (released.event or "")
        back = await link_becomes(driver, states, "connected")
        assert back.stamp_s - released.stamp_s == pytest.approx(0.5, abs=0.3)


async def test_a_hand_off_out_of_range_is_refused_and_keeps_the_port(
    robot: Robot, server: RobotServer
) -> None:
    async with RobotClient.connect(server.url) as driver:
        await driver.acquire()
        with pytest.raises(ValueError, match=r"0\.1\.\.3600"):
            await driver.release_port(0.01)
        assert robot.state.link.value == "connected"


def test_ohmni_serve_handoff_and_reclaim_ask_the_running_daemon() -> None:
    listen = f"127.0.0.1:{free_port()}"
    proc, url = start_serving("--listen", listen)
    runner = CliRunner()

    def link() -> str:
        result = runner.invoke(app, ["status", "--json"], env={"OHMNI_DAEMON_URL": url})
        assert result.exit_code == 0, result.output
        value: str = json.loads(result.stdout)["link"]
        return value

    try:
        handed = runner.invoke(app, ["serve", "--handoff", "30", "--listen", listen])
        assert handed.exit_code == 0, handed.output
        assert f"the daemon at {url} released the port for 30 s" in handed.output
        assert link() == "released"
        bad = runner.invoke(
            app, ["serve", "--handoff", "0", "--listen", listen], env={"COLUMNS": "300"}
        )
        assert bad.exit_code == 2
        assert "allowed 0.1..3600 s" in bad.output
        taken = runner.invoke(app, ["serve", "--reclaim", "--listen", listen])
        assert taken.exit_code == 0, taken.output
        assert link() == "connected"
    finally:
        stop_serving(proc)
