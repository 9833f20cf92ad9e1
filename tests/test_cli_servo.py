"""Every ``ohmni servo`` command against the simulator, and the demo."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app

runner = CliRunner()
SIM = ["--port", "sim://"]


def invoke(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, list(args))
    return result.exit_code, result.output


def test_scan_finds_the_neck_and_the_external_servos() -> None:
    code, out = invoke("servo", "scan", *SIM, "--json")
    assert code == 0, out
    found = json.loads(out)
    assert [row["sid"] for row in found] == [3, 11, 12]
    assert found[0]["model"] == "DRS_0101"
    assert found[0]["position_raw"] == 512
    assert found[0]["angle_deg"] == 0.0


def test_scan_table_names_the_models() -> None:
    code, out = invoke("servo", "scan", "--port", "sim://?neck=0201&ext=none", "--last", "20")
    assert code == 0, out
    assert "DRS_0201" in out
    assert "ext1" not in out


def test_info_has_both_memories() -> None:
    code, out = invoke("servo", "info", *SIM, "--sid", "3", "--json")
    assert code == 0, out
    info = json.loads(out)
    assert info["eep"]["id"] == 3
    assert info["ram"]["torque_control"] == 0


def test_read_and_unknown_register() -> None:
    code, out = invoke("servo", "read", "acceleration_ratio", *SIM, "--json")
    assert code == 0, out
    assert json.loads(out) == {"register": "acceleration_ratio", "memory": "RAM", "value": 25}
    code, out = invoke("servo", "read", "acceleration_ratio", *SIM, "--eep")
    assert code == 0, out
    assert "EEP acceleration_ratio = 25" in out
    code, out = invoke("servo", "read", "no_such_register", *SIM)
    assert code == 2
    assert "no_such_register" in out


def test_write_checks_the_range_before_sending() -> None:
    code, out = invoke("servo", "write", "led_control", "1", *SIM)
    assert code == 0, out
    assert "led_control ← 1" in out
    code, out = invoke("servo", "write", "acceleration_ratio", "60", *SIM)
    assert code == 1
    assert "acceleration_ratio=60 is out of range: allowed 0..50" in out
    code, out = invoke("servo", "write", "temperature", "10", *SIM)
    assert code == 1
    assert "read-only" in out


def test_move_needs_torque_and_respects_the_range() -> None:
    code, out = invoke("servo", "move", "400", *SIM)
    assert code == 1
    assert "torque off" in out
    code, out = invoke("servo", "move", "400", *SIM, "--torque-on", "--playtime", "0.5")
    assert code == 0, out
    assert "→ 400" in out
    # The neck (sid 3, the default) is held in its safe range 280..650 unless told otherwise.
    code, out = invoke("servo", "move", "700", *SIM, "--torque-on")
    assert code == 1
    assert "700 is out of range: allowed 280..650" in out
    code, out = invoke("servo", "move", "250", *SIM, "--torque-on", "--min-raw", "200")
    assert code == 0, out
    # Other servos get the factory range, or the one given.
    code, out = invoke("servo", "move", "1010", *SIM, "--sid", "11", "--torque-on")
    assert code == 1
    assert "21..1002" in out
    code, out = invoke("servo", "move", "900", *SIM, "--sid", "11", "--max-raw", "800")
    assert code == 1
    assert "21..800" in out
    code, out = invoke("servo", "move", "400", *SIM, "--playtime", "9")
    assert code == 1
    assert "playtime" in out


@pytest.mark.parametrize("mode", ["free", "brake", "on"])
def test_torque_modes(mode: str) -> None:
    code, out = invoke("servo", "torque", mode, *SIM)
    assert code == 0, out
    assert f"torque {mode}" in out


def test_torque_bad_mode() -> None:
    code, out = invoke("servo", "torque", "loose", *SIM)
    assert code == 2
    assert "loose" in out


def test_stat_and_clear() -> None:
    code, out = invoke("servo", "stat", *SIM, "--json")
    assert code == 0, out
    status = json.loads(out)
    assert status["error"] == 0
    assert status["torque_on"] is False
    code, out = invoke("servo", "clear", *SIM, "--torque-on", "--json")
    assert code == 0, out
    assert json.loads(out)["torque_on"] is True


def test_missing_servo_is_an_error_line_not_a_traceback() -> None:
    code, out = invoke("servo", "stat", *SIM, "--sid", "40", "--timeout", "0.005")
    assert code == 1
    assert "no reply from sid 40" in out
    assert "Traceback" not in out


def test_bad_sid_names_the_value() -> None:
    code, out = invoke("servo", "stat", *SIM, "--sid", "neck")
    assert code == 2
    assert "neck" in out


def test_demo_runs_on_the_simulator() -> None:
    code, out = invoke("demo")
    assert code == 0, out
    assert "firmware 'sim-drive-1.0'" in out
    assert "simulator ground truth" in out
    assert "0.0s:280" in out
    assert ":650" in out
    assert "bus statistics" in out


def test_version() -> None:
    code, out = invoke("version")
    assert code == 0
    assert out.strip().count(".") == 2


def test_demo_moves_a_worm_neck_when_the_robot_has_one() -> None:
    code, out = invoke("demo", "--port", "sim://?neck=worm")
    assert code == 0, out
    assert "firmware 'sim-worm-1.0'" in out
    assert "worm neck: 0 → 60000" in out
