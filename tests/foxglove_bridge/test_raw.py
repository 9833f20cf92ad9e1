"""The bus's own bytes in a recording (``ohmni record --raw``) and decoded again
(``ohmni bus monitor --capture FILE.mcap``): what the Robot wrote and read, byte for
byte, in the order and at the times it happened."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app
from ohmni_tb.cli import record as record_cli
from ohmni_tb.errors import InvalidArgumentError
from ohmni_tb.foxglove import McapRecorder, ReplayError
from ohmni_tb.foxglove.record import RAW_TOPICS
from ohmni_tb.foxglove.replay import raw_bus_bytes
from ohmni_tb.monitor import BusMonitor
from ohmni_tb.protocol import Command, PacketDecoder
from ohmni_tb.robot import LocalRobot
from ohmni_tb.sim.clock import run_virtual

from .test_record import read_back


def test_the_recording_holds_every_byte_the_robot_wrote_and_read(tmp_path: Path) -> None:
    path = tmp_path / "raw.mcap"

    async def record() -> tuple[int, int, dict[str, int]]:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(0.5037)  # off every stream's phase
            async with McapRecorder(robot, path, duration_s=1.0, raw=True) as recorder:
                # The window starts now (virtual time: opening took none) and lasts 1 s.
                out0, in0 = robot.bus.stats.bytes_out, robot.bus.stats.bytes_in
                await asyncio.sleep(1.0)
                out1, in1 = robot.bus.stats.bytes_out, robot.bus.stats.bytes_in
                await recorder.wait()
            counts = {t: s.messages for t, s in recorder.stats().items()}
        return out1 - out0, in1 - in0, counts

    written, read, counts = run_virtual(record())
    chunks = list(raw_bus_bytes(path))
    sent = b"".join(data for _, was_sent, data in chunks if was_sent)
    got = b"".join(data for _, was_sent, data in chunks if not was_sent)
    # Every byte the bus counted in the window, no more.
    assert len(sent) == written
    assert len(got) == read
    assert counts[RAW_TOPICS[0]] == sum(1 for c in chunks if c[1])
    assert counts[RAW_TOPICS[1]] == sum(1 for c in chunks if not c[1])
    topics, _ = read_back(path)
    assert topics[RAW_TOPICS[0]] == counts[RAW_TOPICS[0]]
    # Whole packets, no junk: the host's writes are the schedule's requests.
    decoder = PacketDecoder()
    requests = decoder.feed(sent)
    assert decoder.stats.bytes_discarded == 0
    reads = [p for p in requests if p.cmd == Command.RAM_READ]
    assert sum(p.sid == 0 for p in reads) == pytest.approx(50, abs=1)  # the control tick
    assert sum(p.sid == 3 for p in reads) == pytest.approx(30, abs=1)  # the neck
    assert sum(p.sid == 20 for p in reads) == pytest.approx(10, abs=1)  # the core board
    replies = PacketDecoder().feed(got)
    assert len(replies) == pytest.approx(
        len(reads) + sum(p.cmd == Command.EEP_READ for p in requests), abs=2
    )
    # Times: from 0, in order, over the one-second window.
    times = [t for t, _, _ in chunks]
    assert times == sorted(times)
    assert times[0] == 0.0
    assert 0.95 <= times[-1] < 1.0
    # The monitor pairs them as it would a capture from the line.
    monitor = BusMonitor()
    for t_s, _, data in chunks:
        monitor.feed(data, t_s)
    left = monitor.devices[0]
    assert left.requests == sum(p.sid == 0 for p in reads)
    assert left.replies >= left.requests - 1
    assert left.rate_hz() == pytest.approx(50, rel=0.02)


def test_raw_needs_the_robot_that_owns_the_port(tmp_path: Path) -> None:
    class DaemonClientLike:
        def subscribe(self, name: str, *, maxlen: int = 0) -> object:
            raise AssertionError("not reached")

    with pytest.raises(InvalidArgumentError, match="raw bus bytes need the Robot"):
        McapRecorder(DaemonClientLike(), tmp_path / "x.mcap", raw=True)  # type: ignore[arg-type]  # not a LocalRobot, on purpose
    assert not (tmp_path / "x.mcap").exists()


@pytest.mark.usefixtures("virtual_time")
def test_ohmni_record_raw_then_bus_monitor_decodes_it(tmp_path: Path) -> None:
    path = tmp_path / "bus.mcap"
    runner = CliRunner()
    recorded = runner.invoke(
        app, ["record", str(path), "--raw", "--duration", "0.5", "--port", "sim://", "--json"]
    )
    assert recorded.exit_code == 0, recorded.output
    summary = json.loads(recorded.stdout)
    assert summary["channels"][RAW_TOPICS[0]]["messages"] > 0
    decoded = runner.invoke(app, ["bus", "monitor", "--capture", str(path), "--json"])
    assert decoded.exit_code == 0, decoded.output
    events = [json.loads(line) for line in decoded.stdout.splitlines() if '"t_s"' in line]
    left_reads = [e for e in events if e["sid"] == 0 and e["cmd"] == Command.RAM_READ]
    assert 20 <= len(left_reads) <= 26  # 50 Hz for 0.5 s
    assert all(e["t_s"] is not None for e in events)
    replies = [e for e in events if e["latency_ms"] is not None]
    assert replies
    assert all(0 < e["latency_ms"] < 100 for e in replies)  # times kept: replies after requests


@pytest.mark.usefixtures("virtual_time")
def test_a_recording_without_raw_bytes_is_refused_by_the_monitor(tmp_path: Path) -> None:
    path = tmp_path / "streams.mcap"
    runner = CliRunner()
    assert (
        runner.invoke(
            app, ["record", str(path), "--duration", "0.2", "--port", "sim://", "--json"]
        ).exit_code
        == 0
    )
    decoded = runner.invoke(app, ["bus", "monitor", "--capture", str(path)])
    assert decoded.exit_code == 1
    assert "has no raw bus bytes" in decoded.output
    assert "ohmni record --raw" in decoded.output
    with pytest.raises(ReplayError, match="has no raw bus bytes"):
        list(raw_bus_bytes(path))


def test_raw_through_the_daemon_is_refused_before_anything_opens(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(record_cli, "daemon_for", lambda port, direct: "ws://127.0.0.1:8766")
    result = CliRunner().invoke(
        app, ["record", str(tmp_path / "r.mcap"), "--raw"], env={"COLUMNS": "300"}
    )
    assert result.exit_code == 2
    assert "--raw needs the serial port" in " ".join(result.output.replace("│", " ").split())
    assert not (tmp_path / "r.mcap").exists()
