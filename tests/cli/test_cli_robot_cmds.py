"""``ohmni info``, ``ports``, ``light`` and ``pid`` against the simulator and temp files."""

from __future__ import annotations

import asyncio
import json
import os
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from ohmni_tb.cli import robot_cmds
from ohmni_tb.cli.common import open_robot
from ohmni_tb.config import RobotConfig
from ohmni_tb.control.pid import PidGains
from ohmni_tb.protocol.profile import DEFAULT_PROFILE
from ohmni_tb.transport import ports as port_list

from ._helpers import Opened, invoke, spy_on_ports, words

SIM = ["--port", "sim://"]
DEFAULT_GAINS = {"kp": 600.0, "ki": 300.0, "kd": 0.0, "kff": 940.0, "ff_offset": 60.0}


@pytest.fixture
def opened(monkeypatch: pytest.MonkeyPatch) -> Opened:
    return spy_on_ports(monkeypatch)


@pytest.fixture
def config_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """No config file, no OHMNI_* setting: a clean user config dir and working dir."""
    for key in list(os.environ):
        if key.upper().startswith("OHMNI_"):
            monkeypatch.delenv(key)
    home = tmp_path / "xdg"
    monkeypatch.setenv("XDG_CONFIG_HOME", str(home))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return home


# -- info -------------------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_info_json_names_every_device() -> None:
    result = invoke("info", *SIM, "--json")
    assert result.code == 0, result.out
    found = json.loads(result.stdout)
    settings = found.pop("neck_settings")
    # The bus profile the robot runs with: the assumed one.
    assert found.pop("profile") == DEFAULT_PROFILE.as_json()
    # The HerkuleX neck's own settings, as the servo read them back after the Robot
    # wrote them at open (the config's defaults).
    assert (settings["sid"], settings["memory"], settings["ok"]) == (3, "ram", True)
    assert settings["read_back"]["min_position"] == 280
    assert settings["read_back"]["max_position"] == 650
    assert settings["read_back"] == settings["wanted"]
    assert found == {
        "port": "sim://",
        "firmware": {
            "left_drive": "sim-drive-1.0",
            "right_drive": "sim-drive-1.0",
            "core": "sim-core-1.0",
            "worm_neck": None,
        },
        "neck_kind": "herkulex",
        "servos": [
            {"sid": 3, "role": "neck", "model": "DRS_0101"},
            {"sid": 11, "role": "ext1", "model": "DRS_0101"},
            {"sid": 12, "role": "ext2", "model": "DRS_0101"},
        ],
        "present": [0, 1, 3, 11, 12, 20],
        "absent": [],
    }


@pytest.mark.usefixtures("virtual_time")
def test_info_worm_neck_and_a_silent_servo() -> None:
    result = invoke("info", "--port", "sim://?neck=worm&silent=12", "--json")
    assert result.code == 0, result.out
    found = json.loads(result.stdout)
    assert found["neck_kind"] == "worm"
    assert found["firmware"]["worm_neck"] == "sim-worm-1.0"
    assert found["servos"] == [{"sid": 11, "role": "ext1", "model": "DRS_0101"}]
    assert found["absent"] == [12]
    assert found["neck_settings"] is None  # no HerkuleX neck


@pytest.mark.usefixtures("virtual_time")
def test_info_shows_the_neck_settings_the_config_asked_for(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_NECK_MIN_RAW", "300")
    monkeypatch.setenv("OHMNI_NECK_KP", "250")
    result = invoke("info", *SIM)
    assert result.code == 0, result.out
    assert "neck servo 3: settings in RAM as set: position 300..650, kp/ki/kd 250/0/8000" in (
        words(result.out)
    )


@pytest.mark.usefixtures("virtual_time")
def test_info_table() -> None:
    result = invoke("info", "--port", "sim://?neck=0201&silent=12")
    assert result.code == 0, result.out
    text = words(result.out)
    assert "3 neck HerkuleX DRS-0101/0201 neck servo DRS_0201" in text
    assert "12 ext2 external HerkuleX servo (assumed id) no answer" in text
    assert "20 core core board: battery, dock, light ring firmware sim-core-1.0" in text
    assert "neck: herkulex" in text
    assert "neck servo 3: settings in RAM as set: position 280..650, kp/ki/kd 440/0/8000" in text


# -- ports ------------------------------------------------------------------------------------


def fake_ports(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, *ports: dict[str, Any]) -> None:
    """pyserial lists ``ports``; the robot's own adapter node does not exist."""
    entries = [SimpleNamespace(**{"serial_number": None, **port}) for port in ports]
    monkeypatch.setattr("serial.tools.list_ports.comports", lambda: entries)
    monkeypatch.setattr(port_list, "ROBOT_BUS_LINK", str(tmp_path / "no-such-node"))


FTDI = {"device": "/dev/ttyUSB1", "description": "FT230X Basic UART", "vid": 0x0403, "pid": 0x6015}
OTHER = {"device": "/dev/ttyACM0", "description": "Arduino Uno", "vid": 0x2341, "pid": 0x0043}


@pytest.mark.usefixtures("virtual_time")
def test_ports_marks_the_bus_adapter(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, opened: Opened
) -> None:
    fake_ports(monkeypatch, tmp_path, OTHER, {**FTDI, "serial_number": "DK0AB12"})
    result = invoke("ports")
    assert result.code == 0, result.out
    text = words(result.out)
    assert "/dev/ttyUSB1 0403:6015 FT230X Basic UART DK0AB12 ← likely the bus" in text
    assert "/dev/ttyACM0 2341:0043 Arduino Uno" in text
    assert text.index("ttyUSB1") < text.index("ttyACM0")  # the bus first
    result = invoke("ports", "--json")
    assert result.code == 0, result.out
    listed = json.loads(result.stdout)
    assert [(p["device"], p["usb_id"], p["likely_bus"]) for p in listed] == [
        ("/dev/ttyUSB1", "0403:6015", True),
        ("/dev/ttyACM0", "2341:0043", False),
    ]
    assert opened.urls == []  # listing opens no port


@pytest.mark.usefixtures("virtual_time")
def test_ports_says_when_none_is_the_bus(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    fake_ports(monkeypatch, tmp_path, OTHER)
    result = invoke("ports")
    assert result.code == 0
    assert "none looks like the Ohmni bus adapter (USB 0403:6015)" in words(result.out)


def test_ports_says_when_there_are_none(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, opened: Opened
) -> None:
    fake_ports(monkeypatch, tmp_path)
    result = invoke("ports")
    assert result.code == 0
    assert "no serial ports found" in result.out
    assert "0403:6015" in result.out
    result = invoke("ports", "--json")
    assert result.code == 0
    assert json.loads(result.stdout) == []
    assert opened.urls == []


# -- light ------------------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_light_sets_the_simulated_ring(opened: Opened) -> None:
    result = invoke("light", "120", "255", "0x80", *SIM)
    assert result.code == 0, result.out
    assert "light ring ← hue 120, saturation 255, value 128" in result.out
    assert bytes(opened.sims[0].core.light_ring) == bytes((120, 255, 128))
    result = invoke("light", "0", "0", "0", *SIM, "--json")
    assert result.code == 0, result.out
    assert json.loads(result.stdout) == {"port": "sim://", "hue": 0, "saturation": 0, "value": 0}
    assert bytes(opened.sims[1].core.light_ring) == b"\x00\x00\x00"


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (("256", "0", "0"), "HUE=256 is out of range: allowed 0..255"),
        (("0", "-1", "0"), "SATURATION=-1 is out of range: allowed 0..255"),
        (("0", "0", "1000"), "VALUE=1000 is out of range: allowed 0..255"),
        (("0", "0", "nan"), "VALUE must be an integer (decimal or 0x..), not 'nan'"),
        (("1.5", "0", "0"), "HUE must be an integer"),
        (("٣", "0", "0"), "HUE must be an integer"),
    ],
)
def test_light_refuses_bad_values_before_opening(
    args: tuple[str, str, str], named: str, opened: Opened
) -> None:
    result = invoke("light", *SIM, "--", *args)
    assert result.code == 2, result.out
    assert named in words(result.out)
    assert opened.urls == []  # nothing opened, so nothing sent


@pytest.mark.usefixtures("virtual_time")
def test_light_without_the_core_board_is_an_error() -> None:
    result = invoke("light", "1", "2", "3", "--port", "sim://?silent=20")
    assert result.code == 1
    assert result.out.strip() == (
        "error: the core board (sid 20) does not answer: the light ring was not set"
    )


# -- pid --------------------------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_pid_get_defaults(config_home: Path, opened: Opened) -> None:
    result = invoke("pid", "get", "--config", "--json")
    assert result.code == 0, result.out
    assert json.loads(result.stdout) == {
        "file": None,
        "gains": DEFAULT_GAINS,
        "sources": dict.fromkeys(DEFAULT_GAINS, "default"),
    }
    result = invoke("pid", "get", "--config")
    assert result.code == 0, result.out
    text = words(result.out)
    assert "--kp kp 600 default" in text
    assert "--ff-offset ff_offset 60 default" in text
    assert "config file: none" in text
    assert opened.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_pid_set_writes_the_user_config_and_later_robots_use_it(
    config_home: Path, opened: Opened
) -> None:
    result = invoke("pid", "set", "--config", "--kp", "650", "--ki", "250.5", "--kd", "1e-3")
    assert result.code == 0, result.out
    written = config_home / "ohmni" / "ohmni.toml"
    text = words(result.out)
    assert f"created {written}:" in text
    assert "pid_kp = 650.0 (not set before)" in text
    assert "note" not in text  # the commands read this file
    assert tomllib.loads(written.read_text()) == {
        "pid_kp": 650.0,
        "pid_ki": 250.5,
        "pid_kd": 0.001,
    }
    assert opened.urls == []  # no port opened
    got = json.loads(invoke("pid", "get", "--config", "--json").stdout)
    assert got["gains"] == {**DEFAULT_GAINS, "kp": 650.0, "ki": 250.5, "kd": 0.001}
    assert got["sources"]["kp"] == str(written)
    assert got["sources"]["kff"] == "default"

    # A Robot opened later (any command) runs these gains.
    async def gains() -> PidGains:
        async with open_robot("sim://") as robot:
            return robot.get_pid()

    assert asyncio.run(gains()) == PidGains(kp=650.0, ki=250.5, kd=0.001, kff=940.0, ff_offset=60)
    # A second set changes only what it names, and says what was there.
    result = invoke("pid", "set", "--config", "--kp", "700", "--json")
    assert result.code == 0, result.out
    report = json.loads(result.stdout)
    assert report == {
        "file": str(written),
        "created": False,
        "written": {"pid_kp": 700.0},
        "previous": {"pid_kp": 650.0},
        "read_by_commands": True,
        "overridden_by": {},
    }
    assert tomllib.loads(written.read_text())["pid_ki"] == 250.5


@pytest.mark.usefixtures("virtual_time")
def test_pid_set_keeps_the_rest_of_the_file(config_home: Path, tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    before = (
        "# my robot\n"
        'port = "sim://"   # the simulator\n'
        "pid_kp = 600  # tuned on the carpet\n"
        "ext_servo_ids = [\n"
        "  11,\n"
        "  12,\n"
        "]\n"
        "\n"
        "[notes]\n"
        'text = "pid_ki = 1"\n'
    )
    path.write_text(before)
    result = invoke("pid", "set", "--kp", "620", "--kff", "900", "--file", str(path))
    assert result.code == 0, result.out
    after = path.read_text()
    assert after == (
        "# my robot\n"
        'port = "sim://"   # the simulator\n'
        "pid_kp = 620.0  # tuned on the carpet\n"
        "ext_servo_ids = [\n"
        "  11,\n"
        "  12,\n"
        "]\n"
        "pid_kff = 900.0\n"
        "\n"
        "[notes]\n"
        'text = "pid_ki = 1"\n'
    )
    # Not the file the commands read: the output says how to use it.
    assert "set OHMNI_CONFIG=" in words(result.out)


@pytest.mark.usefixtures("virtual_time")
def test_pid_set_in_a_robot_table(config_home: Path, tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text('[robot]\nport = "sim://"\npid_ki = 100\n\n[other]\nx = 1\n')
    result = invoke("pid", "set", "--ki", "120", "--kd", "2", "--file", str(path))
    assert result.code == 0, result.out
    assert path.read_text() == (
        '[robot]\nport = "sim://"\npid_ki = 120.0\npid_kd = 2.0\n\n[other]\nx = 1\n'
    )


@pytest.mark.usefixtures("virtual_time")
def test_pid_set_keeps_windows_line_ends(config_home: Path, tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_bytes(b'port = "sim://"\r\npid_kp = 1\r\n')
    assert invoke("pid", "set", "--kp", "2", "--kd", "3", "--file", str(path)).code == 0
    assert path.read_bytes() == b'port = "sim://"\r\npid_kp = 2.0\r\npid_kd = 3.0\r\n'


@pytest.mark.parametrize(
    ("content", "why"),
    [
        ("robot.pid_kp = 5\n", "cannot set pid_kp safely"),
        ('notes = """\npid_kp = 5\n"""\n', "cannot set pid_kp safely"),
        ("pid_kp = = 1\n", "not valid TOML"),
        ("robot = 3\n", "robot must be a [robot] table"),
        ("PID_KP = 5\n", "PID_KP is written in another case"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_pid_set_refuses_what_it_cannot_edit_safely(
    content: str, why: str, config_home: Path, tmp_path: Path
) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text(content)
    result = invoke("pid", "set", "--kp", "650", "--file", str(path))
    assert result.code == 1, result.out
    assert why in result.out
    assert len(result.out.strip().splitlines()) == 1, result.out
    assert path.read_text() == content  # untouched


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (("--kp", "-1"), "--kp: pid_kp=-1.0 is out of range: allowed 0..10000 PWM/(m/s)"),
        (("--ki", "2e6"), "--ki: pid_ki=2000000.0 is out of range: allowed 0..10000 PWM/m"),
        (("--kd", "nan"), "--kd must be a finite number, not 'nan': allowed 0..1000 PWM/(m/s²)"),
        (("--kff", "inf"), "--kff must be a finite number, not 'inf'"),
        (("--ff-offset", "٣"), "--ff-offset must be a finite number, not '٣'"),
        (("--kp", "9" * 400), "--kp must be a finite number"),
        ((), "give at least one gain: --kp, --ki, --kd, --kff, --ff-offset"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_pid_set_refuses_bad_gains(
    args: tuple[str, ...], named: str, config_home: Path, opened: Opened
) -> None:
    result = invoke("pid", "set", "--config", *args)
    assert result.code == 2, result.out
    assert named in words(result.out)
    assert not (config_home / "ohmni" / "ohmni.toml").exists()
    assert opened.urls == []


@pytest.mark.usefixtures("virtual_time")
def test_pid_set_says_when_the_environment_wins(
    config_home: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("OHMNI_PID_KP", "700")
    result = invoke("pid", "set", "--config", "--kp", "650")
    assert result.code == 0, result.out
    assert "$OHMNI_PID_KP is set and overrides pid_kp from the file" in words(result.out)
    got = json.loads(invoke("pid", "get", "--config", "--json").stdout)
    assert got["gains"]["kp"] == 700.0
    assert got["sources"]["kp"] == "$OHMNI_PID_KP"


@pytest.mark.usefixtures("virtual_time")
def test_pid_set_writes_the_file_the_commands_read(
    config_home: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # ./ohmni.toml comes before the user's file: that is the one to change.
    local = Path("ohmni.toml")
    local.write_text('port = "sim://"\n')
    assert invoke("pid", "set", "--config", "--kd", "5").code == 0
    assert tomllib.loads(local.read_text()) == {"port": "sim://", "pid_kd": 5.0}
    assert not (config_home / "ohmni").exists()
    # $OHMNI_CONFIG comes first of all, even before it exists.
    named = tmp_path / "named.toml"
    monkeypatch.setenv("OHMNI_CONFIG", str(named))
    assert invoke("pid", "set", "--config", "--kd", "6").code == 0
    assert tomllib.loads(named.read_text()) == {"pid_kd": 6.0}
    assert json.loads(invoke("pid", "get", "--config", "--json").stdout)["gains"]["kd"] == 6.0


def test_pid_get_of_a_file(config_home: Path, tmp_path: Path) -> None:
    path = tmp_path / "x.toml"
    path.write_text("[robot]\npid_kff = 950\n")
    result = invoke("pid", "get", "--file", str(path), "--json")
    assert result.code == 0, result.out
    got = json.loads(result.stdout)
    assert got["gains"]["kff"] == 950.0
    assert got["sources"]["kff"] == str(path)
    result = invoke("pid", "get", "--file", str(tmp_path / "missing.toml"))
    assert result.code == 2
    assert "--file" in result.out
    assert "no such file" in result.out
    path.write_text("pid_kp = -4\n")
    result = invoke("pid", "get", "--file", str(path))
    assert result.code == 1
    assert result.out.startswith("error: pid_kp=-4 is out of range")


@pytest.mark.usefixtures("virtual_time")
def test_pid_get_and_set_act_on_the_running_robot_per_wheel(
    config_home: Path, opened: Opened
) -> None:
    got = json.loads(invoke("pid", "get", *SIM, "--json").stdout)
    assert got == {
        "port": "sim://",
        "wheels": {side: {**DEFAULT_GAINS, "enabled": True} for side in ("left", "right")},
    }
    result = invoke("pid", "set", "--kp", "700", "--wheel", "left", *SIM, "--json")
    assert result.code == 0, result.out
    report = json.loads(result.stdout)
    assert report["set"] == {"kp": 700.0}
    assert report["wheels"] == {"left": {**DEFAULT_GAINS, "kp": 700.0, "enabled": True}}
    assert opened.urls == ["sim://", "sim://"]
    assert not (config_home / "ohmni" / "ohmni.toml").exists()  # the robot's, not the file
    result = invoke("pid", "set", "--kp", "700", "--wheel", "middle", *SIM)
    assert result.code == 2
    assert "--wheel must be left or right, not 'middle'" in words(result.out)
    result = invoke("pid", "set", "--kp", "700", "--wheel", "left", "--config")
    assert result.code == 2
    assert "--wheel is for the running robot" in words(result.out)


@pytest.mark.usefixtures("virtual_time")
def test_pid_disable_shows_the_wheel_off_and_stream_disable_drops_it_from_the_schedule() -> None:
    result = invoke("pid", "disable", "--wheel", "right", *SIM, "--json")
    assert result.code == 0, result.out
    wheels = json.loads(result.stdout)["wheels"]
    assert (wheels["left"]["enabled"], wheels["right"]["enabled"]) == (True, False)
    result = invoke("pid", "disable", *SIM)
    assert result.code == 0, result.out
    assert "enabled off off" in words(result.out)
    assert "the change ended with it" in words(result.out)
    result = invoke("stream", "disable", "tbcore_status", *SIM, "--json")
    assert result.code == 0, result.out
    report = json.loads(result.stdout)
    assert report["enabled"] is False
    assert "tbcore_status" not in report["scheduled"]
    assert "servo_neck" in report["scheduled"]
    result = invoke("stream", "enable", "odom", *SIM)
    assert result.code == 2
    assert "no stream 'odom': the streams are wheel_encoder" in words(result.out)


@pytest.mark.usefixtures("virtual_time")
def test_drive_pwm_and_wheels_move_the_robot_for_the_duration() -> None:
    result = invoke("drive", "--pwm", "250", "250.4", "--duration", "0.5", *SIM, "--json")
    assert result.code == 0, result.out
    drove = json.loads(result.stdout)
    assert drove["mode"] == "pwm"
    assert drove["command"] == {"left_pwm": 250.0, "right_pwm": 250.4, "duration_s": 0.5}
    assert drove["distance_m"] > 0.03
    assert drove["stop"]["confirmed"]
    result = invoke("drive", "--wheels", "0.2", "0.1", "--duration", "1", *SIM, "--json")
    assert result.code == 0, result.out
    drove = json.loads(result.stdout)
    assert drove["mode"] == "wheels"
    assert drove["heading_change_deg"] < -5  # the left wheel faster: a right turn
    for args, named in (
        (("--pwm", "1001", "0"), "--pwm L=1001 is out of range: allowed -1000..1000 PWM"),
        (("--pwm", "0", "nan"), "--pwm R=nan is not a finite number"),
        (("--wheels", "5", "0"), "--wheels L=5 is out of range"),
        (("--pwm", "1", "1", "--linear", "0.2"), "--pwm does not combine with --linear"),
        (("--pwm", "0", "0"), "--pwm 0 0 drives nowhere"),
    ):
        result = invoke("drive", *args, *SIM)
        assert result.code == 2, (args, result.out)
        assert named in words(result.out), args


@pytest.mark.usefixtures("virtual_time")
def test_gain_help_matches_the_config() -> None:
    for flag, field in robot_cmds.PID_FIELDS.items():
        extra = RobotConfig.model_fields[field].json_schema_extra
        assert isinstance(extra, dict)
        assert robot_cmds.GAINS[flag][1] == extra["allowed"], flag


# -- every command ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "command",
    [
        ("info",),
        ("ports",),
        ("light",),
        ("pid", "get"),
        ("pid", "set"),
        ("pid", "enable"),
        ("pid", "disable"),
        ("stream", "enable"),
        ("stream", "disable"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_help_has_an_example(command: tuple[str, ...]) -> None:
    result = invoke(*command, "--help")
    assert result.code == 0, result.out
    assert f"Example: ohmni {' '.join(command)}" in result.out


@pytest.mark.usefixtures("virtual_time")
def test_a_bad_port_is_one_error_line() -> None:
    for command in (("info",), ("light", "1", "2", "3")):
        result = invoke(*command, "--port", "/dev/no-such-ohmni-port")
        assert result.code == 1, result.out
        lines = [line for line in result.out.splitlines() if line.strip()]
        assert len(lines) == 1, result.out
        assert lines[0].startswith("error: ")
