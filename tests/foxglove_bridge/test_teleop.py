"""The Teleop panel's Twists through the daemon: coalesced (latest wins, at most the control
rate) and driven again after the daemon closed the connection — judged on the simulated
robot's odometry, with a daemon (``RobotServer``) in this process, in real time."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from urllib.parse import urlsplit

import pytest

from ohmni_tb import Robot
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import OutOfRangeError
from ohmni_tb.foxglove.teleop import DEFAULT_RATE_HZ, FoxgloveTeleop


@pytest.fixture
async def robot() -> AsyncIterator[Robot]:
    async with Robot.open("sim://") as opened:
        yield opened


def odom_x(robot: Robot) -> float:
    odom = robot.latest("wheel_odom")
    assert odom is not None
    return odom.x_m


async def hold_button(teleop: FoxgloveTeleop, linear: float, seconds: float) -> None:
    """As the panel does while a button is held: a Twist every 0.1 s."""
    for _ in range(round(seconds * 10)):
        teleop(linear, 0.0)
        await asyncio.sleep(0.1)


async def test_a_burst_of_twists_sends_the_latest_and_no_more_than_the_control_rate(
    robot: Robot,
) -> None:
    async with (
        RobotServer(robot, port=0) as server,
        RobotClient.connect(server.url) as client,
        FoxgloveTeleop(client) as teleop,
    ):
        for _ in range(499):
            teleop(0.0, 0.0)
        teleop(0.3, 0.0)  # the latest wins: the robot moves
        await asyncio.sleep(0.4)
        assert teleop.stats().coalesced >= 499 - 1
        assert odom_x(robot) > 0.01
        # A client publishing every millisecond for a second: at most the control rate.
        before = teleop.stats()
        loop = asyncio.get_running_loop()
        end = loop.time() + 1.0
        while loop.time() < end:
            teleop(0.3, 0.0)
            await asyncio.sleep(0.001)
        await asyncio.sleep(0.1)
        after = teleop.stats()
        assert after.sent - before.sent <= DEFAULT_RATE_HZ * 1.1 + 2
        assert after.received - before.received > after.sent - before.sent
        assert after.refused == 0


async def test_the_teleop_drives_again_after_the_daemon_closed_its_connection(
    robot: Robot,
) -> None:
    first = RobotServer(robot, port=0)
    await first.start()
    port = urlsplit(first.url).port
    assert port is not None
    try:
        async with (
            RobotClient.connect(first.url, reconnect=True) as client,
            FoxgloveTeleop(client) as teleop,
        ):
            await hold_button(teleop, 0.3, 1.0)
            assert odom_x(robot) > 0.1
            await first.aclose()  # the daemon goes away, and comes back on its address
            await hold_button(teleop, 0.3, 0.5)  # refused meanwhile, counted
            async with RobotServer(robot, port=port):
                for _ in range(100):
                    if client.connected:
                        break
                    await asyncio.sleep(0.05)
                assert client.connected
                start = odom_x(robot)
                await hold_button(teleop, 0.3, 1.5)
                assert odom_x(robot) - start > 0.2
                assert client.has_lease  # taken anew on the new connection
            assert teleop.stats().refused > 0
    finally:
        await first.aclose()


def test_a_rate_beyond_what_the_daemon_takes_is_refused() -> None:
    with pytest.raises(OutOfRangeError, match=r"rate_hz=200 is out of range: allowed 1.0..50.0"):
        FoxgloveTeleop(None, rate_hz=200)  # type: ignore[arg-type]  # refused before use


async def test_a_pure_twist_reaches_its_speed_at_once_a_ramped_one_ramps(robot: Robot) -> None:
    assert robot.sim is not None

    async def speed_after(ramped: bool) -> float:
        for _ in range(3):
            teleop(0.5, 0.0, ramped)
            await asyncio.sleep(0.1)
        left, right = robot.sim.wheel_speeds_mps()
        robot.stop()
        await asyncio.sleep(1.5)  # ramped down, standing
        return float(left + right) / 2

    async with (
        RobotServer(robot, port=0) as server,
        RobotClient.connect(server.url) as client,
        FoxgloveTeleop(client) as teleop,
    ):
        ramped = await speed_after(True)
        pure = await speed_after(False)
    assert ramped < 0.2  # 0.5 m/s² by default
    assert pure > 0.4
