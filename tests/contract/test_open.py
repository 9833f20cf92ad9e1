"""``Robot.open(port)`` picks the implementation by the port, and each refuses what is not
its own with one clear error."""

from __future__ import annotations

import socket
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import ConfigError, TransportError
from ohmni_tb.robot import LocalRobot, RemoteRobot
from ohmni_tb.sim.clock import run_virtual


def test_a_port_opens_a_local_robot_and_a_daemons_url_a_remote_one() -> None:
    async def kinds() -> tuple[type[Robot], type[Robot]]:
        async with (
            Robot.open("sim://") as local,
            RobotServer(local, port=0) as server,
            Robot.open(server.url) as remote,
        ):
            return type(local), type(remote)

    assert run_virtual(kinds()) == (LocalRobot, RemoteRobot)


@pytest.mark.parametrize(
    ("port", "options", "message"),
    [
        ("ws://127.0.0.1:8766", {}, r"is a daemon's URL: open it with Robot\.open"),
        ("sim://", {"token": "0123456789abcdef"}, "a token is for a daemon's URL"),
    ],
)
async def test_a_local_robot_refuses_a_daemon(
    port: str, options: dict[str, Any], message: str
) -> None:
    with pytest.raises(ConfigError, match=message):
        async with LocalRobot.open(port, **options):
            pass


@pytest.mark.parametrize(
    ("port", "options", "message"),
    [
        ("ws://127.0.0.1:8766", {"watchdog_s": 0.3}, "runs with the daemon's settings: watchdog_s"),
        ("ws://", {}, "'ws://' is not a daemon URL"),
        ("ws://127.0.0.1:0", {}, "is not a daemon URL"),
        ("sim://", {}, "'sim://' is not a daemon URL"),
    ],
)
async def test_a_remote_robot_refuses_settings_and_what_is_not_a_daemon(
    port: str, options: dict[str, Any], message: str
) -> None:
    opener = Robot.open if port.startswith("ws") else RemoteRobot.open
    with pytest.raises(ConfigError, match=message):
        async with opener(port, **options):
            pass


async def test_nothing_listening_is_a_transport_error_naming_the_url() -> None:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]  # free, and nobody listens once closed
    url = f"ws://127.0.0.1:{port}"
    with pytest.raises(TransportError, match=f"cannot connect to the daemon at {url}"):
        async with Robot.open(url, timeout_s=2.0):
            pass
