"""Losing the broker never disturbs the robot: the control tick keeps its rate, the
bridge's queues stay bounded (the oldest dropped, counted), and it connects again when the
broker is back; a command holding the lease when the broker goes ends with the wheels
stopped."""

from __future__ import annotations

import asyncio

from ohmni_tb.mqtt.payloads import StatePayload

from ._helpers import mqtt_client, next_message, payload, served
from .conftest import Mosquitto

#: Every sample of the fast streams: more than the bridge's queue holds in 2 s offline.
_BUSY = "wheel_encoder=50,wheel_odom=50,servo_neck=30,tbcore_status=10"


async def test_the_control_tick_keeps_its_rate_while_the_broker_is_away(
    broker: Mosquitto,
) -> None:
    async with served(broker.url, "a", mqtt_rates=_BUSY) as robot:
        await asyncio.sleep(1.0)
        before = robot.robot.stats().streams["wheel_encoder"]
        await asyncio.to_thread(broker.stop)
        await asyncio.sleep(2.5)
        during = robot.robot.stats().streams["wheel_encoder"]
        assert not robot.bridge.connected
        # The tick at 50 Hz throughout: its rate, its samples, hardly a cycle skipped
        # (a busy machine skips a few with or without a broker).
        cycles = 2.5 * during.requested_hz
        assert during.achieved_hz > 0.95 * during.requested_hz
        assert during.samples - before.samples >= 0.95 * cycles
        assert during.skipped - before.skipped <= 0.05 * cycles
        # What could not go out was dropped, oldest first, and counted.
        dropped = robot.bridge.dropped
        assert dropped > 0
        await asyncio.to_thread(broker.start)
        async with asyncio.timeout(10):
            while robot.bridge.connects < 2 or not robot.bridge.connected:  # noqa: ASYNC110
                await asyncio.sleep(0.05)
        async with mqtt_client(broker.url) as client:
            await client.subscribe("ohmni/a/availability")
            assert (await next_message(client, "ohmni/a/availability")).payload == b"online"
            await client.subscribe("ohmni/a/state")
            state = StatePayload.model_validate(
                payload(await next_message(client, "ohmni/a/state"))
            )
        after = robot.robot.stats().streams["wheel_encoder"]
        assert after.achieved_hz > 0.95 * after.requested_hz
    assert state.bridge.connects == 2
    assert state.bridge.dropped >= dropped


async def test_a_command_holding_the_lease_ends_when_the_broker_goes(broker: Mosquitto) -> None:
    """Nobody could stop it over MQTT any more: the lease is released, the wheels stop."""
    async with served(broker.url, "a", mqtt_drive=True) as robot:
        async with mqtt_client(broker.url) as client:
            await client.publish(
                "ohmni/a/cmd/rotate", '{"angle_rad": 6.0, "speed_radps": 0.5}', qos=1
            )
        async with asyncio.timeout(5):
            while robot.server.lease_holder is None:  # noqa: ASYNC110
                await asyncio.sleep(0.02)
        await asyncio.sleep(0.5)
        sim = robot.robot.sim
        assert sim is not None
        assert max(abs(s) for s in sim.wheel_speeds_mps()) > 0.01
        await asyncio.to_thread(broker.stop)
        async with asyncio.timeout(5):
            while robot.server.lease_holder is not None:  # noqa: ASYNC110
                await asyncio.sleep(0.02)
        await asyncio.sleep(0.5)
        assert max(abs(s) for s in sim.wheel_speeds_mps()) < 0.01
