"""How the Robot's streams look in Foxglove: one table of channels, their schemas, encoders.

Every stream has a JSON channel named like tb_control's topic (``/tb_control/<stream>``)
whose message is the stream's sample exactly as the daemon sends it
(:func:`ohmni_tb.robot.wire.sample_json`: enums by value, tuples as lists), so a
recording holds every field and the samples can be rebuilt from it. The odometry also
goes out in Foxglove's well-known schemas, protobuf-encoded, for the 3D panel: the
transform between the sample's frames (``frame_id_odom`` → ``frame_id_baselink``,
``odom`` → ``base_link`` by default) on ``/tf`` — unless ``enable_broadcast_transform``
is off — and the pose on ``/tb_control/wheel_odom`` (its JSON on
``/tb_control/wheel_odom/json``). The Robot's state changes, in words, go
to ``/tb_control/log`` as ``foxglove.Log`` for the Log panel. The robot's health goes on
``/diagnostics`` (as ROS names its diagnostics topic), its level changes in words on
``/diagnostics/log`` as ``foxglove.Log``.

Time: a sample's ``stamp_s`` is the event loop's monotonic clock; Foxglove and MCAP want
wall-clock nanoseconds. :class:`WallClock` converts with one offset taken when
publishing starts, so the stamps keep their spacing exactly and a wall-clock step (NTP,
a manual change) during a run does not reorder them.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from typing import Any, Final

from foxglove import Schema
from foxglove.messages import (
    FrameTransform,
    Log,
    LogLevel,
    Pose,
    PoseInFrame,
    Quaternion,
    Timestamp,
    Vector3,
)
from pydantic import TypeAdapter

from ohmni_tb.control.defaults import DEFAULT_BASE_FRAME, DEFAULT_ODOM_FRAME
from ohmni_tb.robot.samples import (
    STREAMS,
    DiagnosticLevel,
    DiagnosticsSample,
    RobotStateSample,
    Sample,
    WheelOdomSample,
)

__all__ = [
    "BASE_FRAME",
    "CHANNELS",
    "ODOM_FRAME",
    "ChannelSpec",
    "Encoder",
    "WallClock",
    "channel_schema",
    "channels_of",
    "encoder_for",
    "json_schema_of",
]

#: The odometry frame by default (``frame_id_odom``): where the robot was when the Robot
#: opened (or the odometry was reset).
ODOM_FRAME: Final = DEFAULT_ODOM_FRAME
#: The robot's body frame by default (``frame_id_baselink``), between the wheels on the
#: floor (ROS's convention).
BASE_FRAME: Final = DEFAULT_BASE_FRAME
#: The transforms' topic.
TF_TOPIC: Final = "/tf"

_PREFIX = "/tb_control"


@dataclass(frozen=True, slots=True)
class ChannelSpec:
    """One Foxglove channel.

    Attributes:
        topic: The channel's topic.
        stream: The Robot stream its messages come from.
        schema_name: ``foxglove.…`` for a well-known schema, ``ohmni_tb.…`` for ours.
        message_encoding: ``protobuf`` (well-known schemas) or ``json``.
        description: What it carries, for the docs and ``ohmni record``'s summary.
    """

    topic: str
    stream: str
    schema_name: str
    message_encoding: str
    description: str


def _json_channel(stream: str, topic: str | None = None, what: str = "") -> ChannelSpec:
    cls = STREAMS[stream].sample_type
    return ChannelSpec(
        topic or f"{_PREFIX}/{stream}",
        stream,
        f"ohmni_tb.{cls.__name__}",
        "json",
        what or f"the {stream} stream's samples ({cls.__name__}), every field",
    )


#: Every channel, in a fixed order: the WebSocket server advertises them in this order,
#: with ids 1, 2, … when it is the only user of its context.
CHANNELS: Final[tuple[ChannelSpec, ...]] = (
    ChannelSpec(
        TF_TOPIC,
        "wheel_odom",
        "foxglove.FrameTransform",
        "protobuf",
        "the odometry as the transform frame_id_odom → frame_id_baselink "
        f"({ODOM_FRAME} → {BASE_FRAME} by default)",
    ),
    ChannelSpec(
        f"{_PREFIX}/wheel_odom",
        "wheel_odom",
        "foxglove.PoseInFrame",
        "protobuf",
        f"the odometry pose in frame_id_odom ({ODOM_FRAME} by default)",
    ),
    _json_channel(
        "wheel_odom",
        f"{_PREFIX}/wheel_odom/json",
        "the odometry samples (WheelOdomSample): pose, speeds, covariance, the command",
    ),
    _json_channel("wheel_encoder"),
    _json_channel("tbcore_status"),
    _json_channel("servo_neck"),
    _json_channel("servo_ext1"),
    _json_channel("servo_ext2"),
    _json_channel("new_neck"),
    _json_channel("robot_state"),
    _json_channel("pid_debug"),
    ChannelSpec(
        f"{_PREFIX}/log",
        "robot_state",
        "foxglove.Log",
        "protobuf",
        "what changed in the Robot's state, in words (robot_state samples with an event)",
    ),
    _json_channel(
        "diagnostics",
        "/diagnostics",
        "the robot's health (DiagnosticsSample): each device's and the link's level, "
        "message and figures",
    ),
    ChannelSpec(
        "/diagnostics/log",
        "diagnostics",
        "foxglove.Log",
        "protobuf",
        "the health's level changes, in words (diagnostics samples with an event)",
    ),
)

#: One sample and its wall-clock time (ns) → the channel's message, or ``None`` when the
#: channel has nothing for this sample (``/tb_control/log`` for a state without an event).
Encoder = Callable[[Any, int], bytes | None]


def channels_of(stream: str) -> tuple[ChannelSpec, ...]:
    """The channels a stream's samples go to, in :data:`CHANNELS` order."""
    return tuple(spec for spec in CHANNELS if spec.stream == stream)


def channel_schema(spec: ChannelSpec) -> Schema:
    """The schema a channel advertises: the SDK's protobuf descriptor for a well-known
    schema, a JSON Schema (no ``$ref``) for ours."""
    well_known = _WELL_KNOWN.get(spec.schema_name)
    if well_known is not None:
        schema: Schema = well_known.get_schema()
        return schema
    data = json_schema_of(spec.stream, spec.schema_name).encode()
    return Schema(name=spec.schema_name, encoding="jsonschema", data=data)


@cache
def json_schema_of(stream: str, title: str) -> str:
    """The JSON Schema of a stream's sample, its ``$ref`` s resolved in place (the
    Foxglove app reads plain schemas), with ``title`` as its name."""
    schema = TypeAdapter(STREAMS[stream].sample_type).json_schema()
    definitions = schema.pop("$defs", {})
    resolved = _resolve(schema, definitions)
    resolved["title"] = title
    return json.dumps(resolved, separators=(",", ":"), ensure_ascii=False)


def encoder_for(spec: ChannelSpec) -> Encoder:
    """The encoder of a channel: its stream's sample → the channel's message."""
    special = _ENCODERS.get(spec.topic)
    if special is not None:
        return special
    dump = _json_dumper(spec.stream)
    return lambda sample, _ns: dump(sample)


@dataclass(frozen=True, slots=True)
class WallClock:
    """The event loop's monotonic stamps as wall-clock nanoseconds since the Unix epoch.

    Attributes:
        offset_ns: Wall clock minus loop clock, taken once.
    """

    offset_ns: int

    @classmethod
    def at(cls, loop_time_s: float) -> WallClock:
        """The offset now, given the loop's clock now (``loop.time()``)."""
        return cls(time.time_ns() - round(loop_time_s * 1e9))

    def ns(self, stamp_s: float) -> int:
        """A loop-clock stamp as wall-clock nanoseconds."""
        return self.offset_ns + round(stamp_s * 1e9)


_WELL_KNOWN: Final[dict[str, Any]] = {
    "foxglove.FrameTransform": FrameTransform,
    "foxglove.PoseInFrame": PoseInFrame,
    "foxglove.Log": Log,
}


def _resolve(node: Any, definitions: dict[str, Any]) -> Any:
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str):
            target = _resolve(definitions[ref.rsplit("/", 1)[-1]], definitions)
            rest = {k: _resolve(v, definitions) for k, v in node.items() if k != "$ref"}
            return {**target, **rest}
        return {k: _resolve(v, definitions) for k, v in node.items()}
    if isinstance(node, list):
        return [_resolve(v, definitions) for v in node]
    return node


def _json_dumper(stream: str) -> Callable[[Sample], bytes]:
    # pydantic's serializer, the daemon's rules (sample_json), straight to bytes in Rust:
    # a few µs a sample instead of a dict and json.dumps.
    adapter: TypeAdapter[Any] = TypeAdapter(STREAMS[stream].sample_type)
    return adapter.dump_json


def _timestamp(ns: int) -> Timestamp:
    sec, nsec = divmod(ns, 1_000_000_000)
    return Timestamp(sec, nsec)


def _rotation(sample: WheelOdomSample) -> Quaternion:
    x, y, z, w = sample.orientation
    return Quaternion(x=x, y=y, z=z, w=w)


def _encode_transform(sample: WheelOdomSample, ns: int) -> bytes:
    return FrameTransform(
        timestamp=_timestamp(ns),
        parent_frame_id=sample.frame_id,
        child_frame_id=sample.child_frame_id,
        translation=Vector3(x=sample.x_m, y=sample.y_m, z=0.0),
        rotation=_rotation(sample),
    ).encode()


def _encode_pose(sample: WheelOdomSample, ns: int) -> bytes:
    return PoseInFrame(
        timestamp=_timestamp(ns),
        frame_id=sample.frame_id,
        pose=Pose(
            position=Vector3(x=sample.x_m, y=sample.y_m, z=0.0),
            orientation=_rotation(sample),
        ),
    ).encode()


def _encode_log(sample: RobotStateSample, ns: int) -> bytes | None:
    if sample.event is None:
        return None
    troubled = sample.estopped or bool(sample.faults)
    return Log(
        timestamp=_timestamp(ns),
        level=LogLevel.Warning if troubled else LogLevel.Info,
        message=sample.event,
        name="ohmni_tb.robot",
    ).encode()


#: A diagnostics level as a Log's level.
_LOG_LEVELS: Final = {
    DiagnosticLevel.OK: LogLevel.Info,
    DiagnosticLevel.WARN: LogLevel.Warning,
    DiagnosticLevel.ERROR: LogLevel.Error,
}


def _encode_diagnostics_log(sample: DiagnosticsSample, ns: int) -> bytes | None:
    if sample.event is None:
        return None
    return Log(
        timestamp=_timestamp(ns),
        level=_LOG_LEVELS[sample.level],
        message=sample.event,
        name="ohmni_tb.diagnostics",
    ).encode()


_ENCODERS: Final[dict[str, Encoder]] = {
    "/tf": _encode_transform,
    f"{_PREFIX}/wheel_odom": _encode_pose,
    f"{_PREFIX}/log": _encode_log,
    "/diagnostics/log": _encode_diagnostics_log,
}
