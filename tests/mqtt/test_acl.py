"""A broker that authenticates, with the ACL of docs/fleet.md: a robot publishes only under
its own prefix, a client without the ACL's rights cannot command, nobody without a
password gets in."""

from __future__ import annotations

import asyncio
import json

import pytest

from ohmni_tb.errors import TransportError
from ohmni_tb.fleet import Fleet
from ohmni_tb.mqtt import Broker

from ._helpers import mqtt_client, served
from .conftest import USERS, Mosquitto


def fleet_of(url: str, user: str = "fleet") -> Fleet:
    return Fleet(Broker.from_url(url, username=user, password=USERS[user]))


async def test_the_fleet_sees_and_commands_a_robot_that_logs_in(
    secure_broker: Mosquitto,
) -> None:
    url = secure_broker.url
    async with (
        served(url, "a", mqtt_username="a", mqtt_password=USERS["a"]) as robot,
        fleet_of(url) as fleet,
    ):
        seen = fleet.robot("a")
        assert seen is not None
        assert seen.online
        await fleet.call("a", "light_ring", {"hue": 9, "saturation": 8, "value": 7})
        assert robot.robot.sim is not None
        assert bytes(robot.robot.sim.core.light_ring) == bytes((9, 8, 7))


async def test_a_client_without_the_acls_rights_cannot_command(secure_broker: Mosquitto) -> None:
    url = secure_broker.url
    async with served(url, "a", mqtt_username="a", mqtt_password=USERS["a"]) as robot:
        async with mqtt_client(url, "intruder", USERS["intruder"]) as intruder:
            body = json.dumps({"hue": 1, "saturation": 2, "value": 3})
            await intruder.publish("ohmni/a/cmd/light_ring", body, qos=1)
            # Robot b's credentials are no better for robot a.
        async with mqtt_client(url, "b", USERS["b"]) as other_robot:
            await other_robot.publish("ohmni/a/cmd/light_ring", body, qos=1)
        # The fleet's own command after theirs: had theirs reached the robot, it would
        # have been answered first.
        async with fleet_of(url) as fleet:
            await fleet.call("a", "stop")
        assert robot.robot.sim is not None
        assert bytes(robot.robot.sim.core.light_ring) != bytes((1, 2, 3))
        assert (robot.bridge.commands, robot.bridge.refused) == (1, 0)
        # Nor can it listen to the robot's replies, or read the fleet.
        async with fleet_of(url, "intruder") as snooper:
            assert snooper.robots == []
            with pytest.raises(TimeoutError):
                await snooper.call("a", "stop", timeout_s=0.5)


async def test_a_robot_cannot_publish_under_another_robots_prefix(
    secure_broker: Mosquitto,
) -> None:
    url = secure_broker.url
    async with mqtt_client(url, "a", USERS["a"]) as robot_a:
        await robot_a.publish("ohmni/b/availability", "online", qos=1, retain=True)
        await robot_a.publish("ohmni/a/availability", "online", qos=1, retain=True)
    async with fleet_of(url) as fleet:
        assert [robot.robot_id for robot in fleet.robots] == ["a"]


async def test_nobody_gets_in_without_a_password(secure_broker: Mosquitto) -> None:
    with pytest.raises(TransportError, match="cannot reach the broker"):
        async with Fleet(secure_broker.url):
            pass
    wrong = Broker.from_url(secure_broker.url, username="fleet", password="guess")
    with pytest.raises(TransportError):
        async with Fleet(wrong):
            pass
    await asyncio.sleep(0)
