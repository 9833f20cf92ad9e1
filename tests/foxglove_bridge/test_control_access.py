"""Foxglove control needs the token, and a flood of Twists does not disable it.

Through ``ohmni serve --foxglove --foxglove-control`` as a user runs it, judged by what a
daemon client reads (``wheel_odom``, the PID gains) and what the Foxglove client is told:
every client watches; only a client that called ``/tb_control/unlock`` with the token
drives, sets parameters or calls services — a web page (``Origin: https://evil.example``)
and a local program alike, since the SDK's server shows no client's origin.
"""

from __future__ import annotations

import asyncio
import os
import re
import secrets
import subprocess
import sys
from pathlib import Path

import pytest

from daemon_api._serving import free_port, stop_serving
from ohmni_tb import Robot
from ohmni_tb.cli.serve import parse_foxglove
from ohmni_tb.client import RobotClient
from ohmni_tb.errors import ConfigError
from ohmni_tb.foxglove import FoxgloveBridge

from ._wire import UNLOCK, FoxgloveClient
from .test_serve_foxglove import gains_now, serving_with_view, unlock_token

P = "/tb_control/"


@pytest.fixture
def config_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """$XDG_CONFIG_HOME of the daemon: its default token file is made there."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    return tmp_path


async def odom_x(url: str) -> float:
    async with RobotClient.connect(url) as client:
        odom = client.latest("wheel_odom")
        assert odom is not None
        return float(odom.x_m)


async def drive_for(foxglove: FoxgloveClient, linear: float, seconds: float) -> None:
    """Twists at 10 Hz, as the Teleop panel sends them while a button is held."""
    for _ in range(round(seconds * 10)):
        await foxglove.send_twist(linear)
        await asyncio.sleep(0.1)


def test_a_client_drives_changes_and_calls_only_after_unlocking(config_home: Path) -> None:
    proc, url, view = serving_with_view("--foxglove-control")
    try:

        async def run() -> None:
            # A web page and a local program: both watch, neither controls.
            for origin in ("https://evil.example", None):
                locked = await FoxgloveClient.connect(view, origin=origin)
                try:
                    await locked.subscribe("/tf")
                    assert await locked.messages(0.5), "a locked client still watches"
                    await locked.advertise_twist()
                    await drive_for(locked, 0.3, 1.0)
                    assert await odom_x(url) == pytest.approx(0.0, abs=0.002)
                    assert UNLOCK in locked.services
                    said = await locked.status("control is locked")
                    assert UNLOCK in said["message"]

                    async with RobotClient.connect(url) as reader:
                        kp = reader.get_pid().kp
                        await locked.set_parameters({P + "pid_kp": kp + 50.0})
                        assert (await gains_now(url)).kp == kp
                    assert any(
                        "control is locked" in s["message"] and "parameters not set" in s["message"]
                        for s in locked.statuses
                    ), locked.statuses
                    refused = await locked.call_service(P + "reset_odom", {"x_m": 2.0}, call_id=3)
                    assert UNLOCK in refused["failure"], refused
                    wrong = await locked.unlock("not-the-token-" + secrets.token_urlsafe(8))
                    assert "wrong token" in wrong["failure"], wrong
                    await drive_for(locked, 0.3, 0.5)
                    assert await odom_x(url) == pytest.approx(0.0, abs=0.002)
                finally:
                    await locked.close()

            # The app, unlocked with the token: it drives.
            foxglove = await FoxgloveClient.connect(view)
            try:
                assert await foxglove.unlock(unlock_token(config_home)) == {"unlocked": True}
                await foxglove.advertise_twist()
                await drive_for(foxglove, 0.3, 1.5)
                assert await odom_x(url) > 0.2
            finally:
                await foxglove.close()

        asyncio.run(run())
    finally:
        log = stop_serving(proc)
    assert "Traceback" not in log


def test_a_flood_of_twists_leaves_the_teleop_working(config_home: Path) -> None:
    proc, url, view = serving_with_view("--foxglove-control")
    token = unlock_token(config_home)
    try:

        async def run() -> None:
            foxglove = await FoxgloveClient.connect(view)
            try:
                assert await foxglove.unlock(token) == {"unlocked": True}
                await foxglove.advertise_twist()
                for _ in range(500):  # as fast as the socket takes them
                    await foxglove.send_twist(0.0)
                await asyncio.sleep(1.0)
                start = await odom_x(url)
                await drive_for(foxglove, 0.3, 1.5)
                assert await odom_x(url) - start > 0.2
                values = await foxglove.get_parameters(P + "pid_kp")
                assert P + "pid_kp" in values, foxglove.statuses
            finally:
                await foxglove.close()

        asyncio.run(run())
    finally:
        log = stop_serving(proc)
    assert "rate limit" not in log
    assert "Traceback" not in log


#: Values the Robot refuses, and the words of its refusal: the value and the range.
REFUSED = [
    (P + "pid_ff_offset", 1e6, "pid ff_offset=1000000.0 is out of range: allowed 0.0..200.0"),
    (P + "rate/wheel_encoder", 0.1, "wheel_encoder rate=0.1 is out of range: allowed 10"),
    (P + "pid_kp", "fast", "must be a number, not 'fast'"),
]


def test_a_refused_parameter_is_told_at_once_and_the_next_twist_drives(
    config_home: Path,
) -> None:
    proc, url, view = serving_with_view("--foxglove-control")
    token = unlock_token(config_home)
    try:

        async def run() -> None:
            foxglove = await FoxgloveClient.connect(view)
            try:
                assert await foxglove.unlock(token) == {"unlocked": True}
                await foxglove.advertise_twist()
                before = await foxglove.get_parameters()
                for request, (name, value, said) in enumerate(REFUSED):
                    answered = await foxglove.set_parameters({name: value}, request_id=name)
                    # Told by the time of the answer, not later.
                    assert any(said in s["message"] for s in foxglove.statuses), (
                        said,
                        foxglove.statuses,
                    )
                    assert answered.get(name, before[name]) == before[name]
                    async with RobotClient.connect(url) as reader:
                        gains = reader.get_pid()
                        stats = reader.stats()
                    assert (gains.kp, gains.ff_offset) == (
                        before[P + "pid_kp"],
                        before[P + "pid_ff_offset"],
                    ), request
                    assert stats.streams["wheel_encoder"].requested_hz == 50.0
                    # One Twist right after: not the one an earlier refusal drops.
                    start = await odom_x(url)
                    await foxglove.send_twist(0.3)
                    await asyncio.sleep(0.8)
                    assert await odom_x(url) - start > 0.02, request
            finally:
                await foxglove.close()

        asyncio.run(run())
    finally:
        log = stop_serving(proc)
    assert "foxglove teleop" not in log  # no Twist was refused
    assert "Traceback" not in log


def test_control_beyond_loopback_needs_the_daemons_token() -> None:
    # Its own process: a daemon that would start anyway is ended, and the test fails.
    try:
        done = subprocess.run(
            [
                sys.executable,
                "-m",
                "ohmni_tb",
                "serve",
                "--port",
                "sim://",
                "--listen",
                f"127.0.0.1:{free_port()}",
                "--foxglove",
                f"0.0.0.0:{free_port()}",
                "--foxglove-control",
            ],
            check=False,
            capture_output=True,
            timeout=30,
            env={**os.environ, "COLUMNS": "300"},
        )
    except subprocess.TimeoutExpired:
        pytest.fail("ohmni serve started with --foxglove-control beyond loopback and no token")
    assert done.returncode == 2
    text = " ".join(done.stderr.decode().replace("│", " ").split())
    assert "--foxglove-control on 0.0.0.0, beyond loopback, needs the daemon's token" in text
    assert "--token-file" in text


def test_the_warning_beyond_loopback_says_what_a_client_there_can_do(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert parse_foxglove("0.0.0.0:0", control=True, token=secrets.token_urlsafe(32)) == (
        "0.0.0.0",
        0,
    )
    warned = " ".join(capsys.readouterr().err.split())
    assert re.search(
        r"anyone who reaches it can watch every stream and read the parameters, and drive, "
        r"set parameters and call services only with the token \(/tb_control/unlock",
        warned,
    ), warned
    parse_foxglove("0.0.0.0:0")
    warned = " ".join(capsys.readouterr().err.split())
    assert "can watch every stream and read the parameters, and change nothing" in warned


async def test_a_bridge_that_takes_control_needs_a_token() -> None:
    async with Robot.open("sim://") as robot:
        with pytest.raises(ConfigError, match="needs a token"):
            FoxgloveBridge(robot, port=0, teleop=lambda linear, angular, ramped: None)
        with pytest.raises(ConfigError, match="16"):
            FoxgloveBridge(
                robot, port=0, teleop=lambda linear, angular, ramped: None, token="short"
            )
