"""``ohmni drive``: timed, distance and turn drives judged by the simulator's ground truth,
the argument checks, the consent, and the keyboard teleop through a pseudo-terminal.

The simulator runs in real time here (as the command does): a drive takes its seconds.
The truth is the :class:`~ohmni_tb.sim.robot.SimRobot` behind ``sim://``, caught by
wrapping :func:`ohmni_tb.cli.common.open_robot`.
"""

from __future__ import annotations

import asyncio
import fcntl
import json
import math
import os
import re
import select
import signal
import struct
import subprocess
import sys
import termios
import time
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest
from typer.testing import CliRunner

from cli._helpers import needs_pty, sim_on_pty
from ohmni_tb.cli import app, common
from ohmni_tb.cli import drive as drive_cli
from ohmni_tb.robot import LocalRobot
from ohmni_tb.sim.transport import SimTransport

runner = CliRunner()
SIM = ["--port", "sim://"]
#: Wide enough that rich wraps no line a test reads.
WIDE = {"COLUMNS": "300"}


def invoke(*args: str, env: dict[str, str] | None = None) -> tuple[int, str]:
    result = runner.invoke(app, ["drive", *args], env={**WIDE, **(env or {})})
    assert result.exception is None or isinstance(result.exception, SystemExit), (
        result.output,
        result.exception,
    )
    return result.exit_code, result.output


def words(text: str) -> str:
    """The output with rich's error box and line wrapping undone."""
    return " ".join(text.replace("│", " ").split())


@dataclass
class Truth:
    """What the command opened, and the simulated robot's truth once it had closed."""

    urls: list[str] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)
    wheel_speeds: list[tuple[float, float]] = field(default_factory=list)

    @property
    def pose(self) -> tuple[float, float, float]:
        (pose,) = self.poses
        return pose


@pytest.fixture
def truth(monkeypatch: pytest.MonkeyPatch) -> Truth:
    """Wrap ``common.open_robot``: record the port, and the sim's pose after closing."""
    seen = Truth()
    real = common.open_robot

    @asynccontextmanager
    async def spy(port: str, **overrides: Any) -> AsyncIterator[Any]:
        seen.urls.append(port)
        sim = None
        try:
            async with real(port, **overrides) as robot:
                sim = robot.sim
                yield robot
        finally:
            if sim is not None:
                pose = sim.pose
                seen.poses.append((pose.x, pose.y, pose.yaw))
                seen.wheel_speeds.append(sim.wheel_speeds_mps())

    monkeypatch.setattr(common, "open_robot", spy)
    return seen


def run_json(*args: str) -> dict[str, Any]:
    code, out = invoke(*args, *SIM, "--json")
    assert code == 0, out
    result: dict[str, Any] = json.loads(out)
    return result


def assert_stopped(truth: Truth) -> None:
    (speeds,) = truth.wheel_speeds
    assert speeds == pytest.approx((0.0, 0.0), abs=1e-3)


# -- timed drives -----------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_a_timed_drive_moves_the_robot_as_far_as_the_ramps_allow_and_stops(truth: Truth) -> None:
    result = run_json("--linear", "0.3", "--duration", "1")
    x, y, yaw = truth.pose
    # The ramps: 0 → 0.3 m/s at 0.5 m/s² takes 0.6 s (0.09 m), then 0.4 s at 0.3 m/s
    # (0.12 m), then braking at 1 m/s² (0.045 m): 0.255 m; the wheel PIDs trail the ramp
    # by some 0.1 s each way, which adds a little. A full second at 0.3 m/s plus the
    # braking would be 0.345 m; a drive cut short by a slow host would fall below 0.2.
    assert 0.22 < x < 0.31
    assert abs(y) < 0.01
    assert abs(yaw) < math.radians(1)
    assert_stopped(truth)
    # The odometry printed agrees with the truth.
    assert result["distance_m"] == pytest.approx(x, abs=0.005)
    assert result["pose"]["x_m"] == pytest.approx(x, abs=0.005)
    assert result["truth"]["x_m"] == pytest.approx(x, abs=1e-3)
    assert result["stop"]["confirmed"] is True
    assert result["command"] == {
        "linear_mps": 0.3,
        "angular_radps": 0.0,
        "ramped": True,
        "duration_s": 1.0,
    }
    # The average is over the first command to the confirmed stop: below the command.
    assert 0.1 < result["average_linear_mps"] < 0.3
    assert result["elapsed_s"] >= 1.0


@pytest.mark.usefixtures("virtual_time")
def test_no_ramp_is_the_pure_velocity_command(truth: Truth) -> None:
    # tb_control's /tb_cmd_vel: the wheels get the target at once. 0.2 s at 0.3 m/s goes
    # about 0.06 m before the braking ramp; through the ramps (0.5 m/s² up) it is 0.01 m.
    result = run_json("--linear", "0.3", "--duration", "0.2", "--no-ramp")
    assert result["command"]["ramped"] is False
    assert truth.pose[0] > 0.07
    assert_stopped(truth)
    ramped = run_json("--linear", "0.3", "--duration", "0.2")
    assert ramped["distance_m"] < 0.03


@pytest.mark.usefixtures("virtual_time")
def test_the_json_has_one_schema_for_every_drive(truth: Truth) -> None:
    result = run_json("--angular", "-0.8", "--linear", "0.1", "--duration", "0.3")
    assert truth.urls == ["sim://"]
    assert set(result) == {
        "port",
        "source",
        "mode",
        "command",
        "goal",
        "distance_m",
        "heading_change_deg",
        "heading_change_rad",
        "pose",
        "elapsed_s",
        "average_linear_mps",
        "average_angular_radps",
        "truth",
        "stop",
        "link_losses",
        "missed_counts",
    }
    assert result["port"] == "sim://"
    assert result["source"] == "local"  # a person at the robot: this computer opened the port
    assert result["mode"] == "duration"
    assert result["goal"] is None
    assert set(result["pose"]) == {"x_m", "y_m", "yaw_deg"}
    assert set(result["truth"]) == {"x_m", "y_m", "yaw_deg", "heading_change_deg"}
    assert set(result["stop"]) == {"confirmed", "after_s", "samples"}
    assert result["heading_change_deg"] < 0  # clockwise
    assert result["heading_change_deg"] == pytest.approx(math.degrees(truth.pose[2]), abs=0.5)
    for value in (result["distance_m"], result["elapsed_s"], result["average_angular_radps"]):
        assert isinstance(value, float)


@pytest.mark.usefixtures("virtual_time")
def test_the_table_names_what_was_measured() -> None:
    code, out = invoke("--linear", "-0.2", "--duration", "0.3", *SIM)
    assert code == 0, out
    text = words(out)
    assert "drive: -0.20 m/s, +0.00 rad/s for 0.3 s (drive() re-sent every 0.1 s), then stop" in (
        text
    )
    assert re.search(r"stop confirmed \d\.\d{3} s after the stop", text)
    distance = re.search(r"distance (-\d\.\d{3}) m", text)
    assert distance is not None
    assert float(distance.group(1)) < -0.01  # backward
    assert re.search(
        r"pose x=-\d\.\d{3} m y=[+-]\d\.\d{3} m yaw=[+-]\d+\.\d° \(from the start\)", text
    )
    assert "average -0." in text
    assert "(the simulator's; odometry" in text


# -- goal drives ------------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_a_distance_ends_within_a_few_mm_of_the_goal_by_truth(truth: Truth) -> None:
    result = run_json("--distance", "0.5")
    x, y, _ = truth.pose
    # Tuned on this simulator to land within ~1 mm; a few cm is the promise.
    assert x == pytest.approx(0.5, abs=0.02)
    assert abs(y) < 0.01
    assert_stopped(truth)
    assert result["mode"] == "distance"
    assert result["goal"]["distance_m"] == 0.5
    assert result["goal"]["error_m"] == pytest.approx(result["distance_m"] - 0.5, abs=1e-4)
    assert result["distance_m"] == pytest.approx(x, abs=0.005)
    assert result["command"]["linear_mps"] == drive_cli.DEFAULT_LINEAR_MPS


@pytest.mark.usefixtures("virtual_time")
def test_a_turn_ends_within_a_few_degrees_of_the_goal_by_truth(truth: Truth) -> None:
    result = run_json("--turn", "90")
    x, y, yaw = truth.pose
    assert math.degrees(yaw) == pytest.approx(90, abs=3)
    assert math.hypot(x, y) < 0.01  # on the spot
    assert_stopped(truth)
    assert result["mode"] == "turn"
    assert result["goal"]["turn_deg"] == 90
    assert result["heading_change_deg"] == pytest.approx(math.degrees(yaw), abs=0.5)


@pytest.mark.parametrize(
    ("args", "axis", "goal"),
    [
        (("--distance", "-0.2", "--linear", "0.5"), "x", -0.2),  # the sign of --linear is ignored
        (("--turn", "-45", "--angular", "-1.5"), "yaw", -45.0),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_goals_take_their_sign_from_the_goal(
    truth: Truth, args: tuple[str, ...], axis: str, goal: float
) -> None:
    code, out = invoke(*args, *SIM)
    assert code == 0, out
    x, _, yaw = truth.pose
    if axis == "x":
        assert x == pytest.approx(goal, abs=0.02)
        assert "goal -0.200 m, went -0.2" in words(out)
    else:
        assert math.degrees(yaw) == pytest.approx(goal, abs=3)
        assert "goal -45.0°, turned -4" in words(out)
    assert_stopped(truth)


@pytest.mark.usefixtures("virtual_time")
def test_a_goal_not_reached_in_time_is_one_error_line_and_the_robot_stops(
    truth: Truth, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(drive_cli, "_goal_timeout", lambda *_: 0.4)
    code, out = invoke("--distance", "1", *SIM, "--json")
    assert code == 1, out
    (line,) = out.strip().splitlines()
    assert line.startswith("error: the goal was not reached within 0.4 s: went +0.")
    assert "of +1.000 m by odometry; the robot is stopped" in line
    assert 0.01 < truth.pose[0] < 0.2
    assert_stopped(truth)


@pytest.mark.usefixtures("virtual_time")
def test_a_stop_the_counts_do_not_confirm_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(drive_cli, "STOP_CONFIRM_TIMEOUT_S", 0.0)
    code, out = invoke("--linear", "0.1", "--duration", "0.1", *SIM)
    assert code == 1, out
    assert (
        out.strip()
        .splitlines()[-1]
        .startswith("error: WHEEL STOP NOT CONFIRMED, the robot may still be moving")
    )


def test_ctrl_c_stops_the_drive_and_exits_130() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "drive", "--distance", "5", "--port", "sim://"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env={**os.environ, **WIDE},
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], 30)
        assert ready
        assert proc.stdout.readline().startswith(b"drive: straight +5.000 m")
        time.sleep(0.5)  # on its way
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130
    assert out.decode().strip() == "interrupted: the wheel stop was confirmed on the way out"


@pytest.mark.parametrize(
    ("silent", "message"),
    [
        ("0", "error: drive board 0 does not answer: the robot cannot drive"),
        ("0,1", "error: drive boards 0 and 1 do not answer: the robot cannot drive"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_silent_drive_boards_are_refused(truth: Truth, silent: str, message: str) -> None:
    code, out = invoke("--linear", "0.1", "--port", f"sim://?silent={silent}")
    assert code == 1, out
    assert out.splitlines()[0] == message
    assert truth.pose == (0.0, 0.0, 0.0)


def test_ctrl_c_while_the_robot_opens_does_not_claim_a_confirmed_stop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    @asynccontextmanager
    async def interrupted(port: str, **overrides: Any) -> AsyncIterator[Any]:
        if port:  # Ctrl-C while the port opens
            raise KeyboardInterrupt
        yield None

    monkeypatch.setattr(common, "open_robot", interrupted)
    code, out = invoke("--linear", "0.1", *SIM)
    assert code == 130
    assert out.strip() == "interrupted while the robot was opening: nothing was driven"


DRIVE_CMD = (sys.executable, "-m", "ohmni_tb", "drive")


@needs_pty
@pytest.mark.parametrize(
    "signals",
    [(signal.SIGINT, signal.SIGINT), (signal.SIGTERM,), (signal.SIGHUP,)],
    ids=["ctrl-c-twice", "sigterm", "sighup"],
)
def test_signals_mid_drive_leave_the_robot_stopped(signals: tuple[int, ...]) -> None:
    # The drive boards keep their last command (the simulator's too), and the Robot's
    # watchdog dies with the process: a signal must end the drive through its stop.
    with sim_on_pty() as (port, _sim):
        proc = subprocess.Popen(
            [*DRIVE_CMD, "--linear", "0.3", "--duration", "5", "--port", port, "--yes"],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            env={**os.environ, **WIDE},
        )
        try:
            assert proc.stdout is not None
            ready, _, _ = select.select([proc.stdout], [], [], 30)
            assert ready
            assert proc.stdout.readline().startswith(b"drive: +0.30 m/s")
            time.sleep(0.8)  # on its way
            for signum in signals:
                proc.send_signal(signum)
                time.sleep(0.002)
            _, err = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        assert proc.returncode == 128 + signals[0], err
        assert b"Traceback" not in err
        assert b"the wheel stop was confirmed on the way out" in err
        wheels = [
            json.loads(
                subprocess.run(
                    [sys.executable, "-m", "ohmni_tb", "status", "--json", "--port", port],
                    capture_output=True,
                    check=True,
                    timeout=60,
                ).stdout
            )["wheels"]
            for _ in range(2)
        ]
        # Standing still, and the counts did not move between the two looks.
        assert wheels[1]["left_mps"] == wheels[1]["right_mps"] == 0.0
        assert wheels[0]["left_raw"] == wheels[1]["left_raw"]


# -- arguments --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--linear", "1.5"), "--linear=1.5 is out of range: allowed -1..1 m/s (max_linear_mps)"),
        (("--linear", "-1.01"), "--linear=-1.01 is out of range: allowed -1..1 m/s"),
        (("--angular", "2.5"), "--angular=2.5 is out of range: allowed -2..2 rad/s"),
        (("--linear", "nan"), "--linear=nan is not a finite number"),
        (("--angular", "-inf"), "--angular=-inf is not a finite number"),
        (("--linear", "1e309"), "--linear=inf is not a finite number"),
        (("--linear", "٣"), "Invalid value for '--linear'"),
        (("--linear", "0x0B"), "Invalid value for '--linear'"),
        (
            ("--linear", "1", "--angular", "2"),
            "--linear=1 with --angular=2 asks a wheel for 1.33 m/s: allowed up to 1 m/s "
            "(max_wheel_mps)",
        ),
        (("--linear", "0.1", "--duration", "0"), "--duration=0 is out of range: allowed >0..600 s"),
        (("--linear", "0.1", "--duration", "-1"), "--duration=-1 is out of range"),
        (("--linear", "0.1", "--duration", "1e308"), "--duration=1e+308 is out of range"),
        (("--distance", "1", "--turn", "90"), "--distance and --turn do not combine"),
        (("--distance", "1", "--duration", "2"), "--duration and --distance do not combine"),
        (("--turn", "90", "--teleop"), "--turn and --teleop do not combine"),
        (("--distance", "1", "--angular", "1"), "--angular does not combine with --distance"),
        (("--turn", "90", "--linear", "0.2"), "--linear does not combine with --turn"),
        (("--distance", "0"), "--distance=0 goes nowhere"),
        (("--turn", "-0.0"), "--turn=0 turns nothing"),
        (("--distance", "101"), "--distance=101 is out of range: allowed -100..100 m"),
        (("--turn", "3601"), "--turn=3601 is out of range: allowed -3600..3600 degrees"),
        (("--distance", "1", "--linear", "0.01"), "--linear=0.01 is too slow for --distance"),
        (("--turn", "10", "--angular", "0.1"), "--angular=0.1 is too slow for --turn"),
        ((), "nothing to drive: give --linear and/or --angular"),
        (("--duration", "2"), "nothing to drive"),
        (("--linear", "0", "--angular", "0"), "--linear=0 with --angular=0 drives nowhere"),
        (("--teleop", "--json"), "--json does not combine with --teleop"),
        (("--distance", "1", "--no-ramp"), "--no-ramp does not combine with --distance"),
        (("--pwm", "100", "100", "--no-ramp"), "--no-ramp does not combine with --pwm"),
        (("--wheels", "0.1", "0.1", "--no-ramp"), "--no-ramp does not combine with --wheels"),
        (("--teleop", "--linear", "0"), "--linear=0 gives a --teleop key no speed"),
        # CliRunner's stdin is no terminal.
        (("--teleop",), "--teleop reads keys from a terminal, and stdin is not one"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_bad_arguments_exit_2_naming_them_and_nothing_opens(
    truth: Truth, args: tuple[str, ...], message: str
) -> None:
    code, out = invoke(*args, *SIM)
    assert code == 2, out
    assert message in words(out)
    assert "Traceback" not in out
    assert truth.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_the_limits_come_from_the_config(truth: Truth) -> None:
    env = {"OHMNI_MAX_LINEAR_MPS": "0.5", "OHMNI_MAX_ANGULAR_RADPS": "1"}
    code, out = invoke("--linear", "0.6", *SIM, env=env)
    assert code == 2
    assert "--linear=0.6 is out of range: allowed -0.5..0.5 m/s (max_linear_mps)" in words(out)
    code, out = invoke("--turn", "30", "--angular", "1.2", *SIM, env=env)
    assert code == 2
    assert "--angular=1.2 is out of range: allowed -1..1 rad/s" in words(out)
    assert truth.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_a_bad_config_is_one_error_line(truth: Truth) -> None:
    code, out = invoke("--linear", "0.1", *SIM, env={"OHMNI_WATCHDOG_S": "-1"})
    assert code == 1
    (line,) = out.strip().splitlines()
    assert line.startswith("error: watchdog_s=-1")
    assert truth.urls == []


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize("port", ["/dev/ttyUSB0", "serial:///dev/ttyUSB7?baudrate=115200"])
@pytest.mark.parametrize("args", [("--linear", "0.1"), ("--distance", "0.1"), ("--turn", "5")])
def test_a_real_port_needs_consent_and_nothing_opens_without_it(
    truth: Truth, port: str, args: tuple[str, ...]
) -> None:
    code, out = invoke(*args, "--port", port)
    assert code == 1
    (line,) = out.strip().splitlines()
    assert line.startswith("error: ohmni drive")
    assert f"on {port} moves the robot: pass --yes to allow it" in line
    assert truth.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_with_yes_a_real_port_is_opened_and_its_error_is_one_line(truth: Truth) -> None:
    code, out = invoke("--linear", "0.1", "--port", "/dev/ohmni-no-such-port", "--yes")
    assert code == 1
    (line,) = out.strip().splitlines()
    assert line.startswith("error: ")
    assert "/dev/ohmni-no-such-port" in line
    assert truth.urls == ["/dev/ohmni-no-such-port"]


@pytest.mark.usefixtures("virtual_time")
def test_help_has_an_example() -> None:
    code, out = invoke("--help")
    assert code == 0
    assert "ohmni drive --linear 0.3 --duration 2 --port sim://" in out
    assert "--teleop" in out


def test_the_module_imports_neither_the_robot_nor_numpy() -> None:
    probe = (
        "import sys, ohmni_tb.cli.drive; "
        "print(sorted(m for m in ('numpy', 'ohmni_tb.robot', 'ohmni_tb.sim') if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, check=True, timeout=30
    )
    assert out.stdout.strip() == "[]"


# -- teleop -----------------------------------------------------------------------------------


class Terminal:
    """``ohmni drive --teleop`` running on a pseudo-terminal; the test is its keyboard."""

    def __init__(self, *args: str) -> None:
        self.master, self.slave = os.openpty()
        # A screen of 120×30, so rich lays out the same everywhere.
        fcntl.ioctl(self.slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 120, 0, 0))
        self.settings = termios.tcgetattr(self.slave)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ohmni_tb", "drive", "--teleop", *args],
            stdin=self.slave,
            stdout=self.slave,
            stderr=self.slave,
            start_new_session=True,
            env={**os.environ, "TERM": "xterm-256color", "COLUMNS": "120", "LINES": "30"},
        )
        self.screen = bytearray()

    def read(self, seconds: float) -> None:
        """Collect the output for ``seconds`` (the terminal must be drained anyway)."""
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            ready, _, _ = select.select([self.master], [], [], left)
            if ready:
                try:
                    self.screen.extend(os.read(self.master, 65536))
                except OSError:
                    return

    def wait_for(self, text: str, seconds: float) -> None:
        end = time.monotonic() + seconds
        while text.encode() not in self.screen:
            assert time.monotonic() < end, f"no {text!r} in {self.text()[-2000:]!r}"
            assert self.proc.poll() is None, f"ended early: {self.text()[-2000:]!r}"
            self.read(0.05)

    def key(self, keys: bytes) -> None:
        os.write(self.master, keys)

    def text(self) -> str:
        # Colours and cursor moves out; what is left is the text drawn.
        plain = re.sub(rb"\x1b\[[0-9;?]*[A-Za-z]", b"", bytes(self.screen))
        return plain.decode("utf-8", errors="replace")

    def odometry_x(self) -> list[float]:
        return [float(x) for x in re.findall(r"odometry\s+x=([+-]\d+\.\d{3}) m", self.text())]

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(5)
        os.close(self.master)
        os.close(self.slave)


@contextmanager
def teleop(*args: str) -> Iterator[Terminal]:
    terminal = Terminal(*args)
    try:
        yield terminal
    finally:
        terminal.close()


@pytest.mark.usefixtures("virtual_time")
def test_teleop_drives_while_a_key_repeats_and_quits_with_the_terminal_restored() -> None:
    with teleop("--port", "sim://") as term:
        term.wait_for("odometry", 10.0)
        # Key repeat: 'w' every 50 ms for 1 s drives forward.
        for _ in range(20):
            term.key(b"w")
            term.read(0.05)
        term.wait_for("forward: +0.30 m/s", 2.0)
        # No key for longer than the watchdog: the command decays to a stop.
        term.wait_for("stopped (no key for 0.5 s)", 3.0)
        term.read(0.3)
        xs = term.odometry_x()
        assert xs[0] == pytest.approx(0.0, abs=0.005)
        assert max(xs) > 0.1  # ~1 s of 0.3 m/s behind a 0.5 m/s² ramp: about 0.25 m
        term.key(b"q")
        assert term.proc.wait(10) == 0
        term.read(0.3)
        text = term.text()
        assert re.search(r"teleop: \d+ key presses", text)
        assert "stop confirmed" in text
        assert re.search(r"distance\s+\+0\.[1-9]\d\d m", text)
        # The terminal is as it was: echo and line editing back on.
        assert termios.tcgetattr(term.slave) == term.settings


def test_teleop_turns_with_the_arrows_and_ctrl_c_quits() -> None:
    with teleop("--port", "sim://", "--angular", "1.5") as term:
        term.wait_for("odometry", 10.0)
        for _ in range(12):
            term.key(b"\x1b[D")  # left arrow: counter-clockwise
            term.read(0.05)
        term.wait_for("left: +0.00 m/s, +1.50 rad/s", 2.0)
        term.key(b" ")  # space stops at once
        term.wait_for("stopped (space)", 2.0)
        term.key(b"\x03")
        assert term.proc.wait(10) == 0
        term.read(0.3)
        heading = re.search(r"heading\s+\+(\d+\.\d)°", term.text())
        assert heading is not None, term.text()[-1500:]
        assert float(heading.group(1)) > 5
        assert termios.tcgetattr(term.slave) == term.settings


# -- against `ohmni sim --pty` ----------------------------------------------------------------


@needs_pty
def test_drive_over_a_pty_to_the_simulator_process() -> None:
    with sim_on_pty() as (path, _):
        assert path.startswith("/dev/")
        # Not sim://: a real port to the command, so it needs --yes.
        code, out = invoke("--linear", "0.2", "--duration", "0.5", "--port", path, "--json")
        assert code == 1
        assert "pass --yes" in out
        code, out = invoke(
            "--linear", "0.2", "--duration", "0.5", "--port", path, "--yes", "--json"
        )
        assert code == 0, out
        result = json.loads(out)
        assert result["port"] == path
        assert result["truth"] is None  # no ground truth through a serial port
        assert result["stop"]["confirmed"] is True
        # 0.5 s behind the 0.5 m/s² ramp (0.06 m), then braking: ~0.07 m.
        assert 0.03 < result["distance_m"] < 0.15
        code, out = invoke("--turn", "30", "--port", path, "--yes", "--json")
        assert code == 0, out
        assert json.loads(out)["heading_change_deg"] == pytest.approx(30, abs=3)


@pytest.mark.usefixtures("virtual_time")
def test_the_teleop_summary_counts_one_key_press_in_the_singular(
    capsys: pytest.CaptureFixture[str],
) -> None:
    result = {
        "keys": 1,
        "goal": None,
        "stop": {"confirmed": True, "after_s": 0.1, "samples": 5},
        "distance_m": 0.0,
        "heading_change_deg": 0.0,
        "heading_change_rad": 0.0,
        "pose": {"x_m": 0.0, "y_m": 0.0, "yaw_deg": 0.0},
        "elapsed_s": 0.1,
        "average_linear_mps": 0.0,
        "average_angular_radps": 0.0,
        "truth": None,
    }
    drive_cli._print_result(result, teleop=True)
    assert capsys.readouterr().out.splitlines()[0] == "teleop: 1 key press"


@pytest.mark.usefixtures("virtual_time")
def test_a_goal_drive_whose_counts_stop_coming_stops_at_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The motion watchdog off and the stale-feedback stop at its slowest (100 ticks, 2 s):
    # the goal drive itself must not steer blind until its timeout when the counts stop.
    real = common.open_robot
    silenced: list[float] = []

    @asynccontextmanager
    async def blind(port: str, **overrides: Any) -> AsyncIterator[Any]:
        overrides = {**overrides, "watchdog_s": 0.0, "stale_ticks": 100}
        async with real(port, **overrides) as robot:
            loop = asyncio.get_running_loop()

            def silence() -> None:
                silenced.append(loop.time())
                assert isinstance(robot, LocalRobot)  # the port, opened by the command
                transport = robot.bus.transport
                assert isinstance(transport, SimTransport)
                transport.line.faults.silent = {0, 1}

            loop.call_later(1.0, silence)
            yield robot

    monkeypatch.setattr(common, "open_robot", blind)
    started = time.monotonic()
    code, out = invoke("--distance", "5", "--linear", "0.3", *SIM)
    assert silenced
    assert code == 1
    # It stopped steering half a second after the last counts and sent the stop; with
    # the boards silent nothing can confirm it, and it says so in one error line.
    [error] = [line for line in out.splitlines() if line.startswith("error:")]
    assert "WHEEL STOP NOT CONFIRMED" in error
    assert time.monotonic() - started < 10  # not the goal's timeout of 38.9 s


# -- the command source -------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_the_drive_goes_as_the_source_named(truth: Truth) -> None:
    result = run_json("--linear", "0.2", "--duration", "0.2", "--source", "remote")
    assert result["source"] == "remote"
    assert result["distance_m"] > 0.005  # nothing above remote drives: taken
    assert_stopped(truth)


def test_a_source_not_in_the_table_is_refused_before_the_port_opens() -> None:
    code, out = invoke("--linear", "0.2", "--source", "operator", *SIM)
    assert code == 2
    assert (
        "--source='operator' is not a command source: allowed safety, local, remote, autonomy "
        "(command_sources)" in words(out)
    )
