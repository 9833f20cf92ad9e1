"""The channel table and its encoders: what a Foxglove client decodes from each sample."""

from __future__ import annotations

import asyncio
import json
import math
import time
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.foxglove.channels import (
    CHANNELS,
    WallClock,
    channel_schema,
    channels_of,
    encoder_for,
)
from ohmni_tb.robot import (
    STREAM_NAMES,
    DiagnosticEntry,
    DiagnosticLevel,
    DiagnosticsSample,
    Link,
    RobotStateSample,
    WheelOdomSample,
)
from ohmni_tb.robot.samples import STREAMS
from ohmni_tb.robot.wire import sample_from_json, sample_json
from ohmni_tb.sim.clock import run_virtual

from ._wire import Descriptors

TOPICS = [spec.topic for spec in CHANNELS]

ODOM = WheelOdomSample(
    stamp_s=12.5,
    x_m=1.25,
    y_m=-0.5,
    yaw_rad=math.pi / 2,
    heading_rad=math.pi / 2 + 2 * math.pi,
    linear_mps=0.3,
    angular_radps=-0.2,
    covariance=(1e-4, 0.0, 0.0, 0.0, 1e-4, 0.0, 0.0, 0.0, 1e-3),
    commanded_linear_mps=0.3,
    commanded_angular_radps=-0.2,
)


def spec_of(topic: str) -> Any:
    return next(spec for spec in CHANNELS if spec.topic == topic)


def test_every_stream_has_a_json_channel_named_like_tb_control() -> None:
    assert len(set(TOPICS)) == len(TOPICS)
    json_topics = {spec.stream: spec.topic for spec in CHANNELS if spec.message_encoding == "json"}
    assert set(json_topics) == set(STREAM_NAMES)
    for stream, topic in json_topics.items():
        expected = {
            "wheel_odom": "/tb_control/wheel_odom/json",
            "diagnostics": "/diagnostics",  # as ROS names it: not a tb_control topic
        }.get(stream, f"/tb_control/{stream}")
        assert topic == expected
    assert [spec.topic for spec in channels_of("wheel_odom")] == [
        "/tf",
        "/tb_control/wheel_odom",
        "/tb_control/wheel_odom/json",
    ]


@pytest.mark.parametrize("topic", TOPICS)
def test_each_schema_is_what_the_channel_says(topic: str) -> None:
    spec = spec_of(topic)
    schema = channel_schema(spec)
    assert schema.name == spec.schema_name
    if spec.message_encoding == "protobuf":
        assert schema.encoding == "protobuf"
        assert spec.schema_name in Descriptors.parse(schema.data).messages
        return
    assert schema.encoding == "jsonschema"
    body = json.loads(schema.data)
    # Plain, self-contained schemas: the app does not have to resolve references.
    assert "$ref" not in schema.data.decode()
    assert "$defs" not in body
    assert body["type"] == "object"
    assert body["title"] == spec.schema_name
    fields = STREAMS[spec.stream].sample_type.__dataclass_fields__
    assert set(body["properties"]) == set(fields)


def _json_type_matches(value: Any, schema: dict[str, Any]) -> bool:
    options = schema.get("anyOf", [schema])
    for option in options:
        kind = option.get("type")
        if kind is None and "enum" in option:
            return value in option["enum"]
        if (
            (kind == "null" and value is None)
            or (kind == "boolean" and isinstance(value, bool))
            or (kind == "integer" and isinstance(value, int) and not isinstance(value, bool))
            or (kind == "number" and isinstance(value, int | float) and not isinstance(value, bool))
            or (kind == "string" and isinstance(value, str))
            or (kind == "array" and isinstance(value, list))
            or (kind == "object" and isinstance(value, dict))
        ):
            return True
    return False


def test_json_messages_are_the_daemons_samples_and_fit_their_schema() -> None:
    async def collect() -> dict[str, Any]:
        seen: dict[str, Any] = {}
        for url, pid_debug in (("sim://", True), ("sim://?neck=worm", False)):
            async with Robot.open(url, pid_debug=pid_debug) as robot:
                for _ in range(20):
                    robot.drive(0.2, 0.3)  # pid_debug publishes while driving
                    await asyncio.sleep(0.05)
                seen.update({n: robot.latest(n) for n in STREAM_NAMES if robot.latest(n)})
        return seen

    samples = run_virtual(collect())
    assert set(samples) == set(STREAM_NAMES)
    checked = 0
    for spec in CHANNELS:
        if spec.message_encoding != "json":
            continue
        sample = samples[spec.stream]
        payload = encoder_for(spec)(sample, 0)
        assert payload is not None
        data = json.loads(payload)
        assert data == sample_json(sample), spec.topic
        assert sample_from_json(spec.stream, data) == sample
        properties = json.loads(channel_schema(spec).data)["properties"]
        for name, value in data.items():
            assert _json_type_matches(value, properties[name]), (spec.topic, name, value)
        checked += 1
    assert checked == len(STREAM_NAMES)


def test_the_odometry_decodes_as_a_transform_and_a_pose() -> None:
    ns = 1_700_000_000_123_456_789
    transform_spec, pose_spec = spec_of("/tf"), spec_of("/tb_control/wheel_odom")
    transform = Descriptors.parse(channel_schema(transform_spec).data).decode(
        "foxglove.FrameTransform", encoder_for(transform_spec)(ODOM, ns) or b""
    )
    assert transform["parent_frame_id"] == "odom"
    assert transform["child_frame_id"] == "base_link"
    assert transform["timestamp"] == {"seconds": 1_700_000_000, "nanos": 123_456_789}
    assert transform["translation"] == {"x": 1.25, "y": -0.5}  # proto3 leaves out z = 0
    rotation = transform["rotation"]
    assert rotation.get("x", 0.0) == rotation.get("y", 0.0) == 0.0
    assert rotation["z"] == pytest.approx(math.sqrt(0.5))
    assert rotation["w"] == pytest.approx(math.sqrt(0.5))
    pose = Descriptors.parse(channel_schema(pose_spec).data).decode(
        "foxglove.PoseInFrame", encoder_for(pose_spec)(ODOM, ns) or b""
    )
    assert pose["frame_id"] == "odom"
    assert pose["pose"]["position"] == transform["translation"]
    assert pose["pose"]["orientation"] == rotation


def test_a_state_change_goes_to_the_log_and_a_periodic_state_does_not() -> None:
    spec = spec_of("/tb_control/log")
    encode = encoder_for(spec)
    quiet = RobotStateSample(1.0, Link.CONNECTED, False, False, (), "herkulex", (0, 1), ())
    assert encode(quiet, 0) is None
    lost = RobotStateSample(
        2.0, Link.LOST, False, False, ("link_lost",), "herkulex", (), (0, 1), "link lost: EOF"
    )
    descriptors = Descriptors.parse(channel_schema(spec).data)
    log = descriptors.decode("foxglove.Log", encode(lost, 5_000_000_000) or b"")
    assert log["message"] == "link lost: EOF"
    assert log["name"] == "ohmni_tb.robot"
    assert log["level"] == 3  # WARNING: a fault
    assert log["timestamp"] == {"seconds": 5}
    back = descriptors.decode(
        "foxglove.Log", encode(quiet.__class__(**{**_fields(quiet), "event": "opened"}), 0) or b""
    )
    assert back["level"] == 2  # INFO


def test_a_health_level_change_goes_to_the_diagnostics_log_at_its_level() -> None:
    spec = spec_of("/diagnostics/log")
    assert spec.stream == "diagnostics"
    encode = encoder_for(spec)
    silent = DiagnosticEntry(
        "ext1", 11, DiagnosticLevel.ERROR, "silent: 9 requests in a row unanswered", {}
    )
    link = DiagnosticEntry("link", None, DiagnosticLevel.OK, "ok", {"state": "connected"})
    steady = DiagnosticsSample(3.0, DiagnosticLevel.ERROR, (silent, link))
    assert encode(steady, 0) is None  # nothing changed: nothing to log
    event = "ext1 ok → error: silent: 9 requests in a row unanswered"
    changed = DiagnosticsSample(2.0, DiagnosticLevel.ERROR, (silent, link), event)
    descriptors = Descriptors.parse(channel_schema(spec).data)
    log = descriptors.decode("foxglove.Log", encode(changed, 7_000_000_000) or b"")
    assert log["message"] == event
    assert log["name"] == "ohmni_tb.diagnostics"
    assert log["level"] == 4  # ERROR
    assert log["timestamp"] == {"seconds": 7}
    recovered = DiagnosticsSample(4.0, DiagnosticLevel.OK, (link,), "ext1 error → ok: ok")
    assert descriptors.decode("foxglove.Log", encode(recovered, 0) or b"")["level"] == 2  # INFO


def _fields(sample: RobotStateSample) -> dict[str, Any]:
    return {name: getattr(sample, name) for name in sample.__dataclass_fields__}


def test_the_wall_clock_keeps_the_spacing_of_the_stamps() -> None:
    before = time.time_ns()
    clock = WallClock.at(100.0)
    after = time.time_ns()
    assert before <= clock.ns(100.0) <= after
    assert clock.ns(100.02) - clock.ns(100.0) == 20_000_000
    assert clock.ns(3600.0 + 100.0) - clock.ns(100.0) == 3_600_000_000_000
