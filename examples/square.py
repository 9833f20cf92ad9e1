"""Drive a 1 m square by odometry with the Robot, and compare odometry with the truth.

    python examples/square.py                          # the simulator (default)
    python examples/square.py --png path.png           # where the plot goes (matplotlib)
    python examples/square.py --port /dev/ttyUSB0 --yes

Four legs, each straight ahead by distance and then a quarter turn to the left in place
by heading, steered from the Robot's 50 Hz ``wheel_odom`` stream. ``robot.drive()`` is
sent again every 50 ms (20 Hz): the watchdog stops the wheels half a second after the
last one, so a script that hangs stops the robot. On the simulator the true pose
(``robot.sim.pose``) is recorded next to the odometry; the end shows how far odometry
drifted from the truth, and how far from its start the robot really stopped. With
matplotlib installed (optional, not a dependency) both paths are plotted to a PNG.
Leaving the ``async with`` stops the wheels whatever happened, Ctrl-C included.
"""

from __future__ import annotations

import argparse
import asyncio
import importlib
import math
import sys
from pathlib import Path
from typing import Any

import ohmni_tb
from ohmni_tb import Robot, RobotConfig
from ohmni_tb.errors import StateError
from ohmni_tb.robot import SampleStream, WheelOdomSample

#: drive() is re-sent at 20 Hz: well inside the 0.5 s watchdog.
COMMAND_PERIOD_S = 0.05
#: A leg ends within 2 mm of its length, a turn within 0.1° of its heading.
POSITION_TOLERANCE_M = 0.002
HEADING_TOLERANCE_RAD = math.radians(0.1)
#: The approach plans to brake well inside the Robot's deceleration limits (1 m/s²,
#: 4 rad/s²), so the ramp and the wheel PIDs can follow the braking curve.
BRAKE_MPS2 = 0.5
TURN_BRAKE_RADPS2 = 1.0
#: Slowest commands: the wheel PIDs' feed-forward offset carries them over the dead band.
MIN_SPEED_MPS = 0.02
MIN_TURN_RADPS = 0.05
#: Steering on a leg: yaw rate per radian of heading error and per metre off the line.
HEADING_GAIN = 2.0
CROSS_TRACK_GAIN = 2.0
#: Standing still: both speeds below these for SETTLE_SAMPLES odometry samples.
STILL_MPS = 0.001
STILL_RADPS = 0.005
SETTLE_SAMPLES = 5


class Track:
    """The path as odometry and (on the simulator) the truth saw it, (x, y) in metres."""

    def __init__(self) -> None:
        self.odometry: list[tuple[float, float]] = []
        self.truth: list[tuple[float, float]] = []


class Square:
    """Drives legs and turns on one Robot and records the path."""

    def __init__(self, robot: Robot) -> None:
        self.robot = robot
        self.track = Track()
        self._loop = asyncio.get_running_loop()
        self._due = self._loop.time()

    async def odometry(self) -> WheelOdomSample:
        """The newest odometry (waiting for the first sample after open)."""
        sample = self.robot.latest("wheel_odom")
        if sample is not None:
            return sample
        samples: SampleStream[WheelOdomSample] = self.robot.subscribe("wheel_odom")
        async for first in samples:
            return first
        raise StateError("the Robot closed before the first odometry sample")

    async def tick(self, odom: WheelOdomSample) -> None:
        """Record where the robot is, then wait for the next 20 Hz command time."""
        self.track.odometry.append((odom.x_m, odom.y_m))
        if self.robot.sim is not None:
            pose = self.robot.sim.pose
            self.track.truth.append((pose.x, pose.y))
        # Absolute due times: the command rate does not drift with the loop's delays.
        self._due = max(self._due + COMMAND_PERIOD_S, self._loop.time())
        await asyncio.sleep(self._due - self._loop.time())

    async def straight(self, distance_m: float, heading_rad: float, speed_mps: float) -> None:
        """Drive ``distance_m`` along ``heading_rad`` (odometry frame) from where it stands."""
        start = await self.odometry()
        cos_h, sin_h = math.cos(heading_rad), math.sin(heading_rad)
        while True:
            odom = await self.odometry()
            dx, dy = odom.x_m - start.x_m, odom.y_m - start.y_m
            remaining_m = distance_m - (dx * cos_h + dy * sin_h)
            # Stop early by what the wheels need to brake from their measured speed.
            braking_m = odom.linear_mps**2 / (2 * self.robot.config.linear_decel_mps2)
            if remaining_m <= POSITION_TOLERANCE_M + braking_m:
                break
            speed = min(speed_mps, math.sqrt(2 * BRAKE_MPS2 * remaining_m))
            cross_m = dy * cos_h - dx * sin_h  # left of the line is positive
            turn = HEADING_GAIN * (heading_rad - odom.heading_rad) - CROSS_TRACK_GAIN * cross_m
            self.robot.drive(max(speed, MIN_SPEED_MPS), turn)
            await self.tick(odom)
        await self.settle()

    async def turn_to(self, heading_rad: float, rate_radps: float) -> None:
        """Turn in place to ``heading_rad`` (odometry frame, unwrapped)."""
        while True:
            odom = await self.odometry()
            error = heading_rad - odom.heading_rad
            braking_rad = odom.angular_radps**2 / (2 * self.robot.config.angular_decel_radps2)
            if abs(error) <= HEADING_TOLERANCE_RAD + braking_rad:
                break
            rate = min(rate_radps, math.sqrt(2 * TURN_BRAKE_RADPS2 * abs(error)))
            self.robot.drive(0.0, math.copysign(max(rate, MIN_TURN_RADPS), error))
            await self.tick(odom)
        await self.settle()

    async def settle(self, timeout_s: float = 3.0) -> None:
        """Stop, and wait until odometry shows the robot standing."""
        self.robot.stop()
        still = 0
        try:
            async with asyncio.timeout(timeout_s):
                async for odom in self.robot.subscribe("wheel_odom"):
                    moving = (
                        abs(odom.linear_mps) > STILL_MPS or abs(odom.angular_radps) > STILL_RADPS
                    )
                    still = 0 if moving else still + 1
                    if still >= SETTLE_SAMPLES:
                        self.track.odometry.append((odom.x_m, odom.y_m))
                        return
        except TimeoutError:
            print(f"  (odometry still shows motion {timeout_s:g} s after the stop; going on)")


async def run(
    port: str,
    *,
    side_m: float = 1.0,
    speed_mps: float = 0.3,
    turn_radps: float = 0.8,
    png: Path | None = Path("square.png"),
) -> int:
    """Drive the square on ``port`` and report; returns the exit code."""
    async with Robot.open(port, config=RobotConfig.load()) as robot:
        truth = robot.sim  # only the simulator knows the truth
        if truth is not None:
            # Start odometry at the true pose, so both paths share one frame.
            pose = truth.pose
            robot.reset_odometry(pose.x, pose.y, pose.yaw)
            start_truth = pose
        square = Square(robot)
        start = await square.odometry()
        print(
            f"square: 4 legs of {side_m:.2f} m at {speed_mps:.2f} m/s, "
            f"quarter turns left at {turn_radps:.2f} rad/s"
        )
        for leg in range(4):
            heading = start.heading_rad + leg * math.pi / 2
            await square.straight(side_m, heading, speed_mps)
            await square.turn_to(heading + math.pi / 2, turn_radps)
            odom = await square.odometry()
            print(
                f"  leg {leg + 1}: odometry x={odom.x_m:+.4f} m  y={odom.y_m:+.4f} m  "
                f"heading={math.degrees(odom.heading_rad):+.2f}°"
            )

        end = await square.odometry()
        turned = end.heading_rad - (start.heading_rad + 2 * math.pi)
        away_m = math.hypot(end.x_m - start.x_m, end.y_m - start.y_m)
        print(f"odometry end: x={end.x_m:+.4f} m  y={end.y_m:+.4f} m  yaw={end.yaw_rad:+.4f} rad")
        print(f"odometry says: {away_m * 100:.2f} cm, {math.degrees(turned):+.2f}° from the start")
        if truth is not None:
            real = truth.pose
            yaw = _wrap(real.yaw)
            print(f"ground truth: x={real.x:+.4f} m  y={real.y:+.4f} m  yaw={yaw:+.4f} rad")
            drift_m = math.hypot(end.x_m - real.x, end.y_m - real.y)
            drift_rad = _wrap(end.heading_rad - real.yaw)
            print(
                f"final error (odometry vs truth): {drift_m * 100:.2f} cm, "
                f"{abs(math.degrees(drift_rad)):.2f}°"
            )
            closure_m = math.hypot(real.x - start_truth.x, real.y - start_truth.y)
            closure_rad = _wrap(real.yaw - start_truth.yaw)
            print(
                f"back at the start (truth): {closure_m * 100:.2f} cm, "
                f"{abs(math.degrees(closure_rad)):.2f}° away"
            )
        print(f"bus: {robot.stats().bus.wire_utilisation:.0%} of the line in use")
    if png is not None:
        plot(square.track, png)
    return 0


def plot(track: Track, png: Path) -> None:
    """Odometry and truth paths to ``png``, or one line saying why not."""
    try:
        matplotlib: Any = importlib.import_module("matplotlib")
    except ImportError:
        print("plot skipped: matplotlib is not installed (pip install matplotlib)")
        return
    matplotlib.use("Agg")  # no display needed
    pyplot: Any = importlib.import_module("matplotlib.pyplot")
    figure, axes = pyplot.subplots(figsize=(6, 6))
    if track.truth:
        axes.plot(*zip(*track.truth, strict=True), label="truth (simulator)", linewidth=3)
    axes.plot(*zip(*track.odometry, strict=True), label="odometry", linestyle="--")
    axes.set_aspect("equal")
    axes.set_xlabel("x, m")
    axes.set_ylabel("y, m")
    axes.set_title("a square by odometry")
    axes.legend()
    figure.savefig(png, dpi=100)
    pyplot.close(figure)
    print(f"plot: {png}")


def _wrap(angle_rad: float) -> float:
    """An angle in (−π, π]."""
    wrapped = math.remainder(angle_rad, 2 * math.pi)
    return math.pi if wrapped == -math.pi else wrapped


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", default="sim://", help="default: the built-in simulator")
    parser.add_argument("--side", type=float, default=1.0, help="side of the square, m")
    parser.add_argument("--speed", type=float, default=0.3, help="top speed on a leg, m/s")
    parser.add_argument("--png", type=Path, default=Path("square.png"), help="plot file")
    parser.add_argument("--yes", action="store_true", help="drive a real robot")
    args = parser.parse_args()
    if not args.port.startswith("sim:") and not args.yes:
        parser.error(f"this drives a real robot around a {args.side:g} m square: add --yes")
    if not 0.1 <= args.side <= 5.0 or not 0.05 <= args.speed <= 0.5:
        parser.error("--side must be 0.1..5 m and --speed 0.05..0.5 m/s")
    # ohmni_tb.run: asyncio.run on a loop whose timers keep the bus's schedule (robot.md).
    return ohmni_tb.run(run(args.port, side_m=args.side, speed_mps=args.speed, png=args.png))


if __name__ == "__main__":
    sys.exit(main())
