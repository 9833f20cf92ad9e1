"""A Robot on ``sim://`` served on a free loopback port.

The async tests run on the simulator's virtual clock: the daemon and its clients talk over
real loopback sockets, but their waits take no wall time and what they time is exact
(``@pytest.mark.real_time`` for the exceptions)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from _virtual_loops import virtual_unless_real_time as pytest_asyncio_loop_factories
from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer

__all__ = ["pytest_asyncio_loop_factories"]


@pytest.fixture
async def robot() -> AsyncIterator[Robot]:
    async with Robot.open("sim://") as opened:
        yield opened


@pytest.fixture
async def server(robot: Robot) -> AsyncIterator[RobotServer]:
    async with RobotServer(robot, port=0) as serving:
        yield serving
