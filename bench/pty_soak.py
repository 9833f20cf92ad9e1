"""tb_control's schedule written as a user would, against ``ohmni sim --pty``, many times.

Run: ``python bench/pty_soak.py`` (``--runs``, ``--seconds`` a run, ``--jobs`` at a time,
``--hogs`` busy-loop processes competing for the cores, ``--caution-s`` for the bus).

Each run starts ``ohmni sim --pty`` in its own process and drives it over the serial
transport with one loop per stream on absolute deadlines — the two wheel counts and a
wheel command every 20 ms (``bus.query`` / ``bus.send`` one after the other), servos 3,
11 and 12 read at 30 Hz (``bus.read``), the core board's status at 10 Hz — skipping a
cycle that is already late. A run *fails* when any call raises (a read that got no reply
after its three attempts, a link error). The table gives the failed runs and, per run,
the reads that timed out, the checksum errors the decoder saw (garbled replies: on the
simulator, collisions with a request sent while it still believed its reply on the wire)
and the transactions per second achieved (the schedule asks for 250).

The host and the simulator share the machine's cores: ``--hogs 2`` shows what a loaded
2-core machine does to the line timing. Takes ``runs × seconds / jobs`` plus start-up.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from ohmni_tb.bus import Bus
from ohmni_tb.errors import OhmniError
from ohmni_tb.protocol import core, drive
from ohmni_tb.protocol.connection import DEFAULT_CAUTION_S
from ohmni_tb.transport import open_transport

sys.path.insert(0, str(Path(__file__).parent))
from _pty import simulator_on_pty

SERVOS = (3, 11, 12)


async def client(path: str, seconds: float, caution_s: float) -> dict[str, Any]:
    """One run's schedule against the pty at ``path``: what failed, and the bus's counts."""
    loop = asyncio.get_running_loop()
    failures: list[str] = []
    counts: dict[str, int] = {}
    bus = Bus(await open_transport(path), caution_s=caution_s)
    stop_at = loop.time() + seconds

    async def periodic(name: str, period_s: float, body: Callable[[], Awaitable[object]]) -> None:
        counts[name] = 0
        due = loop.time()
        while True:
            if due > loop.time():
                await asyncio.sleep(due - loop.time())
            if loop.time() >= stop_at:
                return
            try:
                await body()
                counts[name] += 1
            except OhmniError as exc:
                failures.append(f"{name}: {type(exc).__name__}: {exc}")
                if not bus.connected:
                    return
            due += period_s
            if due < loop.time():  # late: skip the cycles already missed
                due += (int((loop.time() - due) / period_s) + 1) * period_s

    async def wheels() -> None:
        await bus.query(drive.read_count(0))
        await bus.query(drive.read_count(1))
        await bus.send(drive.wheel_command(0, 0))

    def servo(sid: int) -> Callable[[], Awaitable[object]]:
        return lambda: bus.read(sid, 48, 12)

    async with bus, asyncio.TaskGroup() as tg:
        tg.create_task(periodic("wheels", 0.020, wheels))
        for sid in SERVOS:
            tg.create_task(periodic(f"servo {sid}", 1 / 30, servo(sid)))
        tg.create_task(periodic("core", 0.100, lambda: bus.query(core.read_status())))
    stats = bus.stats
    return {
        "failures": failures,
        "timeouts": sum(d.timeouts for d in stats.devices.values()),
        "checksum_errors": stats.decoder.checksum_errors,
        "cautions": stats.cautions,
        "tx_per_s": (3 * counts["wheels"] + sum(v for k, v in counts.items() if k != "wheels"))
        / seconds,
    }


def child(seconds: float, caution_s: float) -> dict[str, Any]:
    """One run: a simulator process on a pty, the schedule against it, the simulator stopped."""
    with simulator_on_pty() as path:
        try:
            return asyncio.run(client(path, seconds, caution_s))
        except (OhmniError, OSError) as exc:
            return {"failures": [f"start: {type(exc).__name__}: {exc}"]}


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--runs", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--hogs", type=int, default=0)
    parser.add_argument("--caution-s", type=float, default=DEFAULT_CAUTION_S)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.seconds, args.caution_s)), flush=True)
        return 0

    def one(_: int) -> dict[str, Any]:
        cmd = [sys.executable, os.path.abspath(__file__), "--child"]
        cmd += ["--seconds", str(args.seconds), "--caution-s", str(args.caution_s)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=False)
        lines = out.stdout.strip().splitlines()
        if out.returncode or not lines:
            return {"failures": [f"run crashed: {(out.stderr or out.stdout)[-300:]}"]}
        result: dict[str, Any] = json.loads(lines[-1])
        return result

    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hogs)]
    started = time.monotonic()
    try:
        with ThreadPoolExecutor(args.jobs) as pool:
            results = list(pool.map(one, range(args.runs)))
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    done = [r for r in results if "timeouts" in r]
    failed = [r for r in results if r["failures"]]
    print(
        f"{args.runs} runs of {args.seconds:g} s, {args.jobs} at a time, {args.hogs} busy "
        f"loop(s), caution_s {args.caution_s:g}; {time.monotonic() - started:.0f} s"
    )
    print(f"runs failed: {len(failed)} / {args.runs}")
    if done:
        for key, label in (
            ("timeouts", "timeouts per run"),
            ("checksum_errors", "checksum errors per run"),
            ("cautions", "cautious spells per run"),
            ("tx_per_s", "transactions/s (of 250)"),
        ):
            values = [float(r[key]) for r in done]
            print(f"{label:>26}: mean {statistics.mean(values):6.1f}  max {max(values):6.1f}")
    for r in failed[:5]:
        print("  ", r["failures"][0][:150])
    return 0


if __name__ == "__main__":
    sys.exit(main())
