"""The commands go through ``ohmni serve`` when it runs, and open the port otherwise.

One daemon on ``sim://`` in its own process for the module; each command runs as a user
runs it. Through the daemon the commands share one Robot: what one command did (a drive,
an odometry reset, a neck move) the next one sees.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app

from ._serving import free_port, start_serving, stop_serving

runner = CliRunner()


@dataclass
class Result:
    code: int
    out: str  # stdout and stderr
    stdout: str


def invoke(*args: str) -> Result:
    """``ohmni ARGS`` as a user types it (wide: rich wraps nothing looked for)."""
    result = runner.invoke(app, list(args), env={"COLUMNS": "200"})
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return Result(result.exit_code, result.output, result.stdout)


@pytest.fixture(scope="module")
def daemon() -> Iterator[str]:
    proc, url = start_serving("--listen", f"127.0.0.1:{free_port()}")
    try:
        yield url
    finally:
        stop_serving(proc)


@pytest.fixture
def via(daemon: str, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setenv("OHMNI_DAEMON_URL", daemon)
    monkeypatch.delenv("OHMNI_PORT", raising=False)
    return daemon


def odometry(via: str) -> dict[str, float]:
    result = invoke("status", "--json")
    assert result.code == 0, result.out
    data = json.loads(result.stdout)
    assert data["port"] == via
    odom: dict[str, float] = data["odometry"]
    return odom


def test_status_goes_through_the_daemon_and_says_so(via: str) -> None:
    result = invoke("status")
    assert result.code == 0, result.out
    assert result.stdout.startswith(f"{via} · link connected")
    assert f"via the daemon at {via} (--direct: open the port)" in result.out
    assert "sim-core-1.0" in result.out


def test_a_drive_moves_the_daemons_robot_and_the_next_command_sees_it(via: str) -> None:
    before = odometry(via)
    result = invoke("drive", "--distance", "0.2", "--yes", "--json")
    assert result.code == 0, result.out
    drove = json.loads(result.stdout)
    assert drove["port"] == via
    assert drove["stop"]["confirmed"]
    # In real time on a machine busy with other tests a control tick can come a few tens
    # of milliseconds late; the goal's precision itself is tested in virtual time
    # (tests/robot_api/test_motion.py, tests/contract: by the simulator's truth).
    assert drove["goal"]["error_m"] == pytest.approx(0.0, abs=0.02)
    after = odometry(via)
    moved = ((after["x_m"] - before["x_m"]) ** 2 + (after["y_m"] - before["y_m"]) ** 2) ** 0.5
    assert moved == pytest.approx(0.2, abs=0.01)


def test_odom_reset_resets_the_daemons_odometry_for_every_client(via: str) -> None:
    result = invoke("odom", "reset", "--x", "1.5", "--y", "-0.5")
    assert result.code == 0, result.out
    assert "the daemon's odometry, for every client" in result.stdout
    odom = odometry(via)
    assert (odom["x_m"], odom["y_m"]) == pytest.approx((1.5, -0.5), abs=1e-3)
    lines = invoke("odom", "--count", "2", "--json")
    assert lines.code == 0, lines.out
    first = json.loads(lines.stdout.splitlines()[0])
    assert first["x_m"] == pytest.approx(1.5, abs=1e-3)


def test_odom_set_sets_the_daemons_odometry_for_every_client(via: str) -> None:
    result = invoke("odom", "set", "-2.5", "0.75", "-1")
    assert result.code == 0, result.out
    assert "odometry set: x -2.500 m  y +0.750 m  yaw -1.0000 rad" in result.stdout
    assert "the daemon's odometry, for every client" in result.stdout
    odom = odometry(via)
    assert (odom["x_m"], odom["y_m"], odom["yaw_rad"]) == pytest.approx((-2.5, 0.75, -1), abs=1e-3)


def test_diag_goes_through_the_daemon(via: str) -> None:
    result = invoke("diag", "--json")
    assert result.code == 0, result.out
    assert f"via the daemon at {via}" in result.out
    health = json.loads(result.stdout)
    assert health["port"] == via
    # A healthy simulator; WARN at most (a machine busy with other work may delay a
    # reply past the latency threshold, which the link's entry then reports).
    assert health["level"] in {"ok", "warn"}, health
    assert [e["name"] for e in health["entries"]][-1] == "link"


def test_a_neck_move_stays_for_the_next_command(via: str) -> None:
    moved = invoke("neck", "--raw", "420", "--playtime", "0.3", "--yes", "--json")
    assert moved.code == 0, moved.out
    assert json.loads(moved.stdout)["position_raw"] == pytest.approx(420, abs=3)
    read = invoke("neck", "--json")
    assert read.code == 0, read.out
    assert json.loads(read.stdout)["position_raw"] == pytest.approx(420, abs=3)


def test_info_and_light_go_through_the_daemon(via: str) -> None:
    info = invoke("info", "--json")
    assert info.code == 0, info.out
    assert json.loads(info.stdout)["port"] == via
    light = invoke("light", "10", "20", "30")
    assert light.code == 0, light.out


def test_a_command_that_moves_is_refused_while_another_client_drives(via: str) -> None:
    # Another person at the robot holds the lease of ohmni drive's source here (local).
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import asyncio, sys\n"
            "from ohmni_tb.client import RobotClient\n"
            "async def main():\n"
            f"    async with RobotClient.connect({via!r}, source='local') as client:\n"
            "        await client.acquire()\n"
            "        print(client.peer, flush=True)\n"
            "        sys.stdin.readline()\n"
            "asyncio.run(main())\n",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None
        peer = holder.stdout.readline().strip()
        assert peer.startswith("127.0.0.1:")
        refused: Result = invoke("drive", "--linear", "0.2", "--duration", "0.3", "--yes")
        assert refused.code == 1
        assert f"another client of the daemon at {via} drives the robot ({peer})" in refused.out
        assert "control lease" in refused.out
        # Reading needs no lease.
        assert invoke("status").code == 0
    finally:
        holder.communicate(timeout=10)  # its stdin closed: it leaves
    # Released when it left: the command may drive now.
    again = invoke("drive", "--linear", "0.2", "--duration", "0.3", "--yes")
    assert again.code == 0, again.out


def test_a_drive_at_the_robot_overrides_a_script_and_the_script_is_told(via: str) -> None:
    script = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import asyncio, sys\n"
            "from ohmni_tb import Robot\n"
            "from ohmni_tb.errors import SourceOverriddenError\n"
            "async def main():\n"
            f"    async with Robot.open({via!r}) as robot:\n"  # a script: autonomy
            # The test before may have driven as local a moment ago: its turn first.
            "        for _ in range(40):\n"
            "            try:\n"
            "                robot.drive(-0.1, 0.0)\n"
            "                await robot.confirm()\n"
            "                break\n"
            "            except SourceOverriddenError:\n"
            "                await asyncio.sleep(0.05)\n"
            "        print('driving', flush=True)\n"
            "        refused = set()\n"
            "        for _ in range(60):\n"
            "            try:\n"
            "                robot.drive(-0.1, 0.0)\n"
            "                await robot.confirm()\n"
            "            except SourceOverriddenError as exc:\n"
            "                refused.add(exc.active)\n"
            "            await asyncio.sleep(0.05)\n"
            "        print(sorted(refused), flush=True)\n"
            "asyncio.run(main())\n",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert script.stdout is not None
        assert script.stdout.readline().strip() == "driving"
        # The person's drive, on the robot's computer: local, above the script.
        result = invoke("drive", "--linear", "0.2", "--duration", "0.5", "--yes", "--json")
        assert result.code == 0, result.out
        drove = json.loads(result.stdout)
        assert drove["source"] == "local"
        assert drove["distance_m"] > 0.03  # forward: the script's backward commands refused
        told, _ = script.communicate(timeout=20)
    finally:
        if script.poll() is None:
            script.kill()
    assert told.strip() == "['local']"


def test_direct_opens_the_port_even_while_the_daemon_runs(via: str) -> None:
    # No adapter on this machine and no --port: opening the port itself fails, which
    # shows it did not go through the daemon.
    result = invoke("status", "--direct")
    assert result.code == 1
    assert "no Ohmni bus adapter found" in result.out
    assert "via the daemon" not in result.out
    # --port names what to open: the command opens it.
    sim = invoke("status", "--json", "--port", "sim://")
    assert sim.code == 0, sim.out
    assert json.loads(sim.stdout)["port"] == "sim://"


def test_without_a_daemon_the_commands_open_the_port(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OHMNI_DAEMON_URL", f"ws://127.0.0.1:{free_port()}")  # nobody there
    monkeypatch.setenv("OHMNI_PORT", "sim://")
    result = invoke("status", "--json")
    assert result.code == 0, result.out
    assert json.loads(result.stdout)["port"] == "sim://"
    assert "via the daemon" not in result.out
    assert os.environ["OHMNI_DAEMON_URL"] != "off"


def test_the_commands_look_for_the_daemon_where_it_listens_by_default() -> None:
    from ohmni_tb.cli import common
    from ohmni_tb.client import DEFAULT_URL
    from ohmni_tb.daemon.server import DEFAULT_HOST, DEFAULT_PORT

    assert common._DEFAULT_DAEMON_URL == DEFAULT_URL == f"ws://{DEFAULT_HOST}:{DEFAULT_PORT}"


def test_pid_and_stream_commands_change_the_daemons_robot_for_the_next_command(via: str) -> None:
    result = invoke("pid", "set", "--kd", "2", "--wheel", "right", "--json")
    assert result.code == 0, result.out
    assert json.loads(result.stdout)["via_daemon"] is True
    result = invoke("pid", "disable", "--wheel", "left")
    assert result.code == 0, result.out
    assert "for every client, until the daemon stops" in " ".join(result.out.split())
    try:
        state = json.loads(invoke("pid", "get", "--json").stdout)["wheels"]
        assert (state["left"]["kd"], state["right"]["kd"]) == (0.0, 2.0)
        assert (state["left"]["enabled"], state["right"]["enabled"]) == (False, True)
        refused = invoke("drive", "--linear", "0.2", "--duration", "0.3", "--yes")
        assert refused.code == 1
        assert "the left wheel's controller is off" in refused.out
        pwm = invoke("drive", "--pwm", "200", "200", "--duration", "0.3", "--yes", "--json")
        assert pwm.code == 0, pwm.out
        assert json.loads(pwm.stdout)["distance_m"] > 0.005
    finally:
        assert invoke("pid", "enable").code == 0
        assert invoke("pid", "set", "--kd", "0", "--wheel", "right").code == 0
    result = invoke("stream", "disable", "tbcore_status", "--json")
    assert result.code == 0, result.out
    try:
        assert "tbcore_status" not in json.loads(result.stdout)["scheduled"]
        status = json.loads(invoke("status", "--json").stdout)
        assert status["bus"]["streams"]["tbcore_status"]["enabled"] is False
    finally:
        assert invoke("stream", "enable", "tbcore_status").code == 0
