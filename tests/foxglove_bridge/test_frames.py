"""Foxglove's ``/tf`` and pose follow the configured frames (``frame_id_odom``,
``frame_id_baselink``), and ``enable_broadcast_transform=False`` publishes no ``/tf``, live
or recorded."""

from __future__ import annotations

import asyncio
import json
from collections import Counter
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from ohmni_tb import Robot
from ohmni_tb.foxglove import CHANNELS, FoxgloveBridge, McapRecorder
from ohmni_tb.robot import WheelOdomSample
from ohmni_tb.robot.wire import sample_from_json
from ohmni_tb.sim.clock import run_virtual

from ._wire import Descriptors, FoxgloveClient

#: Off every stream's phase, so the window's counts are exact.
SETTLE_S = 0.5037
DURATION_S = 0.5


async def _record(path: Path, **settings: Any) -> dict[str, int]:
    async with Robot.open("sim://", **settings) as robot:
        await asyncio.sleep(SETTLE_S)
        async with McapRecorder(robot, path, duration_s=DURATION_S) as recorder:
            await recorder.wait()
    return {topic: s.messages for topic, s in recorder.stats().items()}


def _read(path: Path) -> list[tuple[Any, Any, Any]]:
    with path.open("rb") as file:
        return list(make_reader(file).iter_messages(log_time_order=False))


def _decoded(records: list[tuple[Any, Any, Any]], topic: str) -> list[dict[str, Any]]:
    out = []
    for schema, channel, message in records:
        if channel.topic == topic:
            out.append(Descriptors.parse(schema.data).decode(schema.name, message.data))
    return out


def test_the_transform_and_the_pose_are_in_the_configured_frames(tmp_path: Path) -> None:
    path = tmp_path / "frames.mcap"
    run_virtual(_record(path, frame_id_odom="map", frame_id_baselink="base_footprint"))
    records = _read(path)
    transforms = _decoded(records, "/tf")
    poses = _decoded(records, "/tb_control/wheel_odom")
    assert len(transforms) == len(poses) == 25
    for transform in transforms:
        assert transform["parent_frame_id"] == "map"
        assert transform["child_frame_id"] == "base_footprint"
    assert {pose["frame_id"] for pose in poses} == {"map"}
    frames = set()
    for _, channel, message in records:
        if channel.topic == "/tb_control/wheel_odom/json":
            sample = sample_from_json("wheel_odom", json.loads(message.data))
            assert isinstance(sample, WheelOdomSample)
            frames.add((sample.frame_id, sample.child_frame_id))
    assert frames == {("map", "base_footprint")}


def test_without_broadcast_transform_no_tf_is_recorded(tmp_path: Path) -> None:
    path = tmp_path / "no-tf.mcap"
    written = run_virtual(_record(path, enable_broadcast_transform=False))
    assert "/tf" not in written
    assert written["/tb_control/wheel_odom"] == 25  # the pose still goes out
    counts = Counter(channel.topic for _, channel, _ in _read(path))
    assert counts["/tf"] == 0
    assert counts["/tb_control/wheel_odom"] == 25
    assert counts["/tb_control/wheel_odom/json"] == 25


async def test_without_broadcast_transform_the_live_view_offers_no_tf() -> None:
    async with (
        Robot.open("sim://", enable_broadcast_transform=False) as robot,
        FoxgloveBridge(robot, port=0) as bridge,
    ):
        client = await FoxgloveClient.connect(bridge.url)
        try:
            offered = set(client.channels)
        finally:
            await client.close()
    assert offered == {spec.topic for spec in CHANNELS} - {"/tf"}
