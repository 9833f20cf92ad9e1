"""ohmni_tb.config_file: settings written into a config file in place, from a script."""

from __future__ import annotations

from pathlib import Path

import pytest

from ohmni_tb.config import RobotConfig
from ohmni_tb.config_file import read_settings, write_settings
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
