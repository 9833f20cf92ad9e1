"""One contract, two robots: every test here runs against ``Robot.open("sim://")`` (this
process runs the bus) and against ``Robot.open(url)`` of a daemon serving a simulated
robot in this process (the daemon's own robot is a local one on ``sim://``).

Both run on virtual time (:func:`ohmni_tb.sim.clock.run_virtual`): the simulator's
clock jumps when nothing is due, so seconds of driving take milliseconds; the daemon's
WebSocket goes through real loopback sockets, which the loop keeps polling.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from typing import Any, TypeVar

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.robot import LocalRobot
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.robot import SimRobot

T = TypeVar("T")

#: The two ways to the same robot.
KINDS = ("local", "remote")


@asynccontextmanager
async def opened(kind: str, **settings: Any) -> AsyncIterator[tuple[Robot, SimRobot]]:
    """A simulated robot through ``kind``, and the simulator behind it (its truth)."""
    if kind == "local":
        async with Robot.open("sim://", **settings) as robot:
            yield robot, robot.sim
        return
    async with (
        LocalRobot.open("sim://", **settings) as served,
        RobotServer(served, port=0) as server,
        Robot.open(server.url) as robot,
    ):
        assert robot.sim is None  # the simulator runs in the daemon
        yield robot, served.sim


@pytest.fixture(params=KINDS)
def kind(request: pytest.FixtureRequest) -> str:
    """``local`` or ``remote``."""
    value: str = request.param
    return value


def run(kind: str, test: Callable[[Robot, SimRobot], Awaitable[T]], **settings: Any) -> T:
    """Run ``test(robot, truth)`` on virtual time with a robot opened as ``kind``."""

    async def main() -> T:
        async with opened(kind, **settings) as (robot, truth):
            return await test(robot, truth)

    return run_virtual(main())
