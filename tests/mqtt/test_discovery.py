"""Home Assistant's MQTT discovery (``--mqtt-discovery``): the robot's device and its
entities, each config valid by Home Assistant's documentation (its topic, the keys its
component requires, unique ids, the device, the availability topic), and each template
working on what the robot really publishes: the states read, the commands act."""

from __future__ import annotations

import asyncio
import json
import re
from typing import Any

import pytest

from ._helpers import command, mqtt_client, next_message, payload, served
from .conftest import Mosquitto

jinja2 = pytest.importorskip("jinja2")

#: ``<prefix>/<component>/[<node_id>/]<object_id>/config``, ids of [a-zA-Z0-9_-].
_TOPIC = re.compile(
    r"^homeassistant/(?P<component>[a-z_]+)/(?P<node>[\w-]+)/(?P<object>[\w-]+)/config$"
)
#: The keys each component's MQTT platform requires (Home Assistant's docs).
_REQUIRED = {
    "sensor": {"state_topic"},
    "binary_sensor": {"state_topic"},
    "light": {"command_topic"},
    "number": {"command_topic"},
    "button": {"command_topic"},
}
_SENSOR_CLASSES = {"battery", "voltage", "enum", None}
_BINARY_CLASSES = {"plug", "battery_charging", "problem"}


def render(template: str, **values: Any) -> str:
    """A template as Home Assistant renders it (Jinja2; its own filters are not used)."""
    return str(jinja2.Environment().from_string(template).render(**values))


async def test_the_robot_appears_as_a_device_with_valid_entities(broker: Mosquitto) -> None:
    async with mqtt_client(broker.url) as client:
        await client.subscribe("homeassistant/#", qos=1)
        async with served(broker.url, "a", "sim://?docked=1", mqtt_discovery=True) as robot:
            configs: dict[str, dict[str, Any]] = {}
            async with asyncio.timeout(5):
                while len(configs) < 10:
                    message = await next_message(client)
                    assert message.qos == 1
                    configs[str(message.topic)] = payload(message)
            await client.subscribe("ohmni/a/state")
            while True:
                state = payload(await next_message(client, "ohmni/a/state"))
                if state["battery"] is not None:
                    break
            entities: dict[str, tuple[str, dict[str, Any]]] = {}
            for topic, config in configs.items():
                match = _TOPIC.match(topic)
                assert match, topic
                assert match["node"] == "a"
                assert _REQUIRED[match["component"]] <= set(config), topic
                assert config["unique_id"] == f"ohmni_a_{match['object']}"
                assert config["device"]["identifiers"] == ["ohmni_a"]
                assert config["availability"] == [{"topic": "ohmni/a/availability"}]
                entities[match["object"]] = (match["component"], config)
            ids = [config["unique_id"] for _, config in entities.values()]
            assert len(set(ids)) == len(ids)
            assert set(entities) == {
                "battery", "pack_voltage", "docked", "charging", "link", "faults",
                "problem", "light_ring", "stop", "neck",
            }  # fmt: skip
            for component, config in entities.values():
                if component == "sensor":
                    assert config.get("device_class") in _SENSOR_CLASSES
                if component == "binary_sensor":
                    assert config["device_class"] in _BINARY_CLASSES
                    value = render(config["value_template"], value_json=state)
                    assert value in ("ON", "OFF")
                if "state_topic" in config:
                    assert config["state_topic"] == "ohmni/a/state"
            # The states read from what the robot publishes.
            _, battery = entities["battery"]
            assert render(battery["value_template"], value_json=state) == str(
                state["battery"]["percent"]
            )
            _, docked = entities["docked"]
            assert render(docked["value_template"], value_json=state) == "ON"
            _, link = entities["link"]
            assert render(link["value_template"], value_json=state) in link["options"]
            _, faults = entities["faults"]
            assert render(faults["value_template"], value_json=state) == "none"
            # The light is a JSON-schema light with hue and brightness.
            _, light = entities["light_ring"]
            assert light["schema"] == "json"
            assert light["supported_color_modes"] == ["hs"]
            # The neck's number: within the neck's range; its command moves the neck.
            _, neck = entities["neck"]
            settings = robot.robot.config
            assert (neck["min"], neck["max"]) == (settings.neck_min_raw, settings.neck_max_raw)
            assert render(neck["value_template"], value_json=state) == str(
                state["neck"]["position_raw"]
            )
            body = render(neck["command_template"], value=400.0)
            assert json.loads(body) == {"target": "neck", "raw": 400}
            reply, _ = await command(client, "a", "move", body)
            assert reply["op"] == "result", reply
            # The stop button's press is a stop command.
            _, stop = entities["stop"]
            pressed, _ = await command(client, "a", "stop", stop["payload_press"])
            assert pressed["op"] == "result"
    # Retained: Home Assistant started later finds the device all the same.
    async with mqtt_client(broker.url) as later:
        await later.subscribe("homeassistant/#")
        kept = [await next_message(later) for _ in range(len(configs))]
        assert all(message.retain for message in kept)
        assert {str(message.topic) for message in kept} == set(configs)


async def test_no_discovery_unless_asked(broker: Mosquitto) -> None:
    async with mqtt_client(broker.url) as client:
        await client.subscribe("homeassistant/#")
        await client.subscribe("ohmni/a/availability")
        async with served(broker.url, "a"):
            first = await next_message(client)
            assert str(first.topic) == "ohmni/a/availability"
            with pytest.raises(TimeoutError):
                await next_message(client, timeout_s=0.5)
