"""A robot served with its MQTT bridge in the test's process, and a plain MQTT client."""

from __future__ import annotations

import asyncio
import json
import secrets
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any

import aiomqtt
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.mqtt import Broker, MqttBridge


@dataclass
class Served:
    robot: Robot
    server: RobotServer
    bridge: MqttBridge


@asynccontextmanager
async def served(
    url: str, robot_id: str = "a", port: str = "sim://", **settings: Any
) -> AsyncIterator[Served]:
    """``sim://`` served by a daemon with its bridge to ``url`` (1 s keep-alive), connected."""
    settings.setdefault("mqtt_keepalive_s", 1)
    async with (
        Robot.open(port, mqtt_url=url, robot_id=robot_id, **settings) as robot,
        RobotServer(robot, port=0) as server,
        MqttBridge(robot, server) as bridge,
    ):
        async with asyncio.timeout(10):
            await bridge.wait_connected()
        yield Served(robot, server, bridge)


@asynccontextmanager
async def mqtt_client(
    url: str, user: str | None = None, password: str | None = None
) -> AsyncIterator[aiomqtt.Client]:
    """A plain MQTT 5 client of the broker at ``url``."""
    broker = Broker.from_url(url, username=user, password=password)
    async with broker.client(f"test-{secrets.token_hex(4)}") as client:
        yield client


async def next_message(
    client: aiomqtt.Client, topic: str | None = None, timeout_s: float = 5.0
) -> aiomqtt.Message:
    """The next message (on ``topic``, if given), within ``timeout_s``."""
    async with asyncio.timeout(timeout_s):
        async for message in client.messages:
            if topic is None or str(message.topic) == topic:
                return message
    raise AssertionError("the client's messages ended")


async def command(
    client: aiomqtt.Client,
    robot_id: str,
    method: str,
    args: dict[str, Any] | str | None = None,
    *,
    reply_to: str | None = None,
    timeout_s: float = 5.0,
) -> tuple[dict[str, Any], aiomqtt.Message]:
    """Publish a command with a response topic and correlation data; its reply (JSON)."""
    reply_to = reply_to or f"ohmni/{robot_id}/response/test"
    await client.subscribe(reply_to, qos=1)
    correlation = secrets.token_bytes(6)
    properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]  # paho
    properties.ResponseTopic = reply_to
    properties.CorrelationData = correlation
    body = args if isinstance(args, str) else json.dumps(args or {})
    await client.publish(f"ohmni/{robot_id}/cmd/{method}", body, qos=1, properties=properties)
    async with asyncio.timeout(timeout_s):
        async for message in client.messages:
            props = message.properties
            if getattr(props, "CorrelationData", None) == correlation:
                reply: dict[str, Any] = json.loads(message.payload)
                return reply, message
    raise AssertionError("no reply")


def payload(message: aiomqtt.Message) -> Any:
    """A message's JSON payload."""
    assert isinstance(message.payload, bytes)
    return json.loads(message.payload)
