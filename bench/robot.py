"""The Robot's whole schedule in real time: stream rates, jitter, wire, command latency, CPU.

Run: ``python bench/robot.py`` (``--seconds`` per row, 60 by default; ``--quick`` for
5 s rows); ``--ratio`` for the CPU against the floor alone (below), ``--profile`` for the
Python calls per transaction alone.

**The ratio to the floor.** On one ``ohmni sim --pty`` in its own process, rounds of
``--round-seconds`` (10) a side, ``--rounds`` (5) of them, interleaved: first the floor
(``bench/_floor.py``: a minimal asyncio master running the same schedule with raw
``os.read``/``os.write``, a timer per stream, the next request written from the reply's
callback, replies counted, not parsed), then ``Robot.open(pty)`` with every stream on
and ``drive(0.1)`` sent again every 0.1 s. Each side prints its CPU share of one core,
its event loop's waits a second, every stream's rate and its timeouts; each round the
Robot's CPU over the floor's, and at the end the median of those ratios and their
spread, over the rounds in which both sides kept the wheel stream at 49 Hz or more (a side
that fell short did less work: its CPU is no figure). Interleaved rounds in one run keep a
shared machine's load out of the ratio.
``--loop`` runs both sides on ``ohmni_tb.run``'s loop (the default), ``asyncio.run``'s,
or uvloop's (``pip install uvloop``).

**Calls per transaction** (``--profile``): the Robot on the pty under cProfile, and the
Python function calls it makes per request on the line, with the most called functions.

Each row opens ``Robot.open(...)`` with every stream on (wheels 50 Hz, three HerkuleX
servos at 30 Hz, the core board at 10 Hz, robot_state 1 Hz) and, the whole time, sends
the kind of commands a teleop does: a new open-loop wheel PWM every 50–150 ms
(``drive_pwm``, so the packet on the wire carries exactly the commanded value). A tap
under the bus notes when each wheel packet is written. Printed per row:

* every stream's achieved rate (samples over the window) against the requested one;
* control-slot start jitter (when the slot's first byte went on the wire after its due
  time; p50/p99) from the Robot's own figures;
* command → wire: from ``drive_pwm`` returning to the first wheel packet carrying the new
  value being written to the port (p50/p99), against one control period (20 ms);
* the line: measured utilisation (the simulator's busy time; ``-`` on a pty) beside the
  cost model's share for the schedule;
* CPU share of one core of the whole process over the window (``time.process_time``),
  and the event loop's wake-ups a second (its waits in the selector that were not
  already over: each costs the host a sleep and a wake-up, most of the CPU figure here).

Every row runs on ``ohmni_tb.run`` (timers to the tenth of a millisecond, as the CLI and
the daemon), and the 16 ms row also on ``asyncio.run``'s loop, whose timers fire up to a
millisecond late (``ohmni_tb.eventloop``). Rows: ``sim://`` in this process at USB
latency 0 and 16 ms and with one external servo silent (the simulator's CPU is then in
the figure: ``bench/sim_cpu.py`` measures it alone), and ``pty``: ``ohmni sim --pty`` in
its own process, so the CPU is the driver's alone, as on the robot. The last row runs
the same schedule the simple way beside it — one asyncio task per stream looping on
``await bus.transact(...)`` (``bench/schedule.py``'s loops) on the pty — and the CPU
ratio is printed. ``robot pty timers`` is the Robot with every stream on a timer of its
own (the feedback reads not queued on the bus ahead of their due times, as before
2026-11-27), beside ``robot pty``: the wake-ups and CPU the queued reads save.
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import math
import pstats
import random
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ohmni_tb.bus import Bus
from ohmni_tb.eventloop import new_event_loop, run
from ohmni_tb.protocol import Command, PacketDecoder
from ohmni_tb.protocol.drive import decode_wheel_command
from ohmni_tb.robot import LocalRobot, Robot
from ohmni_tb.robot import schedule as schedule_module
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import Transport, open_transport

sys.path.insert(0, str(Path(__file__).parent))
from _floor import FloorMaster
from _pty import simulator_on_pty
from schedule import PHASES_S, PassThrough, Stream, machine, new_bodies, periodic

POLLED = ("wheel_encoder", "servo_neck", "servo_ext1", "servo_ext2", "tbcore_status")
WHEEL_PERIOD_S = 0.020


class WheelTap(PassThrough):
    """Passes everything through; notes when each write happened, and with what bytes.

    The writes are decoded after the run (:meth:`wheel_writes`): decoding them as they go
    would put the instrument's own work into the CPU figure it helps to measure.
    """

    def __init__(self, inner: Transport) -> None:
        super().__init__(inner)
        self.robot = getattr(inner, "robot", None)
        self._loop = asyncio.get_running_loop()
        self._written: list[tuple[float, bytes]] = []

    def write_nowait(self, data: bytes) -> None:
        self.inner.write_nowait(data)
        self._written.append((self._loop.time(), data))

    def wheel_writes(self) -> list[tuple[float, tuple[int, int]]]:
        """When each wheel packet was written, and the PWM it carried."""
        decoder = PacketDecoder()
        out: list[tuple[float, tuple[int, int]]] = []
        for at, data in self._written:
            for packet in decoder.feed(data):
                if packet.cmd in (Command.S_JOG, Command.I_JOG) and packet.sid == 0xFE:
                    pwm = decode_wheel_command(packet)
                    # The right board counts mirrored: un-mirror to the commanded value.
                    out.append((at, (pwm[0], -pwm[1])))
        return out


@dataclass
class Row:
    name: str
    seconds: float
    rates: dict[str, float] = field(default_factory=dict)
    requested: dict[str, float] = field(default_factory=dict)
    jitter_p50_ms: float = math.nan
    jitter_p99_ms: float = math.nan
    latency_ms: list[float] = field(default_factory=list)
    wire: float = math.nan
    budget: float = math.nan
    cpu: float = math.nan
    wakes: float = math.nan


class WakeCounter:
    """Counts the running loop's waits in its selector that could sleep (timeout not 0);
    ``nan`` on a loop without a Python selector to count them in (uvloop)."""

    def __init__(self) -> None:
        self._selector = getattr(asyncio.get_running_loop(), "_selector", None)
        self.count = math.nan if self._selector is None else 0
        self._real = None if self._selector is None else self._selector.select

    def __enter__(self) -> WakeCounter:
        if self._selector is not None and self._real is not None:
            real = self._real

            def select(timeout: float | None = None) -> list[Any]:
                if timeout is None or timeout > 0:
                    self.count += 1
                events: list[Any] = real(timeout)
                return events

            self._selector.select = select
        return self

    def __exit__(self, *exc: object) -> None:
        if self._selector is not None:
            del self._selector.select  # the class's own again


def pct(values: list[float], q: float) -> float:
    if not values:
        return math.nan
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


async def teleop(
    robot: Robot, stop_at: float, commands: list[tuple[float, tuple[int, int]]]
) -> None:
    """New open-loop PWM every 50–150 ms, as a teleop sends; note when each was given."""
    loop = asyncio.get_running_loop()
    rng = random.Random(7)
    previous = (0, 0)
    while loop.time() < stop_at:
        pwm = previous
        while pwm == previous:
            value = rng.randrange(-300, 301, 10)
            pwm = (value, value)
        robot.drive_pwm(*pwm)
        commands.append((loop.time(), pwm))
        previous = pwm
        await asyncio.sleep(rng.uniform(0.05, 0.15))


def latencies(
    commands: list[tuple[float, tuple[int, int]]], writes: list[tuple[float, tuple[int, int]]]
) -> list[float]:
    """Command → first wheel packet written with its value, in ms."""
    out: list[float] = []
    j = 0
    for i, (at, pwm) in enumerate(commands):
        until = commands[i + 1][0] if i + 1 < len(commands) else math.inf
        while j < len(writes) and writes[j][0] < at:
            j += 1
        k = j
        while k < len(writes) and writes[k][0] < until:
            if writes[k][1] == pwm:
                out.append((writes[k][0] - at) * 1e3)
                break
            k += 1
    return out


async def run_robot(
    name: str, port: str, seconds: float, *, usb_latency_ms: int = 0, ahead: bool = True
) -> Row:
    if not ahead:
        # Every stream on a timer of its own: the feedback reads not queued ahead.
        original = schedule_module.Periodic.__init__

        def on_timers(self: schedule_module.Periodic, *args: Any, **kwargs: Any) -> None:
            kwargs["ahead"] = False
            original(self, *args, **kwargs)

        schedule_module.Periodic.__init__ = on_timers  # type: ignore[method-assign]  # A/B row
        try:
            return await run_robot(name, port, seconds, usb_latency_ms=usb_latency_ms)
        finally:
            schedule_module.Periodic.__init__ = original  # type: ignore[method-assign]
    inner = await open_transport(port)
    tap = WheelTap(inner)
    row = Row(name, seconds)
    loop = asyncio.get_running_loop()
    async with Robot.open(tap, usb_latency_ms=usb_latency_ms, watchdog_s=1.0) as robot:
        await asyncio.sleep(1.0)  # settle: discovery done, every stream running
        start = robot.stats()
        busy0 = inner.line.stats.busy_s if isinstance(inner, SimTransport) else math.nan
        cpu0 = time.process_time()
        wall0 = time.perf_counter()
        commands: list[tuple[float, tuple[int, int]]] = []
        with WakeCounter() as wakes:
            await teleop(robot, loop.time() + seconds, commands)
        cpu = time.process_time() - cpu0
        wall = time.perf_counter() - wall0
        end = robot.stats()
        busy = inner.line.stats.busy_s if isinstance(inner, SimTransport) else math.nan
        robot.drive_pwm(0, 0)
    for stream in POLLED:
        got = end.streams[stream].samples - start.streams[stream].samples
        row.rates[stream] = got / wall
        row.requested[stream] = end.streams[stream].requested_hz
    control = end.streams["wheel_encoder"]
    row.jitter_p50_ms = control.jitter_p50_ms or math.nan
    row.jitter_p99_ms = control.jitter_p99_ms or math.nan
    row.latency_ms = latencies(commands, tap.wheel_writes())
    row.wire = (busy - busy0) / wall
    row.budget = end.bus.budget_share
    row.cpu = cpu / wall
    row.wakes = wakes.count / wall
    return row


async def run_tasks(name: str, port: str, seconds: float) -> Row:
    """The same polling schedule the simple way: one task per stream on bus.transact."""
    row = Row(name, seconds)
    loop = asyncio.get_running_loop()
    async with Bus(await open_transport(port)) as bus:
        bodies = new_bodies(bus)
        streams = {key: Stream(key, 1.0 / period) for key, period in _periods().items()}
        t0 = loop.time() + 0.05
        cpu0 = time.process_time()
        wall0 = time.perf_counter()
        with WakeCounter() as wakes:
            async with asyncio.TaskGroup() as tg:
                for key, body in bodies.items():
                    tg.create_task(periodic(streams[key], body, t0, t0 + seconds, PHASES_S[key]))
        cpu = time.process_time() - cpu0
        wall = time.perf_counter() - wall0
    names = dict(zip(("wheels", "servo 3", "servo 11", "servo 12", "core"), POLLED, strict=True))
    for key, stream in streams.items():
        row.rates[names[key]] = stream.done / seconds
        row.requested[names[key]] = stream.hz
    row.cpu = cpu / wall
    row.wakes = wakes.count / wall
    return row


def _periods() -> dict[str, float]:
    return {
        "wheels": 1 / 50,
        "servo 3": 1 / 30,
        "servo 11": 1 / 30,
        "servo 12": 1 / 30,
        "core": 1 / 10,
    }


def show(row: Row) -> None:
    rates = " ".join(f"{row.rates.get(s, math.nan):6.2f}" for s in POLLED)
    latency = row.latency_ms
    print(
        f"{row.name:<16} | {rates} | {row.jitter_p50_ms:5.1f} {row.jitter_p99_ms:5.1f} | "
        f"{pct(latency, 0.5):5.1f} {pct(latency, 0.99):5.1f} {len(latency):5d} | "
        f"{'    -' if math.isnan(row.wire) else f'{row.wire:5.1%}'} "
        f"{'    -' if math.isnan(row.budget) else f'{row.budget:5.1%}'} | {row.cpu:5.1%} "
        f"{row.wakes:6.0f}"
    )


# -- the ratio to the floor ----------------------------------------------------------------

#: The streams both sides poll, as the Robot names them and as the floor does.
RATIO_STREAMS = dict(
    zip(POLLED, ("wheels", "servo 3", "servo 11", "servo 12", "core"), strict=True)
)


def loop_factory(name: str) -> Callable[[], asyncio.AbstractEventLoop]:
    """The loop a round runs on: ``ohmni`` (ohmni_tb.run's), ``asyncio`` or ``uvloop``."""
    if name == "ohmni":
        return new_event_loop
    if name == "asyncio":
        return asyncio.new_event_loop
    import uvloop  # noqa: PLC0415  # an optional benchmark dependency

    return uvloop.new_event_loop


@dataclass
class Round:
    """One side of one interleaved round: CPU share, loop passes, rates, timeouts."""

    cpu: float
    wakes: float
    rates: dict[str, float]
    timeouts: int
    skipped: int = 0


async def floor_round(path: str, seconds: float) -> Round:
    """The minimal master (``bench/_floor.py``) on the pty for ``seconds``, after 0.5 s."""
    master = FloorMaster(path)
    master.start()
    try:
        await asyncio.sleep(0.5)
        before = {s.name: (s.cycles, s.timeouts, s.skipped) for s in master.streams}
        with WakeCounter() as wakes:
            cpu0, wall0 = time.process_time(), time.perf_counter()
            await asyncio.sleep(seconds)
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    finally:
        master.close()
    rates = {s.name: (s.cycles - before[s.name][0]) / wall for s in master.streams}
    timeouts = sum(s.timeouts - before[s.name][1] for s in master.streams)
    skipped = sum(s.skipped - before[s.name][2] for s in master.streams)
    return Round(cpu / wall, wakes.count / wall, rates, timeouts, skipped)


async def robot_round(path: str, seconds: float) -> Round:
    """``Robot.open(pty)`` with every stream on, ``drive(0.1)`` re-sent every 0.1 s."""
    async with Robot.open(path) as robot:
        robot.drive(0.1)
        await asyncio.sleep(1.0)  # discovery done, every stream running
        start = robot.stats()
        with WakeCounter() as wakes:
            cpu0, wall0 = time.process_time(), time.perf_counter()
            stop_at = time.perf_counter() + seconds
            while time.perf_counter() < stop_at:
                robot.drive(0.1)
                await asyncio.sleep(0.1)
            cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
        end = robot.stats()
        robot.stop()
    rates = {
        RATIO_STREAMS[name]: (end.streams[name].samples - start.streams[name].samples) / wall
        for name in POLLED
    }
    skipped = sum(end.streams[n].skipped - start.streams[n].skipped for n in POLLED)
    return Round(
        cpu / wall, wakes.count / wall, rates, end.bus.timeouts - start.bus.timeouts, skipped
    )


#: A round counts only if both sides kept the wheel stream at least this fast (of 50 Hz).
FULL_RATE_HZ = 49.0


def ratio(seconds: float, rounds: int, loop_name: str) -> list[float]:
    """Interleaved rounds, floor then Robot, on one ``ohmni sim --pty``; print each, and
    the median ratio of the Robot's CPU to the floor's with its spread, over the rounds in
    which both sides kept their wheel stream at 49 Hz or more."""
    factory = loop_factory(loop_name)
    print(
        f"\nCPU against the floor on {loop_name}: {rounds} interleaved rounds of {seconds:g} s "
        "on one `ohmni sim --pty` (rates in Hz; requested: wheels 50, servos 30, core 10)"
    )
    names = list(RATIO_STREAMS.values())
    header = (
        f"{'round':<10} | {'CPU':>6} {'wake/s':>6} | "
        + " ".join(f"{n:>8}" for n in names)
        + f" | {'timeouts':>8} {'skipped':>7} | {'ratio':>5}"
    )
    print(header)
    print("-" * len(header))
    ratios: list[float] = []
    with simulator_on_pty() as path:
        for k in range(rounds):
            sides = []
            for label, side in (("floor", floor_round), ("robot", robot_round)):
                with asyncio.Runner(loop_factory=factory) as runner:
                    result = runner.run(side(path, seconds))
                sides.append(result)
                wakes = "     -" if math.isnan(result.wakes) else f"{result.wakes:6.0f}"
                extra = f"{result.cpu / sides[0].cpu:5.2f}" if label == "robot" else ""
                print(
                    f"{label} {k + 1:<4} | {result.cpu:6.2%} {wakes} | "
                    + " ".join(f"{result.rates[n]:8.2f}" for n in names)
                    + f" | {result.timeouts:8d} {result.skipped:7d} | {extra}"
                )
            short = [
                label
                for label, side in zip(("floor", "robot"), sides, strict=True)
                if side.rates["wheels"] < FULL_RATE_HZ
            ]
            if short:
                # A side that did not keep its schedule did less work: its CPU is no figure.
                print(f"  round {k + 1} left out: the {' and the '.join(short)} fell short")
            else:
                ratios.append(sides[1].cpu / sides[0].cpu)
    if not ratios:
        print(f"Robot / floor CPU on {loop_name}: no round kept its schedule on both sides")
        return ratios
    ordered = sorted(ratios)
    print(
        f"Robot / floor CPU on {loop_name}: median {statistics.median(ratios):.2f} "
        f"(spread {ordered[0]:.2f}..{ordered[-1]:.2f} over {len(ratios)} of {rounds} rounds)"
    )
    return ratios


async def profile_robot(path: str, seconds: float) -> None:
    """cProfile the Robot on the pty: Python calls per bus transaction, and the top callees."""
    async with LocalRobot.open(path) as robot:
        robot.drive(0.1)
        await asyncio.sleep(1.0)
        start = robot.bus.stats
        profiler = cProfile.Profile()
        profiler.enable()
        stop_at = time.perf_counter() + seconds
        while time.perf_counter() < stop_at:
            robot.drive(0.1)
            await asyncio.sleep(0.1)
        profiler.disable()
        end = robot.bus.stats
        robot.stop()
    replies = sum(d.replies for d in end.devices.values()) - sum(
        d.replies for d in start.devices.values()
    )
    requests = sum(d.requests for d in end.devices.values()) - sum(
        d.requests for d in start.devices.values()
    )
    stats = pstats.Stats(profiler)
    table = stats.stats  # type: ignore[attr-defined]  # set by Stats, not in the stubs
    # (file, line, name) -> (primitive calls, calls, ...): "~" is C (builtins, methods).
    python = sum(row[1] for (file, _, _), row in table.items() if file != "~")
    total = sum(row[1] for row in table.values())
    print(
        f"\ncProfile, Robot on the pty for {seconds:g} s: {requests} requests, {replies} "
        f"replies; {python} calls of Python functions ({total} with C functions and "
        f"methods): {python / requests:.0f} Python calls per transaction "
        f"({total / requests:.0f} with C)"
    )
    stats.sort_stats("ncalls").print_stats(40)


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--quick", action="store_true", help="5 s a row")
    parser.add_argument(
        "--ratio",
        action="store_true",
        help="only the CPU against the floor (interleaved rounds on one pty)",
    )
    parser.add_argument("--rounds", type=int, default=5, help="rounds of the ratio (5)")
    parser.add_argument(
        "--round-seconds", type=float, default=10.0, help="seconds a side of a round (10)"
    )
    parser.add_argument(
        "--loop",
        choices=("ohmni", "asyncio", "uvloop"),
        default="ohmni",
        help="the loop of the ratio: ohmni_tb.run's (default), asyncio.run's, or uvloop",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help="only cProfile the Robot on the pty: Python calls per transaction",
    )
    args = parser.parse_args()
    seconds = 5.0 if args.quick else args.seconds
    print(machine())
    if args.profile:
        with simulator_on_pty() as path:
            asyncio.Runner(loop_factory=loop_factory(args.loop)).run(
                profile_robot(path, args.round_seconds)
            )
        return 0
    if args.ratio:
        ratio(args.round_seconds, args.rounds, args.loop)
        return 0
    print(f"{seconds:g} s a row, real time; requested: wheels 50, servos 3 at 30, core 10 Hz")
    header = (
        f"{'row':<16} | {'wheel':>6} {'neck':>6} {'ext1':>6} {'ext2':>6} {'core':>6} | "
        f"{'jit50':>5} {'jit99':>5} | {'cmd50':>5} {'cmd99':>5} {'cmds':>5} | "
        f"{'wire':>5} {'model':>5} | {'CPU':>5} {'wake/s':>6}"
    )
    print(header)
    print("-" * len(header))
    rows = [
        run(run_robot("robot usb0", "sim://", seconds)),
        run(run_robot("robot usb16", "sim://?usb_latency_ms=16", seconds, usb_latency_ms=16)),
        # The same row on asyncio's own loop (epoll: timers in whole milliseconds).
        asyncio.run(
            run_robot("usb16 asyncio", "sim://?usb_latency_ms=16", seconds, usb_latency_ms=16)
        ),
        run(run_robot("robot silent 11", "sim://?silent=11", seconds)),
    ]
    for row in rows:
        show(row)
    with simulator_on_pty() as path:
        pty_row = run(run_robot("robot pty", path, seconds))
    show(pty_row)
    with simulator_on_pty() as path:
        timers_row = run(run_robot("robot pty timers", path, seconds, ahead=False))
    show(timers_row)
    with simulator_on_pty() as path:
        tasks_row = run(run_tasks("tasks pty", path, seconds))
    show(tasks_row)
    print(
        f"CPU, driver alone on the pty: Robot {pty_row.cpu:.1%} (with teleop commands and "
        f"control) vs one task per stream {tasks_row.cpu:.1%} (polling only): "
        f"ratio {pty_row.cpu / tasks_row.cpu:.2f}"
    )
    print(
        f"feedback reads queued ahead vs every stream on its own timer (pty): wake-ups "
        f"{pty_row.wakes:.0f} vs {timers_row.wakes:.0f} a second "
        f"(ratio {pty_row.wakes / timers_row.wakes:.2f}), CPU {pty_row.cpu:.1%} vs "
        f"{timers_row.cpu:.1%} (ratio {pty_row.cpu / timers_row.cpu:.2f})"
    )
    precise, coarse = rows[1], rows[2]
    worst = min(POLLED, key=lambda s: coarse.rates[s] / coarse.requested[s])
    print(
        f"usb16, ohmni_tb.run vs asyncio.run: slowest stream {worst} "
        f"{precise.rates[worst]:.2f} vs {coarse.rates[worst]:.2f} Hz, control jitter p99 "
        f"{precise.jitter_p99_ms:.1f} vs {coarse.jitter_p99_ms:.1f} ms"
    )
    print("units: Hz | ms | ms | share of the line | share of one core")
    ratio(args.round_seconds, args.rounds, args.loop)
    return 0


if __name__ == "__main__":
    sys.exit(main())
