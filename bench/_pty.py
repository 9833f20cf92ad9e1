"""``ohmni sim --pty`` in its own process, for the benchmarks that drive it over a pty."""

from __future__ import annotations

import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def simulator_on_pty() -> Iterator[str]:
    """Start ``ohmni sim --pty``; yield the pty's path; stop it (SIGINT, then kill)."""
    server = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "sim", "--pty"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
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
