"""Recording to MCAP: read back with the ``mcap`` reader, counted, decoded; a disk that
fills up mid-recording leaves a file that still reads."""

from __future__ import annotations

import asyncio
import errno
import io
import json
import os
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader

from ohmni_tb import Robot
from ohmni_tb.foxglove import CHANNELS, McapRecorder, RecordingError
from ohmni_tb.foxglove import record as record_module
from ohmni_tb.foxglove.record import _McapScanner
from ohmni_tb.robot import STREAM_NAMES, WheelOdomSample
from ohmni_tb.robot.wire import sample_from_json
from ohmni_tb.sim.clock import run_virtual

from ._wire import Descriptors

#: Start recording off every stream's phase (they all start when the Robot opens), so a
#: window edge never falls on a sample and the counts are exact.
SETTLE_S = 0.5037
DURATION_S = 3.0
#: Expected per channel: the stream's rate × the duration.
RATES_HZ = {
    "/tf": 50,
    "/tb_control/wheel_odom": 50,
    "/tb_control/wheel_odom/json": 50,
    "/tb_control/wheel_encoder": 50,
    "/tb_control/pid_debug": 50,
    "/tb_control/tbcore_status": 10,
    "/tb_control/servo_neck": 30,
    "/tb_control/servo_ext1": 30,
    "/tb_control/servo_ext2": 30,
    "/tb_control/robot_state": 1,
    "/diagnostics": 1,
}


def read_back(path: Path) -> tuple[Counter[str], list[tuple[Any, Any, Any]]]:
    """Messages per topic, and every (schema, channel, message), as any reader sees them."""
    with path.open("rb") as file:
        records = list(make_reader(file).iter_messages(log_time_order=False))
    return Counter(channel.topic for _, channel, _ in records), records


async def _record(url: str, path: Path, *, pid_debug: bool) -> tuple[McapRecorder, int]:
    async with Robot.open(url, pid_debug=pid_debug) as robot:
        await asyncio.sleep(SETTLE_S)
        driving = asyncio.create_task(_drive(robot, SETTLE_S + DURATION_S + 1))
        async with McapRecorder(robot, path, duration_s=DURATION_S) as recorder:
            start_ns = recorder.start_ns
            await recorder.wait()
        driving.cancel()
        await asyncio.gather(driving, return_exceptions=True)
    assert start_ns is not None
    return recorder, start_ns


async def _drive(robot: Robot, seconds: float) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + seconds
    while loop.time() < end:
        robot.drive(0.3, 0.4)  # pid_debug publishes while the PIDs run
        await asyncio.sleep(0.05)


def test_three_seconds_of_every_stream_read_back_and_decode(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    recorder, start_ns = run_virtual(_record("sim://", path, pid_debug=True))
    counts, records = read_back(path)
    expected = {topic: round(hz * DURATION_S) for topic, hz in RATES_HZ.items()}
    assert dict(counts) == expected  # exact in virtual time; ±2 % is the requirement
    # What the recorder says it wrote is what the file holds.
    stats = recorder.stats()
    assert {t: s.messages for t, s in stats.items() if s.messages} == expected
    assert all(s.dropped == 0 for s in stats.values())
    assert recorder.error is None
    assert recorder.bytes_written == path.stat().st_size

    with path.open("rb") as file:
        reader = make_reader(file)
        summary = reader.get_summary()
        assert summary is not None
        assert summary.statistics is not None
        # A channel is written with its first message: the quiet ones are not in the file.
        assert {ch.topic for ch in summary.channels.values()} == set(expected)
        by_topic = {
            summary.channels[i].topic: n
            for i, n in summary.statistics.channel_message_counts.items()
        }
        assert by_topic == expected
        assert "foxglove-sdk-python" in reader.get_header().library
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata["ohmni_tb"]["library"].startswith("ohmni_tb ")
    assert int(metadata["ohmni_tb"]["clock_offset_ns"]) != 0

    descriptors: dict[str, Descriptors] = {}
    xs = []
    for schema, channel, message in records:
        assert start_ns <= message.log_time <= start_ns + DURATION_S * 1e9
        if channel.message_encoding == "json":
            stream = next(s.stream for s in CHANNELS if s.topic == channel.topic)
            sample = sample_from_json(stream, json.loads(message.data))
            assert sample.stamp_s * 0 == 0  # a sample of that stream, every field present
            if isinstance(sample, WheelOdomSample):
                xs.append(sample.x_m)
        else:
            assert schema.encoding == "protobuf"
            decoded = descriptors.setdefault(schema.name, Descriptors.parse(schema.data))
            fields = decoded.decode(schema.name, message.data)
            stamp = fields["timestamp"]
            assert stamp["seconds"] * 10**9 + stamp.get("nanos", 0) == message.log_time
    assert xs[-1] > xs[0] + 0.5  # it drove for 3 s at 0.3 m/s, in curves


def test_a_worm_neck_is_recorded_on_new_neck(tmp_path: Path) -> None:
    path = tmp_path / "worm.mcap"
    run_virtual(_record("sim://?neck=worm", path, pid_debug=False))
    counts, _ = read_back(path)
    assert counts["/tb_control/new_neck"] == 90
    assert counts["/tb_control/servo_neck"] == 0
    assert counts["/tb_control/pid_debug"] == 0


def test_the_file_is_not_clobbered_and_a_bad_path_is_one_clear_error(tmp_path: Path) -> None:
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"keep me")

    async def main() -> None:
        async with Robot.open("sim://") as robot:
            for path, words in (
                (existing, "exists: choose another name, or overwrite it"),
                (tmp_path, "it is a directory"),
                (tmp_path / "missing" / "x.mcap", f"the directory {tmp_path / 'missing'} does not"),
            ):
                with pytest.raises(RecordingError, match=words) as caught:
                    await McapRecorder(robot, path).start()
                assert "\n" not in str(caught.value)
                assert caught.value.path == str(path)
            assert existing.read_bytes() == b"keep me"
            async with McapRecorder(robot, existing, overwrite=True, duration_s=0.3) as recorder:
                await recorder.wait()

    run_virtual(main())
    counts, _ = read_back(existing)
    assert counts["/tf"] >= 10


def test_a_full_disk_stops_the_recording_and_the_file_still_reads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_write_all = record_module._write_all
    room_bytes = 40_000  # about two seconds of recording

    def filling_disk(fd: int, data: bytes) -> None:
        # A disk with room for the file up to room_bytes: what a cut frees is free again.
        room = room_bytes - os.fstat(fd).st_size
        if len(data) > room:
            os.write(fd, data[: max(room, 0)])  # the part that fits, as a real disk does
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_write_all(fd, data)

    monkeypatch.setattr(record_module, "_write_all", filling_disk)
    path = tmp_path / "full.mcap"

    async def main() -> tuple[McapRecorder, float]:
        async with Robot.open("sim://") as robot:
            recorder = McapRecorder(robot, path)
            with pytest.raises(RecordingError) as caught:
                async with recorder:
                    await recorder.wait()  # no duration: only the disk ends it
            assert caught.value is recorder.error
            return recorder, asyncio.get_running_loop().time()

    recorder, _ = run_virtual(main())
    message = str(recorder.error)
    assert "\n" not in message
    assert f"recording to {path} stopped after" in message
    assert "the disk is full (No space left on device)" in message
    assert "the file is closed and readable, with the first" in message
    kept_s = float(message.rsplit("the first ", 1)[1].split(" s", 1)[0])
    counts, records = read_back(path)
    # Whole seconds of data up to the last chunk that made it, every message intact.
    assert counts["/tf"] == pytest.approx(50 * kept_s, abs=1)
    assert counts["/tf"] >= 50
    assert {channel.topic for _, channel, _ in records} >= {"/tf", "/tb_control/tbcore_status"}
    # Cut back and closed: the data end, a footer, the magic.
    assert path.read_bytes().endswith(b"\x89MCAP0\r\n")


async def test_in_real_time_the_file_holds_every_sample_the_robot_published(
    tmp_path: Path,
) -> None:
    path = tmp_path / "real.mcap"
    async with Robot.open("sim://") as robot:
        watched = {name: robot.subscribe(name, maxlen=10_000) for name in STREAM_NAMES}
        async with McapRecorder(robot, path, duration_s=2.0) as recorder:
            await recorder.wait()
        published = {name: [s.stamp_s for s in _drain(sub)] for name, sub in watched.items()}
    assert all(s.dropped == 0 for s in recorder.stats().values())
    _, records = read_back(path)
    recorded: dict[str, list[float]] = {}
    for _, channel, message in records:
        spec = next(s for s in CHANNELS if s.topic == channel.topic)
        if spec.message_encoding == "json":
            recorded.setdefault(spec.stream, []).append(json.loads(message.data)["stamp_s"])
    assert set(recorded) >= {"wheel_encoder", "wheel_odom", "tbcore_status", "servo_neck"}
    for stream, stamps in recorded.items():
        first, last = min(stamps), max(stamps)
        assert sorted(stamps) == [t for t in published[stream] if first <= t <= last], stream
        assert last - first <= 2.0


def _drain(subscription: Any) -> list[Any]:
    out = []
    while (sample := subscription.get_nowait()) is not None:
        out.append(sample)
    subscription.close()
    return out


# -- the scanner that knows where a cut keeps the file whole -------------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("scan") / "scan.mcap"

    async def main() -> None:
        async with (
            Robot.open("sim://") as robot,
            McapRecorder(robot, path, duration_s=2.0, flush_interval_s=0.25) as rec,
        ):
            await rec.wait()

    run_virtual(main())
    return path.read_bytes()


def _boundaries(data: bytes) -> list[int]:
    stream = io.BytesIO(data)
    reader = StreamReader(stream, skip_magic=False, emit_chunks=True)
    return [stream.tell() for _ in reader.records]


def _feed(scanner: _McapScanner, data: bytes, sizes: list[int]) -> None:
    at = 0
    for size in sizes:
        scanner.feed(data[at : at + size])
        at += size
    scanner.feed(data[at:])


@pytest.mark.parametrize("way", ["whole", "halves", "bytes"])
def test_the_scanner_follows_a_whole_file_however_it_is_written(recording: bytes, way: str) -> None:
    scanner = _McapScanner()
    sizes = {"whole": [], "halves": [len(recording) // 2], "bytes": [1] * len(recording)}[way]
    _feed(scanner, recording, sizes)
    assert scanner.complete
    assert scanner.safe_end == len(recording)
    assert scanner.closing() == b""
    with io.BytesIO(recording) as file:
        summary = make_reader(file).get_summary()
    assert summary is not None
    last_chunk = max(index.message_end_time for index in summary.chunk_indexes)
    assert scanner.chunk_end_ns == last_chunk


@settings(max_examples=60, deadline=None)
@given(cut=st.floats(0.0, 1.0), chunking=st.lists(st.integers(1, 5000), max_size=30))
def test_a_file_cut_anywhere_and_closed_reads_up_to_its_last_whole_chunk(
    recording: bytes, cut: float, chunking: list[int]
) -> None:
    prefix = recording[: int(cut * len(recording))]
    scanner = _McapScanner()
    _feed(scanner, prefix, chunking)
    if scanner.prefix is None:
        assert len(prefix) < 100  # only the header record can be missing
        return
    assert scanner.safe_end in [*_boundaries(recording), len(recording)]
    assert scanner.safe_end <= len(prefix)
    assert scanner.cuts()[0] == scanner.safe_end
    with io.BytesIO(recording) as file:
        everything = [
            m.log_time for _, _, m in make_reader(file).iter_messages(log_time_order=False)
        ]
    # The last cut, and an earlier one (where a repair falls back to when the closing
    # bytes do not fit): each reads, with exactly the messages of its whole chunks.
    cuts = scanner.cuts()
    for at in {cuts[0], cuts[int(cut * 7) % len(cuts)], cuts[-1]}:
        assert at in [*_boundaries(recording), len(recording)]
        repaired = prefix[:at] + scanner.closing(at)
        with io.BytesIO(repaired) as file:
            times = [message.log_time for _, _, message in make_reader(file).iter_messages()]
        assert sorted(times) == sorted(everything[: len(times)])
        kept = scanner.chunk_end_before(at)
        assert (max(times) if times else None) == kept


@settings(max_examples=40, deadline=None)
@given(at=st.floats(0.02, 0.98), spare=st.integers(0, 60))
def test_a_repair_fits_in_what_the_disk_has_left(recording: bytes, at: float, spare: int) -> None:
    # The disk took the file up to a record boundary plus a few bytes of the next record
    # (`spare`), then filled: the closing bytes (50) may not fit after the last boundary.
    boundaries = [b for b in _boundaries(recording) if b < len(recording) - 200]
    room = boundaries[int(at * len(boundaries))] + spare
    loop = asyncio.new_event_loop()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp, "cut.mcap")
        fd = os.open(path, os.O_RDWR | os.O_CREAT)
        try:
            sink = record_module._FileSink(fd, loop, lambda: None)
            os.write(fd, recording[:room])
            sink._first += recording[:4096]
            last = max(b for b in boundaries if b <= room)
            sink._scanner.feed(recording[:last])  # what went out whole before the failure
            sink.error = OSError(errno.ENOSPC, "No space left on device")

            def full_disk(fd: int, data: bytes) -> None:
                if os.fstat(fd).st_size + len(data) > room:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                os.write(fd, data)

            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(record_module, "_write_all", full_disk)
                sink._repair()
        finally:
            os.close(fd)
            loop.close()
        assert sink.repair_error is None
        data = path.read_bytes()
        assert len(data) <= room
        assert data.endswith(b"\x89MCAP0\r\n")
        with io.BytesIO(data) as file:
            times = [m.log_time for _, _, m in make_reader(file).iter_messages()]
        assert (max(times) if times else None) == sink.kept_until_ns


def test_on_virtual_time_closing_takes_no_robot_time(tmp_path: Path) -> None:
    # The file is finished by the writer thread; the loop waits for it without running
    # the robot on meanwhile (a virtual clock would otherwise race ahead of the thread).
    path = tmp_path / "close.mcap"

    async def main() -> float:
        loop = asyncio.get_running_loop()
        async with Robot.open("sim://") as robot:
            recorder = McapRecorder(robot, path, duration_s=1.0)
            async with recorder:
                await recorder.wait()
                waited = loop.time()
            return loop.time() - waited

    assert run_virtual(main()) < 0.1
    counts, _ = read_back(path)
    assert counts["/tf"] >= 45
