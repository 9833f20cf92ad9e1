"""Back-to-back servo reads over the simulated bus, against the wire-limited maximum.

Run: ``python bench/servo.py`` (``--seconds`` per measurement).

The simulated line is byte-accurate: a byte takes 10 / 115200 s, the servo answers after a
turnaround. A 2-byte RAM read is a 9-byte request and a 13-byte reply, 22 bytes = 1.91 ms
of wire, so no driver can exceed 524 reads/s at 115200 baud. Each read here waits for
the one before (one caller, no pipelining to gain), so the figure is the per-transaction
overhead of the engine: the bus engine (``new``) and the request-at-a-time engine it
replaced (``old``, ``bench/_old_bus.py``), with the default guard (0.2 ms new, 1 ms old)
and the simulator's 0.5 ms turnaround, then with both at 0; in real time (Python and the
event loop count) and in virtual time (the model alone).
"""

from __future__ import annotations

import argparse
import asyncio
import platform
import sys
from pathlib import Path

from ohmni_tb.bus import DEFAULT_GUARD_S, Bus
from ohmni_tb.herkulex import ram_read
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.transport import open_transport

sys.path.insert(0, str(Path(__file__).parent))
from _old_bus import DEFAULT_GAP_S, OldBus

_BAUD = 115_200
_REQUEST_BYTES = 9
_REPLY_BYTES = 13  # 2-byte read: header 7 + addr, len + 2 bytes + 2 status bytes


async def measure(
    engine: str, seconds: float, defaults: bool, turnaround_us: int
) -> tuple[float, float]:
    """Reads/s and the p99 latency (ms) of back-to-back reads of the neck's position."""
    transport = await open_transport(f"sim://?turnaround_us={turnaround_us}")
    bus: Bus | OldBus
    if engine == "new":
        bus = Bus(transport) if defaults else Bus(transport, guard_s=0.0, turnaround_s=0.0)
    else:
        bus = OldBus(transport) if defaults else OldBus(transport, gap_s=0.0)
    async with bus:
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
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0)
    args = parser.parse_args()

    wire_s = (_REQUEST_BYTES + _REPLY_BYTES) * 10 / _BAUD
    wire_max = 1 / wire_s
    print(f"python {platform.python_version()}, {platform.machine()}")
    print(f"wire-limited maximum: {wire_max:.0f} reads/s ({wire_s * 1e3:.2f} ms a read)")
    print(
        f"{'engine':>6} {'guard':>6} {'turnaround':>11} {'clock':>8} {'reads/s':>9} "
        f"{'x max':>7} {'p99 ms':>7}"
    )
    for defaults, turnaround_us in ((True, 500), (False, 0)):
        for engine in ("old", "new"):
            guard_s = 0.0 if not defaults else DEFAULT_GUARD_S if engine == "new" else DEFAULT_GAP_S
            for clock in ("real", "virtual"):
                coro = measure(engine, args.seconds, defaults, turnaround_us)
                rate, p99 = asyncio.run(coro) if clock == "real" else run_virtual(coro)
                print(
                    f"{engine:>6} {guard_s * 1e3:4.1f}ms {turnaround_us:9d}us {clock:>8} "
                    f"{rate:9.0f} {rate / wire_max:7.2f} {p99:7.2f}"
                )
        floor_s = wire_s + turnaround_us * 1e-6
        print(f"{'':36}wire + turnaround: {1 / floor_s:5.0f} reads/s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
