"""The simulator's tb-node capture log (``sim://?tbnode_log=PATH``): the bytes at the host's
end of the line, with the line's times, in the format the tb-node plugin writes on a real
robot; converted with ``ohmni bus convert`` and decoded by ``ohmni bus monitor``, it shows
what the Robot did. Everything runs on the virtual clock."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner, Result

from ohmni_tb.capture.tbnode import LogReader, LogRecord
from ohmni_tb.cli import app
from ohmni_tb.errors import ConfigError
from ohmni_tb.protocol import Command, Packet, encode_packet
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count
from ohmni_tb.robot import LocalRobot
from ohmni_tb.robot.samples import TbcoreStatusSample, WheelEncoderSample
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.sim.url import build_line
from ohmni_tb.transport import open_transport

_BYTE_S = 10 / 115_200
_TURNAROUND_S = 0.0005

runner = CliRunner()


def _records(path: Path) -> list[LogRecord]:
    reader = LogReader()
    records = reader.feed(path.read_bytes()) + reader.finish()
    assert reader.summary.skipped == 0
    assert reader.summary.backwards == 0  # the log's own times never go back
    return records


def _invoke(*args: str) -> Result:
    return runner.invoke(app, list(args), env={"COLUMNS": "300"})


async def _exchange(transport: SimTransport, packet: Packet, reply_size: int) -> bytes:
    transport.write_nowait(encode_packet(packet))
    got = b""
    while len(got) < reply_size:
        got += await transport.read()
    return got


def test_the_log_holds_the_hosts_bytes_at_the_lines_times(tmp_path: Path) -> None:
    log = tmp_path / "bus.ndjson"

    async def main() -> bytes:
        transport = await open_transport(f"sim://?tbnode_log={log}")
        assert isinstance(transport, SimTransport)
        async with transport:
            await asyncio.sleep(0.25)
            return await _exchange(transport, read_count(0), 15)

    reply = run_virtual(main())
    request = encode_packet(read_count(0))
    done_s = 0.25 + len(request) * _BYTE_S + _TURNAROUND_S + len(reply) * _BYTE_S
    assert [(r.line, r.sent, r.data) for r in _records(log)] == [
        (1, True, request),
        (2, False, reply),
    ]
    assert [r.t_s for r in _records(log)] == pytest.approx([0.25, done_s], abs=1e-6)


def test_with_faults_the_log_has_what_the_host_wrote_and_what_it_got(tmp_path: Path) -> None:
    log = tmp_path / "bus.ndjson"
    request = encode_packet(read_status())

    async def main() -> list[bytes]:
        transport = await open_transport(f"sim://?corrupt=0.05&seed=4&tbnode_log={log}")
        assert isinstance(transport, SimTransport)
        got: list[bytes] = []
        async with transport:
            for _ in range(20):
                transport.write_nowait(request)
                await asyncio.sleep(0.01)
                while True:
                    try:
                        async with asyncio.timeout(0):
                            got.append(await transport.read())
                    except TimeoutError:
                        break
            assert transport.line.stats.corrupted_bytes > 0
        return got

    got = run_virtual(main())
    records = _records(log)
    # The host's writes as written (the line garbled some on the way); its reads as read.
    assert [r.data for r in records if r.sent] == [request] * 20
    assert [r.data for r in records if not r.sent] == got


@pytest.mark.parametrize("options", ["", "realtime=0", "usb_latency_ms=16"])
def test_the_logs_times_never_go_back(tmp_path: Path, options: str) -> None:
    log = tmp_path / "bus.ndjson"

    async def main() -> None:
        async with LocalRobot.open(f"sim://?{options}&tbnode_log={log}") as robot:
            robot.drive_pwm(200, 200)
            await asyncio.sleep(0.3)

    run_virtual(main())
    reader = LogReader()
    records = reader.feed(log.read_bytes())
    assert len(records) > 50
    assert reader.summary.backwards == 0
    assert reader.summary.skipped == 0


def test_a_late_loop_logs_the_reply_when_the_host_got_it(tmp_path: Path) -> None:
    # On the wall clock: the loop is held up past a reply's time, and the host writes
    # again before the reply is handed over. The log, as a plugin's at the host would,
    # has the reply after that write, never before it in time.
    log = tmp_path / "bus.ndjson"

    async def main() -> None:
        transport = await open_transport(f"sim://?tbnode_log={log}")
        assert isinstance(transport, SimTransport)
        async with transport:
            transport.write_nowait(encode_packet(read_count(0)))
            time.sleep(0.01)  # noqa: ASYNC251  # late on purpose: the reply is due at 2.6 ms
            transport.write_nowait(encode_packet(read_count(1)))
            got = b""
            while len(got) < 30:
                got += await transport.read()

    asyncio.run(main())
    records = _records(log)
    assert [(r.sent, r.data[3]) for r in records] == [(True, 0), (True, 1), (False, 0), (False, 1)]
    times = [r.t_s for r in records]
    assert times == sorted(times)
    assert times[1] >= 0.01


def test_the_log_carries_on_across_a_reconnection(tmp_path: Path) -> None:
    log = tmp_path / "bus.ndjson"

    async def main() -> None:
        first = await open_transport(f"sim://?tbnode_log={log}")
        assert isinstance(first, SimTransport)
        async with first:
            await _exchange(first, read_count(0), 15)
        async with await first.reopen() as second:
            assert isinstance(second, SimTransport)
            await _exchange(second, read_count(1), 15)

    run_virtual(main())
    assert [(r.sent, r.data[3]) for r in _records(log)] == [
        (True, 0),
        (False, 0),
        (True, 1),
        (False, 1),
    ]


def test_a_log_that_fails_is_counted_and_the_line_goes_on(tmp_path: Path) -> None:
    from ohmni_tb.sim.tbnode_log import TbnodeLog

    where = tmp_path / "logs"
    where.mkdir()
    tap = TbnodeLog(where / "bus.ndjson")
    line, robot = build_line({})
    line.add_tap(tap)

    async def main() -> bytes:
        async with SimTransport(line, robot=robot) as transport:
            await _exchange(transport, read_count(0), 15)
            (where / "bus.ndjson").unlink()
            where.rmdir()  # the disk went away
            return await _exchange(transport, read_count(0), 15)

    reply = run_virtual(main())
    assert len(reply) == 15
    assert (tap.records, tap.write_errors) == (2, 2)


@pytest.mark.parametrize("path", ["", "/nonexistent-dir/bus.ndjson"])
def test_a_log_that_cannot_be_created_is_refused_naming_the_option(path: str) -> None:
    with pytest.raises(ConfigError, match=r"option tbnode_log=.*: cannot create it: "):
        build_line({"tbnode_log": path})


def test_a_robots_traffic_logged_converted_and_decoded_by_the_monitor(tmp_path: Path) -> None:
    log = tmp_path / "bus.ndjson"

    async def drive() -> tuple[Any, WheelEncoderSample, TbcoreStatusSample]:
        async with LocalRobot.open(f"sim://?tbnode_log={log}") as robot:
            robot.drive_pwm(300, 300)
            await asyncio.sleep(0.5)
            robot.stop()
            await asyncio.sleep(0.3)
            encoder = robot.latest("wheel_encoder")
            battery = robot.latest("tbcore_status")
        assert encoder is not None
        assert battery is not None
        return robot.bus.stats, encoder, battery

    stats, encoder, battery = run_virtual(drive())
    mcap = tmp_path / "bus.mcap"
    converted = _invoke("bus", "convert", str(log), str(mcap), "--json")
    assert converted.exit_code == 0, converted.output
    summary = json.loads(converted.stdout)
    # Every byte the Robot's bus counted, and no line lost.
    assert summary["tx"]["bytes"] == stats.bytes_out
    assert summary["rx"]["bytes"] == stats.bytes_in
    assert summary["skipped"] == 0
    assert summary["time_went_back"] == 0
    assert 0.8 <= summary["span_s"] < 1.0

    decoded = _invoke("bus", "monitor", "--capture", str(mcap), "--json")
    assert decoded.exit_code == 0, decoded.output
    docs = [json.loads(line) for line in decoded.stdout.splitlines()]
    events, table = docs[:-1], docs[-1]
    assert table["decoder"]["bytes_discarded"] == 0
    # Per device, the requests and replies the Robot's bus counted.
    rows = {row["sid"]: row for row in table["devices"]}
    assert {sid: (row["requests"], row["replies"]) for sid, row in rows.items()} == {
        sid: (dev.requests, dev.replies) for sid, dev in stats.devices.items()
    }
    # The wheel commands: +300 both ways (the right board's mirrored), then the stop.
    jogs = [e["text"] for e in events if e["cmd"] == Command.S_JOG]
    assert len(jogs) == stats.devices[0xFE].requests
    assert set(jogs[:-1]) <= {
        "S_JOG wheels: left pwm +300, right pwm -300 (board frame)",
        "S_JOG wheels: left pwm +0, right pwm +0 (board frame)",
    }
    assert jogs[0] == "S_JOG wheels: left pwm +300, right pwm -300 (board frame)"
    assert jogs[-1] == "S_JOG wheels: left pwm +0, right pwm +0 (board frame)"
    # The wheel counts: each read answered after its wire time and the
    # turnaround, with the counts the
    # Robot read.
    for sid, raw in ((0, encoder.left_raw), (1, encoder.right_raw)):
        reads = [e for e in events if e["sid"] == sid and e["text"] == "RAM_READ count len 4"]
        replies = [e for e in events if e["sid"] == sid and e["cmd"] == Command.RAM_READ | 0x40]
        # Every request to the board: the count reads, and its firmware tag read at open.
        tag = [e for e in events if e["sid"] == sid and e["text"] == "EEP_READ firmware_tag len 0"]
        assert len(reads) == len(replies)
        assert len(reads) + len(tag) == stats.devices[sid].requests
        wire_ms = ((9 + 15) * _BYTE_S + _TURNAROUND_S) * 1e3
        assert [e["latency_ms"] for e in replies] == pytest.approx(
            [wire_ms] * len(replies), abs=2e-3
        )
        assert f"RAM_READ reply count = {raw}" in {e["text"] for e in replies}
    # The battery query and its fields, as the Robot decoded them.
    cells = "/".join(str(round(v * 1000)) for v in battery.cell_v)
    status = (
        f"RAM_READ reply status (assumed) = cells {cells} mV, pack "
        f"{round(battery.pack_v * 1000)} mV, {round(battery.current_a * 1000)} mA, "
        f"{'docked' if battery.docked else 'undocked'}, {battery.percent} %"
    )
    core = [e["text"] for e in events if e["sid"] == 20]
    # The status reads, and the core board's firmware tag read at open.
    assert (
        core.count("RAM_READ status (assumed) len 18") + core.count("EEP_READ firmware_tag len 0")
        == stats.devices[20].requests
    )
    assert status in core
    # The battery stream's rate, from the times the log gave its reads (the monitor's
    # per-device rate counts the tag read at open too).
    times = [
        e["t_s"]
        for e in events
        if e["sid"] == 20 and e["text"] == "RAM_READ status (assumed) len 18"
    ]
    assert (len(times) - 1) / (times[-1] - times[0]) == pytest.approx(10, rel=0.15)

    # The same log as raw bytes: the same packets, without times.
    raw_bytes = tmp_path / "bus.bin"
    assert _invoke("bus", "convert", str(log), str(raw_bytes)).exit_code == 0
    plain = _invoke("bus", "monitor", "--capture", str(raw_bytes), "--json")
    assert plain.exit_code == 0, plain.output
    plain_events = [json.loads(line) for line in plain.stdout.splitlines()][:-1]
    assert [e["text"] for e in plain_events] == [e["text"] for e in events]
    assert {e["t_s"] for e in plain_events} == {None}
