"""Servo reads per second over the simulated bus, against the wire-limited maximum.

Run: ``python bench/servo.py`` (``--seconds`` per measurement).

The simulated line is byte-accurate: a byte takes 10 / 115200 s, the servo answers after a
turnaround. A 2-byte RAM read is a 9-byte request and a 13-byte reply, 22 bytes = 1.91 ms
of wire, so no driver can exceed 524 reads/s at 115200 baud. The table shows what the bus
achieves with the default request gap (1 ms) and turnaround (0.5 ms), and with both at 0
(the bus's own overhead only), in real time (Python and the event loop count) and in
virtual time (the model alone).
"""

from __future__ import annotations

import argparse
import asyncio
import platform
import sys

from ohmni_tb.bus import Bus
from ohmni_tb.herkulex import ram_read
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.transport import open_transport

_BAUD = 115_200
_REQUEST_BYTES = 9
_REPLY_BYTES = 13  # 2-byte read: header 7 + addr, len + 2 bytes + 2 status bytes


async def measure(seconds: float, guard_s: float, turnaround_us: int) -> tuple[float, float]:
    """Reads/s and the p99 latency (ms) of back-to-back reads of the neck's position."""
    transport = await open_transport(f"sim://?turnaround_us={turnaround_us}")
    async with Bus(transport, guard_s=guard_s) as bus:
        loop = asyncio.get_running_loop()
        request = ram_read(3, "calibrated_position")
        for _ in range(20):  # warm up
            await bus.request(request)
        n = 0
        t0 = loop.time()
        while loop.time() - t0 < seconds:
            await bus.request(request)
            n += 1
        rate = n / (loop.time() - t0)
        p99 = bus.stats.devices[3].latency_p99_s or 0.0
    return rate, p99 * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args()

    wire_s = (_REQUEST_BYTES + _REPLY_BYTES) * 10 / _BAUD
    wire_max = 1 / wire_s
    print(f"python {platform.python_version()}, {platform.machine()}")
    print(f"wire-limited maximum: {wire_max:.0f} reads/s ({wire_s * 1e3:.2f} ms a read)")
    print(f"{'gap':>6} {'turnaround':>11} {'clock':>8} {'reads/s':>9} {'x max':>7} {'p99 ms':>7}")
    for guard_s, turnaround_us in ((0.001, 500), (0.0, 0)):
        floor_s = wire_s + guard_s + turnaround_us * 1e-6
        for clock in ("real", "virtual"):
            coro = measure(args.seconds, guard_s, turnaround_us)
            rate, p99 = asyncio.run(coro) if clock == "real" else run_virtual(coro)
            print(
                f"{guard_s * 1e3:4.1f}ms {turnaround_us:9d}us {clock:>8} {rate:9.0f} "
                f"{rate / wire_max:7.2f} {p99:7.2f}"
            )
        print(f"{'':28}model floor {1 / floor_s:5.0f} reads/s for this gap and turnaround")
    return 0


if __name__ == "__main__":
    sys.exit(main())
