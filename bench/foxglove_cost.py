"""What publishing to Foxglove costs the Robot: CPU, stream rates and control jitter.

Run: ``python bench/foxglove_cost.py`` (``--seconds`` per row, 30 by default; ``--quick`` for
5 s rows). Needs the ``foxglove`` extra.

Each row opens ``Robot.open(...)`` on ``ohmni sim --pty`` (the simulator in its own
process, so the CPU is the driver's alone, as on the robot) with every stream on, drives
it as a teleop does (``drive`` at 20 Hz, so ``pid_debug`` publishes too), and adds:

* ``off``: nothing;
* ``bridge idle``: a :class:`~ohmni_tb.foxglove.FoxgloveBridge`, nobody connected;
* ``bridge 1 client``: the same with one Foxglove client (another process) subscribed
  to every channel;
* ``record``: an :class:`~ohmni_tb.foxglove.McapRecorder` to a file in /tmp;
* ``both``: the bridge with its client, and the recorder.

Printed per row: every stream's achieved rate, the control slot's start jitter (p50,
p99) and cycles skipped, the messages published a second, the CPU share of one core of
the whole process over the window (``time.process_time``: the SDK's server threads
included) and what it adds over ``off`` per message published.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import sys
import tempfile
import time
from contextlib import AsyncExitStack
from dataclasses import dataclass, field
from pathlib import Path

from ohmni_tb.foxglove import FoxgloveBridge, McapRecorder
from ohmni_tb.robot import Robot

sys.path.insert(0, str(Path(__file__).parent))
from _pty import simulator_on_pty
from schedule import machine

STREAMS = ("wheel_encoder", "servo_neck", "servo_ext1", "servo_ext2", "tbcore_status")

#: A Foxglove client in its own process: subscribes to every channel, counts messages.
_CLIENT = """
import json, sys, time
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
with connect(sys.argv[1], subprotocols=["foxglove.sdk.v1"]) as ws:
    ws.recv()
    channels = json.loads(ws.recv())["channels"]
    subs = [{"id": c["id"], "channelId": c["id"]} for c in channels]
    ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
    print("subscribed", flush=True)
    count = 0
    end = time.monotonic() + float(sys.argv[2])
    while time.monotonic() < end:
        try:
            frame = ws.recv(timeout=0.5)
        except TimeoutError:
            continue
        except ConnectionClosed:
            break
        count += isinstance(frame, bytes) and frame[0] == 1
    print(count, flush=True)
"""


@dataclass
class Row:
    name: str
    rates: dict[str, float] = field(default_factory=dict)
    jitter_p50_ms: float = math.nan
    jitter_p99_ms: float = math.nan
    skipped: int = 0
    messages_per_s: float = 0.0
    received: int | None = None
    cpu: float = math.nan


async def run(
    name: str, port: str, seconds: float, *, bridge: bool, client: bool, record: bool
) -> Row:
    row = Row(name)
    loop = asyncio.get_running_loop()
    with tempfile.TemporaryDirectory() as tmp:
        async with AsyncExitStack() as stack:
            robot = await stack.enter_async_context(
                Robot.open(port, pid_debug=True, watchdog_s=1.0)
            )
            publishers: list[FoxgloveBridge | McapRecorder] = []
            viewer = None
            if bridge:
                served = await stack.enter_async_context(FoxgloveBridge(robot, port=0))
                publishers.append(served)
                if client:
                    viewer = await asyncio.create_subprocess_exec(
                        sys.executable,
                        "-c",
                        _CLIENT,
                        served.url,
                        str(seconds + 3),
                        stdout=asyncio.subprocess.PIPE,
                    )
                    assert viewer.stdout is not None
                    line = await viewer.stdout.readline()
                    assert line.strip() == b"subscribed", line
            if record:
                recorder = McapRecorder(robot, Path(tmp, "bench.mcap"))
                publishers.append(await stack.enter_async_context(recorder))
            driving = loop.create_task(_teleop(robot))
            await asyncio.sleep(1.0)  # settle
            start = robot.stats()
            sent0 = _sent(publishers)
            cpu0 = time.process_time()
            wall0 = time.perf_counter()
            await asyncio.sleep(seconds)
            cpu = time.process_time() - cpu0
            wall = time.perf_counter() - wall0
            end = robot.stats()
            sent = _sent(publishers) - sent0
            driving.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await driving
        if viewer is not None:
            out, _ = await viewer.communicate()
            row.received = int(out.split()[-1])
    for stream in STREAMS:
        row.rates[stream] = (end.streams[stream].samples - start.streams[stream].samples) / wall
    control = end.streams["wheel_encoder"]
    row.jitter_p50_ms = control.jitter_p50_ms or math.nan
    row.jitter_p99_ms = control.jitter_p99_ms or math.nan
    row.skipped = control.skipped - start.streams["wheel_encoder"].skipped
    row.messages_per_s = sent / wall
    row.cpu = cpu / wall
    return row


async def _teleop(robot: Robot) -> None:
    turn = 0.3
    while True:
        robot.drive(0.2, turn)
        turn = -turn if robot.latest("wheel_odom") and int(time.monotonic()) % 4 == 0 else turn
        await asyncio.sleep(0.05)


def _sent(publishers: list[FoxgloveBridge | McapRecorder]) -> int:
    return sum(s.messages for p in publishers for s in p.stats().values())


def show(row: Row, off: Row | None) -> None:
    rates = " ".join(f"{row.rates[s]:6.2f}" for s in STREAMS)
    extra = "     -"
    if off is not None and row.messages_per_s:
        extra = f"{(row.cpu - off.cpu) / row.messages_per_s * 1e6:6.1f}"
    print(
        f"{row.name:<16} | {rates} | {row.jitter_p50_ms:5.1f} {row.jitter_p99_ms:5.1f} "
        f"{row.skipped:4d} | {row.messages_per_s:6.0f} | {row.cpu:6.1%} | {extra}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--quick", action="store_true", help="5 s a row")
    args = parser.parse_args()
    seconds = 5.0 if args.quick else args.seconds
    print(machine())
    print(f"{seconds:g} s a row, real time, on ohmni sim --pty; pid_debug on, teleop at 20 Hz")
    header = (
        f"{'row':<16} | {'wheel':>6} {'neck':>6} {'ext1':>6} {'ext2':>6} {'core':>6} | "
        f"{'jit50':>5} {'jit99':>5} {'skip':>4} | {'msg/s':>6} | {'CPU':>6} | {'µs/msg':>6}"
    )
    print(header)
    print("-" * len(header))
    cases = (
        ("off", False, False, False),
        ("bridge idle", True, False, False),
        ("bridge 1 client", True, True, False),
        ("record", False, False, True),
        ("both", True, True, True),
    )
    off: Row | None = None
    for name, bridge, client, record in cases:
        with simulator_on_pty() as path:
            row = asyncio.run(run(name, path, seconds, bridge=bridge, client=client, record=record))
        show(row, off)
        if row.received is not None:
            print(f"{'':<16}   the client received {row.received} messages")
        off = off or row
    print("units: Hz | ms, cycles | messages a second | share of one core | CPU over off")
    return 0


if __name__ == "__main__":
    sys.exit(main())
