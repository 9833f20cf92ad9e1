"""A Robot on ``sim://`` served on a free loopback port, in real asyncio."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer


@pytest.fixture
async def robot() -> AsyncIterator[Robot]:
    async with Robot.open("sim://") as opened:
        yield opened


@pytest.fixture
async def server(robot: Robot) -> AsyncIterator[RobotServer]:
    async with RobotServer(robot, port=0) as serving:
        yield serving
