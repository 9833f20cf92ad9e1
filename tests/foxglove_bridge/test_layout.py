"""docs/foxglove-layout.json, the layout the docs offer for the app, against what the
bridge serves: every panel placed and configured, every topic one the bridge advertises
(or the Teleop topic it takes), every plotted field one the channel's schema has, and a
Teleop panel that publishes fast enough for the watchdog and within the Robot's limits."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from ohmni_tb.config import RobotConfig
from ohmni_tb.foxglove import CHANNELS
from ohmni_tb.foxglove.bridge import TELEOP_TOPICS
from ohmni_tb.foxglove.channels import channel_schema

LAYOUT = Path(__file__).parents[2] / "docs" / "foxglove-layout.json"
#: Panel types of the Foxglove app this layout uses.
PANEL_TYPES = {"3D", "Plot", "RawMessages", "Parameters", "Teleop"}


@pytest.fixture(scope="module")
def layout() -> dict[str, Any]:
    data: dict[str, Any] = json.loads(LAYOUT.read_text())
    return data


def placed(node: Any) -> list[str]:
    """The panel ids in the layout tree, left to right."""
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"direction", "first", "second", "splitPercentage"}, node
    assert node["direction"] in ("row", "column")
    assert 0 < node.get("splitPercentage", 50) < 100
    return placed(node["first"]) + placed(node["second"])


def field_exists(topic: str, path: str) -> bool:
    """Whether ``path`` (``a`` or ``a.b``) is a field of ``topic``'s JSON schema."""
    spec = next(s for s in CHANNELS if s.topic == topic)
    node: Any = json.loads(channel_schema(spec).data)
    for name in path.split("."):
        properties = node.get("properties", {})
        if name not in properties:
            return False
        node = properties[name]
    return True


def split(message_path: str) -> tuple[str, str]:
    """``/topic/name.field.sub`` → (``/topic/name``, ``field.sub``)."""
    topic, _, field = message_path.partition(".")
    return topic, field


def test_every_panel_is_placed_once_and_configured(layout: dict[str, Any]) -> None:
    ids = placed(layout["layout"])
    assert len(ids) == len(set(ids))
    assert set(ids) == set(layout["configById"])
    assert {panel.split("!")[0] for panel in ids} == PANEL_TYPES


def test_every_topic_and_field_is_one_the_bridge_serves(layout: dict[str, Any]) -> None:
    served = {spec.topic for spec in CHANNELS}
    configs = layout["configById"]
    plotted: list[str] = []
    for panel, config in configs.items():
        kind = panel.split("!")[0]
        if kind == "Plot":
            plotted += [p["value"] for p in config["paths"]]
            if "xAxisPath" in config:
                plotted.append(config["xAxisPath"]["value"])
        elif kind == "RawMessages":
            assert config["topicPath"] in served
        elif kind == "3D":
            assert set(config["topics"]) <= served
            assert config["followTf"] == "base_link"
    assert plotted
    for path in plotted:
        topic, field = split(path)
        assert topic in served, path
        assert field_exists(topic, field), path


def test_the_teleop_panel_drives_within_the_limits_and_ahead_of_the_watchdog(
    layout: dict[str, Any],
) -> None:
    config = RobotConfig()
    teleop = layout["configById"]["Teleop!ohmni_drive"]
    assert teleop["topic"] in TELEOP_TOPICS
    # A held button repeats faster than the watchdog stops the wheels.
    assert 1 / teleop["publishRate"] < config.watchdog_s
    for button in ("upButton", "downButton", "leftButton", "rightButton"):
        field, value = teleop[button]["field"], teleop[button]["value"]
        limit = config.max_linear_mps if field == "linear-x" else config.max_angular_radps
        assert field in ("linear-x", "angular-z")
        assert 0 < abs(value) <= limit
