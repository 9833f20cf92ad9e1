"""The stall and slip guards, judged the same way on a local robot and on a daemon's: a
wheel blocked mid-goal ends the goal with ``WheelStallError`` within ``stall_s`` + 0.1 s
and its power is cut; a wheel that loses its grip mid-goal ends it with
``WheelSlipError``; both are faults of ``robot_state`` and show on the drive board's
``diagnostics`` entry. The simulator's truth says what the wheels really did."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import MotionError, WheelSlipError, WheelStallError
from ohmni_tb.robot import DiagnosticLevel, DiagnosticsSample
from ohmni_tb.sim.robot import SimRobot

from .conftest import run

#: The issue's bound: a stall mid-goal ends it within the threshold and this.
STALL_REPORTED_S = 0.1
#: How often a teleop loop sends its command again (inside the watchdog's 0.5 s).
TICK_S = 0.05


async def goal_error(
    robot: Robot, goal: Awaitable[object], inject: Callable[[], None], after_s: float
) -> tuple[MotionError, float]:
    """Start ``goal``, call ``inject`` ``after_s`` later; the goal's error and how long after
    ``inject`` it came."""
    task = asyncio.ensure_future(goal)
    await asyncio.sleep(after_s)
    assert not task.done()
    loop = asyncio.get_running_loop()
    injected = loop.time()
    inject()
    with pytest.raises(MotionError) as caught:
        await task
    return caught.value, loop.time() - injected


async def keep_driving(robot: Robot, seconds: float, linear: float, angular: float) -> None:
    for _ in range(round(seconds / TICK_S)):
        robot.drive(linear, angular)
        await asyncio.sleep(TICK_S)


async def diagnostics_where(
    robot: Robot, test: Callable[[DiagnosticsSample], bool]
) -> DiagnosticsSample:
    """The first ``diagnostics`` sample from now on that passes ``test`` (within 2.5 s)."""
    async with robot.subscribe("diagnostics") as samples, asyncio.timeout(2.5):
        async for sample in samples:
            if test(sample):
                return sample
    raise AssertionError("the stream ended")


def right_drive_not_ok(sample: DiagnosticsSample) -> bool:
    entry = sample.entry("right_drive")
    return entry is not None and entry.level is not DiagnosticLevel.OK


@pytest.mark.parametrize("stall_s", [0.5, 0.3])
def test_a_stall_mid_drive_distance_ends_it_within_the_threshold(kind: str, stall_s: float) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[MotionError, float, tuple[str, ...]]:
        error, took = await goal_error(
            robot, robot.drive_distance(2.0), lambda: truth.stall(0), after_s=1.0
        )
        await asyncio.sleep(0.05)
        return error, took, robot.state.faults

    error, took, faults = run(kind, check, stall_s=stall_s)
    assert isinstance(error, WheelStallError)
    assert took <= stall_s + STALL_REPORTED_S
    assert error.result.reason == "stalled"
    assert error.wheels == ("left",)
    assert error.pwm[0] > 100  # the PID pushed against the obstacle
    assert error.stalled_s == pytest.approx(stall_s, abs=0.03)
    assert f"the left wheel did not turn for {error.stalled_s:.2f} s driven at PWM" in str(error)
    assert 0.1 < error.result.distance_m < 1.0  # it had gone some way
    assert "wheel_stall:0" in faults


#: The simulator's true wheel speeds, left and right, m/s.
Speeds = tuple[float, float]
#: What the stall-and-hold test saw: faults and true speeds at each step.
HoldSeen = tuple[tuple[str, ...], Speeds, Speeds, tuple[str, ...], Speeds, tuple[str, ...]]


def test_a_stall_stops_the_wheels_and_holds_them_until_another_command(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> HoldSeen:
        truth.stall(1)
        await keep_driving(robot, 1.0, 0.3, 0.0)  # the right wheel blocked, the left turns
        stalled, wheels = robot.state.faults, truth.wheel_speeds_mps()
        # A teleop loop sending the same command does not push against the obstacle again.
        await keep_driving(robot, 1.0, 0.3, 0.0)
        held, held_faults = truth.wheel_speeds_mps(), robot.state.faults
        truth.stall(1, on=False)
        await keep_driving(robot, 0.5, 0.2, 0.0)  # another command: driving again
        again, again_faults = truth.wheel_speeds_mps(), robot.state.faults
        robot.stop()
        await asyncio.sleep(1.0)
        return stalled, wheels, held, held_faults, again, again_faults

    stalled, wheels, held, held_faults, (left, right), again_faults = run(kind, check)
    assert stalled == ("wheel_stall:1",)
    assert wheels == (0.0, 0.0)  # by the truth: both wheels stand
    assert held == (0.0, 0.0)
    assert held_faults == ("wheel_stall:1",)
    assert left > 0.1
    assert right > 0.1
    assert again_faults == ()


def test_a_slipping_wheel_ends_a_goal_with_wheel_slip_error(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[MotionError, float, bool]:
        error, took = await goal_error(
            robot,
            robot.drive_distance(3.0, speed_mps=0.3),
            lambda: truth.slip(1),
            after_s=1.5,
        )
        left, right = truth.wheel_speeds_mps()
        return error, took, left == right == 0.0

    error, took, at_rest = run(kind, check)
    assert isinstance(error, WheelSlipError)
    assert error.result.reason == "slipped"
    assert error.wheel == "right"
    assert error.measured_mps > error.setpoint_mps == pytest.approx(0.3)
    assert error.slipped_s >= 1.0  # slip_s
    assert took < 3.0
    assert "the right wheel ran at" in str(error)
    assert "off the commanded curve" in str(error)
    assert at_rest  # the goal stopped and waited for rest


def test_stall_and_slip_show_on_the_drive_boards_entries(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[DiagnosticsSample, DiagnosticsSample]:
        truth.stall(0)
        await keep_driving(robot, 0.8, 0.3, 0.0)
        stalled = await diagnostics_where(robot, lambda s: s.level is not DiagnosticLevel.OK)
        truth.stall(0, on=False)
        robot.stop()
        await asyncio.sleep(0.5)
        drive = asyncio.ensure_future(keep_driving(robot, 4.0, 0.3, 0.0))
        await asyncio.sleep(1.0)
        truth.slip(1)
        try:
            slipping = await diagnostics_where(robot, right_drive_not_ok)
        finally:
            drive.cancel()
        return stalled, slipping

    stalled, slipping = run(kind, check)
    left = stalled.entry("left_drive")
    assert left is not None
    assert left.level is DiagnosticLevel.ERROR
    assert "wheel_stall:0" in left.message
    assert left.values["stalls"] == 1
    right = slipping.entry("right_drive")
    assert right is not None
    assert right.level is DiagnosticLevel.WARN
    assert "wheel_slip:1" in right.message
    assert right.values["slips"] == 1
