"""Replaying a recording to the Foxglove app: a Foxglove client receives exactly the
recorded messages, in order, on the recorded channels, at the recorded pace; files that
are not recordings are refused with a clear error; ``ohmni replay`` in its own process."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from daemon_api._serving import free_port
from ohmni_tb import Robot
from ohmni_tb.errors import OutOfRangeError
from ohmni_tb.foxglove import McapRecorder, McapReplay, ReplayError
from ohmni_tb.sim.clock import run_virtual

from ._wire import FoxgloveClient

TOPICS = ("/tf", "/tb_control/tbcore_status")
RECORDED_S = 2.0


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two seconds of every stream, recorded in virtual time."""
    path = tmp_path_factory.mktemp("replay") / "run.mcap"

    async def record() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.5037)
            async with McapRecorder(robot, path, duration_s=RECORDED_S) as recorder:
                await recorder.wait()

    run_virtual(record())
    return path


def recorded(path: Path, topics: tuple[str, ...]) -> list[tuple[str, int, bytes]]:
    with path.open("rb") as file:
        return [
            (channel.topic, message.log_time, message.data)
            for _, channel, message in make_reader(file).iter_messages(log_time_order=True)
            if channel.topic in topics
        ]


async def test_a_client_receives_the_recording_as_it_was_recorded(recording: Path) -> None:
    speed = 4.0
    async with McapReplay(recording, port=0, speed=speed) as replay:
        client = await FoxgloveClient.connect(replay.url)
        try:
            with recording.open("rb") as file:
                summary = make_reader(file).get_summary()
            assert summary is not None
            assert set(client.channels) == {c.topic for c in summary.channels.values()}
            assert replay.topics == sorted(client.channels)
            odom = client.channels["/tb_control/wheel_odom"]
            assert (odom.encoding, odom.schema_name) == ("protobuf", "foxglove.PoseInFrame")
            await client.subscribe(*TOPICS)
            await asyncio.sleep(0.2)  # the subscription reaches the server's threads
            loop = asyncio.get_running_loop()
            started = loop.time()
            # Read until the server closes (below), however long a busy machine takes.
            receiving = asyncio.ensure_future(client.messages(60.0))
            sent = await replay.run()
            took = loop.time() - started
            await asyncio.sleep(0.3)  # the last messages leave the SDK's queue
        finally:
            await replay.aclose()
            messages = await receiving
            await client.close()
    expected = recorded(recording, TOPICS)
    assert [(m.topic, m.log_time_ns, m.payload) for m in messages] == expected
    assert sent == sum(replay.sent.values()) >= len(expected)
    span_s = (expected[-1][1] - expected[0][1]) / 1e9
    assert span_s / speed <= took < span_s / speed + 2.0  # paced, not dumped at once


async def test_what_is_not_a_recording_is_refused_by_name(tmp_path: Path) -> None:
    missing = tmp_path / "nothing.mcap"
    with pytest.raises(ReplayError, match=r"cannot open .*nothing\.mcap"):
        await McapReplay(missing, port=0).start()
    text = tmp_path / "notes.mcap"
    text.write_text("not a recording\n")
    with pytest.raises(ReplayError, match=r"notes\.mcap is not an MCAP recording"):
        await McapReplay(text, port=0).start()
    for speed in (0.0, 41.0, float("nan")):
        with pytest.raises((OutOfRangeError, ValueError), match="speed"):
            McapReplay(text, speed=speed)


async def test_ohmni_replay_serves_the_file_then_ends(recording: Path) -> None:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "ohmni_tb", "replay", str(recording),
        "--foxglove", f"127.0.0.1:{free_port()}", "--speed", "8", "--linger", "1",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    assert proc.stdout is not None
    assert proc.stderr is not None
    try:
        url = (await asyncio.wait_for(proc.stdout.readline(), 30)).decode().strip()
        assert url.startswith("ws://127.0.0.1:")
        client = await FoxgloveClient.connect(url)
        try:
            await client.subscribe("/tb_control/tbcore_status")
            messages: list[Any] = await client.messages(60.0)  # until the replay ends
        finally:
            await client.close()
        assert len(messages) == len(recorded(recording, ("/tb_control/tbcore_status",)))
        code = await asyncio.wait_for(proc.wait(), 30)
        err = (await proc.stderr.read()).decode()
    finally:
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
    assert code == 0, err
    assert "replayed" in err
    assert "speed 8" in err
