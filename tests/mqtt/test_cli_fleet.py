"""``ohmni fleet`` as a person runs it, and ``ohmni serve``'s MQTT options refused before
anything opens."""

from __future__ import annotations

import asyncio
import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

from typer.testing import CliRunner

from ohmni_tb.cli import app
from ohmni_tb.mqtt.payloads import BatteryState, BridgeFigures, NeckState, StatePayload

from ._helpers import mqtt_client
from .conftest import Mosquitto, free_port


def state(robot_id: str, *, percent: int, docked: bool, faults: list[str]) -> str:
    """A state as a robot's bridge publishes it."""
    return StatePayload(
        robot_id=robot_id,
        time=time.time() - 3,
        version="0",
        simulated=True,
        link="connected",
        estopped=False,
        faults=faults,
        battery=BatteryState(
            percent=percent,
            pack_v=16.0,
            cell_v=[3.2] * 5,
            current_a=0.0,
            docked=docked,
            charging=docked,
        ),
        neck=NeckState(kind="none", position_raw=None),
        lease=None,
        firmware={},
        drive=False,
        uptime_s=9.0,
        bridge=BridgeFigures(connects=1, published=1, dropped=0, commands=0, refused=0),
    ).model_dump_json()


async def publish(url: str, *messages: tuple[str, str]) -> None:
    async with mqtt_client(url) as client:
        for topic, text in messages:
            await client.publish(topic, text, qos=1, retain=True)


def test_the_table_lists_every_robot(broker: Mosquitto) -> None:
    asyncio.run(
        publish(
            broker.url,
            ("ohmni/ward-2/availability", "online"),
            ("ohmni/ward-2/state", state("ward-2", percent=80, docked=True, faults=[])),
            ("ohmni/lobby/availability", "offline"),
            ("ohmni/lobby/state", state("lobby", percent=20, docked=False, faults=["link_lost"])),
        )
    )
    result = CliRunner().invoke(app, ["fleet", "--mqtt", broker.url], env={"COLUMNS": "120"})
    assert result.exit_code == 0, result.output
    lines = [line.split() for line in result.stdout.splitlines() if line.strip()]
    assert lines[0] == ["robot", "online", "battery", "docked", "faults", "last", "seen"]
    assert lines[2][:6] == ["lobby", "no", "20", "%", "no", "link_lost"]
    assert lines[3][:6] == ["ward-2", "yes", "80", "%", "yes", "none"]
    assert lines[3][6:] == ["3", "s", "ago"]


def test_it_says_when_the_broker_knows_no_robot(broker: Mosquitto) -> None:
    result = CliRunner().invoke(app, ["fleet", "--mqtt", broker.url])
    assert result.exit_code == 0, result.output
    assert "the broker knows no robot" in result.stdout
    listed = CliRunner().invoke(app, ["fleet", "--mqtt", broker.url, "--json"])
    assert json.loads(listed.stdout) == []


def test_watch_prints_the_fleet_again_on_every_change(broker: Mosquitto) -> None:
    asyncio.run(publish(broker.url, ("ohmni/x/availability", "online")))
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "fleet", "--mqtt", broker.url, "--watch", "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None
    try:
        first = _line(proc)
        assert [(r["robot_id"], r["online"]) for r in first] == [("x", True)]
        asyncio.run(publish(broker.url, ("ohmni/x/availability", "offline")))
        second = _line(proc)
        assert [(r["robot_id"], r["online"]) for r in second] == [("x", False)]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()
        if proc.stderr is not None:
            proc.stderr.close()


def _line(proc: subprocess.Popen[bytes]) -> list[dict[str, object]]:
    assert proc.stdout is not None
    ready, _, _ = select.select([proc.stdout], [], [], 15)
    assert ready, "no line from ohmni fleet --watch"
    listed: list[dict[str, object]] = json.loads(proc.stdout.readline())
    return listed


def test_without_a_broker_it_says_where_to_name_one(tmp_path: Path) -> None:
    env = {name: "" for name in os.environ if name.startswith("OHMNI_MQTT")}
    env["XDG_CONFIG_HOME"] = str(tmp_path)  # no config file of this machine's
    result = CliRunner().invoke(app, ["fleet"], env=env)
    assert result.exit_code == 2
    assert "no broker: give --mqtt URL, or set mqtt_url" in result.output
    bad = CliRunner().invoke(app, ["fleet", "--mqtt", "http://broker"])
    assert bad.exit_code == 2
    assert "mqtt_url='http://broker' is not a broker URL" in bad.output


def test_a_broker_that_does_not_answer_is_one_error_line() -> None:
    result = CliRunner().invoke(app, ["fleet", "--mqtt", f"mqtt://127.0.0.1:{free_port()}"])
    assert result.exit_code == 1
    assert "cannot reach the broker at mqtt://127.0.0.1:" in result.output


def test_serve_refuses_a_bad_mqtt_option_before_opening_the_port() -> None:
    result = CliRunner().invoke(
        app, ["serve", "--port", "sim://", "--mqtt", "mqtt://broker/x", "--robot-id", "a"]
    )
    assert result.exit_code == 2
    assert "mqtt_url='mqtt://broker/x' is not a broker URL" in result.output
    named = CliRunner().invoke(
        app, ["serve", "--port", "sim://", "--mqtt", "mqtt://broker", "--robot-id", "a b"]
    )
    assert named.exit_code == 2
    assert "robot_id='a b' is not a name" in named.output
    rates = CliRunner().invoke(
        app,
        ["serve", "--port", "sim://", "--mqtt", "mqtt://broker"],
        env={"OHMNI_MQTT_RATES": "odometry=5"},
    )
    assert rates.exit_code == 2
    assert "names no stream odometry" in rates.output
