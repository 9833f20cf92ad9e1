"""``ohmni probe``: on every simulated profile it reports what the boards speak, moves the
wheels only with ``--allow-motion`` (each stop confirmed), and ``--write`` makes the other
commands work on that robot.

The simulator runs on virtual time (the ``virtual_time`` fixture): a full scan of 254 ids
takes its 7 s of bus timeouts in a fraction of a second.
"""

from __future__ import annotations

import json
import math
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from cli._helpers import Result, invoke, words
from ohmni_tb.cli import common
from ohmni_tb.config import RobotConfig
from ohmni_tb.config_file import read_settings
from ohmni_tb.protocol import Command, Packet, PacketDecoder
from ohmni_tb.protocol.drive import DriveProfile, WheelJogForm, decode_wheel_command
from ohmni_tb.protocol.profile import BusProfile
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import Transport, open_transport

pytestmark = pytest.mark.usefixtures("virtual_time")

_JOGS = (Command.S_JOG, Command.I_JOG)


@dataclass
class Watched:
    """What the probe's port carried, and the simulated robot as it was when it closed."""

    sims: list[SimRobot] = field(default_factory=list)
    packets: list[Packet] = field(default_factory=list)
    closing_speeds: list[tuple[float, float]] = field(default_factory=list)
    closing_poses: list[tuple[float, float, float]] = field(default_factory=list)

    def wheel_commands(self) -> list[Packet]:
        return [p for p in self.packets if p.cmd in _JOGS]


@pytest.fixture
def watched(monkeypatch: pytest.MonkeyPatch) -> Watched:
    return watch(monkeypatch)


def watch(
    monkeypatch: pytest.MonkeyPatch, on_packet: Callable[[SimLine, Packet], None] | None = None
) -> Watched:
    """Record every packet the host writes on the simulated line the command opens (on the
    line itself: what reaches the boards), and the robot's truth when the port closes."""
    seen = Watched()

    async def spy(url: str) -> Transport:
        transport = await open_transport(url)
        assert isinstance(transport, SimTransport)
        assert transport.robot is not None
        sim = transport.robot
        seen.sims.append(sim)
        line = transport.line
        write = line.host_write
        decoder = PacketDecoder()

        def record(data: bytes) -> None:
            for packet in decoder.feed(bytes(data)):
                seen.packets.append(packet)
                if on_packet is not None:
                    on_packet(line, packet)
            write(data)

        setattr(line, "host_write", record)  # noqa: B010 - mypy forbids assigning a method
        close = transport.aclose

        async def aclose() -> None:
            seen.closing_speeds.append(sim.wheel_speeds_mps())
            pose = sim.pose
            seen.closing_poses.append((pose.x, pose.y, pose.yaw))
            await close()

        setattr(transport, "aclose", aclose)  # noqa: B010 - as above
        return transport

    monkeypatch.setattr(common, "open_transport", spy)
    return seen


def probe(*args: str, env: dict[str, str] | None = None) -> Result:
    return invoke("probe", *args, env=env)


def probe_json(url: str, *args: str) -> dict[str, Any]:
    done = probe("--port", url, "--json", *args)
    assert done.code == 0, done.out
    data: dict[str, Any] = json.loads(done.stdout)
    return data


def statuses(data: dict[str, Any]) -> dict[str, str]:
    return {f["name"]: f["status"] for f in data["findings"]}


# -- each simulated profile is reported exactly -----------------------------------------------

VARIANTS = [
    ("wheel_form=i_jog", {"wheel_form": "i_jog"}),
    ("battery_addr=0xB0", {"battery_addr": 0xB0}),
    ("ext_servos=13,14", {"ext_servo_ids": [13, 14]}),
    (
        "wheel_form=i_jog&battery_addr=0xB0&ext_servos=13,14",
        {"wheel_form": "i_jog", "battery_addr": 0xB0, "ext_servo_ids": [13, 14]},
    ),
    ("battery_layout=cells&battery_length=10", {"battery_layout": "cells", "battery_length": 10}),
    (
        "battery_addr=0x30&battery_layout=cells&battery_length=10&wheel_form=i_jog&ext_servos=15",
        {
            "battery_addr": 0x30,
            "battery_layout": "cells",
            "battery_length": 10,
            "wheel_form": "i_jog",
            "ext_servo_ids": [15],
        },
    ),
    ("neck=worm", {}),
]


@pytest.mark.parametrize(("options", "differs"), VARIANTS, ids=[v[0] for v in VARIANTS])
def test_each_simulated_profile_is_found_exactly(
    options: str, differs: dict[str, Any], watched: Watched
) -> None:
    data = probe_json(f"sim://?{options}", "--allow-motion")

    truth = BusProfile.from_settings(differs).settings()
    profile = data["profile"]
    for name in ("wheel_form", "battery_addr", "battery_length", "battery_layout"):
        assert profile[name] == truth[name], name
    assert profile["ext_servo_ids"] == list(truth["ext_servo_ids"])
    assert {name: value["found"] for name, value in data["differs"].items()} == differs
    assert set(data["measured"]) >= {
        "wheel_form",
        "drive_torque_addr",
        "battery_addr",
        "battery_length",
        "battery_layout",
        "ext_servo_ids",
    }
    found = statuses(data)
    for name, setting in (
        ("wheel_form", "wheel_form"),
        ("battery", "battery_addr"),
        ("ext_servos", "ext_servo_ids"),
    ):
        changed = setting in differs or (name == "battery" and "battery_layout" in differs)
        assert found[name] == ("differs" if changed else "confirmed"), name
    if "neck=worm" in options:
        assert found["worm_neck"] == "confirmed"
        assert 4 in [d["sid"] for d in data["devices"]]
    # What the simulated boards speak, read from the simulator itself.
    (sim,) = watched.sims
    speaks = {**sim.profile.settings(), "ext_servo_ids": tuple(s.sid for s in sim.ext_servos)}
    assert BusProfile.from_settings(data["profile"]).settings() == speaks


def test_the_default_simulator_confirms_every_finding_and_the_wheels_end_still(
    watched: Watched,
) -> None:
    data = probe_json("sim://", "--allow-motion")

    assert statuses(data) == {
        "devices": "confirmed",
        "battery": "confirmed",
        "drive_torque": "confirmed",
        "ext_servos": "confirmed",
        "wheel_form": "confirmed",
    }
    skipped = {s["name"]: s["why"] for s in data["skipped"]}
    assert skipped["usb_adapter"] == "not a USB serial adapter"
    assert data["adapter"]["usb"] is False
    assert data["differs"] == {}
    assert [d["sid"] for d in data["devices"]] == [0, 1, 3, 11, 12, 20]
    for device in data["devices"]:
        assert 0 < device["latency_ms"] < 5  # wire time and turnaround, no adapter latency
    assert data["scanned"] == "0..253"
    # Each wheel turned in the S_JOG tries, by more than the threshold, the right way.
    wheel = next(f for f in data["findings"] if f["name"] == "wheel_form")
    assert wheel["found"]["left_ticks"] > 100
    assert wheel["found"]["right_ticks"] > 100
    assert (
        wheel["found"]["left_sign"]
        == wheel["found"]["right_sign"]
        == ("+PWM gives +counts, as expected")
    )
    assert "right_mirrored cannot be measured by counts" in wheel["detail"]
    # Every stop was confirmed: the wheels stand still as the port closes, and the robot
    # moved little (each wheel a few millimetres).
    (speeds,) = watched.closing_speeds
    assert speeds == (0.0, 0.0)
    ((x, y, yaw),) = watched.closing_poses
    assert math.hypot(x, y) < 0.02
    assert abs(math.degrees(yaw)) < 5
    # The last packets written are the zero wheel command in both forms.
    last_two = watched.packets[-2:]
    assert {p.cmd for p in last_two} == set(_JOGS)
    for packet in last_two:
        form = WheelJogForm(packet.cmd)
        assert set(decode_wheel_command(packet, DriveProfile(wheel_form=form)).values()) == {0}


def test_without_allow_motion_no_wheel_command_is_sent(watched: Watched) -> None:
    data = probe_json("sim://?wheel_form=i_jog")

    assert watched.packets  # the scan went out
    assert watched.wheel_commands() == []
    (sim,) = watched.sims
    assert sim.pose.x == sim.pose.y == sim.pose.yaw == 0.0
    assert watched.closing_speeds == [(0.0, 0.0)]
    assert "wheel_form" not in statuses(data)
    assert {s["name"]: s["why"] for s in data["skipped"]}["wheel_form"] == (
        "the wheels turn to find it: pass --allow-motion"
    )
    assert "wheel_form" not in data["measured"]


def test_the_motion_warning_comes_first_on_stderr_for_json(watched: Watched) -> None:
    done = probe("--port", "sim://", "--json", "--allow-motion", "--ids", "0,1")
    assert done.code == 0, done.out
    assert done.out.startswith("ohmni probe --allow-motion: the wheels will turn")
    assert "on a stand" in done.out
    json.loads(done.stdout)  # stdout is the JSON alone


def test_the_table_has_a_row_per_finding_and_the_settings_that_differ() -> None:
    done = probe("--port", "sim://?battery_addr=0xB0", "--ids", "0..20")
    assert done.code == 0, done.out
    text = words(done.out)
    assert "battery differs 0xA0, 18 bytes, tbcore 0xB0, 18 bytes, tbcore" in text
    assert "drive_torque confirmed" in text
    assert "wheel_form skipped" in text
    assert "settings that differ (--write saves them): battery_addr = 0xB0 (assumed 0xA0)" in text


def test_a_stop_the_counts_do_not_confirm_ends_the_probe_with_exit_1(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def board_goes_quiet(line: SimLine, packet: Packet) -> None:
        # The right board stops answering once the wheels are first commanded: its count
        # cannot confirm the stop. It still acts on what it hears (the stops).
        if packet.cmd in _JOGS:
            form = DriveProfile(wheel_form=WheelJogForm(packet.cmd))
            if any(decode_wheel_command(packet, form).values()):
                line.faults.silent = {1}

    seen = watch(monkeypatch, board_goes_quiet)
    done = probe("--port", "sim://", "--allow-motion", "--ids", "0,1")

    assert done.code == 1
    assert "the wheels may still be moving" in done.out
    assert "probe aborted" in done.out
    # The stops went out in both forms, and the wheels stand still.
    assert {p.cmd for p in seen.packets[-2:]} == set(_JOGS)
    assert seen.closing_speeds == [(0.0, 0.0)]


# -- --write ---------------------------------------------------------------------------------

WRITTEN_VARIANT = "sim://?wheel_form=i_jog&battery_addr=0xB0&ext_servos=13,14"


def test_write_makes_status_and_drive_work_on_that_robot(tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    env = {"OHMNI_CONFIG": str(path)}
    # Before: the assumed profile reads no battery there and does not move the wheels.
    before = invoke("status", "--port", WRITTEN_VARIANT, "--json")
    assert before.code == 0, before.out
    assert max(json.loads(before.stdout)["battery"]["cell_v"]) == 0.0
    stuck = invoke("drive", "--distance", "0.3", "--port", WRITTEN_VARIANT, "--json")
    assert stuck.code == 1
    assert "did not turn" in stuck.out

    done = probe("--port", WRITTEN_VARIANT, "--allow-motion", "--write", env=env)
    assert done.code == 0, done.out
    text = words(done.out)
    assert f"created {path}:" in text
    assert "wheel_form: not set, s_jog → i_jog" in text
    assert "battery_addr: not set, 0xA0 → 0xB0" in text
    assert "ext_servo_ids: not set, [11, 12] → [13, 14]" in text
    assert "as before: drive_torque_addr, battery_length, battery_layout" in text
    assert "note:" not in text  # the file written is the one the commands read

    # The file holds the measured settings and nothing else, and loads as that profile.
    assert read_settings(path) == {
        "wheel_form": "i_jog",
        "drive_torque_addr": 52,
        "battery_addr": 0xB0,
        "battery_length": 18,
        "battery_layout": "tbcore",
        "ext_servo_ids": [13, 14],
    }
    loaded = RobotConfig.load(path)
    assert loaded.profile() == BusProfile.from_settings(
        {"wheel_form": "i_jog", "battery_addr": 0xB0, "ext_servo_ids": [13, 14]}
    )
    assert (
        loaded.model_dump()
        == RobotConfig()
        .replace(wheel_form="i_jog", battery_addr=0xB0, ext_servo_ids=(13, 14))
        .model_dump()
    )

    status = invoke("status", "--port", WRITTEN_VARIANT, "--json", env=env)
    assert status.code == 0, status.out
    data = json.loads(status.stdout)
    assert all(3.0 < v < 3.5 for v in data["battery"]["cell_v"])
    assert [data["servos"][role]["sid"] for role in ("ext1", "ext2")] == [13, 14]
    drive = invoke("drive", "--distance", "0.3", "--port", WRITTEN_VARIANT, "--json", env=env)
    assert drive.code == 0, drive.out
    assert json.loads(drive.stdout)["distance_m"] == pytest.approx(0.3, abs=0.01)


def test_write_goes_to_the_config_file_named_and_keeps_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text('# my robot\nport = "sim://"  # the simulator\nbattery_addr = 0xA0\n')
    other = tmp_path / "ohmni.toml"
    other.write_text("")
    done = probe(
        "--port", "sim://?battery_addr=0xB0", "--ids", "0..20", "--write", "--config", str(path),
        "--json", env={"OHMNI_CONFIG": str(other)},
    )  # fmt: skip
    assert done.code == 0, done.out
    written = json.loads(done.stdout)["written"]
    assert written["file"] == str(path)
    assert written["created"] is False
    assert written["read_by_commands"] is False  # they read $OHMNI_CONFIG's
    assert written["settings"]["battery_addr"] == {"old": 0xA0, "assumed": 0xA0, "new": 0xB0}
    text = path.read_text()
    assert text.startswith('# my robot\nport = "sim://"  # the simulator\nbattery_addr = 176\n')
    # Only what the probe measured: no wheel form without --allow-motion.
    assert "wheel_form" not in read_settings(path)
    assert RobotConfig.load(path).battery_addr == 0xB0


# -- --share ---------------------------------------------------------------------------------


def test_share_writes_the_report_with_the_environment(tmp_path: Path) -> None:
    path = tmp_path / "report.json"
    done = probe("--port", "sim://", "--ids", "0..20", "--json", "--share", str(path))
    assert done.code == 0, done.out
    printed = json.loads(done.stdout)
    shared = json.loads(path.read_text())
    environment = shared.pop("environment")
    assert set(environment) >= {"ohmni_tb", "python", "os"}
    assert shared == printed
    assert shared["port"] == "sim://"


# -- arguments, the daemon -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (("--ids", "0..300"), "--ids=300 is out of range: allowed 0..253"),
        (("--ids", "20..3"), "the range 20..3 runs backwards"),
        (("--ids", "x"), "--ids must be an integer"),
        (("--pwm", "1000"), "--pwm=1000 is out of range: allowed 20..300"),
        (("--share-serials",), "--share-serials goes with --share FILE"),
    ],
)
def test_a_bad_argument_is_exit_2_and_opens_nothing(
    args: tuple[str, ...], named: str, watched: Watched
) -> None:
    done = probe("--port", "sim://", *args)
    assert done.code == 2
    assert named in words(done.out)
    assert watched.sims == []


def test_ids_narrow_the_scan(watched: Watched) -> None:
    data = probe_json("sim://", "--ids", "0..1,20,0x14")
    assert data["scanned"] == "0..1,20"
    assert [d["sid"] for d in data["devices"]] == [0, 1, 20]
    assert {s["name"] for s in data["skipped"]} >= {"ext_servos", "worm_neck"}
    stats = {p.sid for p in watched.packets if p.cmd == Command.STAT}
    assert stats == {0, 1, 20}


@pytest.fixture
def listening_daemon(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        monkeypatch.setenv("OHMNI_DAEMON_URL", f"ws://127.0.0.1:{port}")
        yield


@pytest.mark.usefixtures("listening_daemon")
def test_while_the_daemon_holds_the_port_it_says_so(watched: Watched) -> None:
    done = probe()
    assert done.code == 1
    assert "ohmni serve holds the port" in done.out
    assert watched.sims == []


# -- what the boards may differ in beyond the profile's settings ----------------------------


def test_a_torque_register_elsewhere_is_not_found() -> None:
    data = probe_json("sim://?drive_torque_addr=0x60", "--ids", "0..1")
    torque = next(f for f in data["findings"] if f["name"] == "drive_torque")
    assert torque["status"] == "not found"
    assert "flagged RAM 52 as outside its registers" in torque["detail"]
    assert "drive_torque_addr" not in data["measured"]


def test_worm_registers_elsewhere_are_not_found() -> None:
    data = probe_json("sim://?neck=worm&worm_feedback_addr=0x80", "--ids", "4")
    worm = next(f for f in data["findings"] if f["name"] == "worm_neck")
    assert worm["status"] == "not found"
    assert "RAM 0x74 is outside its registers" in worm["detail"]
    assert worm["found"]["target"] == 0
