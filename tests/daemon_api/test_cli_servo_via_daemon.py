"""``ohmni servo`` while ``ohmni serve`` holds the port: the maintenance commands go through
the daemon (the robot follows an id change), the others say why they cannot.

The daemon runs in this process, on its own thread and event loop (a RobotServer over a
LocalRobot on ``sim://``); each command runs as a user runs it.
"""

from __future__ import annotations

import asyncio
import json
import threading
from collections.abc import Iterator

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.robot import LocalRobot

runner = CliRunner()


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


def test_a_servo_command_the_daemon_does_not_take_says_why(via: _Daemon) -> None:
    code, out, _ = invoke("servo", "stat", "--sid", "3")
    assert code == 1
    assert "ohmni serve holds the port" in out
    assert "Could not exclusively lock" not in out
