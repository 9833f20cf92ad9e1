"""Read what the robot reports: firmware tags, battery and dock, wheel counts.

    python examples/read_sensors.py                       # the simulator (default)
    python examples/read_sensors.py --port /dev/ttyUSB0   # a robot (tb-node stopped)

Nothing moves. Every read goes through the same Bus a control loop uses, and the bus's
per-device statistics are printed at the end.
"""

from __future__ import annotations

import argparse
import asyncio
import sys

from ohmni_tb.bus import Bus
from ohmni_tb.errors import BusTimeoutError
from ohmni_tb.protocol.core import parse_status, read_status
from ohmni_tb.protocol.devices import DeviceId, device_name
from ohmni_tb.protocol.drive import (
    parse_count,
    parse_motor_position,
    read_count,
    read_firmware_tag,
    read_motor_position,
)
from ohmni_tb.transport import open_transport


async def report(port: str) -> int:
    async with Bus(await open_transport(port)) as bus:
        for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE):
            try:
                tag = await bus.query(read_firmware_tag(sid))
                print(f"{device_name(sid):>6} firmware {tag.data.decode('ascii', 'replace')!r}")
            except BusTimeoutError as exc:
                print(f"{device_name(sid):>6} {exc}")
        status = parse_status(await bus.query(read_status()))
        print(
            f"battery: {status.pack_mv / 1000:.2f} V "
            f"(cells {', '.join(str(mv) for mv in status.cell_mv)} mV), "
            f"{status.charging_current_ma:+d} mA, {status.percent} %, "
            f"{'on the dock' if status.docked else 'off the dock'}"
        )
        for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
            count = parse_count(await bus.query(read_count(sid)))
            position = parse_motor_position(await bus.query(read_motor_position(sid)))
            print(f"{device_name(sid):>6} count {count:+d}, motor position {position}")
        for stats in bus.stats.devices.values():
            print(f"  {device_name(stats.sid):>6}: {stats.replies}/{stats.requests} answered")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", default="sim://")
    return asyncio.run(report(parser.parse_args().port))


if __name__ == "__main__":
    sys.exit(main())
