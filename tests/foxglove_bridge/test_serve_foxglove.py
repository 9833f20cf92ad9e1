"""``ohmni serve --foxglove``: the daemon serves the Foxglove app beside its own clients."""

from __future__ import annotations

import asyncio
import json
import os
import select
import struct
import time
from pathlib import Path
from subprocess import Popen

import pytest
from typer.testing import CliRunner

from daemon_api._serving import free_port, start_serving, stop_serving
from ohmni_tb.cli import app
from ohmni_tb.client import RobotClient
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import LeaseError, SourceOverriddenError
from ohmni_tb.foxglove.bridge import parse_twist

from ._wire import FoxgloveClient


async def gains_now(url: str) -> PidGains:
    """The daemon's wheel gains now: a new connection fetches them."""
    async with RobotClient.connect(url) as reader:
        return reader.get_pid()


def next_line(proc: Popen[bytes], timeout_s: float = 20.0) -> str:
    """The next line ``ohmni serve`` writes to stdout."""
    assert proc.stdout is not None
    deadline = time.monotonic() + timeout_s
    line = b""
    while not line.endswith(b"\n"):
        ready, _, _ = select.select([proc.stdout], [], [], deadline - time.monotonic())
        assert ready, "ohmni serve printed no second line"
        chunk = os.read(proc.stdout.fileno(), 1)
        assert chunk, "ohmni serve ended early"
        line += chunk
    return line.decode().strip()


def serving_with_view(*args: str) -> tuple[Popen[bytes], str, str]:
    """``ohmni serve --foxglove`` on free ports: the process, its URL and the view's."""
    proc, url = start_serving(
        "--listen", f"127.0.0.1:{free_port()}", "--foxglove", f"127.0.0.1:{free_port()}", *args
    )
    try:
        return proc, url, next_line(proc)
    except BaseException:
        stop_serving(proc)
        raise


def test_the_daemon_serves_the_foxglove_app_and_its_clients_at_once() -> None:
    proc, url = start_serving(
        "--listen", f"127.0.0.1:{free_port()}", "--foxglove", f"127.0.0.1:{free_port()}"
    )
    try:
        view = next_line(proc)
        assert view.startswith("ws://127.0.0.1:")

        async def watch() -> None:
            foxglove = await FoxgloveClient.connect(view)
            try:
                assert {"/tf", "/tb_control/wheel_odom", "/tb_control/tbcore_status"} <= set(
                    foxglove.channels
                )
                await foxglove.subscribe("/tb_control/tbcore_status", "/tf")
                async with (
                    RobotClient.connect(url) as client,  # the daemon's own client
                    client.subscribe("tbcore_status") as status,
                ):
                    assert (await anext(status)).pack_v > 10
                messages = await foxglove.messages(1.0)
            finally:
                await foxglove.close()
            battery = [m for m in messages if m.topic == "/tb_control/tbcore_status"]
            assert len(battery) >= 5  # 10 Hz
            assert json.loads(battery[-1].payload)["pack_v"] > 10
            assert sum(m.topic == "/tf" for m in messages) >= 25  # 50 Hz

        asyncio.run(watch())
    finally:
        log = stop_serving(proc)
    assert "Traceback" not in log


def test_a_bad_foxglove_address_is_refused_before_the_port_opens() -> None:
    result = CliRunner().invoke(
        app, ["serve", "--port", "sim://", "--foxglove", "localhost:99999"], env={"COLUMNS": "300"}
    )
    assert result.exit_code == 2
    assert "--foxglove must be [HOST:]PORT with a port 0..65535, not 'localhost:99999'" in (
        " ".join(result.output.replace("│", " ").split())
    )


def unlock_token(config_home: Path) -> str:
    """The token a loopback daemon without one unlocks Foxglove control with: the default
    token file's ($XDG_CONFIG_HOME/ohmni/daemon-token)."""
    return (config_home / "ohmni" / "daemon-token").read_text().strip()


@pytest.fixture
def config_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """$XDG_CONFIG_HOME for the daemons these tests start (their token file is there)."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    return tmp_path


async def publish_twists(
    view: str, linear: float, seconds: float, token: str | None = None
) -> None:
    """As the Foxglove Teleop panel does: advertise a Twist channel, publish at 10 Hz
    (having unlocked control with ``token``, when given)."""
    foxglove = await FoxgloveClient.connect(view)
    try:
        if token is not None:
            assert await foxglove.unlock(token) == {"unlocked": True}
        await foxglove.ws.send(
            json.dumps(
                {
                    "op": "advertise",
                    "channels": [
                        {
                            "id": 1,
                            "topic": "/tb_cmd_vel",
                            "encoding": "json",
                            "schemaName": "geometry_msgs/Twist",
                        }
                    ],
                }
            )
        )
        twist = json.dumps(
            {"linear": {"x": linear, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0}}
        ).encode()
        for _ in range(round(seconds * 10)):
            await foxglove.ws.send(struct.pack("<BI", 1, 1) + twist)
            await asyncio.sleep(0.1)
    finally:
        await foxglove.close()


async def travelled(url: str) -> float:
    async with RobotClient.connect(url) as client:
        odom = client.latest("wheel_odom")
        assert odom is not None
        return float(odom.x_m)


async def lease_is_free_again(url: str) -> None:
    """The app gives the lease back a second after its last use: another client takes it
    (asked until then: on a loaded machine the daemon's timer runs late)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 10.0
    await asyncio.sleep(1.0)
    async with RobotClient.connect(url, source="remote") as after:
        while True:
            try:
                await after.acquire()
            except LeaseError:
                assert loop.time() < deadline, "the app kept the lease"
                await asyncio.sleep(0.1)
            else:
                return


def test_the_teleop_panel_drives_only_with_control_and_the_lease(config_home: Path) -> None:
    proc, url, view = serving_with_view("--foxglove-control")
    token = unlock_token(config_home)
    try:

        async def drive() -> None:
            # Another client holds the lease of the panel's command source (remote): the
            # panel's Twists move nothing.
            async with RobotClient.connect(url, source="remote") as holder:
                await holder.acquire()
                await publish_twists(view, 0.3, 1.0, token)
                assert await travelled(url) == pytest.approx(0.0, abs=0.002)
                # Given back in order (a closing connection frees it only once the daemon
                # has seen the close).
                await holder.release()
            # Free: the panel takes the lease and drives; the wheels follow. A script
            # (autonomy, below remote) holding its own lease does not hold it back: the
            # panel overrides it, and the script's drive commands are refused meanwhile.
            async with RobotClient.connect(url) as script:
                await script.acquire()
                panel = asyncio.create_task(publish_twists(view, 0.3, 1.5, token))
                await asyncio.sleep(1.0)
                script.drive(-0.3, 0.0)
                with pytest.raises(SourceOverriddenError, match="'remote'"):
                    await script.confirm()
                await panel
            assert await travelled(url) > 0.2
            # It gives the lease back after its last Twist: another client may drive.
            await lease_is_free_again(url)

        asyncio.run(drive())
    finally:
        log = stop_serving(proc)
    assert "foxglove teleop refused" in log


def test_parameters_and_services_change_the_robot_only_through_the_lease(
    config_home: Path,
) -> None:
    proc, url, view = serving_with_view("--foxglove-control")
    token = unlock_token(config_home)
    try:

        async def change() -> None:
            foxglove = await FoxgloveClient.connect(view)
            try:
                assert set(foxglove.services) == {
                    "/tb_control/unlock",
                    "/tb_control/reset_odom",
                    "/tb_control/set_odometry",
                    "/tb_control/neck_move",
                }
                assert await foxglove.unlock(token) == {"unlocked": True}
                # Another client holds the lease: refused, named, nothing changed.
                async with RobotClient.connect(url, source="remote") as holder:
                    await holder.acquire()
                    refused = await foxglove.call_service(
                        "/tb_control/reset_odom", {"x_m": 2.0}, call_id=1
                    )
                    assert "lease" in refused["failure"], refused
                    kp = holder.get_pid().kp
                    await foxglove.set_parameters({"/tb_control/pid_kp": kp + 100})
                    assert (await gains_now(url)).kp == kp
                    await holder.release()  # in order: before the call below
                # Free: the app takes the lease for the call, and the daemon's Robot changes.
                pose = await foxglove.call_service(
                    "/tb_control/reset_odom", {"x_m": 2.0, "yaw_rad": 0.25}, call_id=2
                )
                assert pose == {"x_m": 2.0, "y_m": 0.0, "yaw_rad": 0.25}
                values = await foxglove.set_parameters(
                    {"/tb_control/pid_kp": kp + 100, "/tb_control/rate/tbcore_status": 5.0}
                )
                assert values["/tb_control/pid_kp"] == kp + 100
                assert values["/tb_control/rate/tbcore_status"] == 5.0
            finally:
                await foxglove.close()
            await asyncio.sleep(0.2)
            async with RobotClient.connect(url) as reader:
                odom = reader.latest("wheel_odom")
                assert odom is not None
                assert (odom.x_m, odom.yaw_rad) == pytest.approx((2.0, 0.25), abs=1e-3)
                assert reader.get_pid().kp == kp + 100
                stats = reader.stats()
                assert stats.streams["tbcore_status"].requested_hz == 5.0
            # Given back a second after the last change: another client may drive.
            await lease_is_free_again(url)

        asyncio.run(change())
    finally:
        log = stop_serving(proc)
    assert "Traceback" not in log


def test_without_control_the_panel_cannot_publish() -> None:
    proc, url = start_serving(
        "--listen", f"127.0.0.1:{free_port()}", "--foxglove", f"127.0.0.1:{free_port()}"
    )
    try:
        view = next_line(proc)

        async def drive() -> None:
            foxglove = await FoxgloveClient.connect(view)
            capabilities = foxglove.server_info.get("capabilities", [])
            await foxglove.close()
            assert "clientPublish" not in capabilities
            await publish_twists(view, 0.3, 1.0)
            assert await travelled(url) == pytest.approx(0.0, abs=0.002)

        asyncio.run(drive())
    finally:
        stop_serving(proc)


def test_control_without_a_view_is_refused() -> None:
    result = CliRunner().invoke(
        app, ["serve", "--port", "sim://", "--foxglove-control"], env={"COLUMNS": "300"}
    )
    assert result.exit_code == 2
    assert "--foxglove-control needs --foxglove" in result.output


@pytest.mark.parametrize(
    ("data", "said"),
    [
        (b"not json", "Expecting value"),
        (b'{"linear": {"x": 1}}', "not a geometry_msgs/Twist"),
        (b'{"linear": {"x": "fast"}, "angular": {"z": 0}}', "linear.x must be a finite number"),
        (b'{"linear": {"x": 1e999}, "angular": {"z": 0}}', "linear.x must be a finite number"),
        (b'{"linear": {"x": 0}, "angular": {"z": NaN}}', "angular.z must be a finite number"),
    ],
)
def test_a_twist_that_is_not_one_is_refused(data: bytes, said: str) -> None:
    with pytest.raises(ValueError, match=said):
        parse_twist(data)
    assert parse_twist(b'{"linear": {"x": 0.2}, "angular": {"z": -0.5}}') == (0.2, -0.5)
