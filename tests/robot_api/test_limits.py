"""The acceleration, braking and jerk limits through the Robot, on ``sim://`` in virtual time.

What a user sees: ``wheel_odom``'s ``commanded_linear_mps`` (the command after the limits)
and ``linear_mps`` (what the simulated wheels did). A reversal brakes at the braking limit
down to zero in either direction of travel, then speeds up at the acceleration limit; a
jerk limit eases a drive command in, but never a stop.
"""

from __future__ import annotations

import asyncio
import itertools
import math
from typing import Any

import pytest

from ohmni_tb.errors import MotionResult
from ohmni_tb.robot import LocalRobot, WheelOdomSample
from ohmni_tb.sim.clock import run_virtual

#: The control tick at the default ``wheel_hz`` of 50.
PERIOD_S = 0.02
#: Deliberately far apart, so a limiter that swapped them when backing up shows.
ACCEL_MPS2 = 0.25
DECEL_MPS2 = 1.0
SPEED_MPS = 0.4


async def keep_driving(robot: LocalRobot, linear_mps: float, seconds: float) -> float:
    """``drive(linear_mps)`` every 0.1 s for ``seconds``, as a teleop does; the start time."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    while loop.time() < start + seconds:
        robot.drive(linear_mps, 0.0)
        await asyncio.sleep(0.1)
    return start


def drain(robot_stream: Any) -> list[WheelOdomSample]:
    out: list[WheelOdomSample] = []
    while (item := robot_stream.get_nowait()) is not None:
        out.append(item)
    return out


def check_reversal(samples: list[WheelOdomSample], start_s: float, sign: float) -> None:
    """From ``sign`` × SPEED_MPS to the other way, commanded at ``start_s``."""
    after = [s for s in samples if s.stamp_s >= start_s and s.stamp_s <= start_s + 2.5]
    commanded = [s.commanded_linear_mps * sign for s in after]  # forward-positive here
    # (The first sample may already carry the first braking step.)
    assert commanded[0] >= SPEED_MPS - DECEL_MPS2 * PERIOD_S - 1e-9
    zero = next(i for i, v in enumerate(commanded) if v <= 0.0)
    braking_s = after[zero].stamp_s - start_s
    # Braking at the braking limit: 0.4 m/s at 1 m/s² is 0.4 s (within a tick), where the
    # acceleration limit would have taken 1.6 s.
    assert SPEED_MPS / DECEL_MPS2 - PERIOD_S <= braking_s <= SPEED_MPS / DECEL_MPS2 + 2 * PERIOD_S
    for (a, va), (b, vb) in itertools.pairwise(zip(after, commanded, strict=True)):
        gap_s = max(b.stamp_s - a.stamp_s, PERIOD_S) * 1.25  # a tick, the stamps' jitter
        if vb >= 0.0:
            assert va - vb <= DECEL_MPS2 * gap_s  # braking, never faster than its limit
        elif va <= 0.0:
            assert va - vb <= ACCEL_MPS2 * gap_s  # then speeding up the other way
        else:  # through zero within a tick: some braking, then some speeding up
            assert va <= DECEL_MPS2 * gap_s
            assert -vb <= ACCEL_MPS2 * gap_s
    # After zero, the other way at the acceleration limit: 0.1 m/s 0.4 s later.
    later = next(s for s in after if s.stamp_s >= after[zero].stamp_s + 0.4)
    assert later.commanded_linear_mps * sign == pytest.approx(-0.1, abs=ACCEL_MPS2 * 2 * PERIOD_S)
    # And the wheels followed: the robot itself was through zero within 0.2 s of the
    # command (the PIDs trail the ramp), going the other way.
    measured_zero = next(s for s in after if s.linear_mps * sign <= 0.0)
    assert measured_zero.stamp_s - after[zero].stamp_s <= 0.2
    assert later.linear_mps * sign < 0.0


def test_reversing_brakes_at_the_braking_limit_in_both_directions_of_travel() -> None:
    async def main() -> tuple[float, float, list[WheelOdomSample]]:
        async with LocalRobot.open(
            "sim://", linear_accel_mps2=ACCEL_MPS2, linear_decel_mps2=DECEL_MPS2
        ) as robot:
            odom = robot.subscribe("wheel_odom", maxlen=2000)
            await keep_driving(robot, SPEED_MPS, 2.0)  # 1.6 s to get there
            backward = await keep_driving(robot, -SPEED_MPS, 2.5)
            forward = await keep_driving(robot, SPEED_MPS, 2.5)
            robot.stop()
            return backward, forward, drain(odom)

    backward, forward, samples = run_virtual(main())
    check_reversal(samples, backward, 1.0)  # forward → backward
    check_reversal(samples, forward, -1.0)  # backward → forward: ROS1 swapped the limits here


def test_a_jerk_limit_eases_a_drive_command_in_but_not_a_stop() -> None:
    jerk = 2.0

    async def main() -> tuple[float, list[WheelOdomSample]]:
        async with LocalRobot.open(
            "sim://", linear_accel_mps2=ACCEL_MPS2, linear_jerk_mps3=jerk
        ) as robot:
            odom = robot.subscribe("wheel_odom", maxlen=2000)
            await keep_driving(robot, SPEED_MPS, 2.5)
            stop_s = asyncio.get_running_loop().time()
            robot.stop()
            await asyncio.sleep(1.0)
            return stop_s, drain(odom)

    stop_s, samples = run_virtual(main())
    moving = [s for s in samples if s.stamp_s < stop_s]
    speeds = [0.0] + [s.commanded_linear_mps for s in moving]  # from a standstill
    first = next(i for i, v in enumerate(speeds) if v > 0.0)
    # Eased in: the first step is j·dt² = 0.8 mm/s, not a·dt = 5 mm/s; then the
    # acceleration grows by at most j·dt a tick, up to the limit.
    assert speeds[first] == pytest.approx(jerk * PERIOD_S**2, rel=0.2)
    accels = [(b - a) / PERIOD_S for a, b in itertools.pairwise(speeds[first - 1 :])]
    assert max(accels) == pytest.approx(ACCEL_MPS2)
    assert all(b - a <= jerk * PERIOD_S * 1.2 for a, b in itertools.pairwise(accels))
    # Landed on the target, never past it: v/a + a/j = 1.6 + 0.125 s, a few ticks more.
    assert max(speeds) == SPEED_MPS
    arrived = next(s for s in moving if s.commanded_linear_mps == SPEED_MPS)
    assert arrived.stamp_s - moving[first - 1].stamp_s == pytest.approx(1.725, abs=0.1)
    # The stop: at the braking limit (1 m/s² by default) from its first tick.
    braking = [s.commanded_linear_mps for s in samples if s.stamp_s >= stop_s]
    assert SPEED_MPS - braking[0] == pytest.approx(1.0 * PERIOD_S, abs=1e-9)
    zero = next(s for s in samples if s.stamp_s >= stop_s and s.commanded_linear_mps == 0.0)
    assert zero.stamp_s - stop_s <= SPEED_MPS / 1.0 + 2 * PERIOD_S


def test_motion_goals_land_as_precisely_with_a_jerk_limit() -> None:
    # A goal follows its own braking curve (within the braking limit); held to a low
    # jerk limit its command would trail the curve and overshoot the goal by degrees.
    async def main() -> tuple[MotionResult, MotionResult]:
        async with LocalRobot.open("sim://", linear_jerk_mps3=1, angular_jerk_radps3=1) as robot:
            return await robot.drive_distance(0.3), await robot.rotate(math.pi / 2)

    drove, turned = run_virtual(main())
    assert drove.reason == turned.reason == "arrived"
    assert abs(drove.remaining_m) < 0.005
    assert abs(turned.remaining_rad) < math.radians(0.5)
