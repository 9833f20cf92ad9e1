"""The odometry's frame settings (tb_control's ``~frame_id_odom``, ``~frame_id_baselink``,
``~enable_broadcast_transform``): defaults, and one clear error for a bad name."""

from __future__ import annotations

import os
from typing import Any

import pytest

from ohmni_tb.config import RobotConfig
from ohmni_tb.errors import ConfigError


@pytest.fixture(autouse=True)
def hermetic(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in list(os.environ):
        if name.upper().startswith("OHMNI_"):
            monkeypatch.delenv(name)


def test_the_defaults_are_tb_controls() -> None:
    config = RobotConfig()
    assert config.frame_id_odom == "odom"
    assert config.frame_id_baselink == "base_link"
    assert config.enable_broadcast_transform is True


def test_frames_and_the_switch_are_read_from_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_FRAME_ID_ODOM", "map")
    monkeypatch.setenv("OHMNI_FRAME_ID_BASELINK", "robot1/base_link")
    monkeypatch.setenv("OHMNI_ENABLE_BROADCAST_TRANSFORM", "false")
    config = RobotConfig()
    assert (config.frame_id_odom, config.frame_id_baselink) == ("map", "robot1/base_link")
    assert config.enable_broadcast_transform is False


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        (
            {"frame_id_odom": "my odom"},
            "frame_id_odom='my odom' has a space: allowed a non-empty name without spaces "
            "(argument)",
        ),
        (
            {"frame_id_baselink": "base\tlink"},
            "frame_id_baselink='base\\tlink' has a space: allowed a non-empty name without "
            "spaces (argument)",
        ),
        (
            {"frame_id_odom": ""},
            "frame_id_odom='' is empty: allowed a non-empty name without spaces (argument)",
        ),
        (
            {"frame_id_odom": "odom", "frame_id_baselink": "odom"},
            "frame_id_baselink='odom' is frame_id_odom's too: the body frame needs a name of "
            "its own (argument)",
        ),
    ],
)
def test_a_bad_frame_is_one_clear_error(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        RobotConfig(**settings)
    assert str(caught.value) == message


def test_a_bad_frame_from_the_environment_says_where_it_came_from(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_FRAME_ID_BASELINK", "base link")
    with pytest.raises(ConfigError) as caught:
        RobotConfig()
    assert str(caught.value) == (
        "frame_id_baselink='base link' has a space: allowed a non-empty name without spaces "
        "(from OHMNI_FRAME_ID_BASELINK)"
    )
