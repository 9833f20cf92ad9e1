"""The Robot's async tests run on the simulator's virtual clock (:mod:`ohmni_tb.sim.clock`):
their waits take no wall time and what they time is exact. A test that needs the wall
clock (a pseudo-terminal, a subprocess, a thread that keeps real time) says so with
``@pytest.mark.real_time``."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping

import pytest

from ohmni_tb.sim.clock import VirtualClockLoop


def pytest_asyncio_loop_factories(
    config: pytest.Config, item: pytest.Item
) -> Mapping[str, Callable[[], asyncio.AbstractEventLoop]]:
    if item.get_closest_marker("real_time") is not None:
        return {"real_time": asyncio.new_event_loop}
    return {"virtual_time": VirtualClockLoop}
