"""``ohmni status`` against the simulator: what a user sees, the JSON schema, --watch."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest
from rich.console import Console

from ohmni_tb.cli import status as status_cli
from ohmni_tb.cli.common import open_robot
from ohmni_tb.cli.status import FRAME_S
from ohmni_tb.herkulex import TorqueControl, parse_reply, ram_read, ram_write
from ohmni_tb.robot import LocalRobot, Robot
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import SimServo

from ._helpers import invoke, needs_pty, operator, sim_on_pty, spy_on_ports, words

SIM = ["--port", "sim://"]

#: The documented schema (docs/cli.md): every key of every object, none more.
TOP_KEYS = {
    "schema",
    "port",
    "uptime_s",
    "link",
    "estopped",
    "watchdog_tripped",
    "faults",
    "present",
    "absent",
    "neck_kind",
    "battery",
    "wheels",
    "odometry",
    "neck",
    "servos",
    "firmware",
    "bus",
    "diagnostics",
}
BATTERY_KEYS = {
    "cell_v",
    "pack_v",
    "current_a",
    "percent",
    "docked",
    "charging",
    "fet_status",
    "age_s",
}
WHEEL_KEYS = {
    "left_ticks",
    "right_ticks",
    "left_raw",
    "right_raw",
    "left_m",
    "right_m",
    "left_mps",
    "right_mps",
    "age_s",
}
ODOM_KEYS = {
    "x_m",
    "y_m",
    "yaw_rad",
    "yaw_deg",
    "heading_rad",
    "linear_mps",
    "angular_radps",
    "age_s",
}
SERVO_KEYS = {
    "sid",
    "model",
    "position_raw",
    "angle_rad",
    "angle_deg",
    "temperature_raw",
    "voltage_v",
    "torque",
    "status_error",
    "status_detail",
    "moving",
    "age_s",
}
NECK_KEYS = SERVO_KEYS | {"kind", "stalled"}
FIRMWARE_KEYS = {"left_drive", "right_drive", "core", "worm_neck"}
BUS_KEYS = {
    "wire_utilisation",
    "budget_share",
    "transactions_per_s",
    "timeouts",
    "deadline_misses",
    "rejected_samples",
    "link_losses",
    "reconnects",
    "streams",
}
DIAGNOSTICS_KEYS = {"level", "event", "entries"}
ENTRY_KEYS = {"name", "sid", "level", "message", "values"}
STREAM_KEYS = {
    "enabled",
    "requested_hz",
    "achieved_hz",
    "samples",
    "missed",
    "skipped",
    "dropped",
    "jitter_p50_ms",
    "jitter_p99_ms",
}


def status_json(port: str = "sim://") -> dict[str, Any]:
    result = invoke("status", "--port", port, "--json")
    assert result.code == 0, result.out
    data: dict[str, Any] = json.loads(result.stdout)
    return data


def check_schema(data: dict[str, Any]) -> None:
    assert set(data) == TOP_KEYS
    assert data["schema"] == 1
    for key, keys in (("battery", BATTERY_KEYS), ("wheels", WHEEL_KEYS), ("odometry", ODOM_KEYS)):
        assert data[key] is None or set(data[key]) == keys, key
    assert data["neck"] is None or set(data["neck"]) == NECK_KEYS
    assert set(data["servos"]) == {"ext1", "ext2"}
    for servo in data["servos"].values():
        assert servo is None or set(servo) == SERVO_KEYS
    assert set(data["firmware"]) == FIRMWARE_KEYS
    assert set(data["bus"]) == BUS_KEYS
    assert set(data["bus"]["streams"]) == {
        "wheel_encoder",
        "wheel_odom",
        "tbcore_status",
        "servo_neck",
        "servo_ext1",
        "servo_ext2",
        "new_neck",
        "robot_state",
        "pid_debug",
        "diagnostics",
    }
    for stream in data["bus"]["streams"].values():
        assert set(stream) == STREAM_KEYS
    health = data["diagnostics"]
    assert health is None or set(health) == DIAGNOSTICS_KEYS
    for entry in [] if health is None else health["entries"]:
        assert set(entry) == ENTRY_KEYS


# -- one status -----------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_json_is_the_documented_schema_with_the_simulators_values() -> None:
    data = status_json()
    check_schema(data)
    assert data["port"] == "sim://"
    assert data["link"] == "connected"
    assert data["faults"] == []
    assert data["present"] == [0, 1, 3, 11, 12, 20]
    assert data["absent"] == []
    # The simulated robot stands at the origin, off the dock, at 80 % charge.
    battery = data["battery"]
    assert len(battery["cell_v"]) == 5
    assert battery["pack_v"] == pytest.approx(sum(battery["cell_v"]), abs=0.01)
    assert 14.0 < battery["pack_v"] < 18.5
    assert battery["percent"] == 80
    assert battery["docked"] is False
    assert battery["charging"] is False
    assert battery["current_a"] < 0  # the electronics draw from the pack
    assert data["wheels"]["left_ticks"] == data["wheels"]["right_ticks"] == 0
    assert data["odometry"]["x_m"] == data["odometry"]["yaw_rad"] == 0.0
    neck = data["neck"]
    assert data["neck_kind"] == neck["kind"] == "herkulex"
    assert (neck["sid"], neck["model"], neck["position_raw"]) == (3, "DRS_0101", 512)
    assert neck["angle_rad"] == neck["angle_deg"] == 0.0
    assert neck["torque"] == "free"
    assert neck["status_error"] == []
    assert neck["stalled"] is None
    assert [data["servos"][role]["sid"] for role in ("ext1", "ext2")] == [11, 12]
    assert data["firmware"] == {
        "left_drive": "sim-drive-1.0",
        "right_drive": "sim-drive-1.0",
        "core": "sim-core-1.0",
        "worm_neck": None,
    }
    streams = data["bus"]["streams"]
    assert streams["wheel_encoder"]["requested_hz"] == 50.0
    assert streams["servo_neck"]["requested_hz"] == 30.0
    assert streams["tbcore_status"]["requested_hz"] == 10.0
    # The single status waits until every stream has samples to measure a rate on.
    for name in ("wheel_encoder", "tbcore_status", "servo_neck", "servo_ext1", "servo_ext2"):
        assert streams[name]["samples"] >= 2, name
        assert streams[name]["achieved_hz"] > 0, name
    assert not streams["new_neck"]["enabled"]
    assert 0 < data["bus"]["wire_utilisation"] < 1
    assert data["bus"]["timeouts"] == 0


@pytest.mark.usefixtures("virtual_time")
def test_docked_robot_is_docked_and_charging() -> None:
    battery = status_json("sim://?docked=1")["battery"]
    assert battery["docked"] is True
    assert battery["charging"] is True
    assert battery["current_a"] > 0


@pytest.mark.usefixtures("virtual_time")
def test_worm_neck() -> None:
    data = status_json("sim://?neck=worm")
    check_schema(data)
    neck = data["neck"]
    assert data["neck_kind"] == neck["kind"] == "worm"
    assert (neck["sid"], neck["position_raw"], neck["stalled"]) == (4, 0, False)
    assert neck["angle_rad"] is None
    assert neck["torque"] is None
    assert data["firmware"]["worm_neck"] == "sim-worm-1.0"
    assert data["bus"]["streams"]["new_neck"]["samples"] >= 1
    assert not data["bus"]["streams"]["servo_neck"]["enabled"]


@pytest.mark.usefixtures("virtual_time")
def test_silent_devices_are_absent_and_null() -> None:
    data = status_json("sim://?silent=11,20")
    check_schema(data)
    assert data["servos"]["ext1"] is None
    assert data["servos"]["ext2"]["sid"] == 12
    assert data["battery"] is None
    assert data["firmware"]["core"] is None
    assert data["absent"] == [11, 20]
    assert "ext1 absent" in screen(data, width=120)
    panels = screen(data, width=40)  # one panel a row
    assert "battery absent" in panels
    assert "core -" in panels  # no firmware tag


def screen(data: dict[str, Any], width: int) -> str:
    """The screen of a JSON snapshot at ``width`` columns, boxes removed."""
    console = Console(file=io.StringIO(), width=width, color_system=None)
    console.print(status_cli.render(data))
    text = console.file.getvalue()  # type: ignore[attr-defined]
    return words(re.sub("[─╭╮╰╯]", " ", text))


@pytest.mark.usefixtures("virtual_time")
def test_status_without_drive_boards_shows_the_rest() -> None:
    # The command to find out what is missing must work when the drive boards are.
    result = invoke("status", "--port", "sim://?silent=0,1", "--json")
    assert result.code == 0, result.out
    data = json.loads(result.stdout)
    assert data["absent"] == [0, 1]
    assert data["battery"] is not None
    assert result.out == result.stdout  # nothing on stderr


@pytest.mark.usefixtures("virtual_time")
def test_no_neck_at_all() -> None:
    data = status_json("sim://?silent=3")
    assert data["neck_kind"] == "none"
    assert data["neck"] is None
    assert "neck none answered" in screen(data, width=120)


@pytest.mark.usefixtures("virtual_time")
def test_the_values_are_the_simulated_robots(monkeypatch: pytest.MonkeyPatch) -> None:
    def prepare(sim: SimRobot) -> None:
        assert isinstance(sim.neck, SimServo)
        sim.neck.set_supply_voltage(8.2)
        sim.set_docked(True)

    opened = spy_on_ports(monkeypatch, prepare)
    data = status_json()
    assert opened.urls == ["sim://"]
    assert data["neck"]["voltage_v"] == pytest.approx(8.2, abs=0.08)  # 0.074 V a count
    assert data["servos"]["ext1"]["voltage_v"] == pytest.approx(7.4, abs=0.08)
    assert data["battery"]["docked"] is True
    cells = opened.sims[0].core.status().cell_mv
    assert data["battery"]["cell_v"] == pytest.approx([mv / 1000 for mv in cells], abs=0.005)


@pytest.mark.usefixtures("virtual_time")
def test_the_screen_shows_every_part() -> None:
    result = invoke("status", *SIM)
    assert result.code == 0, result.out
    text = words(result.out)
    for part in (
        "sim:// · link connected",
        "battery",
        "off the dock, not charging",
        "80 %",
        "wheels",
        "odometry",
        "firmware",
        "sim-core-1.0",
        "neck and servos",
        "neck 3 DRS_0101 512 +0.0° free 160 7.40 ok",
        "ext2 12 DRS_0101 512",
        "wheel_encoder 50.0",
        "tbcore_status 10.0",
        "transactions/s",
        "0 timeouts",
    ):
        assert part in text, part
    assert "robot_state" not in text  # not a bus stream


def torque_on(sim: SimRobot) -> None:
    """Turn the simulated neck's torque on, as a command before this one left it."""
    sim.neck.handle(ram_write(3, "torque_control", int(TorqueControl.ON)), sim.sync())


def neck_torque(sim: SimRobot) -> int:
    reply = sim.neck.handle(ram_read(3, "torque_control"), sim.sync())
    assert reply is not None
    return parse_reply(reply).data[-1]


@pytest.mark.usefixtures("virtual_time")
def test_the_neck_is_left_as_it_was(monkeypatch: pytest.MonkeyPatch) -> None:
    # A status reads: it does not free (or rest) the neck on its way out, as a Robot
    # closing with the default on_exit_neck=free would.
    opened = spy_on_ports(monkeypatch, torque_on)
    data = status_json()
    assert data["neck"]["torque"] == "on"
    assert data["neck"]["position_raw"] == 512
    assert neck_torque(opened.sims[0]) == TorqueControl.ON


def test_a_port_that_cannot_open_is_one_error_line() -> None:
    result = invoke("status", "--port", "/dev/no-such-ohmni-port")
    assert result.code == 1
    lines = [line for line in result.out.splitlines() if line.strip()]
    assert len(lines) == 1, result.out
    assert lines[0].startswith("error: ")
    assert "Traceback" not in result.out


@pytest.mark.usefixtures("virtual_time")
def test_a_bad_simulator_option_is_one_error_line() -> None:
    result = invoke("status", "--port", "sim://?neck=9999")
    assert result.code == 1
    assert result.out.startswith("error: "), result.out


@pytest.mark.usefixtures("virtual_time")
def test_help_has_an_example() -> None:
    result = invoke("status", "--help")
    assert result.code == 0
    assert "Example: ohmni status --port sim:// --watch" in result.out
    assert "--watch" in result.out


def test_ohmni_help_imports_neither_module() -> None:
    code = (
        "import sys\n"
        "from ohmni_tb.cli import app\n"
        "try:\n"
        "    app(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "mine = sorted(m for m in sys.modules if m.startswith('ohmni_tb.cli.'))\n"
        "heavy = sorted(m for m in ('ohmni_tb.robot', 'numpy', 'rich.live') if m in sys.modules)\n"
        "print('MODULES', mine, heavy)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    line = next(line for line in out.splitlines() if line.startswith("MODULES"))
    assert "ohmni_tb.cli.status" not in line
    assert "ohmni_tb.cli.robot_cmds" not in line
    assert line.endswith("[]"), line  # no Robot, numpy or rich.live


def test_status_help_loads_no_robot() -> None:
    code = (
        "import sys\n"
        "from ohmni_tb.cli import app\n"
        "try:\n"
        "    app(['status', '--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print('HEAVY', sorted(m for m in ('ohmni_tb.robot', 'numpy', 'rich.live') "
        "if m in sys.modules))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert "HEAVY []" in out


# -- --watch ----------------------------------------------------------------------------------


class Frames:
    """The frames' clock and wait, virtual: each wait moves the clock on by what was asked
    (and lets the Robot run a little in real time). Presses Ctrl-C (or raises SIGINT)
    after ``stop_after`` frames."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, stop_after: int, *, sigint: bool = False):
        self.stop_after = stop_after
        self.sigint = sigint
        self.now = 1000.0
        self.delays: list[float] = []
        monkeypatch.setattr(status_cli, "_clock", lambda: self.now)
        monkeypatch.setattr(status_cli, "_pause", self.pause)

    async def pause(self, delay_s: float) -> None:
        self.delays.append(delay_s)
        self.now += delay_s
        if len(self.delays) >= self.stop_after:
            if self.sigint:
                signal.raise_signal(signal.SIGINT)
            else:
                raise KeyboardInterrupt
        await asyncio.sleep(0.005)


@pytest.fixture
def robots(monkeypatch: pytest.MonkeyPatch) -> list[LocalRobot]:
    """Every Robot the status command opens."""
    opened: list[LocalRobot] = []
    real = open_robot

    @contextlib.asynccontextmanager
    async def spy(port: str, **overrides: Any) -> AsyncIterator[Robot]:
        async with real(port, **overrides) as robot:
            assert isinstance(robot, LocalRobot)  # the port, opened by the command
            opened.append(robot)
            yield robot

    monkeypatch.setattr(status_cli, "open_robot", spy)
    return opened


@pytest.mark.usefixtures("virtual_time")
def test_watch_redraws_at_10_hz_and_ctrl_c_ends_it_cleanly(
    monkeypatch: pytest.MonkeyPatch, robots: list[LocalRobot]
) -> None:
    frames = Frames(monkeypatch, stop_after=12)
    renders: list[Any] = []
    real_render = status_cli.render

    def counted(snap: Any) -> Any:
        renders.append(snap)
        return real_render(snap)

    monkeypatch.setattr(status_cli, "render", counted)
    result = invoke("status", *SIM, "--watch")
    assert result.code == 0, result.out
    assert "Traceback" not in result.out
    # One redraw per frame, each 100 ms of the frames' clock after the one before: 10
    # frames a second (>= 5), counted in virtual time whatever the host's speed.
    assert len(renders) == 12
    assert frames.delays == [pytest.approx(FRAME_S)] * 12
    assert len(renders) / sum(frames.delays) >= 5.0
    # The snapshots move on: uptime grows frame by frame.
    uptimes = [snap["uptime_s"] for snap in renders]
    assert uptimes == sorted(uptimes)
    assert uptimes[-1] > uptimes[0]
    # The last frame stays on the screen, and the Robot closed properly.
    assert "wheel_encoder" in result.out
    assert len(robots) == 1
    assert robots[0].closed
    assert robots[0].exit_error is None


@pytest.mark.usefixtures("virtual_time")
def test_watch_ends_cleanly_on_a_real_sigint(
    monkeypatch: pytest.MonkeyPatch, robots: list[LocalRobot]
) -> None:
    # SIGINT as Ctrl-C sends it: asyncio.run cancels the command's task.
    Frames(monkeypatch, stop_after=3, sigint=True)
    result = invoke("status", *SIM, "--watch")
    assert result.code == 0, result.out
    assert "Traceback" not in result.out
    assert robots[0].closed


@pytest.mark.usefixtures("virtual_time")
def test_watch_json_prints_one_object_per_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    Frames(monkeypatch, stop_after=4)
    result = invoke("status", *SIM, "--watch", "--json")
    assert result.code == 0, result.out
    lines = result.stdout.splitlines()
    assert len(lines) == 4
    for line in lines:
        check_schema(json.loads(line))


@pytest.mark.usefixtures("virtual_time")
def test_watch_ctrl_c_before_the_first_frame_exits_0(monkeypatch: pytest.MonkeyPatch) -> None:
    async def interrupted(robot: Any, not_before_s: float) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(status_cli, "_first_samples", interrupted)
    assert invoke("status", *SIM, "--watch").code == 0
    # Without --watch, Ctrl-C is the usual 130.
    assert invoke("status", *SIM).code == 130


@needs_pty
def test_watch_on_a_terminal_until_ctrl_c() -> None:
    """The real thing: a terminal, frames redrawn in place, SIGINT, exit code 0."""
    master, slave = os.openpty()
    env = {**os.environ, "COLUMNS": "120", "LINES": "60", "TERM": "xterm"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "status", "--watch", "--port", "sim://"],
        stdin=subprocess.DEVNULL,
        stdout=slave,
        stderr=slave,
        env=env,
    )
    os.close(slave)
    seen = b""
    try:
        deadline = time.monotonic() + 30.0
        # Wait for three frames (each draws the bus table), then press Ctrl-C.
        while seen.count(b"wheel_encoder") < 3:
            ready, _, _ = select.select([master], [], [], max(0.0, deadline - time.monotonic()))
            assert ready, f"no frames: {seen[-2000:]!r}"
            seen += os.read(master, 65536)
        proc.send_signal(signal.SIGINT)
        # Read on while it ends: a terminal nobody reads fills up, and the command's last
        # frames and its goodbye wait in their writes.
        deadline = time.monotonic() + 30.0
        while proc.poll() is None:
            assert time.monotonic() < deadline, f"it did not end: {seen[-2000:]!r}"
            ready, _, _ = select.select([master], [], [], 0.1)
            if ready:
                try:
                    seen += os.read(master, 65536)
                except OSError:  # the terminal's other end is closed
                    break
        code = proc.wait(timeout=30)
        while True:
            ready, _, _ = select.select([master], [], [], 0.5)
            if not ready:
                break
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the terminal's other end is closed
                break
            if not chunk:
                break
            seen += chunk
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
    text = seen.decode(errors="replace")
    assert code == 0, text[-2000:]
    assert "Traceback" not in text
    assert "\x1b[" in text  # drawn in place on the terminal (cursor moves), not appended


# -- over a pseudo-terminal: a port that is not sim:// --------------------------------------


@needs_pty
def test_status_json_over_ohmni_sim_pty() -> None:
    with sim_on_pty() as (path, proc):
        assert not path.startswith("sim:")
        data = status_json(path)
        check_schema(data)
        assert data["port"] == path
        assert data["link"] == "connected"
        assert data["present"] == [0, 1, 3, 11, 12, 20]
        assert data["firmware"]["core"] == "sim-core-1.0"
        assert data["battery"]["docked"] is False
        # The simulator keeps its state between commands: dock it, and status says so.
        operator(proc, "dock")
        assert status_json(path)["battery"]["docked"] is True
        operator(proc, "silent 12")
        again = status_json(path)
        assert again["servos"]["ext2"] is None
        assert 12 in again["absent"]


def test_watch_json_into_a_pipe_that_closes() -> None:
    # `ohmni status --watch --json | head -1`: the reader goes, the command ends quietly.
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "status", "--watch", "--json", "--port", "sim://"],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        proc.stdout.close()
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    check_schema(json.loads(first))
    assert proc.returncode == 0, err
    assert b"Traceback" not in err
    assert b"BrokenPipe" not in err


@pytest.mark.usefixtures("virtual_time")
def test_a_present_device_without_a_reading_says_so() -> None:
    data = status_json()
    data["neck"] = None
    data["battery"] = None
    assert "neck no reading yet" in screen(data, width=120)
    assert "battery no reading yet" in screen(data, width=40)
