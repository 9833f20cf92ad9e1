"""Drive an arc open-loop and track it with wheel odometry at 50 Hz.

    python examples/drive_and_odometry.py                 # the simulator (default)
    python examples/drive_and_odometry.py --port /dev/ttyUSB0 --i-am-clear-of-obstacles

Reads both wheel counts every 20 ms, turns them into wheel travel with
``ohmni_tb.control`` (encoder unwrap, mirrored right wheel, exact-arc odometry), and on the
simulator compares the result with the simulator's ground-truth pose. The wheels are
stopped on the way out whatever happens (Ctrl-C included).
"""

from __future__ import annotations

import argparse
import asyncio
import math
import sys

from ohmni_tb.bus import Bus
from ohmni_tb.control import EncoderConfig, Odometry, WheelEncoder
from ohmni_tb.protocol.drive import parse_count, read_count, wheel_command
from ohmni_tb.transport import open_transport

PERIOD_S = 0.02  # 50 Hz, the rate of tb_control's wheel loop


async def drive(port: str, left_pwm: int, right_pwm: int, seconds: float) -> int:
    transport = await open_transport(port)
    truth = getattr(transport, "robot", None)  # only the simulator knows the truth
    async with Bus(transport) as bus:
        loop = asyncio.get_running_loop()
        left, right = WheelEncoder(EncoderConfig.left()), WheelEncoder(EncoderConfig.right())
        odometry = Odometry(0.330)

        async def sample() -> None:
            t_s = loop.time()
            l_sample = left.update(parse_count(await bus.query(read_count(0))), t_s)
            r_sample = right.update(parse_count(await bus.query(read_count(1))), t_s)
            if l_sample is not None and r_sample is not None:
                odometry.update(l_sample.delta_m, r_sample.delta_m, t_s)

        await sample()  # the first reading sets the origin
        try:
            await bus.send(wheel_command(left_pwm, right_pwm))
            due = loop.time()
            end = due + seconds
            while due < end:
                due += PERIOD_S  # absolute deadlines: jitter never adds up to drift
                await asyncio.sleep(max(0.0, due - loop.time()))
                await sample()
        finally:
            await asyncio.shield(bus.send(wheel_command(0, 0)))
        for _ in range(25):  # let it coast to a stop, still tracking
            await asyncio.sleep(PERIOD_S)
            await sample()

        pose = odometry.pose
        print(f"odometry:     x={pose.x:+.4f} m  y={pose.y:+.4f} m  yaw={pose.yaw:+.4f} rad")
        if truth is not None:
            real = truth.pose
            error_m = math.hypot(pose.x - real.x, pose.y - real.y)
            print(f"ground truth: x={real.x:+.4f} m  y={real.y:+.4f} m  yaw={real.yaw:+.4f} rad")
            print(f"position error {error_m * 1000:.1f} mm")
        print(f"left wheel: {bus.stats.devices[0]}")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", default="sim://")
    parser.add_argument("--left", type=int, default=300, help="left PWM, forward-positive")
    parser.add_argument("--right", type=int, default=450, help="right PWM, forward-positive")
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--i-am-clear-of-obstacles", action="store_true", dest="clear")
    args = parser.parse_args()
    if not args.port.startswith("sim:") and not args.clear:
        parser.error("this drives a real robot ~1 m: add --i-am-clear-of-obstacles")
    return asyncio.run(drive(args.port, args.left, args.right, args.seconds))


if __name__ == "__main__":
    sys.exit(main())
