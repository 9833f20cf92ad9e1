"""``ohmni servo`` while ``ohmni serve`` holds the port: the maintenance commands go through
the daemon (the robot follows an id change), the others say why they cannot.

The daemon runs in this process, on its own thread and event loop (a RobotServer over a
LocalRobot on ``sim://``); each command runs as a user runs it.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Coroutine, Iterator
from typing import Any, TypeVar

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.herkulex import TorqueControl, parse_reply, ram_read
from ohmni_tb.robot import LocalRobot
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import SimServo

runner = CliRunner()
T = TypeVar("T")


class _Daemon:
    """A daemon on its own thread: ``url``, and ``call`` to run a coroutine on its loop."""

    def __init__(self) -> None:
        self.url = ""
        self.robot: LocalRobot | None = None
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=asyncio.run, args=(self._main(),), daemon=True)

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with (
            LocalRobot.open("sim://") as robot,
            RobotServer(robot, port=0) as server,
        ):
            self.robot = robot
            self.url = server.url
            self._ready.set()
            await self._stop.wait()

    def start(self) -> None:
        self._thread.start()
        assert self._ready.wait(30), "the daemon did not start"

    def call(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run ``coro`` on the daemon's loop and return what it returned."""
        assert self._loop is not None
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(30)

    def sim(self) -> SimRobot:
        """The simulator behind the daemon's robot (touch it only through :meth:`call`)."""
        assert self.robot is not None
        sim: SimRobot = self.robot.sim
        return sim

    def stop(self) -> None:
        assert self._loop is not None
        assert self._stop is not None
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(30)


@pytest.fixture(scope="module")
def daemon() -> Iterator[_Daemon]:
    served = _Daemon()
    served.start()
    try:
        yield served
    finally:
        served.stop()


@pytest.fixture
def via(daemon: _Daemon, monkeypatch: pytest.MonkeyPatch) -> _Daemon:
    monkeypatch.setenv("OHMNI_DAEMON_URL", daemon.url)
    monkeypatch.delenv("OHMNI_PORT", raising=False)
    return daemon


def invoke(*args: str) -> tuple[int, str, str]:
    result = runner.invoke(app, list(args), env={"COLUMNS": "200"})
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result.exit_code, result.output, result.stdout


def test_servo_info_goes_through_the_daemon(via: _Daemon) -> None:
    code, out, stdout = invoke("servo", "info", "--sid", "3", "--json")
    assert code == 0, out
    assert f"via the daemon at {via.url}" in out
    assert json.loads(stdout)["ram"]["id"] == 3


def test_servo_write_goes_through_the_daemon_and_reaches_the_servo(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "write", "led_control", "4", "--sid", "12")
    assert code == 0, out
    code, out, stdout = invoke("servo", "info", "--sid", "12", "--json")
    assert json.loads(stdout)["ram"]["led_control"] == 4


def test_set_id_through_the_daemon_is_followed_by_its_robot(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "set-id", "14", "--sid", "11")
    assert code == 0, out
    assert "servo 11 is now servo 14" in out
    robot = via.robot
    assert robot is not None
    assert robot.servo(14).sid == 14
    assert robot.config.ext_servo_ids == (14, 12)
    code, out, _ = invoke("servo", "set-id", "12", "--sid", "14")
    assert code == 1
    assert "cannot take id 12" in out
    code, out, _ = invoke("servo", "set-id", "11", "--sid", "14")
    assert code == 0, out


def test_the_zero_offset_is_set_on_the_daemons_robot(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "zero-offset", "--sid", "3", "--", "-20")
    assert code == 0, out
    robot = via.robot
    assert robot is not None
    assert robot.servo(3).zero_offset_raw == -20
    assert robot.config.neck_zero_offset_raw == -20
    code, out, _ = invoke("servo", "zero-offset", "0", "--sid", "3")
    assert code == 0, out


def test_board_id_is_refused_without_confirm(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "board-id", "1", "7")
    assert code == 1
    assert "confirm=True" in out
    robot = via.robot
    assert robot is not None
    assert 1 in robot.state.present


def test_a_scan_while_the_daemon_holds_the_port_says_why(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "scan")
    assert code == 1
    assert "ohmni serve holds the port" in out
    assert "--port" in out
    assert "Could not exclusively lock" not in out


# -- read, move, torque, stat and clear through the daemon, judged by the simulator --------


def ext2(daemon: _Daemon) -> SimServo:
    """The simulated servo 12 (``servo_ext2``) behind the daemon."""
    servo = daemon.sim().ext_servos[1]
    assert servo.sid == 12
    return servo


def sim_ram(daemon: _Daemon, name: str) -> int:
    """RAM register ``name`` of the simulated servo 12, as it is now."""

    async def read() -> int:
        sim = daemon.sim()
        reply = ext2(daemon).handle(ram_read(12, name), sim.sync())
        assert reply is not None
        return parse_reply(reply).value(name)

    return daemon.call(read())


def sim_supply(daemon: _Daemon, supply_v: float) -> None:
    """The simulated servo 12's supply voltage, from now."""

    async def change() -> None:
        daemon.sim().sync()
        ext2(daemon).set_supply_voltage(supply_v)

    daemon.call(change())


def test_servo_read_goes_through_the_daemon_and_reads_the_servo(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "write", "led_control", "2", "--sid", "12")
    assert code == 0, out
    code, out, _ = invoke("servo", "read", "led_control", "--sid", "12")
    assert code == 0, out
    assert f"via the daemon at {via.url}" in out
    assert "RAM led_control = 2" in out
    assert sim_ram(via, "led_control") == 2
    code, out, stdout = invoke("servo", "read", "30", "--eep", "--sid", "12", "--json")
    assert code == 0, out
    assert json.loads(stdout) == {"register": "position_kp", "memory": "EEP", "value": 440}


def test_servo_torque_goes_through_the_daemon_and_reaches_the_servo(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "torque", "on", "--sid", "12")
    assert code == 0, out
    assert f"via the daemon at {via.url}" in out
    assert "servo 12: torque on" in out
    assert sim_ram(via, "torque_control") == TorqueControl.ON
    code, out, _ = invoke("servo", "torque", "free", "--sid", "12")
    assert code == 0, out
    assert sim_ram(via, "torque_control") == TorqueControl.FREE


def test_servo_move_goes_through_the_daemon_and_the_servo_moves(via: _Daemon) -> None:
    invoke("servo", "torque", "free", "--sid", "12")
    start = sim_ram(via, "calibrated_position")
    # Torque off and no --torque-on: refused as directly, nothing sent.
    code, out, _ = invoke("servo", "move", "600", "--sid", "12")
    assert code == 1
    assert "torque off" in out
    # Outside the command's range: exit 2 before anything is sent.
    code, out, _ = invoke("servo", "move", "1010", "--sid", "12", "--torque-on")
    assert code == 2
    assert "POSITION=1010 is out of range" in out
    assert sim_ram(via, "torque_control") == TorqueControl.FREE
    goal = 600 if abs(start - 600) > 20 else 400
    code, out, _ = invoke(
        "servo", "move", str(goal), "--sid", "12", "--torque-on", "--playtime", "0.1"
    )
    assert code == 0, out
    assert f"via the daemon at {via.url}" in out
    # The playtime the servo got, in whole ticks, as directly: 0.1 s is 9 ticks.
    assert f"servo 12: moving {start} → {goal} over 0.1008 s (9 ticks)" in out
    assert sim_ram(via, "torque_control") == TorqueControl.ON
    deadline = time.monotonic() + 3
    while abs(sim_ram(via, "calibrated_position") - goal) > 5:
        assert time.monotonic() < deadline, "servo 12 did not get there"
        time.sleep(0.05)
    invoke("servo", "torque", "free", "--sid", "12")


def test_a_move_outside_the_daemons_range_sends_nothing_not_even_the_torque(
    via: _Daemon,
) -> None:
    robot = via.robot
    assert robot is not None
    high = robot.servo(3).max_raw  # the neck's: 650
    invoke("servo", "torque", "free", "--sid", "3")
    code, out, _ = invoke(
        "servo", "move", str(high + 10), "--sid", "3", "--max-raw", "1000", "--torque-on"
    )
    assert code == 1
    assert f"servo 3 position={high + 10} is out of range: allowed 280..{high}" in out

    async def neck_torque() -> int:
        sim = via.sim()
        reply = sim.neck.handle(ram_read(3, "torque_control"), sim.sync())
        assert reply is not None
        return parse_reply(reply).value("torque_control")

    assert via.call(neck_torque()) == TorqueControl.FREE


def test_stat_goes_through_the_daemon_and_shows_a_latched_error(via: _Daemon) -> None:
    invoke("servo", "torque", "on", "--sid", "12")
    code, out, stdout = invoke("servo", "stat", "--sid", "12", "--json")
    assert code == 0, out
    assert f"via the daemon at {via.url}" in out
    status = json.loads(stdout)
    assert status["error"] == 0
    assert status["torque_on"] is True
    # Over-voltage: the servo latches the error and lets go (its torque policy).
    sim_supply(via, 12.0)
    code, out, stdout = invoke("servo", "stat", "--sid", "12", "--json")
    status = json.loads(stdout)
    assert "INPUT_VOLTAGE" in status["error_flags"]
    assert status["torque_on"] is False
    sim_supply(via, 7.4)
    code, out, _ = invoke("servo", "stat", "--sid", "12")
    assert code == 0, out
    assert "servo 12 status" in out
    assert "INPUT_VOLTAGE" in out  # latched until cleared


def test_clear_goes_through_the_daemon_and_clears_the_servos_error(via: _Daemon) -> None:
    invoke("servo", "torque", "on", "--sid", "12")
    sim_supply(via, 12.0)  # the servo latches an over-voltage error and lets go
    sim_supply(via, 7.4)
    assert sim_ram(via, "status_error") != 0
    code, out, stdout = invoke("servo", "clear", "--sid", "12", "--json")
    assert code == 0, out
    status = json.loads(stdout)
    assert status["error"] == 0
    assert status["torque_on"] is False  # left off, as directly
    assert sim_ram(via, "status_error") == 0
    assert sim_ram(via, "torque_control") == TorqueControl.FREE
    code, out, _ = invoke("servo", "clear", "--sid", "12", "--torque-on")
    assert code == 0, out
    assert "servo 12 status after clearing" in out
    assert sim_ram(via, "torque_control") == TorqueControl.ON
    invoke("servo", "torque", "free", "--sid", "12")
