"""One script, two ways to reach the robot: its own Robot, or the daemon's (``ohmni serve``).

    python examples/embedded_or_daemon.py                      # opens sim:// itself
    ohmni serve --port sim:// &                                 # or: the daemon owns the port
    python examples/embedded_or_daemon.py --daemon ws://127.0.0.1:8766

``Robot.open`` takes either: a port (``sim://``, ``/dev/ttyUSB0``) opens the robot in this
process, a daemon's ``ws://`` address reaches the one ``ohmni serve`` runs — the same
``Robot`` API either way, so only the address differs. Through the daemon the first
command takes the control lease (one driver at a time); other programs can watch
meanwhile (``ohmni status``).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys

import ohmni_tb
from ohmni_tb import Robot


async def patrol(robot: Robot, *, speed_mps: float, seconds: float) -> float:
    """Drive forward for ``seconds``, stop; return the distance the odometry measured."""
    loop = asyncio.get_running_loop()
    async with robot.subscribe("wheel_odom", maxlen=1) as odom:
        start = await anext(odom)
        until = loop.time() + seconds
        while loop.time() < until:
            robot.drive(speed_mps, 0.0)  # within the watchdog time: keeps it moving
            await asyncio.sleep(0.05)
        robot.stop()
        end = start
        async for sample in odom:  # until it stands still
            end = sample
            if abs(sample.linear_mps) < 0.005:
                break
    return math.hypot(end.x_m - start.x_m, end.y_m - start.y_m)


async def main(daemon: str | None) -> int:
    async with Robot.open(daemon or "sim://") as robot:
        travelled = await patrol(robot, speed_mps=0.3, seconds=1.0)
    where = f"the daemon at {daemon}" if daemon else "its own Robot on sim://"
    print(f"drove {travelled:.3f} m through {where}")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--daemon", metavar="URL", help="use ohmni serve at URL")
    # ohmni_tb.run: asyncio.run on a loop whose timers keep the bus's schedule (robot.md).
    sys.exit(ohmni_tb.run(main(parser.parse_args().daemon)))
