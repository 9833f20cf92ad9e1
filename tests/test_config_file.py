"""ohmni_tb.config_file: settings written into a config file in place, from a script."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from ohmni_tb.config import RobotConfig
from ohmni_tb.config_file import (
    SettingValue,
    default_config_file,
    loaded_config_file,
    read_settings,
    write_settings,
)
from ohmni_tb.errors import ConfigError


def test_written_settings_are_what_a_robot_loads(tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text('# mine\nport = "sim://"  # the simulator\npid_kp = 600\n')
    outcome = write_settings(path, {"pid_kp": 650.0, "pid_ki": 300.0})
    assert not outcome.created
    assert outcome.previous == {"pid_kp": 600, "pid_ki": None}
    assert path.read_text() == (
        '# mine\nport = "sim://"  # the simulator\npid_kp = 650.0\npid_ki = 300.0\n'
    )
    assert read_settings(path) == {"port": "sim://", "pid_kp": 650.0, "pid_ki": 300.0}
    config = RobotConfig.load(path)
    assert (config.pid_kp, config.pid_ki) == (650.0, 300.0)


def test_a_missing_file_is_created(tmp_path: Path) -> None:
    path = tmp_path / "new" / "ohmni.toml"
    assert write_settings(path, {"pid_kd": 2.0}).created
    assert read_settings(path) == {"pid_kd": 2.0}


@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"pid_kp": -1.0}, "pid_kp=-1.0 is out of range: allowed 0..10000"),
        ({"pid_kp": float("nan")}, "pid_kp=nan is not a finite number"),
        ({"wheel_hz": 500.0}, "wheel_hz=500.0 is out of range: allowed 10..100"),
        ({"pid_kpp": 1.0}, "unknown setting 'pid_kpp'"),
    ],
)
def test_a_bad_value_is_refused_and_the_file_is_untouched(
    values: dict[str, float], named: str, tmp_path: Path
) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text("pid_kp = 600\n")
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        write_settings(path, values)
    assert path.read_text() == "pid_kp = 600\n"


def test_strings_booleans_ints_and_id_lists_are_written_as_toml(tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text('# mine\nport = "sim://"\n\n[robot]\nwheel_form = "s_jog"  # assumed\n')
    values: dict[str, SettingValue] = {
        "wheel_form": "i_jog",
        "right_mirrored": False,
        "battery_addr": 0xB0,
        "ext_servo_ids": [13, 14],
    }
    outcome = write_settings(path, values)
    assert outcome.previous == {
        "wheel_form": "s_jog",
        "right_mirrored": None,
        "battery_addr": None,
        "ext_servo_ids": None,
    }
    assert path.read_text() == (
        '# mine\nport = "sim://"\n\n[robot]\nwheel_form = "i_jog"  # assumed\n'
        "right_mirrored = false\nbattery_addr = 176\next_servo_ids = [13, 14]\n"
    )
    config = RobotConfig.load(path)
    assert (config.wheel_form, config.right_mirrored, config.battery_addr) == ("i_jog", False, 176)
    assert config.ext_servo_ids == (13, 14)
    # A tuple and an empty list are lists in TOML.
    write_settings(path, {"ext_servo_ids": ()})
    assert RobotConfig.load(path).ext_servo_ids == ()


@pytest.mark.parametrize(
    ("values", "named"),
    [
        ({"wheel_form": "x_jog"}, "wheel_form='x_jog'"),
        ({"battery_addr": 256}, "battery_addr=256 is out of range: allowed 0..255"),
        ({"ext_servo_ids": [1]}, "ext_servo_ids"),
        ({"ext_servo_ids": ["13"]}, "ext_servo_ids"),
    ],
)
def test_a_bad_value_of_another_kind_is_refused_and_nothing_written(
    values: dict[str, object], named: str, tmp_path: Path
) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text("battery_addr = 160\n")
    with pytest.raises(ConfigError, match=re.escape(named)):
        write_settings(path, values)  # type: ignore[arg-type]  # the wrong kinds on purpose
    assert path.read_text() == "battery_addr = 160\n"


def test_the_default_file_is_ohmni_config_even_before_it_exists(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    named = tmp_path / "robot.toml"
    monkeypatch.setenv("OHMNI_CONFIG", str(named))
    assert default_config_file() == named
    assert loaded_config_file() is None
    named.write_text("")
    assert loaded_config_file() == named
    monkeypatch.delenv("OHMNI_CONFIG")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    assert default_config_file() == tmp_path / "xdg" / "ohmni" / "ohmni.toml"
    (tmp_path / "ohmni.toml").write_text("")
    assert default_config_file() == tmp_path / "ohmni.toml"


def test_settings_that_only_hold_together_are_written_together(tmp_path: Path) -> None:
    # A cells-only battery block is 10 bytes: the length alone would be too short for
    # the default (tbcore) layout, but the two are written at once.
    path = tmp_path / "ohmni.toml"
    write_settings(path, {"battery_layout": "cells", "battery_length": 10})
    config = RobotConfig.load(path)
    assert (config.battery_layout, config.battery_length) == ("cells", 10)
    # Each value is still checked alone against its own range.
    with pytest.raises(ConfigError, match="battery_length=5 is out of range"):
        write_settings(path, {"battery_length": 5})
    # And the file as a whole must hold together when it is read.
    path.write_text("battery_length = 10\n")
    with pytest.raises(ConfigError, match="shorter than the tbcore layout"):
        RobotConfig.load(path)


def test_a_setting_commented_out_by_config_init_is_set_in_its_line(tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text(RobotConfig.example_file())
    write_settings(path, {"wheel_form": "i_jog", "battery_addr": 0xB0})
    lines = path.read_text().splitlines()
    assert 'wheel_form = "i_jog"' in lines
    assert "battery_addr = 176" in lines
    assert "# wheel_form = " not in path.read_text()
    # In its place, under its description: the line before it is still its comment.
    at = lines.index("battery_addr = 176")
    assert lines[at - 1].startswith("# ")
    assert RobotConfig.load(path).profile().core.status_addr == 0xB0
