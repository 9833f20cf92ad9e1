"""``ohmni diag`` (once, --json, --watch), the health in ``ohmni status``, and ``ohmni odom
set``, against the simulator on virtual time."""

from __future__ import annotations

import itertools
import json
from typing import Any

import pytest

from ohmni_tb.cli import diag as diag_cli
from ohmni_tb.robot import DiagnosticsSample, SampleStream

from ._helpers import invoke, words

SIM = ["--port", "sim://"]
ENTRIES = ["left_drive", "right_drive", "core", "neck", "ext1", "ext2", "link"]


def diag_json(*args: str, env: dict[str, str] | None = None) -> dict[str, Any]:
    result = invoke("diag", *args, "--json", env=env)
    assert result.code == 0, result.out
    data: dict[str, Any] = json.loads(result.stdout)
    return data


@pytest.mark.usefixtures("virtual_time")
def test_diag_prints_one_row_per_device_and_the_link() -> None:
    result = invoke("diag", *SIM)
    assert result.code == 0, result.out
    text = words(result.stdout)
    assert text.startswith("health: ok")
    for name in ENTRIES:
        assert f" {name} " in f" {text} "
    assert "left_drive 0 ok sim-drive-1.0, p99" in text
    assert "core 20 ok sim-core-1.0" in text
    assert "link ok 0 timeouts, connected, wire" in text


@pytest.mark.usefixtures("virtual_time")
def test_diag_json_is_one_object_with_every_entry() -> None:
    data = diag_json(*SIM)
    assert set(data) == {"port", "level", "event", "entries"}
    assert (data["port"], data["level"], data["event"]) == ("sim://", "ok", None)
    assert [entry["name"] for entry in data["entries"]] == ENTRIES
    assert [entry["sid"] for entry in data["entries"]] == [0, 1, 20, 3, 11, 12, None]
    left = data["entries"][0]
    assert (left["level"], left["message"]) == ("ok", "ok")
    assert left["values"]["firmware"] == "sim-drive-1.0"
    assert left["values"]["firmware_known"] is True


@pytest.mark.usefixtures("virtual_time")
def test_diag_of_a_silent_servo_says_error_in_words() -> None:
    data = diag_json("--port", "sim://?silent=11")
    assert data["level"] == "error"
    ext1 = data["entries"][4]
    assert (ext1["name"], ext1["sid"], ext1["level"]) == ("ext1", 11, "error")
    assert ext1["message"].startswith("absent: ")
    result = invoke("diag", "--port", "sim://?silent=11")
    assert result.code == 0, result.out
    text = words(result.stdout)
    assert text.startswith("health: error")
    assert "ext1 11 error absent: it does not answer" in text


@pytest.mark.usefixtures("virtual_time")
def test_diag_with_the_stream_off_says_how_to_turn_it_on() -> None:
    result = invoke("diag", *SIM, env={"OHMNI_DIAGNOSTICS_HZ": "0"})
    assert result.code == 1, result.out
    assert "the diagnostics stream is off" in words(result.out)
    assert "ohmni stream enable diagnostics" in words(result.out)


@pytest.mark.usefixtures("virtual_time")
def test_diag_watch_prints_each_sample_and_ctrl_c_ends_it_with_0(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    real = diag_cli._next
    seen: list[DiagnosticsSample | None] = []

    async def three(samples: SampleStream[DiagnosticsSample]) -> DiagnosticsSample | None:
        if len(seen) == 3:
            raise KeyboardInterrupt
        seen.append(await real(samples))
        return seen[-1]

    monkeypatch.setattr(diag_cli, "_next", three)
    result = invoke("diag", *SIM, "--watch", "--json")
    assert result.code == 0, result.out
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert len(lines) == 4  # the first sample, then one a second
    assert all(line["level"] == "ok" for line in lines)
    stamps = [sample.stamp_s for sample in seen if sample is not None]
    assert [round(b - a, 3) for a, b in itertools.pairwise(stamps)] == [1.0, 1.0]


@pytest.mark.usefixtures("virtual_time")
def test_status_shows_the_health_table_and_its_json() -> None:
    result = invoke("status", *SIM)
    assert result.code == 0, result.out
    text = words(result.stdout)
    assert "health: ok" in text
    assert "ext2 12 ok DRS_0101" in text
    data = json.loads(invoke("status", *SIM, "--json").stdout)
    health = data["diagnostics"]
    assert health["level"] == "ok"
    assert [entry["name"] for entry in health["entries"]] == ENTRIES
    # The bus table lists the streams read on the bus: not the health.
    assert " diagnostics " not in f" {text} "


@pytest.mark.usefixtures("virtual_time")
def test_odom_set_sets_the_pose_given_negative_values_too() -> None:
    result = invoke("odom", "set", "1.5", "-0.5", "-1.25", *SIM, "--json")
    assert result.code == 0, result.out
    pose = json.loads(result.stdout)
    assert (pose["x_m"], pose["y_m"], pose["yaw_rad"]) == pytest.approx((1.5, -0.5, -1.25))
    result = invoke("odom", "set", "2", "0", "0.5", *SIM)
    assert result.code == 0, result.out
    assert "odometry set: x +2.000 m  y +0.000 m  yaw +0.5000 rad" in result.stdout


@pytest.mark.parametrize(
    ("args", "words_said"),
    [
        (("1", "2", "7"), "YAW=7.0 is out of range: allowed -6.2832..6.2832 rad"),
        (("1e5", "2", "0"), "X=100000.0 is out of range: allowed -10000..10000 m"),
        (("1", "2"), "Missing argument 'YAW'"),
        (("1", "nan", "0"), "Y=nan is out of range"),
    ],
)
def test_odom_set_refuses_a_bad_pose_before_opening_the_port(
    args: tuple[str, ...], words_said: str
) -> None:
    result = invoke("odom", "set", *args, "--port", "/dev/nonexistent-ohmni")
    assert result.code == 2, result.out
    assert words_said in words(result.out)
