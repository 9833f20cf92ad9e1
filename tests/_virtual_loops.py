"""The event loop for a test directory whose async tests run on the simulator's virtual
clock (:mod:`ohmni_tb.sim.clock`): its conftest takes this as its
``pytest_asyncio_loop_factories`` hook. A test there that needs the wall clock (a
pseudo-terminal, a subprocess, real clients' timing, load) says so with
``@pytest.mark.real_time``."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping

import pytest

from ohmni_tb.sim.clock import VirtualClockLoop


def virtual_unless_real_time(
    config: pytest.Config, item: pytest.Item
) -> Mapping[str, Callable[[], asyncio.AbstractEventLoop]]:
    """The virtual clock's loop, or asyncio's own for a test marked ``real_time``."""
    if item.get_closest_marker("real_time") is not None:
        return {"real_time": asyncio.new_event_loop}
    return {"virtual_time": VirtualClockLoop}
