"""What the simulator costs: CPU share of one core and µs per request, in real time.

Run: ``python bench/sim_cpu.py`` (``--seconds`` per measurement, ``--rounds`` to keep the
best of several).

A small client drives the simulated line with raw request frames — no Bus — one request
in flight at a time, each stream on absolute deadlines:

* **wheel counts**: the left wheel's count (RAM 59, 4 bytes) at 200 reads/s;
* **full mix**: every 20 ms both wheel counts and a wheel command (the control slot),
  the position of servos 3, 11 and 12 at 30 Hz each, the core board's status at 10 Hz
  (about 250 requests/s).

Each load runs on three ends: ``floor`` (a responder that answers every request with
canned bytes at the wire's time: the client and the event loop alone), ``old`` (the line
as it was — a task per simulator behind an in-memory pipe, every device advanced for
every packet; kept in ``bench/_old_sim_line.py``) and ``new`` (``sim://``: no task,
devices advanced only when a packet concerns them). The CPU share is
``time.process_time()`` over wall time for the whole process; µs/request divides the
CPU time by the requests answered; "above floor" is what the simulator itself adds.

Measured on AMD EPYC (2 cores), Python 3.11.7, 2026-11-23, with the other engineers'
servo and drive-board work of that day::

    load          end      req/s  CPU % of a core  µs/request  above floor
    wheel counts  floor      200             2.0%         101
    wheel counts  old        200             3.7%         184           83
    wheel counts  new        200             2.1%         107            6
    full mix      floor      250             2.0%          79
    full mix      old        250             5.3%         214          135
    full mix      new        250             2.8%         111           32

The machine is shared and noisy: compare ends within one run, not across runs.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import platform
import sys
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path

from ohmni_tb.herkulex import ram_read
from ohmni_tb.protocol import Packet, PacketDecoder, encode_packet
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.protocol.timing import transaction_cost_s, wire_time_s
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.transport import MemoryTransport, Transport, open_transport

sys.path.insert(0, str(Path(__file__).parent))
from _old_sim_line import OldSimLine

#: A stream: its period and the packet it sends.
Stream = tuple[float, Packet]
#: Opens a host end on a fresh simulated robot; returns it and a closer.
Opener = Callable[[], Awaitable[tuple[Transport, Callable[[], Awaitable[None]]]]]

_REPLY_TIMEOUT_S = 0.05

WHEEL_COUNTS: list[Stream] = [(1 / 200, read_count(0))]
FULL_MIX: list[Stream] = [
    (0.020, read_count(0)),
    (0.020, read_count(1)),
    (0.020, wheel_command(300, 300)),
    *((1 / 30, ram_read(sid, "calibrated_position")) for sid in (3, 11, 12)),
    (0.100, read_status()),
]


@dataclass
class Result:
    """One measurement."""

    requests: int
    wall_s: float
    cpu_s: float

    @property
    def share(self) -> float:
        return self.cpu_s / self.wall_s

    @property
    def us_per_request(self) -> float:
        return self.cpu_s / self.requests * 1e6

    @property
    def rate(self) -> float:
        return self.requests / self.wall_s


class Client:
    """Sends the streams' requests one at a time and counts the answered ones."""

    def __init__(self, transport: Transport, streams: list[Stream]) -> None:
        self.transport = transport
        self.loop = asyncio.get_running_loop()
        self.decoder = PacketDecoder()
        self.queue: deque[Packet] = deque()
        self.busy = False
        self.done = 0
        self.timers: dict[int, asyncio.TimerHandle] = {}
        self.guard: asyncio.TimerHandle | None = None
        self.frames = {id(p): encode_packet(p) for _, p in streams}
        self.quiet_s = {id(p): transaction_cost_s(p) for _, p in streams}
        transport.start_receiving(self.on_data, self.on_lost)
        start = self.loop.time()
        for index, (period, packet) in enumerate(streams):
            self.tick(index, start, period, packet)

    def tick(self, index: int, when: float, period: float, packet: Packet) -> None:
        self.queue.append(packet)
        if not self.busy:
            self.send()
        following = when + period
        self.timers[index] = self.loop.call_at(
            following, self.tick, index, following, period, packet
        )

    def send(self) -> None:
        if not self.queue:
            self.busy = False
            return
        packet = self.queue.popleft()
        self.busy = True
        self.transport.write_nowait(self.frames[id(packet)])
        # A broadcast gets no reply: the slot ends after its wire time; a lost reply
        # ends it after a timeout.
        wait_s = self.quiet_s[id(packet)] if packet.sid == 0xFE else _REPLY_TIMEOUT_S
        self.guard = self.loop.call_later(wait_s, self.finished)

    def finished(self) -> None:
        if self.guard is not None:
            self.guard.cancel()
            self.guard = None
        self.done += 1
        self.send()

    def on_data(self, chunk: bytes) -> None:
        for _ in self.decoder.feed(chunk):
            self.finished()

    def on_lost(self, exc: Exception) -> None:
        raise RuntimeError(f"link lost during the benchmark: {exc}")

    def stop(self) -> None:
        for timer in self.timers.values():
            timer.cancel()
        if self.guard is not None:
            self.guard.cancel()


async def measure(opener: Opener, streams: list[Stream], seconds: float) -> Result:
    transport, close = await opener()
    client = Client(transport, streams)
    try:
        await asyncio.sleep(0.3)  # warm up
        done0, wall0, cpu0 = client.done, time.perf_counter(), time.process_time()
        await asyncio.sleep(seconds)
        done1, wall1, cpu1 = client.done, time.perf_counter(), time.process_time()
    finally:
        client.stop()
        await close()
    return Result(done1 - done0, wall1 - wall0, cpu1 - cpu0)


async def open_new() -> tuple[Transport, Callable[[], Awaitable[None]]]:
    transport = await open_transport("sim://")
    return transport, transport.aclose


async def open_old() -> tuple[Transport, Callable[[], Awaitable[None]]]:
    robot = SimRobot()
    line = OldSimLine(robot.devices)
    robot.attach_clock(line.now_s)
    host, device = MemoryTransport.pair("old-sim", baudrate=line.baudrate)
    task = asyncio.create_task(line.serve(device))

    async def close() -> None:
        await host.aclose()
        await device.aclose()
        task.cancel()
        await asyncio.wait({task})

    return host, close


async def open_floor() -> tuple[Transport, Callable[[], Awaitable[None]]]:
    """A responder with canned replies at the wire's time: what the client costs alone."""
    robot = SimRobot()
    line = OldSimLine(robot.devices)
    canned: dict[bytes, bytes] = {}
    for _, packet in FULL_MIX + WHEEL_COUNTS:
        replies = [d.handle(packet, 0.0) for d in line.devices]
        answer = next((r for r in replies if r is not None), None)
        canned[encode_packet(packet)] = encode_packet(answer) if answer else b""
    host, device = MemoryTransport.pair("floor")
    loop = asyncio.get_running_loop()
    handles: set[asyncio.TimerHandle] = set()

    def on_request(frame: bytes) -> None:
        reply = canned[frame]
        if reply:
            at = loop.time() + wire_time_s(len(frame) + len(reply)) + 0.0005
            handles.add(loop.call_at(at, device.write_nowait, reply))

    device.start_receiving(on_request, lambda exc: None)

    async def close() -> None:
        for handle in handles:
            handle.cancel()
        await host.aclose()
        await device.aclose()

    return host, close


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--rounds", type=int, default=3, help="keep the best of this many")
    args = parser.parse_args()
    print(f"python {platform.python_version()} on {_cpu_name()}, {os.cpu_count()} cores")
    print(f"{args.seconds:g} s a measurement, best of {args.rounds}, real time")
    print(
        f"{'load':<14}{'end':<7}{'req/s':>7}{'CPU % of a core':>17}{'µs/request':>12}"
        f"{'above floor':>13}"
    )
    for name, streams in (("wheel counts", WHEEL_COUNTS), ("full mix", FULL_MIX)):
        floor_us = 0.0
        for end, opener in (("floor", open_floor), ("old", open_old), ("new", open_new)):
            runs = [asyncio.run(measure(opener, streams, args.seconds)) for _ in range(args.rounds)]
            best = min(runs, key=lambda r: r.share)
            if end == "floor":
                floor_us = best.us_per_request
                above = ""
            else:
                above = f"{best.us_per_request - floor_us:.0f}"
            print(
                f"{name:<14}{end:<7}{best.rate:>7.0f}{best.share * 100:>16.1f}%"
                f"{best.us_per_request:>12.0f}{above:>13}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
