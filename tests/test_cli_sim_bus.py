"""``ohmni bus send``, ``ohmni bus monitor`` and the argument checks of ``ohmni sim``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner, Result

from ohmni_tb.cli import app
from ohmni_tb.cli import bus as bus_cli
from ohmni_tb.protocol import REPLY_FLAG, Packet, encode_packet
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count, wheel_command

runner = CliRunner()


def _invoke(*args: str) -> Result:
    return runner.invoke(app, list(args))


def _words(text: str) -> str:
    """The output with rich's line wrapping and error box undone."""
    return " ".join(text.replace("│", " ").split())


# -- ohmni bus send -----------------------------------------------------------------------


@pytest.mark.usefixtures("virtual_time")
def test_send_reads_the_left_wheel_count_as_json() -> None:
    result = _invoke("bus", "send", "0", "RAM_READ", "3B", "04", "--port", "sim://", "--json")
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    assert doc["request"] == {
        "sid": 0,
        "cmd": 4,
        "command": "RAM_READ",
        "data": "3b 04",
        "bytes": "ff ff 09 00 04 32 cc 3b 04",
    }
    reply = doc["reply"]
    assert reply["sid"] == 0
    assert reply["cmd"] == 0x44
    assert reply["command"] == "RAM_READ reply"
    assert reply["addr"] == 59
    assert reply["value_hex"] == "00 00 00 00"
    assert reply["status_error"] == "none"
    assert reply["status_detail"] == "none"


@pytest.mark.usefixtures("virtual_time")
def test_send_shows_a_firmware_tag_as_text() -> None:
    result = _invoke("bus", "send", "20", "EEP_READ", "F1", "00", "--port", "sim://", "--json")
    assert result.exit_code == 0, result.output
    reply = json.loads(result.stdout)["reply"]
    assert reply["value_text"] == "sim-core-1.0"
    assert bytes.fromhex(reply["value_hex"]) == b"sim-core-1.0"
    count = _invoke("bus", "send", "0", "RAM_READ", "3B", "04", "--port", "sim://", "--json")
    assert "value_text" not in json.loads(count.stdout)["reply"]  # zeros are not text


@pytest.mark.usefixtures("virtual_time")
def test_send_takes_hex_sids_and_joined_hex_data() -> None:
    result = _invoke("bus", "send", "0x14", "4", "A012", "--port", "sim://", "--json")
    assert result.exit_code == 0, result.output
    reply = json.loads(result.stdout)["reply"]
    assert reply["sid"] == 20
    assert len(bytes.fromhex(reply["value_hex"])) == 18


@pytest.mark.usefixtures("virtual_time")
def test_send_prints_the_decoded_reply() -> None:
    result = _invoke("bus", "send", "20", "EEP_READ", "F1", "00", "--port", "sim://")
    assert result.exit_code == 0, result.output
    assert "request  Packet(sid=20, cmd=EEP_READ" in result.stdout
    assert "reply    Packet(sid=20, cmd=EEP_READ reply" in result.stdout
    assert "addr" in result.stdout
    # 'sim-core-1.0' in hex.
    assert "73 69 6d 2d 63 6f 72 65 2d 31 2e 30" in result.stdout


@pytest.mark.usefixtures("virtual_time")
def test_send_shows_error_bits_of_a_read_outside_the_map() -> None:
    result = _invoke("bus", "send", "0", "RAM_READ", "99", "02", "--port", "sim://", "--json")
    assert result.exit_code == 0, result.output
    reply = json.loads(result.stdout)["reply"]
    assert reply["status_error"] == "INVALID_PACKET"
    assert reply["status_detail"] == "EXCEED_REG_RANGE"


@pytest.mark.usefixtures("virtual_time")
def test_send_a_stat() -> None:
    result = _invoke("bus", "send", "1", "stat", "--port", "sim://", "--json")
    assert result.exit_code == 0, result.output
    reply = json.loads(result.stdout)["reply"]
    assert (reply["sid"], reply["cmd"], reply["data"]) == (1, 0x47, "00 00")


@pytest.mark.usefixtures("virtual_time")
def test_send_a_broadcast_jog_expects_no_reply() -> None:
    jog = wheel_command(100, 100).data.hex(" ").split()
    result = _invoke("bus", "send", "0xFE", "S_JOG", *jog, "--port", "sim://")
    assert result.exit_code == 0, result.output
    assert "no reply expected" in _words(result.stdout)
    result = _invoke("bus", "send", "0xFE", "S_JOG", *jog, "--port", "sim://", "--json")
    assert json.loads(result.stdout)["reply"] is None


@pytest.mark.usefixtures("virtual_time")
def test_send_to_a_silent_device_fails_with_one_error_line() -> None:
    result = _invoke("bus", "send", "20", "STAT", "--port", "sim://?silent=20")
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("error: no reply from sid 20")
    assert "Traceback" not in result.output


@pytest.mark.usefixtures("virtual_time")
def test_send_with_a_bad_port_url_fails_with_an_error_line() -> None:
    result = _invoke("bus", "send", "0", "STAT", "--port", "sim://?neck=9")
    assert result.exit_code == 1
    assert _words(result.output).startswith("error: neck='9'")


@pytest.mark.parametrize(
    ("port", "named"),
    [
        ("http://[::1", "cannot parse the URL 'http://[::1'"),
        ("sim://?seed=٣", "option seed='٣' is not an integer"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_a_port_url_that_cannot_be_read_is_one_error_line(port: str, named: str) -> None:
    result = _invoke("bus", "send", "0", "STAT", "--port", port)
    assert result.exit_code == 1
    assert result.exception is None or isinstance(result.exception, SystemExit)
    (line,) = result.output.splitlines()
    assert line.startswith(f"error: {named}")


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (("zz", "STAT"), "'zz'"),
        (("300", "STAT"), "SID=300"),
        (("--", "-1", "STAT"), "SID=-1"),
        (("0", "JUMP"), "'JUMP'"),
        (("0", "JUMP"), "RAM_READ"),  # the message lists the command names
        (("0", "0x1FF"), "CMD=511"),
        (("0", "RAM_READ", "3G"), "'3G'"),
        (("0", "RAM_READ", "3B", "0"), "'3B 0'"),
        (("٣", "STAT"), "SID must be an integer"),
        (("0", "٣"), "'٣'"),
        (("0", "1e308"), "'1e308'"),
        (("0x" + "F" * 200, "STAT"), "SID='0xFFFFFFFFFFFFFFFFFF"),
        (("0", "RAM_READ", "٣٣"), "DATA must be hex bytes"),
        (("0", "RAM_READ", "00", "FF"), "read of 255 bytes: allowed 0..212"),
        (("0", "RAM_WRITE", "00" * 220), "DATA is 220 bytes: allowed 0..216"),
        (("0xFE", "STAT"), "every device would answer"),
    ],
)
@pytest.mark.usefixtures("virtual_time")
def test_send_refuses_bad_arguments_by_name(args: tuple[str, ...], named: str) -> None:
    result = _invoke("bus", "send", "--port", "sim://", *args)
    assert result.exit_code == 2
    assert named in _words(result.output)
    assert result.exception is None or isinstance(result.exception, SystemExit)


# -- ohmni bus monitor --------------------------------------------------------------------


@pytest.fixture
def capture(tmp_path: Path) -> Path:
    """A capture of a short session with six junk bytes at the end."""
    reply = Packet(0, 0x04 | REPLY_FLAG, bytes((59, 4)) + (4242).to_bytes(4, "little") + b"\0\0")
    packets = [read_count(0), reply, wheel_command(300, 300), read_count(1), read_status()]
    path = tmp_path / "session.bin"
    path.write_bytes(b"".join(encode_packet(p) for p in packets) + b"\x01\x02junk")
    return path


@pytest.mark.usefixtures("virtual_time")
def test_monitor_describes_a_capture_file(capture: Path) -> None:
    result = _invoke("bus", "monitor", "--capture", str(capture))
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0].split() == ["left", "RAM_READ", "count", "len", "4"]
    assert lines[1].split() == ["left", "RAM_READ", "reply", "count", "=", "4242"]
    assert "S_JOG wheels: left pwm +300, right pwm -300 (board frame)" in lines[2]
    assert "bus summary" in result.stdout
    words = _words(result.stdout)
    assert "decoder: packets 5, bytes_in" in words
    assert "bytes_discarded 6" in words


@pytest.mark.usefixtures("virtual_time")
def test_monitor_json_gives_one_document_a_line(capture: Path) -> None:
    result = _invoke("bus", "monitor", "--capture", str(capture), "--json")
    assert result.exit_code == 0, result.output
    docs = [json.loads(line) for line in result.stdout.splitlines()]
    events, summary = docs[:-1], docs[-1]
    assert [e["device"] for e in events] == ["left", "left", "broadcast", "right", "core"]
    assert events[1]["text"] == "RAM_READ reply count = 4242"
    assert events[1]["sid"] == 0
    assert events[1]["cmd"] == 0x44
    assert events[0]["latency_ms"] is None
    devices = {d["sid"]: d for d in summary["devices"]}
    assert devices[0]["requests"] == devices[0]["replies"] == 1
    assert devices[1]["unanswered"] == 1  # the core read followed with no reply between
    assert summary["decoder"]["packets"] == 5
    assert summary["decoder"]["bytes_discarded"] == 6


@pytest.mark.usefixtures("virtual_time")
def test_monitor_quiet_prints_only_the_summary(capture: Path) -> None:
    result = _invoke("bus", "monitor", "--capture", str(capture), "--json", "--quiet")
    assert result.exit_code == 0, result.output
    (line,) = result.stdout.splitlines()
    assert set(json.loads(line)) == {"devices", "decoder"}


@pytest.mark.usefixtures("virtual_time")
def test_monitor_of_a_missing_capture_names_it(tmp_path: Path) -> None:
    result = _invoke("bus", "monitor", "--capture", str(tmp_path / "nope.bin"))
    assert result.exit_code == 2
    # A long temporary path may be folded inside the error box: compare without spaces.
    assert "nope.bin" in "".join(_words(result.output).split())


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize("args", [(), ("--port", "sim://", "--capture", "x.bin")])
def test_monitor_needs_exactly_one_source(args: tuple[str, ...]) -> None:
    result = _invoke("bus", "monitor", *args)
    assert result.exit_code == 2
    assert "exactly one of --port or --capture" in _words(result.output)


def test_monitor_listens_on_a_port_for_a_while() -> None:
    # Nothing talks on a fresh simulated line: an empty summary after the duration.
    result = _invoke("bus", "monitor", "--port", "sim://", "--duration", "0.05", "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.stdout)["devices"] == []


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize("duration", ["inf", "nan", "1e308", "-1", "٣"])
def test_monitor_refuses_a_duration_it_cannot_keep(duration: str) -> None:
    result = _invoke("bus", "monitor", "--port", "sim://", f"--duration={duration}")
    assert result.exit_code == 2
    assert "--duration" in result.output


class _InterruptedLine:
    """A live port that delivers some traffic, then the operator presses Ctrl-C."""

    def __init__(self, *chunks: bytes) -> None:
        self.chunks = list(chunks)
        self.closed = False

    async def read(self) -> bytes:
        if self.chunks:
            return self.chunks.pop(0)
        raise KeyboardInterrupt

    async def aclose(self) -> None:
        self.closed = True


def test_monitor_prints_its_summary_on_ctrl_c_then_exits_130(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    reply = Packet(0, 0x04 | REPLY_FLAG, bytes((59, 4)) + (7).to_bytes(4, "little") + b"\0\0")
    line = _InterruptedLine(encode_packet(read_count(0)), encode_packet(reply))

    async def fake_open(url: str) -> _InterruptedLine:
        return line

    monkeypatch.setattr(bus_cli, "open_transport", fake_open)
    result = _invoke("bus", "monitor", "--port", "sim://", "--json", "--quiet")
    assert result.exit_code == 130, result.output
    (summary,) = [json.loads(text) for text in result.stdout.splitlines()]
    (left,) = summary["devices"]
    assert (left["sid"], left["requests"], left["replies"]) == (0, 1, 1)
    assert summary["decoder"]["packets"] == 2
    assert line.closed


# -- ohmni sim: argument checks (serving is tested in tests/sim/test_pty.py) --------------


def test_sim_without_pty_says_how_to_run_it() -> None:
    result = _invoke("sim")
    assert result.exit_code == 2
    assert "ohmni sim --pty" in _words(result.output)


def test_sim_refuses_a_url_of_another_scheme() -> None:
    result = _invoke("sim", "--pty", "--url", "mem://x")
    assert result.exit_code == 2
    assert "sim://" in _words(result.output)


@pytest.mark.parametrize(("url", "named"), [("sim://?bogus=1", "bogus"), ("sim://?drop=9", "drop")])
def test_sim_refuses_bad_options_before_serving(url: str, named: str) -> None:
    result = _invoke("sim", "--pty", "--url", url)
    assert result.exit_code == 1
    assert result.output.startswith("error:")
    assert named in _words(result.output)
