"""``ohmni serve --mqtt``'s bridge against a real broker: what it publishes, the commands
it takes through the daemon's lease, and what it refuses. The robot, its daemon and its
bridge run in the test's process on ``sim://``; the broker is Mosquitto."""

from __future__ import annotations

import asyncio
import json

import pytest

from ohmni_tb.client import RobotClient
from ohmni_tb.mqtt import Broker
from ohmni_tb.mqtt.payloads import StatePayload

from ._helpers import command, mqtt_client, next_message, payload, served
from .conftest import Mosquitto


async def test_it_says_online_and_its_state_retained_and_offline_when_it_leaves(
    broker: Mosquitto,
) -> None:
    async with served(broker.url, "a", "sim://?soc=50&docked=1") as robot:
        async with mqtt_client(broker.url) as client:
            await client.subscribe("ohmni/a/state")
            while True:  # the first state may come before the battery's first read
                state = StatePayload.model_validate(
                    payload(await next_message(client, "ohmni/a/state"))
                )
                if state.battery is not None:
                    break
        core = robot.robot.latest("tbcore_status")
        assert core is not None
        async with mqtt_client(broker.url) as client:
            # A client that comes later finds both: they are retained.
            await client.subscribe("ohmni/a/availability")
            available = await next_message(client, "ohmni/a/availability")
            assert (available.payload, available.retain) == (b"online", True)
            await client.subscribe("ohmni/a/state")
            message = await next_message(client, "ohmni/a/state")
            assert message.retain
            state = StatePayload.model_validate(payload(message))
    assert state.robot_id == "a"
    assert state.battery is not None
    assert (state.battery.percent, state.battery.docked) == (core.percent, True)
    assert state.battery.cell_v == pytest.approx(list(core.cell_v), abs=1e-3)
    assert state.link == "connected"
    assert state.simulated
    assert state.neck.kind == "herkulex"
    assert state.firmware.get("core", "").startswith("sim-core")
    assert state.drive is False
    async with mqtt_client(broker.url) as client:
        await client.subscribe("ohmni/a/availability")
        left = await next_message(client, "ohmni/a/availability")
        assert left.payload == b"offline"


async def test_the_streams_go_out_at_their_reduced_rates_in_the_daemons_schema(
    broker: Mosquitto,
) -> None:
    async with mqtt_client(broker.url) as client:
        await client.subscribe("ohmni/a/stream/#")
        async with served(broker.url, "a", mqtt_rates="wheel_odom=10,tbcore_status=2"):
            counts: dict[str, int] = {}
            loop = asyncio.get_running_loop()
            first = await next_message(client)
            start = loop.time()
            while loop.time() - start < 1.0:
                message = await next_message(client)
                name = str(message.topic).rsplit("/", 1)[1]
                counts[name] = counts.get(name, 0) + 1
                if name == "wheel_odom":
                    sample = payload(message)
    assert str(first.topic).startswith("ohmni/a/stream/")
    # 10 Hz and 2 Hz of the robot's 50 Hz and 10 Hz: nothing at the full rate.
    assert 8 <= counts["wheel_odom"] <= 12
    assert 1 <= counts["tbcore_status"] <= 3
    assert set(counts) == {"wheel_odom", "tbcore_status"}
    # The daemon's sample, field for field (docs/daemon-schema.json, samples.wheel_odom).
    assert {"stamp_s", "x_m", "y_m", "yaw_rad", "linear_mps", "covariance"} <= set(sample)


async def test_stop_is_anyones_and_answers_on_the_response_topic_with_the_correlation(
    broker: Mosquitto,
) -> None:
    async with served(broker.url, "a"), mqtt_client(broker.url) as client:
        reply, message = await command(client, "a", "stop")
        assert reply == {"op": "result", "method": "stop", "data": None}
        assert str(message.topic) == "ohmni/a/response/test"
        latest, _ = await command(client, "a", "latest", {"topic": "tbcore_status"})
        assert latest["op"] == "result"
        assert latest["data"]["percent"] in (20, 50, 80, 100)


async def test_the_light_ring_takes_the_lease_and_gives_it_back(broker: Mosquitto) -> None:
    async with served(broker.url, "a") as robot, mqtt_client(broker.url) as client:
        told: list[str | None] = []
        async with RobotClient.connect(robot.server.url) as other:
            reply, _ = await command(
                client, "a", "light_ring", {"hue": 10, "saturation": 200, "value": 30}
            )
            told.append(other.lease_holder)
        assert reply["op"] == "result"
        assert robot.robot.sim is not None
        assert bytes(robot.robot.sim.core.light_ring) == bytes((10, 200, 30))
        assert robot.server.lease_holder is None  # given back when the command ended


async def test_a_command_is_refused_while_another_client_drives(broker: Mosquitto) -> None:
    async with served(broker.url, "a") as robot, mqtt_client(broker.url) as client:
        async with RobotClient.connect(robot.server.url) as driver:
            await driver.acquire(source="remote")  # the bridge's own source
            reply, _ = await command(
                client, "a", "light_ring", {"hue": 1, "saturation": 1, "value": 1}
            )
            assert reply["op"] == "error"
            assert reply["code"] == "lease_held"
            assert driver.peer in reply["message"]
            assert robot.server.lease_holder == driver.peer
            # Stopping is still anyone's.
            stopped, _ = await command(client, "a", "stop")
            assert stopped["op"] == "result"
        assert robot.robot.sim is not None
        assert bytes(robot.robot.sim.core.light_ring) != bytes((1, 1, 1))


async def test_driving_is_refused_unless_enabled(broker: Mosquitto) -> None:
    async with served(broker.url, "a") as robot, mqtt_client(broker.url) as client:
        reply, _ = await command(client, "a", "rotate", {"angle_rad": 0.5})
        assert reply["op"] == "error"
        assert reply["code"] == "driving_off"
        assert "mqtt_drive" in reply["message"]
        assert robot.server.lease_holder is None
        odom = robot.robot.latest("wheel_odom")
        assert odom is not None
        assert odom.yaw_rad == 0.0


async def test_driving_when_enabled_goes_through_the_lease(broker: Mosquitto) -> None:
    async with (
        served(broker.url, "a", mqtt_drive=True) as robot,
        mqtt_client(broker.url) as client,
    ):
        reply, _ = await command(
            client, "a", "rotate", {"angle_rad": 0.3, "speed_radps": 1.0}, timeout_s=10
        )
        assert reply["op"] == "result"
        assert reply["data"]["error"] is None
        odom = robot.robot.latest("wheel_odom")
        assert odom is not None
        assert odom.yaw_rad == pytest.approx(0.3, abs=0.05)
        assert robot.server.lease_holder is None


async def test_what_it_refuses_it_says_why(broker: Mosquitto) -> None:
    async with served(broker.url, "a") as robot, mqtt_client(broker.url) as client:
        offered, _ = await command(client, "a", "drive_pwm", {"left": 100, "right": 100})
        assert (offered["op"], offered["code"]) == ("error", "not_offered")
        assert "stop" in offered["message"]
        servo, _ = await command(client, "a", "move", {"target": 11, "raw": 500})
        assert servo["code"] == "not_offered"
        bad, _ = await command(client, "a", "light_ring", "{not json")
        assert bad["code"] == "bad_json"
        wrong, _ = await command(
            client, "a", "light_ring", {"hue": 300, "saturation": 0, "value": 0}
        )
        assert wrong["code"] == "bad_value"
        assert wrong["raised"]["type"] == "OutOfRangeError"
        assert "hue" in wrong["message"]
        assert robot.bridge.refused == 4


async def test_a_retained_command_is_never_run(broker: Mosquitto) -> None:
    """It would run again at every connect of the robot, long after it was meant."""
    ring = {"hue": 5, "saturation": 6, "value": 7}
    async with mqtt_client(broker.url) as client:
        await client.publish("ohmni/a/cmd/light_ring", json.dumps(ring), qos=1, retain=True)
        await client.subscribe("ohmni/a/response")
        async with served(broker.url, "a") as robot:
            refused = payload(await next_message(client, "ohmni/a/response"))
            assert refused["code"] == "retained"
            assert robot.robot.sim is not None
            assert bytes(robot.robot.sim.core.light_ring) != bytes((5, 6, 7))
        await client.publish("ohmni/a/cmd/light_ring", b"", qos=1, retain=True)  # cleared


async def test_a_reply_never_goes_outside_the_robots_own_prefix(broker: Mosquitto) -> None:
    """A commander cannot make the robot publish as another robot: the reply goes to the
    robot's default response topic instead."""
    async with served(broker.url, "a"), mqtt_client(broker.url) as client:
        await client.subscribe("ohmni/a/response")
        await client.subscribe("ohmni/b/state")
        reply, message = await command(client, "a", "stop", reply_to="ohmni/b/state")
        assert str(message.topic) == "ohmni/a/response"
        assert reply["op"] == "result"


async def test_home_assistants_light_sets_the_ring(broker: Mosquitto) -> None:
    async with served(broker.url, "a") as robot, mqtt_client(broker.url) as client:
        await client.subscribe("ohmni/a/response")
        await client.publish(
            "ohmni/a/ha/light/set",
            json.dumps({"state": "ON", "color": {"h": 180, "s": 100}, "brightness": 128}),
        )
        reply = payload(await next_message(client, "ohmni/a/response"))
        assert reply["op"] == "result", reply
        assert robot.robot.sim is not None
        assert bytes(robot.robot.sim.core.light_ring) == bytes((128, 255, 128))
        await client.publish("ohmni/a/ha/light/set", json.dumps({"state": "OFF"}))
        assert payload(await next_message(client, "ohmni/a/response"))["op"] == "result"
        assert bytes(robot.robot.sim.core.light_ring) == bytes((128, 255, 0))


async def test_messages_beyond_what_a_client_holds_unread_are_counted(
    broker: Mosquitto,
) -> None:
    dropped: list[int] = []
    reader = Broker.from_url(broker.url).client(
        "test-reader", max_queued_incoming=3, on_dropped=lambda: dropped.append(1)
    )
    async with reader, mqtt_client(broker.url) as writer:
        await reader.subscribe("flood", qos=1)
        for index in range(10):
            await writer.publish("flood", str(index), qos=1)
        async with asyncio.timeout(5):
            while len(dropped) + len(reader.messages) < 10:  # noqa: ASYNC110  # the client's own
                await asyncio.sleep(0.02)
        assert (len(reader.messages), len(dropped)) == (3, 7)
