"""The Robot's async tests run on the simulator's virtual clock: their waits take no wall
time and what they time is exact (``@pytest.mark.real_time`` for the exceptions)."""

from __future__ import annotations

from _virtual_loops import virtual_unless_real_time as pytest_asyncio_loop_factories

__all__ = ["pytest_asyncio_loop_factories"]
