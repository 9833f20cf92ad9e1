"""Losing the broker never disturbs the robot: the control tick keeps its rate, the
bridge's queues stay bounded (the oldest dropped, counted), and it connects again when the
broker is back; a command holding the lease when the broker goes ends with the wheels
stopped."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.mqtt import MqttBridge
from ohmni_tb.mqtt.payloads import StatePayload
from ohmni_tb.robot import StreamStats
from ohmni_tb.sim.clock import run_virtual

from ._helpers import mqtt_client, next_message, payload, served
from .conftest import Mosquitto, free_port


async def _until(condition: Callable[[], bool], timeout_s: float) -> None:
    async with asyncio.timeout(timeout_s):
        while not condition():  # noqa: ASYNC110  # polled: the robot's and bridge's state
            await asyncio.sleep(0.02)


#: Every sample of the fast streams: more than the bridge's queue holds in 2 s offline.
_BUSY = "wheel_encoder=50,wheel_odom=50,servo_neck=30,tbcore_status=10"


def test_the_control_tick_keeps_its_rate_while_the_broker_is_away() -> None:
    """On the simulator's virtual clock, so the figures are exact: a minute with no broker
    (a port nothing listens on), every stream sampled for it, costs the tick nothing."""

    async def main() -> tuple[StreamStats, StreamStats, MqttBridge]:
        url = f"mqtt://127.0.0.1:{free_port()}"
        async with (
            Robot.open("sim://", mqtt_url=url, robot_id="a", mqtt_rates=_BUSY) as robot,
            RobotServer(robot, port=0) as server,
            MqttBridge(robot, server) as bridge,
        ):
            await asyncio.sleep(1.0)
            before = robot.stats().streams["wheel_encoder"]
            await asyncio.sleep(60.0)
            after = robot.stats().streams["wheel_encoder"]
            assert not bridge.connected
        return before, after, bridge

    before, after, bridge = run_virtual(main())
    assert after.samples - before.samples == pytest.approx(60 * 50, abs=1)
    assert (after.skipped, after.missed) == (before.skipped, before.missed)
    assert after.achieved_hz == pytest.approx(50.0, rel=0.01)
    # 140 samples a second could not go out: the queue kept the newest, the rest counted.
    assert bridge.dropped > 60 * 140 - 2 * 256
    assert bridge.connects == 0


async def test_it_connects_again_when_the_broker_is_back(broker: Mosquitto) -> None:
    async with served(broker.url, "a", mqtt_rates=_BUSY) as robot:
        await asyncio.to_thread(broker.stop)
        await asyncio.sleep(2.5)
        assert not robot.bridge.connected
        dropped = robot.bridge.dropped
        assert dropped > 0  # more than the queue holds waited: the oldest went
        await asyncio.to_thread(broker.start)
        await _until(lambda: robot.bridge.connects == 2 and robot.bridge.connected, 10)
        async with mqtt_client(broker.url) as client:
            await client.subscribe("ohmni/a/availability")
            assert (await next_message(client, "ohmni/a/availability")).payload == b"online"
            await client.subscribe("ohmni/a/state")
            state = StatePayload.model_validate(
                payload(await next_message(client, "ohmni/a/state"))
            )
    assert state.bridge.connects == 2
    assert state.bridge.dropped >= dropped


async def test_a_command_holding_the_lease_ends_when_the_broker_goes(broker: Mosquitto) -> None:
    """Nobody could stop it over MQTT any more: the lease is released, the wheels stop."""
    async with served(broker.url, "a", mqtt_drive=True) as robot:
        async with mqtt_client(broker.url) as client:
            await client.publish(
                "ohmni/a/cmd/rotate", '{"angle_rad": 6.0, "speed_radps": 0.5}', qos=1
            )
        await _until(lambda: robot.server.lease_holder is not None, 5)
        await asyncio.sleep(0.5)
        sim = robot.robot.sim
        assert sim is not None
        assert max(abs(s) for s in sim.wheel_speeds_mps()) > 0.01
        await asyncio.to_thread(broker.stop)
        await _until(lambda: robot.server.lease_holder is None, 5)
        await asyncio.sleep(0.5)
        assert max(abs(s) for s in sim.wheel_speeds_mps()) < 0.01
