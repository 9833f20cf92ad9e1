"""``ohmni sim --pty`` in its own process, for the benchmarks that drive it over a pty."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager


def time_shared() -> None:
    """A child's ``preexec_fn``: normal time sharing, whatever class its parent runs in
    (a benchmark run with ``--daemon-rt`` measures its daemon there, not its helpers)."""
    if hasattr(os, "sched_setscheduler"):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def _scheduled(rt_priority: int) -> Callable[[], None]:
    if not rt_priority:
        return time_shared

    def realtime() -> None:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(rt_priority))

    return realtime


@contextmanager
def simulator_on_pty(rt_priority: int = 0) -> Iterator[str]:
    """Start ``ohmni sim --pty``; yield the pty's path; stop it (SIGINT, then kill).

    Time-shared, or under SCHED_FIFO at ``rt_priority``: it stands in for the robot's
    boards, whose processors no program on the host delays.
    """
    server = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "sim", "--pty"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        preexec_fn=_scheduled(rt_priority),  # noqa: PLW1509  # no threads in the benchmark yet
    )
    try:
        assert server.stdout is not None
        yield server.stdout.readline().decode().strip()
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(timeout=5)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
