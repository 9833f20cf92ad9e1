"""How a noisy line shows up at the bus: timeouts, retries, and wrong values let through.

Run: ``python bench/faults.py`` (``--reads`` per row).

Reads a register of known value from the simulated neck servo, over and over, on a line
that drops or corrupts a share of its bytes (seeded, virtual time, so every run prints the
same table). Each read ends one of four ways: the right value, a ``BusTimeoutError``
after the retries, refused at once (``DeviceUnavailableError``: so many misses in a row
that the bus presumed the servo gone; the loop then waits for the next probe, as a
caller should), or — the figure that matters — a wrong value that passed every check.
The HerkuleX checksums ignore bit 0 (``cs1 = xor & 0xFE``), so a flip of bit 0 in a data
byte cannot be seen by any receiver; this measures how often that reaches a caller.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from ohmni_tb.bus import Bus
from ohmni_tb.errors import BusTimeoutError, DeviceUnavailableError, MalformedReplyError
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport

#: EEP 30..33 of a factory servo: Kp = 440, Kd = 8000 (4 bytes of known value).
_ADDR, _LENGTH, _EXPECTED = 30, 4, bytes.fromhex("B8 01 40 1F")


async def run(reads: int, drop: float, corrupt: float) -> tuple[int, int, int, int, int, int]:
    """Counts of (right, timed out, refused, malformed, wrong, retries) over ``reads``."""
    url = f"sim://?drop={drop}&corrupt={corrupt}&seed=1&ext=none"
    transport = await open_transport(url)
    assert isinstance(transport, SimTransport)
    right = timed_out = refused = malformed = wrong = 0
    async with Bus(transport) as bus:
        # The reference's reads are EEP reads; RAM 24..27 hold the same gains.
        for _ in range(reads):
            try:
                reply = await bus.read(3, _ADDR - 6, _LENGTH)
            except DeviceUnavailableError as exc:
                refused += 1
                await asyncio.sleep(exc.retry_in_s)
                continue
            except BusTimeoutError:
                timed_out += 1
                continue
            except MalformedReplyError:
                malformed += 1
                continue
            if reply.data == _EXPECTED:
                right += 1
            else:
                wrong += 1
        retries = bus.stats.devices[3].retries
    return right, timed_out, refused, malformed, wrong, retries


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reads", type=int, default=10_000)
    args = parser.parse_args()
    print(f"{args.reads} reads of 4 known bytes from the simulated neck, 2 retries each")
    print(
        f"{'drop':>6} {'corrupt':>8} {'right':>7} {'timeout':>8} {'refused':>8} {'malformed':>9} "
        f"{'WRONG':>6} {'retries':>8} {'wrong per 1M reads':>19}"
    )
    for drop, corrupt in ((0.0, 0.0), (0.001, 0.0), (0.01, 0.0), (0.0, 0.001), (0.0, 0.01)):
        counts = run_virtual(run(args.reads, drop, corrupt))
        right, timed_out, refused, malformed, wrong, retries = counts
        per_million = wrong / args.reads * 1e6
        print(
            f"{drop:6.3f} {corrupt:8.3f} {right:7d} {timed_out:8d} {refused:8d} {malformed:9d} "
            f"{wrong:6d} {retries:8d} {per_million:19.0f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
