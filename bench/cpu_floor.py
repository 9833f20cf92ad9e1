"""The least CPU the Robot's schedule can cost: raw bytes on the same timers, over a pty.

Run: ``python bench/cpu_floor.py`` (``--seconds`` per row, 15 by default; ``--only
robot`` for the last part alone).

Against ``ohmni sim --pty`` in its own process, an asyncio loop writes the schedule's
request bytes on the schedule's timers — every 20 ms both wheel-count reads and a wheel
command, servos 3, 11, 12 at 30 Hz (staggered), the core board at 10 Hz — straight to
the pty's descriptor, and reads what comes back from a readiness callback. No bus, no
pairing, no Robot: the floor under ``bench/robot.py``'s CPU figure (which is the share
of one core of the process, like these rows). Two rows: counting the reply bytes only,
and feeding them to the project's :class:`~ohmni_tb.protocol.PacketDecoder`.

Then the wake-ups alone: an asyncio loop whose only work is a timer that re-arms itself,
at 100, 400 (about what the Robot's loop wakes for: ~200 replies, ~150 stream timers and
the bus's own) and 1,000 a second, no I/O. On a virtual machine a wake-up from idle costs
far more than the few microseconds of Python it runs; this row shows how much. Beside
it, a plain ``time.sleep`` loop on the same absolute schedule (no event loop): what the
sleep and wake-up themselves cost, and so how much of each asyncio wake-up is the loop's
own pass (its selector calls, timer heap and handles) — the ratio is printed.

The requests are not paced to the line, so some collide with replies on the simulated
half-duplex line: the reply count is lower than the schedule's 200 a second. The figure
is the loop's and the system calls' cost, which that does not change much. (The minimal
master that paces them, writing each request from the previous reply's callback, is
``bench/_floor.py``: ``bench/robot.py --ratio`` measures the Robot against it.) The pty
is opened locked, as a serial port is: with another process on the line the run stops
with an error instead of printing a figure for half the replies.

Last, the same work warm and cold: the Robot with every stream on, driving, on ``sim://``
in virtual time — the exact same sequence of callbacks every run, the simulator in the
process — back to back (warm: nothing runs between two passes of the loop; the least of
three runs), then with the loop's thread asleep for real (0.2, 1 and 3 ms) each time
virtual time jumps, as it sleeps between wake-ups in real time (about 2.4 ms on average
under the Robot's schedule). The CPU of the loop's thread per virtual second, less what
the sleeps themselves cost, is the work's; its ratio to the warm row is what sleeping
does to the same Python (on a shared virtual machine, the caches it finds after waking).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from _floor import close_locked, open_locked
from _pty import simulator_on_pty
from ohmni_tb import Robot
from ohmni_tb.protocol import PacketDecoder, encode_packet, read_request
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.sim.clock import VirtualClockLoop
from schedule import machine

CONTROL = b"".join(encode_packet(p) for p in (read_count(0), read_count(1), wheel_command(0, 0)))
SERVOS = [encode_packet(read_request(sid, 48, 12)) for sid in (3, 11, 12)]
CORE = encode_packet(read_status())


async def floor(path: str, seconds: float, *, decode: bool) -> tuple[float, int]:
    fd = open_locked(path)  # refused (EBUSY) while another process holds the line
    loop = asyncio.get_running_loop()
    decoder = PacketDecoder()
    got = [0]

    def readable() -> None:
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            return  # readiness without bytes: nothing to count
        got[0] += len(decoder.feed(data)) if decode else len(data)

    loop.add_reader(fd, readable)
    t0 = loop.time() + 0.05
    stop = t0 + seconds

    def every(period: float, frame: bytes, phase: float) -> None:
        k = 0

        def fire() -> None:
            nonlocal k
            os.write(fd, frame)
            k += 1
            due = t0 + phase + k * period
            if due < stop:
                loop.call_at(due, fire)

        loop.call_at(t0 + phase, fire)

    every(0.020, CONTROL, 0.0)
    for i, frame in enumerate(SERVOS):
        every(1 / 30, frame, 0.010 + i / 90)
    every(0.100, CORE, 0.013)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    await asyncio.sleep(seconds + 0.1)
    share = (time.process_time() - cpu0) / (time.perf_counter() - wall0)
    loop.remove_reader(fd)
    close_locked(fd)
    return share, got[0]


async def wakeups(rate_hz: float, seconds: float) -> float:
    """CPU share of a loop that only wakes ``rate_hz`` times a second on a timer."""
    loop = asyncio.get_running_loop()
    t0 = loop.time() + 0.05

    def fire(k: int) -> None:
        loop.call_at(t0 + (k + 1) / rate_hz, fire, k + 1)

    loop.call_at(t0, fire, 0)
    await asyncio.sleep(0.05)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    await asyncio.sleep(seconds)
    return (time.process_time() - cpu0) / (time.perf_counter() - wall0)


def sleeps(rate_hz: float, seconds: float) -> float:
    """CPU share of a plain loop that sleeps (``time.sleep``) to ``rate_hz`` due times."""
    t0 = time.monotonic() + 0.05
    cpu0, wall0 = time.process_time(), time.perf_counter()
    k = 0
    while (now := time.monotonic()) < t0 + seconds:
        k += 1
        time.sleep(max(0.0, t0 + k / rate_hz - now))
    return (time.process_time() - cpu0) / (time.perf_counter() - wall0)


class _SleepingClockLoop(VirtualClockLoop):
    """Virtual time whose every jump first sleeps ``gap_s`` of real time."""

    def __init__(self, gap_s: float) -> None:
        super().__init__()
        self.gap_s = gap_s
        self.sleep_cpu_s = 0.0
        self.jumps = 0

    def advance(self, seconds: float) -> None:
        self.jumps += 1
        if self.gap_s > 0:
            t0 = time.thread_time()
            time.sleep(self.gap_s)
            self.sleep_cpu_s += time.thread_time() - t0
        super().advance(seconds)


def robot_work(gap_s: float, virtual_s: float) -> tuple[float, float]:
    """Thread CPU per virtual second of the Robot's schedule, the sleeps' own cost left
    out, and the loop's jumps (so its sleeps) per virtual second."""
    loop = _SleepingClockLoop(gap_s)

    async def run() -> tuple[float, float]:
        async with Robot.open("sim://", watchdog_s=0.0) as robot:
            robot.drive(0.2, 0.1)
            await asyncio.sleep(1.0)
            cpu0, slept0, jumps0 = time.thread_time(), loop.sleep_cpu_s, loop.jumps
            await asyncio.sleep(virtual_s)
            cpu = time.thread_time() - cpu0 - (loop.sleep_cpu_s - slept0)
            return cpu / virtual_s, (loop.jumps - jumps0) / virtual_s

    with asyncio.Runner(loop_factory=lambda: loop) as runner:
        return runner.run(run())


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument(
        "--only",
        choices=("floor", "wakeups", "robot"),
        help="one part: the raw schedule, the wake-ups alone, or the Robot warm and cold",
    )
    args = parser.parse_args()
    print(machine())
    if args.only in (None, "floor"):
        raw_floor(args.seconds)
    if args.only in (None, "wakeups"):
        wake_costs(args.seconds)
    if args.only in (None, "robot"):
        warm_and_cold(args.seconds)
    return 0


def raw_floor(seconds: float) -> None:
    with simulator_on_pty() as path:
        for decode in (False, True):
            share, got = asyncio.run(floor(path, seconds, decode=decode))
            what = f"{got / seconds:6.0f} replies/s" if decode else f"{got} bytes in"
            label = "raw loop + decoder" if decode else "raw loop"
            print(f"{label:<20} CPU {share:6.2%} of a core   ({what})")


def wake_costs(seconds: float) -> None:
    timer_cost: dict[int, float] = {}
    for rate in (100, 400, 1000):
        share = asyncio.run(wakeups(rate, seconds))
        timer_cost[rate] = share / rate
        label = f"timers {rate}/s"
        print(f"{label:<20} CPU {share:6.2%} of a core   ({share / rate * 1e6:.0f} µs a wake-up)")
    for rate in (100, 400):
        share = sleeps(rate, seconds)
        label = f"time.sleep {rate}/s"
        print(
            f"{label:<20} CPU {share:6.2%} of a core   ({share / rate * 1e6:.0f} µs a wake-up; "
            f"an asyncio timer's costs {timer_cost[rate] / (share / rate):.1f}x)"
        )


def warm_and_cold(seconds: float) -> None:
    virtual_s = max(2.0, seconds / 3)

    def show(label: str, work: float, jumps: float, extra: str = "") -> None:
        print(
            f"{label:<20} CPU {work * 1e3:5.1f} ms per second of schedule "
            f"({work / warm:.1f}x the warm figure; {jumps:.0f} loop passes a second{extra})"
        )

    # Warm: the least of three runs (the first run of a process also warms up the
    # interpreter's specialised code, which the sleeping rows then find done).
    warm, jumps = min(robot_work(0.0, virtual_s) for _ in range(3))
    show("robot, warm", warm, jumps)
    for gap_ms in (0.2, 1.0, 3.0):
        work, jumps = robot_work(gap_ms / 1e3, virtual_s)
        extra = f"; {(work - warm) / jumps * 1e6:.0f} µs more after each"
        show(f"robot, sleep {gap_ms:g} ms", work, jumps, extra)


if __name__ == "__main__":
    sys.exit(main())
