"""``Robot.open(url)``: the daemon's robot takes the control lease with its first command,
never steals it, and keeps its plain reads fresh without asking the daemon per call."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import LeaseError
from ohmni_tb.robot import RemoteRobot
from ohmni_tb.robot.remote import STATS_REFRESH_S


def speed(robot: Robot) -> float:
    """The simulated body's forward speed, m/s (ground truth)."""
    left, right = robot.sim.wheel_speeds_mps()
    return float(left + right) / 2


async def until(condition: Callable[[], bool], timeout_s: float = 3.0) -> None:
    """Wait for ``condition()`` (the simulator's ground truth has no event to wait on)."""
    async with asyncio.timeout(timeout_s):
        while not condition():  # noqa: ASYNC110  # polled: ground truth, no event
            await asyncio.sleep(0.02)


async def test_the_first_command_takes_the_lease_and_nobody_steals_it(
    robot: Robot, server: RobotServer
) -> None:
    async with RemoteRobot.open(server.url) as first, RemoteRobot.open(server.url) as second:
        assert first.lease_holder is None
        first.drive(0.3, 0.0)
        await first.confirm()
        assert server.lease_holder is not None
        await until(lambda: second.lease_holder == server.lease_holder)
        # Another client drives: refused at once, naming it, and nothing sent.
        with pytest.raises(
            LeaseError, match=f"drive needs the control lease: {server.lease_holder}"
        ):
            second.drive(-0.3, 0.0)
        await until(lambda: speed(robot) > 0.2)
        second.stop()  # anyone may stop the robot
        await second.confirm()
        await until(lambda: speed(robot) == 0.0)
    # Closing gave the lease back: the next robot's first command takes it.
    await until(lambda: server.lease_holder is None)
    async with RemoteRobot.open(server.url) as third:
        third.drive(0.3, 0.0)
        await third.confirm()
        assert server.lease_holder is not None
        await until(lambda: speed(robot) > 0.1)
    await until(lambda: speed(robot) == 0.0)  # and closing it stopped the robot


@pytest.mark.real_time  # real clients' connects, accepts and timeouts on the wall clock
async def test_stats_are_a_copy_at_most_the_refresh_interval_old(
    robot: Robot, server: RobotServer
) -> None:
    async with Robot.open(server.url) as remote:
        first = remote.stats().streams["wheel_encoder"].samples
        assert remote.stats().streams["wheel_encoder"].samples == first  # no call per read
        await asyncio.sleep(STATS_REFRESH_S * 2.5)
        later = remote.stats().streams["wheel_encoder"].samples
        local = robot.stats().streams["wheel_encoder"].samples
        # Refreshed meanwhile: behind the Robot's own by at most one interval (50 Hz).
        assert later > first
        assert local - later <= 50 * STATS_REFRESH_S * 2
