"""``ohmni odom`` against the simulator: lines, rates, JSON lines, Ctrl-C, and reset."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import re
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from typing import Any

import pytest

from ohmni_tb.cli import common
from ohmni_tb.cli import odom as odom_cli
from ohmni_tb.robot import Robot

from ._helpers import Opened, invoke, spy_on_ports, words

SIM = ["--port", "sim://"]
KEYS = {"t_s", "x_m", "y_m", "yaw_rad", "linear_mps", "angular_radps"}
LINE = re.compile(
    r"^t +\d+\.\d{3} s  x +[+-]\d+\.\d{3} m  y +[+-]\d+\.\d{3} m  "
    r"yaw [+-]\d\.\d{4} rad \( *[+-]\d+\.\d{2}°\)  linear [+-]\d\.\d{3} m/s  "
    r"angular +[+-]\d\.\d{4} rad/s$"
)


@pytest.fixture
def opened(monkeypatch: pytest.MonkeyPatch) -> Opened:
    return spy_on_ports(monkeypatch)


def json_lines(*args: str) -> list[dict[str, Any]]:
    result = invoke("odom", *args, "--json")
    assert result.code == 0, result.out
    return [json.loads(line) for line in result.stdout.splitlines()]


@pytest.mark.usefixtures("virtual_time")
def test_count_prints_that_many_json_lines_at_the_rate() -> None:
    rows = json_lines(*SIM, "--count", "5", "--rate", "10")
    assert len(rows) == 5
    assert all(set(row) == KEYS for row in rows)
    assert rows[0]["t_s"] == 0.0
    gaps = [b["t_s"] - a["t_s"] for a, b in itertools.pairwise(rows)]
    assert all(0.08 <= gap <= 0.12 for gap in gaps), gaps
    # Standing still at the origin.
    assert {(row["x_m"], row["y_m"], row["yaw_rad"]) for row in rows} == {(0.0, 0.0, 0.0)}


@pytest.mark.usefixtures("virtual_time")
def test_text_lines() -> None:
    result = invoke("odom", *SIM, "--count", "3")
    assert result.code == 0, result.out
    lines = result.stdout.splitlines()
    assert len(lines) == 3
    for line in lines:
        assert LINE.match(line), line


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize(("rate", "expected"), [("50", 25), ("30", 15), ("4", 2)])
def test_duration_at_a_rate(rate: str, expected: int) -> None:
    rows = json_lines(*SIM, "--rate", rate, "--duration", "0.5")
    # The first line comes with the first sample; the stream's first moments are lost
    # to opening, so one or two lines may be missing, never more than one extra.
    assert expected - 3 <= len(rows) <= expected + 1, [row["t_s"] for row in rows]
    gaps = [b["t_s"] - a["t_s"] for a, b in itertools.pairwise(rows)]
    assert sum(gaps) / len(gaps) == pytest.approx(1 / float(rate), rel=0.15)


@pytest.mark.usefixtures("virtual_time")
def test_count_and_duration_together_stop_at_whichever_comes_first() -> None:
    assert len(json_lines(*SIM, "--count", "3", "--duration", "60")) == 3
    rows = json_lines(*SIM, "--count", "1000", "--duration", "0.3", "--rate", "50")
    assert 10 <= len(rows) <= 16


@pytest.fixture
def driving(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Drive the robot in an arc while the command streams; record the truth at the end."""
    seen: dict[str, Any] = {}
    real = common.open_robot

    @contextlib.asynccontextmanager
    async def open_and_drive(port: str, **overrides: Any) -> AsyncIterator[Robot]:
        seen["overrides"] = overrides
        async with real(port, **overrides) as robot:

            async def teleop() -> None:
                while True:
                    robot.drive(0.3, 0.5)
                    await asyncio.sleep(0.05)

            task = asyncio.create_task(teleop())
            try:
                yield robot
            finally:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
                pose = robot.sim.pose
                seen["truth"] = (pose.x, pose.y, pose.yaw)

    monkeypatch.setattr(odom_cli, "open_robot", open_and_drive)
    return seen


@pytest.mark.usefixtures("virtual_time")
def test_the_lines_follow_the_robot(driving: dict[str, Any]) -> None:
    rows = json_lines(*SIM, "--rate", "50", "--duration", "1.5")
    last = rows[-1]
    x, y, yaw = driving["truth"]
    assert last["x_m"] > 0.15
    assert last["linear_mps"] == pytest.approx(0.3, abs=0.05)
    assert last["angular_radps"] == pytest.approx(0.5, abs=0.1)
    # The last line and the simulator's true pose a moment later agree.
    assert (last["x_m"], last["y_m"]) == pytest.approx((x, y), abs=0.03)
    assert last["yaw_rad"] == pytest.approx(yaw, abs=0.05)
    # A read-only command leaves the neck as it is when it exits.
    # Read-only: the neck stays as it is; and no daemon here, so the port is opened.
    assert driving["overrides"] == {"on_exit_neck": "keep", "via": None}


def test_ctrl_c_exits_cleanly() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "odom", *SIM, "--json", "--rate", "20"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        first = [proc.stdout.readline() for _ in range(3)]
        proc.send_signal(signal.SIGINT)
        rest, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert err == ""
    for line in [*first, *rest.splitlines()]:
        assert set(json.loads(line)) == KEYS


def test_a_reader_that_stops_reading_ends_it_quietly() -> None:
    # `ohmni odom | head -2`
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "odom", *SIM, "--json", "--rate", "50"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        assert proc.stderr is not None
        lines = [proc.stdout.readline() for _ in range(2)]
        proc.stdout.close()
        proc.wait(timeout=15)
        err = proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stderr is not None:
            proc.stderr.close()
    assert (proc.returncode, err) == (0, "")
    assert all(set(json.loads(line)) == KEYS for line in lines)


@pytest.mark.usefixtures("virtual_time")
def test_no_drive_boards_is_one_error_line() -> None:
    result = invoke("odom", "--port", "sim://?silent=0,1", "--count", "1")
    assert result.code == 1, result.out
    assert result.out.strip().splitlines() == [
        "error: no wheel_odom sample within 2 s: do the drive boards (ids 0 and 1) answer? "
        "(`ohmni info`)"
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--rate", "60"], "--rate=60.0 is out of range: allowed 0.1..50 Hz"),
        (["--rate", "nan"], "--rate=nan is out of range"),
        (["--rate", "0"], "--rate=0.0 is out of range"),
        (["--duration", "inf"], "--duration=inf is out of range: allowed >0..604800 s"),
        (["--duration", "0"], "--duration=0.0 is out of range"),
        (["--count", "0"], "--count=0 is out of range: allowed 1..1000000000"),
        (["--count", "1e3"], "--count must be an integer"),
        (["reset", "--yaw", "7"], "--yaw=7.0 is out of range: allowed -6.2832..6.2832 rad"),
        (["reset", "--x", "inf"], "--x=inf is out of range: allowed -10000..10000 m"),
        (["reset", "--y", "-1e300"], "--y=-1e+300 is out of range"),
    ],
)
def test_bad_arguments_are_refused_before_the_port_opens(
    opened: Opened, args: list[str], message: str
) -> None:
    result = invoke("odom", *args, *SIM)
    assert result.code == 2, result.out
    assert message in words(result.out)
    assert opened.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_reset_sets_and_prints_the_pose() -> None:
    result = invoke("odom", "reset", "--x", "1", "--y", "-0.5", "--yaw", "1.5", *SIM, "--json")
    assert result.code == 0, result.out
    pose = json.loads(result.stdout)
    assert set(pose) == KEYS - {"t_s"}
    assert (pose["x_m"], pose["y_m"], pose["yaw_rad"]) == pytest.approx((1.0, -0.5, 1.5))
    result = invoke("odom", *SIM, "reset", "--yaw", "-1")  # the group's --port works too
    assert result.code == 0, result.out
    text = words(result.out)
    assert "odometry reset: x +0.000 m y +0.000 m yaw -1.0000 rad (-57.30°)" in text
    assert "the next ohmni command starts at the origin" in text
    # Its own process only: the next command starts at the origin again.
    (row,) = json_lines(*SIM, "--count", "1")
    assert (row["x_m"], row["y_m"], row["yaw_rad"]) == (0.0, 0.0, 0.0)


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize("option", [("--count", "5"), ("--json",), ("--rate", "20")])
def test_streaming_options_before_reset_are_refused_not_ignored(option: tuple[str, ...]) -> None:
    result = invoke("odom", *option, "reset", "--port", "sim://")
    assert result.code == 2
    assert option[0] in words(result.out)
    assert "apply to streaming" in words(result.out)
