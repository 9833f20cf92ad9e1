"""The daemon's ``hello`` says what it serves, and a command through it acts on that: a
daemon serving the built-in simulator moves nothing physical, so driving it needs no
``--yes``, as on ``sim://``; a daemon on a serial port still asks.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator

import pytest
from typer.testing import CliRunner

from cli._helpers import needs_pty, sim_on_pty
from ohmni_tb import Robot
from ohmni_tb.cli import app
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon.server import RobotServer

runner = CliRunner()

#: ``RobotServer`` on a Robot opened on ``argv[1]``, in a process of its own: it prints its
#: URL and serves until its stdin closes.
DAEMON = textwrap.dedent(
    """
    import asyncio, sys
    from ohmni_tb import Robot
    from ohmni_tb.daemon.server import RobotServer

    async def main():
        async with Robot.open(sys.argv[1]) as robot, RobotServer(robot, port=0) as server:
            print(server.url, flush=True)
            await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)

    asyncio.run(main())
    """
)


@pytest.fixture
def daemon_on(monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[[str], str]]:
    """A function: start the daemon on a port, and have the commands go through it."""
    procs: list[subprocess.Popen[str]] = []

    def start(port: str) -> str:
        proc = subprocess.Popen(
            [sys.executable, "-c", DAEMON, port],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        procs.append(proc)
        assert proc.stdout is not None
        url = proc.stdout.readline().strip()
        assert url.startswith("ws://"), "the daemon printed no address"
        monkeypatch.setenv("OHMNI_DAEMON_URL", url)
        monkeypatch.delenv("OHMNI_PORT", raising=False)
        return url

    yield start
    for proc in procs:
        proc.communicate(timeout=20)  # its stdin closed: it stops serving


def drive_distance(*extra: str) -> tuple[int, str]:
    """``ohmni drive --distance 0.1 --json`` as a user types it, without ``--yes``."""
    result = runner.invoke(app, ["drive", "--distance", "0.1", "--json", *extra])
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result.exit_code, result.output


async def test_hello_says_the_daemon_serves_the_simulator(robot: Robot) -> None:
    async with RobotServer(robot, port=0) as server, RobotClient.connect(server.url) as client:
        assert (client.hello.serves, client.hello.simulated) == ("sim://", True)
    async with (
        RobotServer(robot, port=0, serves="sim://?seed=7") as server,
        RobotClient.connect(server.url) as client,
    ):
        assert client.hello.serves == "sim://?seed=7"


def test_driving_through_a_daemon_on_the_simulator_needs_no_yes(
    daemon_on: Callable[[str], str],
) -> None:
    url = daemon_on("sim://")
    code, out = drive_distance()
    assert code == 0, out
    drove = json.loads(out[out.index("{") :])
    assert drove["port"] == url
    # The daemon runs the goal in real time in its own process: on a loaded machine its
    # control ticks come late (the contract suite holds the precision, on virtual time).
    assert drove["goal"]["error_m"] == pytest.approx(0.0, abs=0.02)
    assert "--yes" not in out


@needs_pty
def test_driving_through_a_daemon_on_a_serial_port_still_asks(
    daemon_on: Callable[[str], str],
) -> None:
    with sim_on_pty() as (path, _proc):
        url = daemon_on(path)
        code, out = drive_distance()
        assert code == 1
        assert f"ohmni drive --distance on {url} moves the robot: pass --yes" in out
        # With --yes it drives.
        code, out = drive_distance("--yes")
        assert code == 0, out


def test_moving_the_neck_through_a_daemon_on_the_simulator_needs_no_yes(
    daemon_on: Callable[[str], str],
) -> None:
    daemon_on("sim://")
    result = runner.invoke(app, ["neck", "--raw", "420", "--playtime", "0.3", "--json"])
    assert result.exit_code == 0, result.output
    assert "--yes" not in result.output


def test_serve_max_clients_refuses_the_connection_past_it() -> None:
    import asyncio

    from daemon_api._serving import start_serving, stop_serving
    from ohmni_tb.errors import TransportError

    proc, url = start_serving("--listen", "127.0.0.1:0", "--max-clients", "1")

    async def connect_two() -> str:
        async with RobotClient.connect(url):
            with pytest.raises(TransportError) as refused:
                async with RobotClient.connect(url):
                    pass
            return str(refused.value)

    try:
        message = asyncio.run(connect_two())
    finally:
        log = stop_serving(proc)
    assert "503" in message, message
    assert "at most 1 clients" in message or "at most 1 client" in message, message
    assert "connections refused (503)" in log
