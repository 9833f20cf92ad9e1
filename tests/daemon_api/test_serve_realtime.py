"""``ohmni serve --rt-priority N``: the daemon's event loop under SCHED_FIFO, or one clear
refusal before anything is opened."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from daemon_api._serving import free_port, start_serving, stop_serving

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="SCHED_FIFO is Linux's")


@pytest.mark.parametrize("priority", ["0", "100", "-3"])
def test_a_priority_outside_1_to_99_is_a_usage_error(priority: str) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "ohmni_tb", "serve", "--port", "sim://", "--rt-priority", priority],
        env={**os.environ, "COLUMNS": "200"},  # the message on one line
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 2
    assert f"{priority} is not in 1..99" in done.stderr
    assert done.stdout == ""  # it never served


def _policy_and_priority(pid: int) -> tuple[int, int]:
    # /proc/PID/stat: after the command name in parentheses, field 40 is rt_priority
    # and field 41 the policy (proc(5)); counted from the closing parenthesis.
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return int(fields[38]), int(fields[37])


def test_the_daemon_serves_under_sched_fifo_or_says_what_it_needs() -> None:
    listen = f"127.0.0.1:{free_port()}"
    try:
        proc, url = start_serving("--listen", listen, "--rt-priority", "7")
    except AssertionError as exc:  # ended early: this process may not use SCHED_FIFO
        message = str(exc)
        assert "real-time priority 7 refused" in message
        assert "CAP_SYS_NICE" in message
        return
    try:
        assert url.startswith("ws://127.0.0.1:")
        policy, priority = _policy_and_priority(proc.pid)
        assert (policy, priority) == (1, 7)  # SCHED_FIFO at 7: the loop's (main) thread
    finally:
        stop_serving(proc)
