"""What a Foxglove client does, written out for the tests: the WebSocket protocol's
messages, and protobuf decoded with nothing but the schema the server advertises.

The protobuf schema of a well-known Foxglove message is a ``FileDescriptorSet``
(itself protobuf): :class:`Descriptors` reads it with the same wire decoder, so the tests
need no protobuf package and decode exactly what a client would.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
from dataclasses import dataclass, field
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed
from websockets.typing import Origin

#: The subprotocol foxglove-sdk's server requires (it refuses foxglove.websocket.v1).
SUBPROTOCOL = "foxglove.sdk.v1"
#: Server → client binary opcode of a message on a subscribed channel.
MESSAGE_DATA = 0x01
#: Client → server binary opcode of a service call, and server → client of its response.
SERVICE_CALL_REQUEST = 0x02
SERVICE_CALL_RESPONSE = 0x03
#: The service that unlocks control for the calling client.
UNLOCK = "/tb_control/unlock"
#: How long the server may take to answer (a loaded machine runs its threads late).
_ANSWER_TIMEOUT_S = 10.0

# -- protobuf's wire format -----------------------------------------------------------------

_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5


def _varint(data: bytes, at: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, at
        shift += 7


def fields(data: bytes) -> list[tuple[int, int, Any]]:
    """Every (field number, wire type, raw value) of one message, in order."""
    out: list[tuple[int, int, Any]] = []
    at = 0
    while at < len(data):
        key, at = _varint(data, at)
        number, wire = key >> 3, key & 7
        value: int | bytes
        if wire == _VARINT:
            value, at = _varint(data, at)
        elif wire == _FIXED64:
            value, at = data[at : at + 8], at + 8
        elif wire == _LENGTH:
            size, at = _varint(data, at)
            value, at = data[at : at + size], at + size
        elif wire == _FIXED32:
            value, at = data[at : at + 4], at + 4
        else:
            raise ValueError(f"wire type {wire} at {at}")
        out.append((number, wire, value))
    return out


# FieldDescriptorProto.type values used by Foxglove's schemas.
_DOUBLE, _FLOAT, _INT64, _UINT64, _INT32 = 1, 2, 3, 4, 5
_FIXED64_T, _FIXED32_T, _BOOL, _STRING, _MESSAGE = 6, 7, 8, 9, 11
_BYTES, _UINT32, _ENUM = 12, 13, 14


@dataclass
class _Field:
    name: str
    number: int
    type: int
    type_name: str
    repeated: bool


@dataclass
class Descriptors:
    """Message types by full name (``foxglove.FrameTransform``), from a FileDescriptorSet."""

    messages: dict[str, dict[int, _Field]] = field(default_factory=dict)

    @classmethod
    def parse(cls, file_descriptor_set: bytes) -> Descriptors:
        self = cls()
        for number, _, file_proto in fields(file_descriptor_set):
            if number != 1:
                continue
            parts = fields(file_proto)
            package = next((v.decode() for n, _, v in parts if n == 2), "")
            for n, _, message in parts:
                if n == 4:
                    self._message(package, message)
        return self

    def _message(self, scope: str, data: bytes) -> None:
        parts = fields(data)
        name = next(v.decode() for n, _, v in parts if n == 1)
        full = f"{scope}.{name}" if scope else name
        table: dict[int, _Field] = {}
        for n, _, value in parts:
            if n == 2:
                attrs = {k: v for k, _, v in fields(value)}
                table[attrs[3]] = _Field(
                    name=attrs[1].decode(),
                    number=attrs[3],
                    type=attrs[5],
                    type_name=attrs.get(6, b"").decode().lstrip("."),
                    repeated=attrs.get(4) == 3,
                )
            elif n == 3:
                self._message(full, value)
        self.messages[full] = table

    def decode(self, type_name: str, data: bytes) -> dict[str, Any]:
        """``data`` as a dict of the fields it carries (proto3 omits zeros and empties)."""
        table = self.messages[type_name]
        out: dict[str, Any] = {}
        for number, _, raw in fields(data):
            spec = table.get(number)
            if spec is None:
                continue
            value = self._value(spec, raw)
            if spec.repeated:
                out.setdefault(spec.name, []).append(value)
            else:
                out[spec.name] = value
        return out

    def _value(self, spec: _Field, raw: Any) -> Any:
        if spec.type == _DOUBLE:
            return struct.unpack("<d", raw)[0]
        if spec.type == _FLOAT:
            return struct.unpack("<f", raw)[0]
        if spec.type in (_INT64, _INT32):
            return raw - (1 << 64) if raw >= 1 << 63 else raw
        if spec.type in (_UINT64, _UINT32, _ENUM):
            return raw
        if spec.type == _BOOL:
            return bool(raw)
        if spec.type == _STRING:
            return raw.decode()
        if spec.type == _BYTES:
            return raw
        if spec.type == _MESSAGE:
            return self.decode(spec.type_name, raw)
        if spec.type == _FIXED64_T:
            return struct.unpack("<Q", raw)[0]
        if spec.type == _FIXED32_T:
            return struct.unpack("<I", raw)[0]
        raise ValueError(f"field type {spec.type}")


# -- the WebSocket protocol -----------------------------------------------------------------


@dataclass(frozen=True)
class Advertised:
    """One channel as the server advertised it."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: bytes


@dataclass(frozen=True)
class Message:
    """One message on a subscribed channel."""

    topic: str
    log_time_ns: int
    payload: bytes


class FoxgloveClient:
    """A Foxglove WebSocket client: the server's info and channels, subscribe, receive."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, Advertised] = {}
        #: Advertised services by name: their id and request/response schemas.
        self.services: dict[str, dict[str, Any]] = {}
        #: Status messages the server sent (warnings, errors), in order.
        self.statuses: list[dict[str, Any]] = []
        self._topics: dict[int, str] = {}

    @classmethod
    async def connect(
        cls, url: str, *, close_timeout_s: float = 10.0, origin: str | None = None
    ) -> FoxgloveClient:
        """Connect as the app does; ``origin``: as a web page of that origin would.

        Returns once the server has said what it offers: its info, then its channels
        (``advertise``) and, when it has services, those (``advertiseServices``), which
        the server sends right after the info."""
        ws = await connect(
            url,
            subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
            close_timeout=close_timeout_s,
            origin=None if origin is None else Origin(origin),
        )
        client = cls(ws)
        client.server_info = json.loads(await client.ws.recv())
        assert client.server_info["op"] == "serverInfo", client.server_info
        offers = {"advertise"}
        if "services" in client.server_info.get("capabilities", []):
            offers.add("advertiseServices")
        async with asyncio.timeout(_ANSWER_TIMEOUT_S):
            while offers:
                frame = await client.ws.recv()
                if isinstance(frame, str):
                    offers.discard(client._take(json.loads(frame)).get("op"))
        return client

    def _take(self, message: dict[str, Any]) -> dict[str, Any]:
        """Keep what a text message tells of the server (channels, services, statuses)."""
        op = message.get("op")
        if op == "status":
            self.statuses.append(message)
        elif op == "advertiseServices":
            for service in message["services"]:
                self.services[service["name"]] = service
        elif op == "advertise":
            for channel in message["channels"]:
                schema = channel["schema"]
                encoding = channel.get("schemaEncoding", "")
                raw = base64.b64decode(schema) if encoding == "protobuf" else schema.encode()
                self.channels[channel["topic"]] = Advertised(
                    channel["id"],
                    channel["topic"],
                    channel["encoding"],
                    channel["schemaName"],
                    encoding,
                    raw,
                )
        return message

    async def subscribe(self, *topics: str) -> None:
        subscriptions = []
        for topic in topics:
            channel = self.channels[topic]
            subscriptions.append({"id": channel.id, "channelId": channel.id})
            self._topics[channel.id] = topic
        await self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    async def messages(self, seconds: float) -> list[Message]:
        """Every message on the subscribed channels for ``seconds``, or until the server
        closes the connection."""
        out: list[Message] = []
        loop = asyncio.get_running_loop()
        end = loop.time() + seconds
        while (left := end - loop.time()) > 0:
            try:
                async with asyncio.timeout(left):
                    frame = await self.ws.recv()
            except (TimeoutError, ConnectionClosed):
                break
            if isinstance(frame, str):
                self._take(json.loads(frame))
            elif frame[0] == MESSAGE_DATA:
                subscription, log_time = struct.unpack_from("<IQ", frame, 1)
                out.append(Message(self._topics[subscription], log_time, frame[13:]))
        return out

    async def _next(self, want: Any, seconds: float = _ANSWER_TIMEOUT_S) -> Any:
        """The next frame ``want(frame)`` accepts; status messages are kept on the way."""
        async with asyncio.timeout(seconds):
            while True:
                frame = await self.ws.recv()
                if isinstance(frame, str):
                    message = self._take(json.loads(frame))
                    if want(message):
                        return message
                elif want(frame):
                    return frame

    async def get_parameters(self, *names: str, request_id: str = "get") -> dict[str, Any]:
        """``getParameters``: the values the server answers, by name (no names: all)."""
        await self.ws.send(
            json.dumps({"op": "getParameters", "parameterNames": list(names), "id": request_id})
        )
        return await self._parameter_values(request_id)

    async def set_parameters(
        self, values: dict[str, Any], *, request_id: str = "set"
    ) -> dict[str, Any]:
        """``setParameters`` as the app's Parameters panel sends them (a float as float64,
        anything else as it is); the values answered."""
        parameters = [
            {"name": n, "value": v, "type": "float64"}
            if isinstance(v, float)
            else {"name": n, "value": v}
            for n, v in values.items()
        ]
        await self.ws.send(
            json.dumps({"op": "setParameters", "parameters": parameters, "id": request_id})
        )
        return await self._parameter_values(request_id)

    async def _parameter_values(self, request_id: str) -> dict[str, Any]:
        message = await self._next(
            lambda m: (
                isinstance(m, dict)
                and m.get("op") == "parameterValues"
                and m.get("id") == request_id
            )
        )
        return {p["name"]: p.get("value") for p in message["parameters"]}

    async def call_service(self, name: str, request: dict[str, Any], call_id: int = 1) -> Any:
        """Call service ``name`` with a JSON request: the decoded JSON response, or the
        failure message as ``{"failure": text}``."""
        service_id = self.services[name]["id"]
        encoding = b"json"
        await self.ws.send(
            struct.pack("<BIII", SERVICE_CALL_REQUEST, service_id, call_id, len(encoding))
            + encoding
            + json.dumps(request).encode()
        )

        def answer(frame: Any) -> bool:
            if isinstance(frame, bytes):
                return (
                    frame[0] == SERVICE_CALL_RESPONSE
                    and struct.unpack_from("<I", frame, 5)[0] == call_id
                )
            return bool(frame.get("op") == "serviceCallFailure" and frame.get("callId") == call_id)

        frame = await self._next(answer)
        if isinstance(frame, dict):
            return {"failure": frame["message"]}
        (size,) = struct.unpack_from("<I", frame, 9)
        return json.loads(frame[13 + size :])

    async def unlock(self, token: str, call_id: int = 9000) -> Any:
        """Call the unlock service with ``token``: its answer, or ``{"failure": text}``."""
        return await self.call_service(UNLOCK, {"token": token}, call_id=call_id)

    async def advertise_twist(self, channel_id: int = 1, topic: str = "/tb_cmd_vel") -> None:
        """Advertise a JSON ``geometry_msgs/Twist`` channel, as the Teleop panel does."""
        channel = {
            "id": channel_id,
            "topic": topic,
            "encoding": "json",
            "schemaName": "geometry_msgs/Twist",
        }
        await self.ws.send(json.dumps({"op": "advertise", "channels": [channel]}))

    async def send_twist(self, linear: float, angular: float = 0.0, channel_id: int = 1) -> None:
        """Publish one Twist on an advertised channel."""
        twist = {"linear": {"x": linear, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": angular}}
        await self.ws.send(struct.pack("<BI", 1, channel_id) + json.dumps(twist).encode())

    async def status(self, words: str, seconds: float = 5.0) -> dict[str, Any]:
        """The first status message (kept, or next) whose text has ``words``."""
        for kept in self.statuses:
            if words in kept["message"]:
                return kept
        message: dict[str, Any] = await self._next(
            lambda m: isinstance(m, dict) and m.get("op") == "status" and words in m["message"],
            seconds,
        )
        return message

    async def close(self) -> None:
        """Close as the app does: reading on until the server's close frame, which waits
        behind every message already on its way (a client that stops reading first
        cannot finish the handshake, and waits ``close_timeout_s``)."""
        closing = asyncio.create_task(self.ws.close())
        try:
            while not closing.done():
                await self.ws.recv()
        except ConnectionClosed:
            pass
        finally:
            await closing
