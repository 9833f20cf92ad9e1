"""tb_control's fixed-rate schedule on the simulated bus: rates, jitter, wire, CPU.

Run: ``python bench/schedule.py`` (``--seconds`` per row, 30 by default; ``--quick`` for
a short smoke run).

The load is the Robot's: every 20 ms the control slot (both wheel counts and one wheel
command), each HerkuleX servo (3, 11, 12) read at 30 Hz (RAM 48..59: status, torque,
voltage, temperature, position), the core board's status at 10 Hz — one loop per stream
on absolute deadlines (a cycle starts on time while the previous one still waits for its
replies, at most two in flight), the streams' phases staggered the way a schedule should
stagger them. It runs in real time on ``sim://``,
whose line is byte-timed — in this process, or (rows marked ``/pty``) served by
``ohmni sim --pty`` in its own process, so the CPU figure is the driver's alone — with:

* ``new``: :class:`ohmni_tb.bus.Bus` — the control slot is one ``transact`` at priority
  10 that must start within 15 ms of its due time, servos at priority 5, the core at 1,
  each due before its next cycle;
* ``old``: the request-at-a-time engine this one replaced (``bench/_old_bus.py``, kept
  verbatim): the same loops, one ``query``/``send`` after another behind its lock.

Each row prints the achieved rate of every stream against the requested one (a wheel
cycle counts when both counts came back), the control slot's start jitter (first byte of
the left-count request after its due time, p50/p99), the line's measured utilisation
beside the cost model's share for the schedule, and the CPU share of one core of the
whole process (the simulator runs in it too: ``bench/sim_cpu.py`` measures its part).
``usb`` is the simulated adapter's latency timer (``sim://?usb_latency_ms=N``);
``silent`` lists servos that never answer. Every row runs on ``ohmni_tb.run``'s loop
(timers to the tenth of a millisecond, as the CLI and the daemon; ``ohmni_tb.eventloop``).
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import math
import os
import platform
import sys
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path

from ohmni_tb import eventloop
from ohmni_tb.bus import Bus
from ohmni_tb.errors import BusTimeoutError, DeadlineMissedError, OhmniError
from ohmni_tb.protocol import Packet, encode_packet, read_request
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.protocol.timing import transaction_cost_s
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import Transport, open_transport
from ohmni_tb.transport.base import LostHandler, Receiver

sys.path.insert(0, str(Path(__file__).parent))
from _old_bus import OldBus
from _pty import simulator_on_pty

WHEEL_HZ = 50.0
SERVO_HZ = 30.0
CORE_HZ = 10.0
SERVOS = (3, 11, 12)
#: The control slot must start this soon after its due time, or it is dropped: three
#: quarters of a period, as the Robot's (robot.control_loop.CONTROL_SLACK, which says why).
WHEEL_SLACK_S = 0.015

LEFT, RIGHT, STOP = read_count(0), read_count(1), wheel_command(0, 0)
#: Streams start staggered, as a schedule should: the servos spread over their period
#: and the core between control slots, so the 50 Hz and 30 Hz grids do not pile every
#: stream onto one instant each 100 ms.
PHASES_S = {
    "wheels": 0.0,
    **{f"servo {sid}": 0.010 + k / SERVO_HZ / len(SERVOS) for k, sid in enumerate(SERVOS)},
    "core": 0.013,
}


def servo_read(sid: int) -> Packet:
    """RAM 48..59: status error/detail, torque, LED, voltage, temperature… position."""
    return read_request(sid, 48, 12)


def model_share() -> float:
    """The cost model's share of the line for the whole schedule."""
    wheel = sum(transaction_cost_s(p) for p in (LEFT, RIGHT, STOP)) * WHEEL_HZ
    servos = sum(transaction_cost_s(servo_read(sid)) for sid in SERVOS) * SERVO_HZ
    core = transaction_cost_s(read_status()) * CORE_HZ
    return wheel + servos + core


class PassThrough(Transport):
    """A transport that hands everything to ``inner``: the base of the benchmarks' taps."""

    def __init__(self, inner: Transport) -> None:
        self.inner = inner
        self.baudrate = inner.baudrate

    @property
    def closed(self) -> bool:
        return self.inner.closed

    @property
    def backlog(self) -> int:
        return self.inner.backlog

    async def drain(self) -> None:
        await self.inner.drain()

    def write_nowait(self, data: bytes) -> None:
        self.inner.write_nowait(data)

    async def read(self) -> bytes:
        return await self.inner.read()

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        self.inner.start_receiving(on_data, on_lost)

    async def aclose(self) -> None:
        await self.inner.aclose()


class Tap(PassThrough):
    """Passes everything through; notes when each left-count request is written."""

    def __init__(self, inner: Transport, frame: bytes) -> None:
        super().__init__(inner)
        self.frame = frame
        self.starts: list[float] = []

    def write_nowait(self, data: bytes) -> None:
        if data == self.frame:
            self.starts.append(asyncio.get_running_loop().time())
        self.inner.write_nowait(data)


@dataclass
class Stream:
    """One periodic stream's tally."""

    name: str
    hz: float
    done: int = 0
    skipped: int = 0

    def achieved_hz(self, seconds: float) -> float:
        return self.done / seconds


@dataclass
class Row:
    engine: str
    usb_ms: int
    silent: tuple[int, ...]
    seconds: float
    streams: list[Stream]
    jitter_ms: list[float] = field(default_factory=list)
    wire_share: float = 0.0
    cpu_share: float = 0.0
    host_collisions: int = 0


Body = Callable[[float], Awaitable[bool]]


async def periodic(
    stream: Stream, body: Body, t0: float, stop_at: float, phase_s: float = 0.0
) -> None:
    """Start ``body`` every period on absolute deadlines.

    A cycle starts on time even while the previous one still waits for its replies (an
    adapter may hold them 16 ms, most of a 20 ms period); with two of its cycles already
    in flight a stream skips the cycle instead of piling up.
    """
    loop = asyncio.get_running_loop()
    period = 1.0 / stream.hz
    t0 += phase_s
    in_flight: set[asyncio.Task[None]] = set()

    async def cycle(due: float) -> None:
        if await body(due):
            stream.done += 1

    k = 0
    while True:
        due = t0 + k * period
        if due >= stop_at:
            break
        delay = due - loop.time()
        if delay > 0:
            await asyncio.sleep(delay)
        if len(in_flight) >= 2:
            stream.skipped += 1
        else:
            task = asyncio.ensure_future(cycle(due))
            in_flight.add(task)
            task.add_done_callback(in_flight.discard)
        k += 1
    if in_flight:
        await asyncio.gather(*in_flight)


def new_bodies(bus: Bus) -> dict[str, Body]:
    async def wheels(due: float) -> bool:
        try:
            replies = await bus.transact(
                [LEFT, RIGHT, STOP], priority=10, deadline=due + WHEEL_SLACK_S
            )
        except DeadlineMissedError:
            return False
        return replies[0] is not None and replies[1] is not None

    def servo(sid: int) -> Body:
        async def read(due: float) -> bool:
            try:
                [reply] = await bus.transact(
                    [servo_read(sid)], priority=5, deadline=due + 1 / SERVO_HZ
                )
            except DeadlineMissedError:
                return False
            return reply is not None

        return read

    async def core(due: float) -> bool:
        try:
            [reply] = await bus.transact([read_status()], priority=1, deadline=due + 1 / CORE_HZ)
        except DeadlineMissedError:
            return False
        return reply is not None

    return {"wheels": wheels, **{f"servo {s}": servo(s) for s in SERVOS}, "core": core}


def old_bodies(bus: OldBus) -> dict[str, Body]:
    async def wheels(due: float) -> bool:
        try:
            await bus.query(LEFT)
            await bus.query(RIGHT)
            await bus.send(STOP)
        except BusTimeoutError:
            return False
        return True

    def servo(sid: int) -> Body:
        async def read(due: float) -> bool:
            try:
                await bus.query(servo_read(sid))
            except BusTimeoutError:
                return False
            return True

        return read

    async def core(due: float) -> bool:
        try:
            await bus.query(read_status())
        except BusTimeoutError:
            return False
        return True

    return {"wheels": wheels, **{f"servo {s}": servo(s) for s in SERVOS}, "core": core}


async def run(
    engine: str, seconds: float, usb_ms: int, silent: tuple[int, ...], *, port: str | None = None
) -> Row:
    """One row: on an in-process ``sim://``, or on ``port`` (a simulator served apart)."""
    if port is not None:
        return await _run(engine, seconds, usb_ms, silent, inner=await open_transport(port))
    query = f"usb_latency_ms={usb_ms}"
    if silent:
        query += "&silent=" + ",".join(map(str, silent))
    sim = await open_transport(f"sim://?{query}")
    assert isinstance(sim, SimTransport)
    return await _run(engine, seconds, usb_ms, silent, inner=sim, sim=sim)


def run_on_pty(engine: str, seconds: float) -> Row:
    """One row against ``ohmni sim --pty`` in its own process: this process's CPU is then
    the driver's alone, as on the robot."""
    with simulator_on_pty() as path:
        return eventloop.run(run(engine, seconds, 0, (), port=path))


async def _run(
    engine: str,
    seconds: float,
    usb_ms: int,
    silent: tuple[int, ...],
    *,
    inner: Transport,
    sim: SimTransport | None = None,
) -> Row:
    tap = Tap(inner, encode_packet(LEFT))
    streams = {
        "wheels": Stream("wheels", WHEEL_HZ),
        **{f"servo {s}": Stream(f"servo {s}", SERVO_HZ) for s in SERVOS},
        "core": Stream("core", CORE_HZ),
    }
    loop = asyncio.get_running_loop()
    bus: Bus | OldBus
    if engine == "new":
        bus = Bus(tap)
        bodies = new_bodies(bus)
    else:
        bus = OldBus(tap)
        bodies = old_bodies(bus)
    async with bus:
        t0 = loop.time() + 0.05
        busy0 = sim.line.stats.busy_s if sim is not None else 0.0
        cpu0 = time.process_time()
        wall0 = time.perf_counter()
        stop_at = t0 + seconds
        async with asyncio.TaskGroup() as tg:
            for name, body in bodies.items():
                tg.create_task(periodic(streams[name], body, t0, stop_at, PHASES_S[name]))
        cpu = time.process_time() - cpu0
        wall = time.perf_counter() - wall0
        busy = sim.line.stats.busy_s - busy0 if sim is not None else math.nan
    starts = tap.starts
    jitter: list[float] = []
    for k in range(round(seconds * WHEEL_HZ)):
        due = t0 + k / WHEEL_HZ
        # The first left-count request written in this cycle started its slot.
        i = bisect.bisect_left(starts, due)
        if i < len(starts) and starts[i] < due + 1 / WHEEL_HZ:
            jitter.append((starts[i] - due) * 1e3)
    return Row(
        engine=engine if sim is not None else f"{engine}/pty",
        usb_ms=usb_ms,
        silent=silent,
        seconds=seconds,
        streams=list(streams.values()),
        jitter_ms=sorted(jitter),
        wire_share=busy / seconds,
        cpu_share=cpu / wall,
        host_collisions=sim.line.stats.host_collisions if sim is not None else -1,
    )


def pct(values: list[float], q: float) -> float:
    if not values:
        return math.nan
    return values[min(len(values) - 1, round(q * (len(values) - 1)))]


def _share(value: float) -> str:
    return "    -" if math.isnan(value) else f"{value:5.1%}"


def machine() -> str:
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"python {platform.python_version()} on {model}, {os.cpu_count()} cores"


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--quick", action="store_true", help="3 s a row")
    args = parser.parse_args()
    seconds = 3.0 if args.quick else args.seconds
    configs: list[tuple[str, int, tuple[int, ...], bool]] = [
        ("old", 0, (), False),
        ("new", 0, (), False),
        ("old", 1, (), False),
        ("new", 1, (), False),
        ("old", 16, (), False),
        ("new", 16, (), False),
        ("old", 0, (11,), False),
        ("new", 0, (11,), False),
        ("old", 0, (11, 12), False),
        ("new", 0, (11, 12), False),
        ("old", 0, (), True),
        ("new", 0, (), True),
    ]
    print(machine())
    print(
        f"schedule: wheels {WHEEL_HZ:g} Hz (2 reads + 1 command), servos {SERVOS} "
        f"{SERVO_HZ:g} Hz, core {CORE_HZ:g} Hz; {seconds:g} s a row, real time, sim://"
    )
    print(f"cost model's share of the line for this schedule: {model_share():.1%}")
    header = (
        f"{'engine':>8} {'usb':>4} {'silent':>7} | {'wheels':>6} {'srv3':>5} {'srv11':>5} "
        f"{'srv12':>5} {'core':>5} Hz | {'jit p50':>7} {'p99':>6} ms | {'wire':>5} "
        f"{'CPU':>5} {'coll':>4}"
    )
    print(header)
    print("-" * len(header))
    target = (
        f"{'target':>8} {'':>4} {'':>7} | {WHEEL_HZ:6.1f} {SERVO_HZ:5.1f} {SERVO_HZ:5.1f} "
        f"{SERVO_HZ:5.1f} {CORE_HZ:5.1f}    |"
    )
    print(target)
    for engine, usb_ms, silent, pty in configs:
        try:
            if pty:
                row = run_on_pty(engine, seconds)
            else:
                row = eventloop.run(run(engine, seconds, usb_ms, silent))
        except OhmniError as exc:  # a baseline that fails outright is a figure too
            where = f"{engine}/pty" if pty else engine
            print(f"{where:>8} {usb_ms:4d} {','.join(map(str, silent)) or '-':>7} | failed: {exc}")
            continue
        rates = [s.achieved_hz(seconds) for s in row.streams]
        if os.environ.get("SCHEDULE_DEBUG"):
            print([(s.name, s.done, s.skipped) for s in row.streams])
        print(
            f"{row.engine:>8} {usb_ms:4d} {','.join(map(str, silent)) or '-':>7} | "
            f"{rates[0]:6.1f} {rates[1]:5.1f} {rates[2]:5.1f} {rates[3]:5.1f} {rates[4]:5.1f}"
            f"    | {pct(row.jitter_ms, 0.5):7.2f} {pct(row.jitter_ms, 0.99):6.2f}    | "
            f"{_share(row.wire_share)} {row.cpu_share:5.1%} "
            f"{row.host_collisions if row.host_collisions >= 0 else '-':>4}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
