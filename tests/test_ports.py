"""The ``auto`` port: the bus adapter found by its USB id, and the port every command opens."""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from serial.tools import list_ports as serial_ports

from ohmni_tb.cli.common import resolve_port as cli_port
from ohmni_tb.errors import TransportError
from ohmni_tb.transport import open_transport
from ohmni_tb.transport.ports import (
    ROBOT_BUS_LINK,
    NoBusPortError,
    find_bus_port,
    list_ports,
    resolve_port,
)


@dataclass
class FakePort:
    device: str
    description: str = "USB Serial"
    vid: int | None = None
    pid: int | None = None
    serial_number: str | None = None


def _system(monkeypatch: pytest.MonkeyPatch, *ports: FakePort, link: bool = False) -> None:
    monkeypatch.setattr(serial_ports, "comports", lambda: list(ports))
    real_exists = os.path.exists
    monkeypatch.setattr(
        os.path,
        "exists",
        lambda path: link if path == ROBOT_BUS_LINK else real_exists(path),
    )


def test_auto_finds_the_ftdi_adapter_by_its_usb_id(monkeypatch: pytest.MonkeyPatch) -> None:
    _system(
        monkeypatch,
        FakePort("/dev/ttyACM0", "Arduino", 0x2341, 0x0043),
        FakePort("/dev/ttyUSB1", "FT231X USB UART", 0x0403, 0x6015, "DN0ABC"),
        FakePort("/dev/ttyS0", "ttyS0"),
    )
    assert find_bus_port() == "/dev/ttyUSB1"
    assert resolve_port("auto") == "/dev/ttyUSB1"
    listed = list_ports()
    assert [p.device for p in listed] == ["/dev/ttyUSB1", "/dev/ttyACM0", "/dev/ttyS0"]
    assert [p.likely_bus for p in listed] == [True, False, False]
    assert listed[0].usb_id == "0403:6015"
    assert listed[2].usb_id == ""
    assert listed[0].as_dict()["serial_number"] == "DN0ABC"


def test_auto_falls_back_to_the_robots_own_node(monkeypatch: pytest.MonkeyPatch) -> None:
    _system(monkeypatch, FakePort("/dev/ttyS0", "ttyS0"), link=True)
    assert find_bus_port() == ROBOT_BUS_LINK
    assert list_ports()[0].device == ROBOT_BUS_LINK


def test_auto_without_an_adapter_says_what_to_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    _system(monkeypatch, FakePort("/dev/ttyS0", "ttyS0"))
    assert find_bus_port() is None
    with pytest.raises(NoBusPortError) as caught:
        resolve_port("auto")
    message = str(caught.value)
    assert "0403:6015" in message
    assert ROBOT_BUS_LINK in message
    assert "--port sim://" in message
    assert isinstance(caught.value, TransportError)


async def test_open_transport_auto_opens_what_it_finds(monkeypatch: pytest.MonkeyPatch) -> None:
    _system(monkeypatch)
    with pytest.raises(NoBusPortError):
        await open_transport("auto")


def test_other_ports_pass_through_unchanged() -> None:
    assert resolve_port("sim://") == "sim://"
    assert resolve_port("/dev/ttyUSB3") == "/dev/ttyUSB3"


def test_the_command_port_is_option_then_env_then_config_then_auto(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("OHMNI_PORT", raising=False)
    monkeypatch.delenv("OHMNI_CONFIG", raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert cli_port(None) == "auto"
    (tmp_path / "ohmni.toml").write_text('port = "/dev/ttyUSB7"\n')
    assert cli_port(None) == "/dev/ttyUSB7"
    monkeypatch.setenv("OHMNI_PORT", "sim://?neck=worm")
    assert cli_port(None) == "sim://?neck=worm"
    assert cli_port("/dev/ttyUSB2") == "/dev/ttyUSB2"


def test_a_command_without_an_adapter_is_one_line_suggesting_the_simulator() -> None:
    # A fresh process on this machine: no FTDI adapter is plugged in here.
    if find_bus_port() is not None:
        pytest.skip("a bus adapter is plugged into this machine")
    env = {"PATH": "/usr/bin:/bin", "HOME": "/nonexistent", "XDG_CONFIG_HOME": "/nonexistent"}
    done = subprocess.run(
        [sys.executable, "-m", "ohmni_tb", "bus", "send", "0", "STAT"],
        capture_output=True,
        text=True,
        env=env,
        cwd="/",
        timeout=60,
        check=False,
    )
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "no Ohmni bus adapter found" in lines[0]
    assert "--port sim://" in lines[0]


def test_help_imports_no_command_and_no_heavy_module() -> None:
    # `ohmni --help` must start fast (issue: <= 0.35 s here, the robot's Atom is ~3x
    # slower): it lists the commands from a table and imports none of them.
    probe = (
        "import sys\n"
        "from ohmni_tb.cli import app\n"
        "try:\n"
        "    app(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = [m for m in ('numpy', 'pydantic', 'ohmni_tb.robot', 'ohmni_tb.sim', "
        "'ohmni_tb.bus', 'serial', 'ohmni_tb.cli.status', 'ohmni_tb.cli.drive', "
        "'ohmni_tb.cli.servo') if m in sys.modules]\n"
        "print('HEAVY', heavy, file=sys.stderr)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=60, check=False
    )
    assert "HEAVY []" in done.stderr, done.stderr
    for command in ("status", "drive", "neck", "odom", "ports"):
        assert command in done.stdout


def test_robot_ports_lists_the_same_with_the_adapter_marked(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from ohmni_tb.robot import LocalRobot

    _system(monkeypatch, FakePort("/dev/ttyS0"), FakePort("/dev/ttyUSB0", "FT230X", 0x0403, 0x6015))
    listed = LocalRobot.ports()
    assert [(p["device"], p["likely_bus"], p["usb_id"]) for p in listed] == [
        ("/dev/ttyUSB0", True, "0403:6015"),
        ("/dev/ttyS0", False, ""),
    ]
