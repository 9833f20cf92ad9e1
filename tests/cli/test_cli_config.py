"""``ohmni config``: the settings in effect and where each came from; ``config init``; and
the errors a user meets first (a port that does not open, a port where nothing answers)."""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path

import pytest

from ohmni_tb.config import RobotConfig

from ._helpers import invoke, words


@pytest.fixture(autouse=True)
def _clean_settings(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No OHMNI_* setting and no config file but the test's."""
    for key in list(os.environ):
        if key.upper().startswith("OHMNI_") and key.upper() != "OHMNI_DAEMON_URL":
            monkeypatch.delenv(key)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return work


def test_config_names_each_settings_source(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "robot.toml"
    path.write_text('watchdog_s = 0.3\nwheel_form = "i_jog"\n')
    monkeypatch.setenv("OHMNI_CONFIG", str(path))
    monkeypatch.setenv("OHMNI_WATCHDOG_S", "0.4")  # the environment beats the file
    monkeypatch.setenv("OHMNI_BATTERY_ADDR", "0xB0")
    result = invoke("config", "--json")
    assert result.code == 0, result.out
    shown = json.loads(result.stdout)
    assert shown["config_file"] == str(path)
    rows = {row["name"]: row for row in shown["settings"]}
    assert rows["watchdog_s"] == {"name": "watchdog_s", "value": 0.4, "source": "OHMNI_WATCHDOG_S"}
    assert rows["wheel_form"] == {"name": "wheel_form", "value": "i_jog", "source": str(path)}
    assert rows["battery_addr"]["value"] == 0xB0
    assert rows["port"] == {"name": "port", "value": "auto", "source": "default"}
    assert len(rows) == len(RobotConfig.model_fields)
    changed = invoke("config", "--changed")
    assert changed.code == 0
    text = words(changed.out)
    assert "watchdog_s 0.4 OHMNI_WATCHDOG_S" in text
    assert f"wheel_form i_jog {path}" in text
    assert "port" not in text.split("config file:")[1].replace(str(path), "")


def test_config_says_which_setting_is_bad_and_where_it_came_from(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_BATTERY_ADDR", "512")
    result = invoke("config")
    assert result.code == 1
    assert "battery_addr=512 is out of range: allowed 0..255 (from OHMNI_BATTERY_ADDR)" in words(
        result.out
    )


def test_config_init_writes_a_file_that_loads_as_the_defaults(tmp_path: Path) -> None:
    result = invoke("config", "init")
    assert result.code == 0, result.out
    path = tmp_path / "xdg" / "ohmni" / "ohmni.toml"
    assert f"wrote {path}" in words(result.out)
    text = path.read_text()
    assert RobotConfig.load(path) == RobotConfig()
    # Every setting is there, commented out, with a default TOML reads back as the default.
    lines = [
        line[2:]
        for line in text.splitlines()
        if line.startswith("# ") and line[2:].split(" = ")[0] in RobotConfig.model_fields
    ]
    settings = tomllib.loads("\n".join(lines))
    assert list(settings) == list(RobotConfig.model_fields)
    assert RobotConfig(**settings) == RobotConfig()
    again = invoke("config", "init")
    assert again.code == 1
    assert "exists: keep it, or give --overwrite" in again.out
    assert invoke("config", "init", "--overwrite").code == 0


def test_a_port_that_does_not_open_says_why_once_and_what_to_try() -> None:
    result = invoke("status", "--port", "/dev/ohmni-no-such-port")
    assert result.code == 1
    line = words(result.out)
    assert line == (
        "error: cannot open serial port '/dev/ohmni-no-such-port': No such file or directory; "
        "no such device: `ohmni ports` lists the serial ports here, --port sim:// is the "
        "simulator"
    )


@pytest.mark.usefixtures("virtual_time")
def test_a_port_where_nothing_answers_is_an_error() -> None:
    port = "sim://?silent=0,1,3,11,12,20"
    result = invoke("status", "--port", port)
    assert result.code == 1
    assert f"error: nothing answered on {port}: no board of the robot replied" in words(result.out)
    assert "link connected" not in result.out


def test_config_changed_says_so_when_nothing_is() -> None:
    result = invoke("config", "--changed")
    assert result.code == 0
    assert "every setting is at its default" in result.out
