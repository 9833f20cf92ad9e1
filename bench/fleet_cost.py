"""What a fleet on MQTT costs: the bridge on the robot, and the broker and the fleet view
with 100 robots.

Run: ``python bench/fleet_cost.py`` (``--seconds`` per row, 8 by default: about 30 s in all).
Needs the ``mqtt`` extra and ``mosquitto`` (``apt-get install mosquitto``); it starts its
own broker on a free loopback port.

* ``bridge``: ``Robot.open(...)`` on ``ohmni sim --pty`` (the simulator in its own
  process, so the CPU is the driver's alone, as on the robot) served by a
  :class:`~ohmni_tb.daemon.server.RobotServer`, first alone (``daemon``), then with its
  :class:`~ohmni_tb.mqtt.MqttBridge` at the default rates (``daemon + bridge``): the CPU
  share of one core of the whole process (``time.process_time``) and what the bridge
  adds, the messages it published a second, the control tick's rate and its skipped
  cycles.
* ``100 robots``: one process publishing as 100 bridges do (a connection each, with its
  Last Will; ``online``; the state retained every 10 s; odometry at 5 Hz and the battery
  at 1 Hz, the daemon's own payloads), and ``ohmni fleet --watch --json`` watching them:
  the CPU share of the broker, of the fleet view and of the publishing process.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from ohmni_tb import eventloop
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.mqtt import Broker, MqttBridge
from ohmni_tb.mqtt.payloads import (
    ONLINE,
    STATE_PERIOD_S,
    BatteryState,
    BridgeFigures,
    NeckState,
    StatePayload,
    robot_topic,
)
from ohmni_tb.robot import Robot
from ohmni_tb.robot.wire import sample_json

sys.path.insert(0, str(Path(__file__).parent))
from _pty import simulator_on_pty
from schedule import machine

ROBOTS = 100
_TICKS = os.sysconf("SC_CLK_TCK")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def cpu_s(pid: int) -> float:
    """A process's CPU time so far (user + system), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICKS


def start_broker(directory: Path) -> tuple[subprocess.Popen[bytes], str]:
    search = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin"])
    mosquitto = shutil.which("mosquitto", path=search)
    if mosquitto is None:
        raise SystemExit("needs mosquitto: apt-get install mosquitto")
    port = free_port()
    config = directory / "mosquitto.conf"
    user = subprocess.run(["id", "-un"], capture_output=True, text=True, check=True).stdout
    config.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
        f"log_type error\nuser {user.strip()}\nmax_queued_messages 10000\n"
    )
    proc = subprocess.Popen(
        [mosquitto, "-c", str(config)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    deadline = time.monotonic() + 10
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return proc, f"mqtt://127.0.0.1:{port}"
        except OSError:
            if time.monotonic() > deadline:
                proc.kill()
                raise
            time.sleep(0.05)


async def bridge_rows(path: str, url: str, seconds: float) -> None:
    async with (
        Robot.open(path, mqtt_url=url, robot_id="bench") as robot,
        RobotServer(robot, port=0) as server,
    ):
        await asyncio.sleep(2.0)  # settled: the neck's settings, the first reads

        async def window() -> tuple[float, float, int, int]:
            tick0 = robot.stats().streams["wheel_encoder"]
            cpu0, wall0 = time.process_time(), time.monotonic()
            await asyncio.sleep(seconds)
            tick = robot.stats().streams["wheel_encoder"]
            share = (time.process_time() - cpu0) / (time.monotonic() - wall0)
            return share, tick.achieved_hz, tick.skipped - tick0.skipped, tick.samples

        alone, hz, skipped, _ = await window()
        print(f"  daemon           CPU {alone:6.1%}  tick {hz:5.1f} Hz, {skipped} skipped")
        async with MqttBridge(robot, server) as bridge:
            await bridge.wait_connected()
            await asyncio.sleep(1.0)
            published = bridge.published
            with_bridge, hz, skipped, _ = await window()
            rate = (bridge.published - published) / seconds
        print(
            f"  daemon + bridge  CPU {with_bridge:6.1%}  tick {hz:5.1f} Hz, {skipped} skipped; "
            f"{rate:.1f} messages/s"
        )
        print(f"  the bridge adds  {with_bridge - alone:+.1%} of one core")


async def publish_like_bridges(url: str, seconds: float) -> tuple[float, int]:
    """ROBOTS connections publishing as the bridge does, for ``seconds``; the CPU share
    of this process, and the messages published."""
    async with Robot.open("sim://") as robot:
        await asyncio.sleep(1.2)
        odom = robot.latest("wheel_odom")
        core = robot.latest("tbcore_status")
        assert odom is not None
        assert core is not None
    odom_json = json.dumps(sample_json(odom)).encode()
    core_json = json.dumps(sample_json(core)).encode()
    state_json = (
        StatePayload(
            robot_id="r000",
            time=time.time(),
            version="0",
            simulated=True,
            link="connected",
            estopped=False,
            faults=[],
            battery=BatteryState(
                percent=core.percent,
                pack_v=core.pack_v,
                cell_v=list(core.cell_v),
                current_a=core.current_a,
                docked=core.docked,
                charging=core.charging,
            ),
            neck=NeckState(kind="herkulex", position_raw=465),
            lease=None,
            firmware={"left_drive": "x", "right_drive": "x", "core": "x"},
            drive=False,
            uptime_s=1.0,
            bridge=BridgeFigures(connects=1, published=0, dropped=0, commands=0, refused=0),
        )
        .model_dump_json()
        .encode()
    )
    count = 0

    async def one(index: int) -> None:
        nonlocal count
        robot_id = f"r{index:03d}"
        broker = Broker.from_url(url, keepalive_s=30)
        will = (robot_topic(robot_id, "availability"), "offline")
        async with broker.client(f"bench-{robot_id}", will=will) as client:
            await client.publish(will[0], ONLINE, qos=1, retain=True)
            loop = asyncio.get_running_loop()
            start = loop.time() + index * 0.002  # spread, as robots are
            tick = 0
            while loop.time() - start < seconds:
                await asyncio.sleep(max(0.0, start + tick * 0.2 - loop.time()))
                await client.publish(robot_topic(robot_id, "stream", "wheel_odom"), odom_json)
                count += 1
                if tick % 5 == 0:
                    topic = robot_topic(robot_id, "stream", "tbcore_status")
                    await client.publish(topic, core_json)
                    count += 1
                if tick % round(STATE_PERIOD_S / 0.2) == 0:
                    topic = robot_topic(robot_id, "state")
                    await client.publish(topic, state_json, qos=1, retain=True)
                    count += 1
                tick += 1

    cpu0, wall0 = time.process_time(), time.monotonic()
    await asyncio.gather(*(one(i) for i in range(ROBOTS)))
    return (time.process_time() - cpu0) / (time.monotonic() - wall0), count


def fleet_rows(url: str, broker_pid: int, seconds: float) -> None:
    view = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "fleet", "--mqtt", url, "--watch", "--json"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        time.sleep(1.5)  # started
        broker0, view0, wall0 = cpu_s(broker_pid), cpu_s(view.pid), time.monotonic()
        share, messages = eventloop.run(publish_like_bridges(url, seconds))
        wall = time.monotonic() - wall0
        broker_share = (cpu_s(broker_pid) - broker0) / wall
        view_share = (cpu_s(view.pid) - view0) / wall
    finally:
        view.terminate()
        view.wait()
    print(f"  {ROBOTS} robots: {messages / seconds:.0f} messages/s to the broker")
    print(f"  broker (mosquitto)        CPU {broker_share:6.1%}")
    print(f"  ohmni fleet --watch       CPU {view_share:6.1%}")
    print(f"  the {ROBOTS} publishers       CPU {share:6.1%} ({share / ROBOTS:.2%} a robot)")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=8.0, help="seconds per row")
    args = parser.parse_args()
    print(machine())
    with tempfile.TemporaryDirectory() as directory:
        broker, url = start_broker(Path(directory))
        try:
            print("bridge (default rates: wheel_odom 5 Hz, tbcore_status 1 Hz, state):")
            with simulator_on_pty() as path:
                eventloop.run(bridge_rows(path, url, args.seconds))
            print(f"fleet ({ROBOTS} robots publishing like the bridge):")
            fleet_rows(url, broker.pid, args.seconds)
        finally:
            broker.terminate()
            broker.wait()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
