"""``ohmni serve --foxglove``: the daemon serves the Foxglove app beside its own clients."""

from __future__ import annotations

import asyncio
import json
import os
import select
import time
from subprocess import Popen

from typer.testing import CliRunner

from daemon_api._serving import free_port, start_serving, stop_serving
from ohmni_tb.cli import app
from ohmni_tb.client import RobotClient

from ._wire import FoxgloveClient


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
                async with RobotClient.connect(url) as client:  # the daemon's own client
                    status = await client.latest("tbcore_status")
                    assert status is not None
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
