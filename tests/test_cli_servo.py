"""Every ``ohmni servo`` command against the simulator, and the demo."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app, common
from ohmni_tb.cli import bus as bus_cli
from ohmni_tb.protocol import Command, PacketDecoder
from ohmni_tb.transport import Transport, open_transport

#: Every command here runs in this process on ``sim://``: on virtual time.
pytestmark = pytest.mark.usefixtures("virtual_time")

runner = CliRunner()
SIM = ["--port", "sim://"]


def invoke(*args: str) -> tuple[int, str]:
    result = runner.invoke(app, list(args))
    return result.exit_code, result.output


def words(text: str) -> str:
    """The output with rich's line wrapping and error box undone."""
    return " ".join(text.replace("│", " ").split())


@dataclass
class Wire:
    """What the commands opened and wrote, through every ``open_transport`` of the CLI."""

    opened: list[str] = field(default_factory=list)
    written: list[bytes] = field(default_factory=list)

    def packets(self) -> list[tuple[int, int, bytes]]:
        """(sid, cmd, data) of every packet written."""
        return [(p.sid, p.cmd, p.data) for p in PacketDecoder().feed(b"".join(self.written))]


def spy_on_cli(monkeypatch: pytest.MonkeyPatch) -> Wire:
    """Record every URL the CLI opens and every byte it writes (for the test's duration)."""
    spied = Wire()

    async def spy(url: str) -> Transport:
        transport = await open_transport(url)
        spied.opened.append(url)
        write = transport.write_nowait

        def record(data: bytes) -> None:
            spied.written.append(bytes(data))
            write(data)

        setattr(transport, "write_nowait", record)  # noqa: B010 - mypy forbids assigning a method
        return transport

    monkeypatch.setattr(common, "open_transport", spy)
    monkeypatch.setattr(bus_cli, "open_transport", spy)
    return spied


@pytest.fixture
def wire(monkeypatch: pytest.MonkeyPatch) -> Wire:
    return spy_on_cli(monkeypatch)


@pytest.mark.usefixtures("virtual_time")
def test_scan_finds_the_neck_and_the_external_servos() -> None:
    code, out = invoke("servo", "scan", *SIM, "--json")
    assert code == 0, out
    found = json.loads(out)
    assert [row["sid"] for row in found] == [3, 11, 12]
    assert found[0]["model"] == "DRS_0101"
    assert found[0]["position_raw"] == 512
    assert found[0]["angle_deg"] == 0.0


@pytest.mark.usefixtures("virtual_time")
def test_scan_table_names_the_models() -> None:
    code, out = invoke("servo", "scan", "--port", "sim://?neck=0201&ext=none", "--last", "20")
    assert code == 0, out
    assert "DRS_0201" in out
    assert "ext1" not in out


@pytest.mark.usefixtures("virtual_time")
def test_info_has_both_memories() -> None:
    code, out = invoke("servo", "info", *SIM, "--sid", "3", "--json")
    assert code == 0, out
    info = json.loads(out)
    assert info["eep"]["id"] == 3
    assert info["ram"]["torque_control"] == 0


@pytest.mark.usefixtures("virtual_time")
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


@pytest.mark.usefixtures("virtual_time")
def test_write_checks_the_range_before_sending() -> None:
    code, out = invoke("servo", "write", "led_control", "1", *SIM)
    assert code == 0, out
    assert "led_control ← 1" in out
    # A value or register the servo would refuse is a bad argument: exit 2, nothing sent.
    code, out = invoke("servo", "write", "acceleration_ratio", "60", *SIM)
    assert code == 2
    assert "VALUE=60 is out of range for acceleration_ratio: allowed 0..50" in words(out)
    code, out = invoke("servo", "write", "temperature", "10", *SIM)
    assert code == 2
    assert "read-only" in out


@pytest.mark.usefixtures("virtual_time")
def test_write_takes_an_address_and_eep_alone(wire: Wire) -> None:
    # tb_control's servo_write_eep: EEP 30 (position_kp) by its address.
    code, out = invoke("servo", "write", "30", "200", "--eep", *SIM)
    assert code == 0, out
    assert "EEP 30 position_kp ← 200 (acts after a reboot); reads back 200" in words(out)
    writes = [data for _, cmd, data in wire.packets() if cmd == Command.EEP_WRITE]
    assert writes == [bytes((30, 2, 200, 0))]
    assert not [data for _, cmd, data in wire.packets() if cmd == Command.RAM_WRITE]
    # A RAM address: RAM 0x35 is led_control.
    code, out = invoke("servo", "write", "0x35", "1", *SIM)
    assert code == 0, out
    assert "RAM 53 led_control ← 1; reads back 1" in words(out)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["31", "1", "--eep"], "no EEP register starts at address 31 (it is byte 2 of position_kp"),
        (["99", "1"], "no RAM register starts at address 99 (the RAM addresses are 0..73)"),
        (["0", "1", "--eep"], "EEP 0 (model_no1) is read-only"),
        (["30", "40000", "--eep"], "VALUE=40000 is out of range for position_kp: allowed 0..32767"),
        (["30", "1", "--eep", "--persist"], "give one of them"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_a_bad_write_by_address_exits_2_with_nothing_sent(
    wire: Wire, args: list[str], message: str
) -> None:
    code, out = invoke("servo", "write", *args, *SIM)
    assert code == 2, out
    assert message in words(out)
    assert wire.opened == []


@pytest.mark.usefixtures("virtual_time")
def test_move_needs_torque_and_respects_the_range() -> None:
    code, out = invoke("servo", "move", "400", *SIM)
    assert code == 1
    assert "torque off" in out
    code, out = invoke("servo", "move", "400", *SIM, "--torque-on", "--playtime", "0.5")
    assert code == 0, out
    assert "→ 400" in out
    # The neck (sid 3, the default) is held in its safe range 280..650 unless told otherwise.
    code, out = invoke("servo", "move", "700", *SIM, "--torque-on")
    assert code == 2
    assert (
        "POSITION=700 is out of range for servo 3 (--min-raw/--max-raw): allowed 280..650"
        in words(out)
    )
    code, out = invoke("servo", "move", "250", *SIM, "--torque-on", "--min-raw", "200")
    assert code == 0, out
    # Other servos get the factory range, or the one given.
    code, out = invoke("servo", "move", "1010", *SIM, "--sid", "11", "--torque-on")
    assert code == 2
    assert "21..1002" in out
    code, out = invoke("servo", "move", "900", *SIM, "--sid", "11", "--max-raw", "800")
    assert code == 2
    assert "21..800" in out
    code, out = invoke("servo", "move", "400", *SIM, "--playtime", "9")
    assert code == 2
    assert "--playtime=9.0 is out of range: allowed 0..2.8448 s" in words(out)


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize("mode", ["free", "brake", "on"])
def test_torque_modes(mode: str) -> None:
    code, out = invoke("servo", "torque", mode, *SIM)
    assert code == 0, out
    assert f"torque {mode}" in out


@pytest.mark.usefixtures("virtual_time")
def test_torque_bad_mode() -> None:
    code, out = invoke("servo", "torque", "loose", *SIM)
    assert code == 2
    assert "loose" in out


@pytest.mark.usefixtures("virtual_time")
def test_stat_and_clear() -> None:
    code, out = invoke("servo", "stat", *SIM, "--json")
    assert code == 0, out
    status = json.loads(out)
    assert status["error"] == 0
    assert status["torque_on"] is False
    code, out = invoke("servo", "clear", *SIM, "--torque-on", "--json")
    assert code == 0, out
    assert json.loads(out)["torque_on"] is True


@pytest.mark.usefixtures("virtual_time")
def test_missing_servo_is_an_error_line_not_a_traceback() -> None:
    code, out = invoke("servo", "stat", *SIM, "--sid", "40", "--timeout", "0.005")
    assert code == 1
    assert "no reply from sid 40" in out
    assert "Traceback" not in out


@pytest.mark.usefixtures("virtual_time")
def test_bad_sid_names_the_value() -> None:
    code, out = invoke("servo", "stat", *SIM, "--sid", "neck")
    assert code == 2
    assert "neck" in out


@pytest.mark.usefixtures("virtual_time")
def test_demo_runs_on_the_simulator() -> None:
    code, out = invoke("demo")
    assert code == 0, out
    text = words(out)
    assert "firmware 'sim-drive-1.0'" in out
    assert "DRS_0101 at 512" in out  # the neck, from the servo_neck stream
    assert "battery (tbcore_status): cells 3.294" in text
    assert "drive: forward at 0.30 m/s for 1.0 s" in text
    assert re.search(r"stop confirmed \d\.\d{3} s after the stop by both wheel counts", text)
    truth = re.search(r"simulator ground truth: x=(\d\.\d{3}) m", text)
    assert truth is not None
    assert 0.2 < float(truth.group(1)) < 0.35  # 1 s at 0.3 m/s, with the ramps
    assert "wheels 0.000 m/s, 0.000 m/s" in text
    odometry_error = re.search(r"odometry is (\d+\.\d) mm from the truth", text)
    assert odometry_error is not None
    assert float(odometry_error.group(1)) < 5.0
    assert "0.0s:280" in out
    assert ":650" in out
    assert "streams (robot.stats())" in out
    stats = re.search(r"wheel_encoder │\s+50 │\s+(\d+\.\d)", out)
    assert stats is not None
    assert float(stats.group(1)) > 40  # the control tick ran near its 50 Hz
    assert "bus: the wire carried bytes" in text


@pytest.mark.usefixtures("virtual_time")
def test_version() -> None:
    code, out = invoke("version")
    assert code == 0
    assert out.strip().count(".") == 2


@pytest.mark.usefixtures("virtual_time")
def test_demo_moves_a_worm_neck_when_the_robot_has_one() -> None:
    code, out = invoke("demo", "--port", "sim://?neck=worm")
    assert code == 0, out
    assert "firmware 'sim-worm-1.0'" in out
    assert "worm neck: 0 → 60000 (new_neck samples)" in out
    assert re.search(r"\d\.\d\ds:60000\n", out)  # it got there


# -- hardening: every argument checked before the first byte, one line per error -----------


@pytest.mark.usefixtures("virtual_time")
def test_move_checks_every_argument_before_the_torque_goes_on(wire: Wire) -> None:
    code, out = invoke("servo", "move", "400", *SIM, "--torque-on", "--playtime", "5")
    assert code == 2
    assert "--playtime=5.0 is out of range" in words(out)
    assert wire.written == []  # the torque write used to go out before the refusal


@pytest.mark.usefixtures("virtual_time")
def test_a_valid_move_writes_what_the_spy_sees(wire: Wire) -> None:
    # The spy itself works: a good move puts the torque write and the jog on the wire.
    code, out = invoke("servo", "move", "400", *SIM, "--torque-on", "--playtime", "2.84")
    assert code == 0, out
    cmds = [cmd for _, cmd, _ in wire.packets()]
    assert Command.RAM_WRITE in cmds
    (jog,) = [data for _, cmd, data in wire.packets() if cmd == Command.S_JOG]
    # 2.84 s is sent as 254 ticks of 11.2 ms = 2.8448 s, and that is what is printed.
    assert jog[0] == 254
    assert "over 2.8448 s (254 ticks)" in out
    assert "2.84 " not in out


@pytest.mark.parametrize(
    "playtime", ["1e308", "-1e308", "inf", "nan", "-0.001", "2.86", "2.85", "2.8449"]
)
@pytest.mark.usefixtures("virtual_time")
def test_playtimes_that_cannot_be_sent_are_bad_arguments(wire: Wire, playtime: str) -> None:
    code, out = invoke("servo", "move", "400", *SIM, "--torque-on", f"--playtime={playtime}")
    assert code == 2, out
    assert "Traceback" not in out
    assert "--playtime" in out
    assert "allowed 0..2.8448 s" in words(out)
    assert wire.opened == []


@pytest.mark.usefixtures("virtual_time")
def test_a_zero_playtime_is_sent_as_zero(wire: Wire) -> None:
    code, out = invoke("servo", "move", "400", *SIM, "--torque-on", "--playtime=-0.0")
    assert code == 0, out
    assert "over 0 s (0 ticks)" in out


@pytest.mark.usefixtures("virtual_time")
def test_an_unparsable_port_url_is_one_error_line() -> None:
    result = runner.invoke(app, ["servo", "stat", "--port", "http://[::1"])
    assert result.exit_code == 1
    assert result.exception is None or isinstance(result.exception, SystemExit)
    (line,) = result.output.strip().splitlines()
    assert line.startswith("error: cannot parse the URL 'http://[::1'")


@pytest.mark.usefixtures("virtual_time")
def test_an_error_text_with_brackets_is_printed_not_parsed_as_markup() -> None:
    # The unknown option's name looks like a closing markup tag.
    result = runner.invoke(app, ["servo", "stat", "--port", "sim://?[/x]=1"])
    assert result.exit_code == 1, result.output
    assert "[/x]" in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)


@pytest.mark.usefixtures("virtual_time")
def test_a_long_error_stays_on_one_line() -> None:
    result = runner.invoke(app, ["servo", "stat", "--port", "sim://?" + "x" * 200 + "=1"])
    assert result.exit_code == 1
    assert len(result.output.strip().splitlines()) == 1


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (("stat", "--sid", "-1"), "--sid=-1 is out of range: allowed 0..253"),
        (("stat", "--sid", "999"), "--sid=999 is out of range: allowed 0..253"),
        (("stat", "--sid", "٣"), "--sid must be an integer"),
        (("stat", "--sid", "\uff13"), "--sid must be an integer"),  # fullwidth 3
        (("info", "--sid", "0x1FF"), "--sid=511"),
        (("write", "nope", "1"), "REGISTER: no RAM register 'nope'"),
        (("read", "nope"), "REGISTER: no RAM register 'nope'"),
        (("read", "nope", "--eep"), "no EEP register 'nope'"),
        (("write", "led_control", "٣"), "VALUE must be an integer"),
        (("write", "led_control", "1", "--persist"), "--persist: led_control has no EEP"),
        (("write", "torque_control", "3"), "VALUE=3: torque_control=3 is not one of"),
        (("move", "٤٠٠"), "POSITION must be an integer"),
        (("move", "1e3"), "POSITION must be an integer"),
        (("move", "400", "--min-raw", "-5"), "--min-raw=-5 is out of range: allowed 0..1023"),
        (("move", "400", "--max-raw", "1024"), "--max-raw=1024 is out of range"),
        (("move", "400", "--min-raw", "700"), "--min-raw=700 is above --max-raw=650"),
        (("move", "400", "--sid", "-1"), "--sid=-1"),
        (("torque", "loose"), "MODE must be free, brake or on"),
        (("scan", "--first", "٣"), "--first must be an integer"),
        (("scan", "--last", "0x1FF"), "--last=511 is out of range: allowed 0..253"),
        (("scan", "--first", "0x10", "--last", "3"), "--first=16 is after --last=3"),
        (("clear", "--sid", "1e308"), "--sid must be an integer"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_bad_arguments_exit_2_naming_the_parameter(
    wire: Wire, args: tuple[str, ...], named: str
) -> None:
    code, out = invoke("servo", *args, *SIM)
    assert code == 2, out
    assert named in words(out)
    assert "Traceback" not in out
    assert wire.opened == []


@pytest.mark.usefixtures("virtual_time")
def test_scan_takes_hex_bounds_like_sid() -> None:
    code, out = invoke("servo", "scan", *SIM, "--first", "0x0B", "--last", "0xFD", "--json")
    assert code == 0, out
    assert [row["sid"] for row in json.loads(out)] == [11, 12]


@pytest.mark.usefixtures("virtual_time")
def test_hex_ids_are_printed_as_numbers() -> None:
    code, out = invoke("servo", "torque", "on", *SIM, "--sid", "0x0B")
    assert code == 0, out
    assert "servo 11: torque on" in out
