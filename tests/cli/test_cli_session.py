"""A user's shell session on one simulated robot: separate ``ohmni`` processes, one after
another, against ``ohmni sim --pty``, which keeps the robot between them."""

from __future__ import annotations

import json
import os
import re
import select
import subprocess
import sys
import time
from typing import Any

import pytest

from cli._helpers import can_open_pty, operator, sim_on_pty

pytestmark = pytest.mark.skipif(not can_open_pty(), reason="no pseudo-terminals here")

#: Starting a process (the interpreter, the Robot) on a loaded machine.
START_TIMEOUT_S = 30.0


def ohmni(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "COLUMNS": "200"}
    env.pop("OHMNI_PORT", None)
    return subprocess.run(
        [sys.executable, "-m", "ohmni_tb", *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
        check=False,
    )


def status(port: str) -> dict[str, Any]:
    done = ohmni("status", "--port", port, "--json")
    assert done.returncode == 0, done.stderr
    doc: dict[str, Any] = json.loads(done.stdout)
    return doc


def test_drive_then_status_shows_the_counts_moved_then_the_neck_stays() -> None:
    with sim_on_pty() as (port, _proc):
        before = status(port)["wheels"]
        drove = ohmni("drive", "--port", port, "--yes", "--distance", "0.3", "--json")
        assert drove.returncode == 0, drove.stderr
        went = json.loads(drove.stdout)
        after = status(port)["wheels"]
        # The boards kept their counts between processes: forward on both wheels (the
        # right board counts mirrored), by about the distance the drive measured.
        left = after["left_raw"] - before["left_raw"]
        right = after["right_raw"] - before["right_raw"]
        assert left > 0
        assert right < 0
        assert went["distance_m"] == pytest.approx(0.3, abs=0.02)

        moved = ohmni("neck", "up", "--port", port, "--yes", "--json")
        assert moved.returncode == 0, moved.stderr
        target = json.loads(moved.stdout)
        neck = status(port)["neck"]
        assert neck is not None
        # The neck stays where it was sent after the command exits.
        assert abs(neck["position_raw"] - target["target_raw"]) <= 5


def test_info_light_and_odom_on_the_same_simulated_robot() -> None:
    with sim_on_pty() as (port, _proc):
        info = ohmni("info", "--port", port, "--json")
        assert info.returncode == 0, info.stderr
        assert json.loads(info.stdout)["neck_kind"] == "herkulex"
        lit = ohmni("light", "20", "200", "100", "--port", port)
        assert lit.returncode == 0, lit.stderr
        lines = ohmni("odom", "--port", port, "--json", "--count", "3", "--rate", "20")
        assert lines.returncode == 0, lines.stderr
        rows = [json.loads(line) for line in lines.stdout.splitlines()]
        assert len(rows) == 3
        assert all(row["x_m"] == 0.0 for row in rows)  # standing: each process starts at 0


#: Long enough to unplug the cable for a second once the wheels turn, and plug it back.
DRIVE_3S = ("--linear", "0.2", "--duration", "3", "--json")
_POSE_X = re.compile(rb"pose x=(-?[\d.]+) m")


def true_x(proc: subprocess.Popen[bytes]) -> float:
    """How far the simulated robot truly went along x, in metres (its console's status)."""
    assert proc.stdin is not None
    assert proc.stderr is not None
    proc.stdin.write(b"status\n")
    proc.stdin.flush()
    deadline = time.monotonic() + START_TIMEOUT_S
    said = b""
    while (match := _POSE_X.search(said)) is None:
        ready, _, _ = select.select([proc.stderr], [], [], max(0.0, deadline - time.monotonic()))
        assert ready, f"the simulator did not answer status: {said!r}"
        chunk = os.read(proc.stderr.fileno(), 4096)
        assert chunk, f"the simulator ended: {said!r}"
        said += chunk
    return float(match[1])


def test_a_drive_through_an_unplugged_cable_reports_the_missing_counts() -> None:
    with sim_on_pty() as (port, proc):
        drive = subprocess.Popen(
            [sys.executable, "-m", "ohmni_tb", "drive", "--port", port, "--yes", *DRIVE_3S],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        # Unplugged once it drives (starting the process takes a second or more).
        deadline = time.monotonic() + START_TIMEOUT_S
        while true_x(proc) < 0.01:
            assert drive.poll() is None, drive.communicate()
            assert time.monotonic() < deadline, "the drive did not start"
            time.sleep(0.05)
        operator(proc, "unplug")
        time.sleep(1.0)
        operator(proc, "plug")
        out, err = drive.communicate(timeout=60)
        assert drive.returncode == 0, err
        result = json.loads(out)
        # The simulator went silent for 1 s: ~50 control cycles without counts.
        assert result["missed_counts"] >= 25
        assert result["link_losses"] == 0  # the port stayed open
