"""The daemon's messages: versioned JSON, validated with pydantic at the edge (sans-IO).

Every message is one JSON object in one WebSocket text frame, with ``op`` naming it::

    client → server                          server → client
    subscribe   {id, topic, max_hz?, queue?}  hello   {protocol, version, topics, limits}
    unsubscribe {id, topic}                   sample  {topic, dropped, data}
    call        {id, method, args}            result  {id, data}
                                              error   {id | null, code, message}

``id`` is the client's (an integer or a short string); the ``result`` or ``error`` that
answers a request carries it back. A sample's ``data`` is the Robot's sample dataclass as
JSON (enums by value, tuples as lists, nested dataclasses as objects): :func:`sample_json`
and :func:`sample_from_json` go both ways. :func:`parse_client_message` turns one frame
into a message or raises :class:`RequestError` with the ``error`` to send back.
:func:`json_schema` is the schema of them all, checked in at ``docs/daemon-schema.json``
(regenerate: ``python -m ohmni_tb.daemon.protocol docs/daemon-schema.json``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Annotated, Any, Final, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from ohmni_tb.robot.core import RobotStats
from ohmni_tb.robot.samples import (
    STREAM_NAMES,
    PidDebugSample,
    RobotStateSample,
    Sample,
    ServoSample,
    TbcoreStatusSample,
    WheelEncoderSample,
    WheelOdomSample,
    WormNeckSample,
)

__all__ = [
    "CLIENT_OPS",
    "ERROR_CODES",
    "MAX_QUEUE",
    "METHODS",
    "PROTOCOL_VERSION",
    "SAMPLE_TYPES",
    "Call",
    "ClientMessage",
    "ErrorCode",
    "ErrorMessage",
    "Hello",
    "Limits",
    "RequestError",
    "Result",
    "SampleMessage",
    "ServerMessage",
    "Subscribe",
    "Unsubscribe",
    "encode",
    "json_schema",
    "parse_client_message",
    "parse_server_message",
    "sample_from_json",
    "sample_json",
    "schema_text",
    "stats_from_json",
    "stats_json",
    "write_schema",
]

#: Bumped on any change a peer of the previous version would misread.
PROTOCOL_VERSION: Final = 1
#: What a client may ask (``op``).
CLIENT_OPS: Final = ("subscribe", "unsubscribe", "call")
#: The services a ``call`` may name, all read-only in this version.
METHODS: Final = ("stats", "info", "latest", "schedule")
#: Every stream's sample type, by stream name.
SAMPLE_TYPES: Final[dict[str, type[Sample]]] = {
    "wheel_encoder": WheelEncoderSample,
    "wheel_odom": WheelOdomSample,
    "tbcore_status": TbcoreStatusSample,
    "servo_neck": ServoSample,
    "servo_ext1": ServoSample,
    "servo_ext2": ServoSample,
    "new_neck": WormNeckSample,
    "robot_state": RobotStateSample,
    "pid_debug": PidDebugSample,
}
#: Longest string ``id`` a client may use.
_MAX_ID_CHARS = 64
#: Most samples a subscription's queue may hold (memory per client and topic).
MAX_QUEUE = 1024
#: Fastest rate cap a subscription may ask; no stream is faster than 100 Hz.
_MAX_HZ = 1000.0

ErrorCode = Literal[
    "bad_json",  # not JSON, or not one JSON object
    "bad_message",  # an object, but not a valid message (a field missing or wrong)
    "unknown_op",
    "unknown_method",
    "unknown_topic",
    "not_subscribed",  # unsubscribe from a topic the client is not subscribed to
    "too_large",  # over the message size limit
    "rate_limited",  # over the message rate limit (the connection is then closed)
    "robot_error",  # the Robot raised: the message says what
]
#: The ``code`` of an ``error``, for programs to act on.
ERROR_CODES: Final = ErrorCode.__args__  # type: ignore[attr-defined]  # Literal's members

MessageId = (
    Annotated[int, Field(ge=0, le=2**53 - 1)]
    | Annotated[str, Field(min_length=1, max_length=_MAX_ID_CHARS)]
)
Topic = Literal[STREAM_NAMES]  # type: ignore[valid-type]  # the tuple of names, for the schema
Method = Literal[METHODS]  # type: ignore[valid-type]  # the same


class _Message(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# -- client → server -----------------------------------------------------------------------


class Subscribe(_Message):
    """Send me ``topic``'s samples from now on (again: replaces the options)."""

    op: Literal["subscribe"] = "subscribe"
    id: MessageId
    topic: Topic
    max_hz: Annotated[float, Field(gt=0, le=_MAX_HZ)] | None = Field(
        None, description="Rate cap: at most this many samples a second, the newest each time."
    )
    queue: Annotated[int, Field(ge=1, le=MAX_QUEUE)] = Field(
        64, description="Samples held for this client; when full the oldest is dropped."
    )


class Unsubscribe(_Message):
    """Stop sending ``topic``."""

    op: Literal["unsubscribe"] = "unsubscribe"
    id: MessageId
    topic: Topic


class LatestArgs(_Message):
    """``latest``'s arguments."""

    topic: Topic


class NoArgs(_Message):
    """No arguments (``stats``, ``info``, ``schedule``)."""


class Call(_Message):
    """Call a read-only service: ``stats``, ``info``, ``schedule`` or ``latest {topic}``."""

    op: Literal["call"] = "call"
    id: MessageId
    method: Method
    args: LatestArgs | NoArgs = Field(default_factory=NoArgs)


ClientMessage = Annotated[Subscribe | Unsubscribe | Call, Field(discriminator="op")]


# -- server → client -----------------------------------------------------------------------


class Limits(_Message):
    """The server's limits, told in ``hello``."""

    max_message_bytes: int = Field(description="Longer client messages are refused.")
    max_messages_per_s: float = Field(description="Sustained client message rate allowed.")
    burst_messages: int = Field(description="Messages allowed at once above that rate.")
    max_queue: int = Field(MAX_QUEUE, description="Largest queue a subscription may ask.")


class Hello(_Message):
    """The first message on every connection."""

    op: Literal["hello"] = "hello"
    protocol: int = Field(description="PROTOCOL_VERSION of the server.")
    version: str = Field(description="ohmni_tb's version.")
    read_only: bool = Field(True, description="No motion commands in this version.")
    topics: dict[str, float] = Field(description="Each stream and its rate (Hz; 0: on events).")
    limits: Limits


class SampleMessage(_Message):
    """One sample of a subscribed topic."""

    op: Literal["sample"] = "sample"
    topic: Topic
    dropped: int = Field(
        ge=0, description="Samples of this topic this client lost since the previous one."
    )
    data: dict[str, Any] = Field(description="The sample; its schema is under 'samples'.")


class Result(_Message):
    """The answer to a request."""

    op: Literal["result"] = "result"
    id: MessageId
    data: Any


class ErrorMessage(_Message):
    """A refused request: ``id`` is ``null`` when the request had none readable."""

    op: Literal["error"] = "error"
    id: MessageId | None
    code: ErrorCode
    message: str


ServerMessage = Annotated[Hello | SampleMessage | Result | ErrorMessage, Field(discriminator="op")]

_CLIENT: TypeAdapter[Subscribe | Unsubscribe | Call] = TypeAdapter(ClientMessage)
_SERVER: TypeAdapter[Hello | SampleMessage | Result | ErrorMessage] = TypeAdapter(ServerMessage)
_SAMPLES: dict[type[Any], TypeAdapter[Any]] = {
    cls: TypeAdapter(cls) for cls in dict.fromkeys(SAMPLE_TYPES.values())
}
_STATS: TypeAdapter[RobotStats] = TypeAdapter(RobotStats)


class RequestError(Exception):
    """A client message that cannot be served: the ``error`` to send back."""

    def __init__(self, code: ErrorCode, message: str, id: int | str | None = None) -> None:
        super().__init__(message)
        self.code: ErrorCode = code
        self.message = message
        self.id = id

    def reply(self) -> ErrorMessage:
        """The ``error`` message for the client."""
        return ErrorMessage(id=self.id, code=self.code, message=self.message)


def parse_client_message(frame: str | bytes) -> Subscribe | Unsubscribe | Call:
    """One client frame as a message.

    Raises:
        RequestError: Not JSON, not an object, an unknown ``op``, ``method`` or ``topic``,
            or a field missing or wrong; the message names the value and what is allowed.
    """
    try:
        raw = json.loads(frame)
    except (ValueError, UnicodeDecodeError) as exc:
        raise RequestError("bad_json", f"not JSON: {exc}") from None
    if not isinstance(raw, dict):
        raise RequestError("bad_json", f"a message is a JSON object, not {type(raw).__name__}")
    ident = raw.get("id")
    ident = ident if isinstance(ident, int | str) and not isinstance(ident, bool) else None
    op = raw.get("op")
    if op not in CLIENT_OPS:
        raise RequestError(
            "unknown_op", f"unknown op {_shown(op)}: allowed {_listed(CLIENT_OPS)}", ident
        )
    topic = raw.get("topic") if op != "call" else _args(raw).get("topic")
    if op == "call" and raw.get("method") not in METHODS:
        raise RequestError(
            "unknown_method",
            f"unknown method {_shown(raw.get('method'))}: allowed {_listed(METHODS)}",
            ident,
        )
    wants_topic = op != "call" or raw.get("method") == "latest"
    if wants_topic and isinstance(topic, str) and topic not in STREAM_NAMES:
        raise RequestError(
            "unknown_topic",
            f"unknown topic {_shown(topic)}: the topics are {_listed(STREAM_NAMES)}",
            ident,
        )
    if op == "call" and raw.get("method") != "latest" and _args(raw):
        raise RequestError(
            "bad_message", f"{raw['method']} takes no arguments, not {_shown(_args(raw))}", ident
        )
    try:
        message = _CLIENT.validate_python(raw)
    except ValidationError as exc:
        raise RequestError("bad_message", f"bad {op}: {_problems(exc, op)}", ident) from None
    if (
        isinstance(message, Call)
        and message.method == "latest"
        and not isinstance(message.args, LatestArgs)
    ):
        raise RequestError(
            "bad_message",
            f'latest needs args {{"topic": …}}: one of {_listed(STREAM_NAMES)}',
            ident,
        )
    return message


def parse_server_message(frame: str | bytes) -> Hello | SampleMessage | Result | ErrorMessage:
    """One server frame as a message (the client's edge).

    Raises:
        ValueError: Not a valid server message (a pydantic ``ValidationError``).
    """
    return _SERVER.validate_json(frame)


def encode(message: BaseModel) -> str:
    """A message as its JSON frame."""
    return message.model_dump_json()


def sample_json(sample: Sample) -> dict[str, Any]:
    """A sample as JSON-ready data: enums by value, tuples as lists."""
    data: dict[str, Any] = _SAMPLES[type(sample)].dump_python(sample, mode="json")
    return data


def sample_from_json(topic: str, data: Any) -> Sample:
    """The sample dataclass of ``topic`` rebuilt from :func:`sample_json`'s data.

    Raises:
        KeyError: No such topic.
        ValueError: The data does not fit the topic's sample (a ``ValidationError``).
    """
    sample: Sample = _SAMPLES[SAMPLE_TYPES[topic]].validate_python(data)
    return sample


def stats_json(stats: RobotStats) -> dict[str, Any]:
    """:meth:`Robot.stats` as JSON-ready data."""
    data: dict[str, Any] = _STATS.dump_python(stats, mode="json")
    return data


def stats_from_json(data: Any) -> RobotStats:
    """:class:`RobotStats` rebuilt from :func:`stats_json`'s data."""
    return _STATS.validate_python(data)


def json_schema() -> dict[str, Any]:
    """The JSON Schema of every message, and of each topic's sample (``samples``)."""
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"ohmni_tb daemon protocol {PROTOCOL_VERSION}",
        "protocol": PROTOCOL_VERSION,
        "client_to_server": _CLIENT.json_schema(),
        "server_to_client": _SERVER.json_schema(),
        "samples": {topic: _SAMPLES[cls].json_schema() for topic, cls in SAMPLE_TYPES.items()},
        "results": {
            "stats": _STATS.json_schema(),
            "latest": "the topic's sample (see samples), or null before the first",
            "info": "firmware tags, servo models (keys: servo ids), neck, present, absent",
            "schedule": "[[stream, hz, phase_s, line_time_s], ...]",
            "subscribe": "{topic, max_hz, queue, hz}",
            "unsubscribe": "{topic}",
        },
    }


def write_schema(path: str | os.PathLike[str]) -> None:
    """Write :func:`json_schema` to ``path`` (``docs/daemon-schema.json``), as the repo keeps it."""
    Path(path).write_text(schema_text(), encoding="utf-8")


def schema_text() -> str:
    """:func:`json_schema` as the checked-in file's text."""
    return json.dumps(json_schema(), indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def _args(raw: dict[str, Any]) -> dict[str, Any]:
    args = raw.get("args")
    return args if isinstance(args, dict) else {}


def _shown(value: object) -> str:
    text = json.dumps(value) if not isinstance(value, str) else repr(value)
    return text if len(text) <= 40 else f"{text[:30]}…({len(text)} chars)"


def _listed(names: tuple[str, ...]) -> str:
    return ", ".join(names)


def _problems(exc: ValidationError, op: str) -> str:
    """pydantic's errors, one short clause each: where, what, and the value given."""
    parts = []
    for error in exc.errors(include_url=False):
        loc = error["loc"][1:] if error["loc"][:1] == (op,) else error["loc"]
        where = ".".join(str(p) for p in loc)
        given = "" if error["type"] == "missing" else f" (got {_shown(error.get('input'))})"
        parts.append(f"{where or 'message'}: {error['msg']}{given}")
    return "; ".join(parts)


if __name__ == "__main__":
    import sys

    write_schema(sys.argv[1] if len(sys.argv) > 1 else "docs/daemon-schema.json")
