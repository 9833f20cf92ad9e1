"""``ohmni serve`` in its own process, for the tests that use the daemon as users do."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import time


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def start_serving(*args: str) -> tuple[subprocess.Popen[bytes], str]:
    """``ohmni serve --port sim:// ARGS`` in its own process, and the URL it printed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "serve", "--port", "sim://", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None
    deadline = time.monotonic() + 30
    line = b""
    while not line.endswith(b"\n"):
        ready, _, _ = select.select([proc.stdout], [], [], deadline - time.monotonic())
        assert ready, "ohmni serve printed no address"
        chunk = os.read(proc.stdout.fileno(), 1)
        if not chunk:
            _, err = proc.communicate(timeout=10)
            raise AssertionError(f"ohmni serve ended early: {err.decode()}")
        line += chunk
    return proc, line.decode().strip()


def stop_serving(proc: subprocess.Popen[bytes]) -> str:
    """SIGINT, then what it logged; a daemon that shut down cleanly exits 0."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err.decode()  # a requested stop, not an interruption
    return err.decode()
