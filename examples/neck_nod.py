"""Nod the HerkuleX neck inside its safe range, then rest it.

    python examples/neck_nod.py                           # the simulator (default)
    python examples/neck_nod.py --port /dev/ttyUSB0

The neck is servo 3 and its safe range is 280..650 raw. The servo is freed on the way out
whatever happens: holding torque at the wake position overheats it.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from ohmni_tb.bus import Bus
from ohmni_tb.herkulex import TorqueControl
from ohmni_tb.herkulex.servo import Servo
from ohmni_tb.transport import open_transport


async def nod(port: str, times: int) -> int:
    async with Bus(await open_transport(port)) as bus:
        neck = Servo(bus, 3)  # the neck: held to NECK_RAW_RANGE (280..650)
        print(f"neck: {(await neck.model()).name}, at {await neck.position_raw()}")
        await neck.torque(TorqueControl.ON)
        try:
            for _ in range(times):
                for target in (400, 560):
                    await neck.move_to(target, playtime_s=0.6)
                    await asyncio.sleep(0.65)
                    print(f"  at {await neck.position_raw()} ({await neck.angle_rad():+.3f} rad)")
        finally:
            await asyncio.shield(neck.torque(TorqueControl.FREE))
        print(f"neck: {await neck.status()}, temperature raw {await neck.temperature_raw()}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", default="sim://")
    parser.add_argument("--times", type=int, default=2)
    args = parser.parse_args()
    return asyncio.run(nod(args.port, args.times))


if __name__ == "__main__":
    sys.exit(main())
