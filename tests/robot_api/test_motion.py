"""The Robot's motion goals and waiting neck moves on ``sim://``, in virtual time.

``drive_distance``, ``rotate`` and ``go_to`` are judged by the simulator's ground truth
(its pose and wheels); preemption, cancellation, stalls and bad input by what the robot
then does and by the wheel commands the drive boards decode. The neck's ``move(...,
wait=True)`` by the simulated servo's and worm gear's own positions.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

import pytest

from ohmni_tb import MotionResult, Robot
from ohmni_tb.cli import drive as drive_cli
from ohmni_tb.errors import (
    InvalidArgumentError,
    MotionAbortedError,
    MotionError,
    MotionPreemptedError,
    MotionTimeoutError,
    OutOfRangeError,
    PositionTimeoutError,
    StateError,
    WheelStallError,
)
from ohmni_tb.herkulex import parse_reply, ram_read
from ohmni_tb.protocol import Packet
from ohmni_tb.protocol.drive import decode_wheel_command
from ohmni_tb.robot import MotionResult as RobotMotionResult
from ohmni_tb.robot import ServoHandle, WormNeckHandle, motion
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.servo import SimServo
from ohmni_tb.sim.worm_neck import SimWormNeck

T = TypeVar("T")

#: How often a user's loop re-sends drive(): inside the 0.5 s watchdog.
USER_TICK_S = 0.05


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


class WheelCommands:
    """Every wheel command the left drive board decodes: (time, left PWM, right PWM),
    forward positive for both wheels."""

    def __init__(self, robot: Robot, monkeypatch: pytest.MonkeyPatch) -> None:
        self.seen: list[tuple[float, int, int]] = []
        board = robot.sim.left
        original = board.handle_jog

        def spy(packet: Packet, now_s: float) -> None:
            pwm = decode_wheel_command(packet)
            if 0 in pwm and 1 in pwm:
                self.seen.append((now_s, pwm[0], -pwm[1]))
            original(packet, now_s)

        monkeypatch.setattr(board, "handle_jog", spy)


def at_rest(robot: Robot) -> bool:
    left, right = robot.sim.wheel_speeds_mps()
    return bool(left == right == 0.0)


async def keep_driving(robot: Robot, seconds: float, linear: float, angular: float) -> None:
    for _ in range(round(seconds / USER_TICK_S)):
        robot.drive(linear, angular)
        await asyncio.sleep(USER_TICK_S)


# -- getting there -------------------------------------------------------------------------------


@pytest.mark.parametrize("goal_m", [0.5, -0.5])
def test_drive_distance_ends_within_a_centimetre_by_truth_at_rest(goal_m: float) -> None:
    async def main() -> tuple[MotionResult, tuple[float, float, float], bool]:
        async with Robot.open("sim://") as robot:
            result = await robot.drive_distance(goal_m)
            pose = robot.sim.pose
            return result, (pose.x, pose.y, pose.yaw), at_rest(robot)

    result, (x, y, yaw), rest = virtual(main)
    assert x == pytest.approx(goal_m, abs=0.01)
    assert abs(y) < 0.01
    assert abs(yaw) < math.radians(1)
    assert rest  # it returns once the robot stands still
    assert result.reason == "arrived"
    assert result.kind == "drive_distance"
    assert result.distance_m == pytest.approx(x, abs=0.005)
    assert result.remaining_m == pytest.approx(goal_m - result.distance_m)
    assert abs(result.remaining_m) < 0.005
    assert (result.x_m, result.y_m) == pytest.approx((x, y), abs=0.005)
    # 0.5 m at 0.3 m/s with the ramps: about two seconds, not the timeout's ten.
    assert 1.5 < result.elapsed_s < 4.0


@pytest.mark.parametrize("angle_rad", [math.pi / 2, -math.pi / 2])
def test_rotate_ends_within_a_degree_by_truth_on_the_spot(angle_rad: float) -> None:
    async def main() -> tuple[MotionResult, tuple[float, float, float], bool]:
        async with Robot.open("sim://") as robot:
            result = await robot.rotate(angle_rad, speed_radps=0.8)
            pose = robot.sim.pose
            return result, (pose.x, pose.y, pose.yaw), at_rest(robot)

    result, (x, y, yaw), rest = virtual(main)
    assert math.degrees(yaw) == pytest.approx(math.degrees(angle_rad), abs=1.0)
    assert math.hypot(x, y) < 0.01
    assert rest
    assert result.reason == "arrived"
    assert result.heading_change_rad == pytest.approx(yaw, abs=math.radians(0.5))
    assert abs(result.remaining_rad) < math.radians(0.5)
    assert result.remaining_m == 0.0


def test_go_to_reaches_the_point_and_the_yaw() -> None:
    async def main() -> tuple[MotionResult, tuple[float, float, float], bool]:
        async with Robot.open("sim://") as robot:
            robot.reset_odometry(0.2, 0.1, math.pi / 4)  # the frame is the odometry's
            result = await robot.go_to(1.0, -0.4, yaw_rad=math.pi)
            pose = robot.sim.pose
            return result, (pose.x, pose.y, pose.yaw), at_rest(robot)

    result, (x, y, yaw), rest = virtual(main)
    # By odometry within the documented tolerance; the truth adds the odometry's own
    # error over the way (a few mm on the simulator).
    assert result.reason == "arrived"
    assert result.remaining_m <= motion.GO_TO_TOLERANCE_M
    assert math.hypot(result.x_m - 1.0, result.y_m + 0.4) == pytest.approx(result.remaining_m)
    assert abs(result.remaining_rad) < math.radians(0.5)
    assert result.yaw_rad == pytest.approx(math.pi, abs=math.radians(0.5)) or (
        result.yaw_rad == pytest.approx(-math.pi, abs=math.radians(0.5))
    )
    # The truth starts at (0, 0, 0) where the odometry said (0.2, 0.1, 45°).
    c, s = math.cos(math.pi / 4), math.sin(math.pi / 4)
    true_x, true_y = 0.2 + c * x - s * y, 0.1 + s * x + c * y
    assert math.hypot(true_x - 1.0, true_y + 0.4) < 0.02
    assert math.degrees(math.remainder(yaw + math.pi / 4 - math.pi, 2 * math.pi)) == (
        pytest.approx(0.0, abs=1.0)
    )
    assert rest


def test_go_to_where_the_robot_is_sends_no_drive_and_returns_at_once() -> None:
    async def main() -> tuple[MotionResult, float]:
        async with Robot.open("sim://") as robot:
            result = await robot.go_to(0.0, 0.0)
            return result, robot.sim.pose.x

    result, x = virtual(main)
    assert result.reason == "arrived"
    assert result.remaining_m < 0.001
    assert result.elapsed_s < 0.5
    assert x == 0.0


# -- preemption ------------------------------------------------------------------------------


def test_a_drive_during_a_goal_preempts_it_and_the_drive_stands() -> None:
    async def main() -> tuple[object, float, float, tuple[float, float]]:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.drive_distance(2.0))
            await asyncio.sleep(1.0)
            x_then = robot.sim.pose.x
            await keep_driving(robot, 1.5, 0.0, 0.8)
            odom = robot.latest("wheel_odom")
            assert odom is not None
            pose = robot.sim.pose
            error = await asyncio.gather(goal, return_exceptions=True)
            return (
                error[0],
                pose.x - x_then,
                pose.yaw,
                (odom.commanded_linear_mps, odom.commanded_angular_radps),
            )

    error, forward_after_m, yaw, commanded = virtual(main)
    assert isinstance(error, MotionPreemptedError)
    assert error.by == "drive"
    assert error.result.reason == "preempted"
    assert "preempted by drive()" in str(error)
    assert 0.1 < error.result.distance_m < 0.5
    # The turn stands: the goal's forward command did not come back.
    assert commanded == pytest.approx((0.0, 0.8))
    assert yaw > 0.8  # turning at 0.8 rad/s for most of 1.5 s
    # Only the braking ramp from 0.3 m/s (4.5 cm, the PIDs trailing) went on forward.
    assert forward_after_m < 0.1


@pytest.mark.parametrize("command", ["stop", "estop"])
def test_stop_and_estop_during_a_goal_preempt_it_and_the_robot_stays_stopped(
    command: str,
) -> None:
    async def main() -> tuple[object, float, float, bool]:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.drive_distance(2.0))
            await asyncio.sleep(1.0)
            if command == "stop":
                robot.stop()
            else:
                await robot.estop()
            (error,) = await asyncio.gather(goal, return_exceptions=True)
            await asyncio.sleep(1.0)
            x_rest = robot.sim.pose.x
            await asyncio.sleep(1.0)
            rest = at_rest(robot)
            if command == "estop":
                robot.clear_estop()
            return error, x_rest, robot.sim.pose.x, rest

    error, x_rest, x_later, rest = virtual(main)
    assert isinstance(error, MotionPreemptedError)
    assert error.by == command
    assert f"preempted by {command}()" in str(error)
    assert rest
    assert x_later == x_rest < 0.5  # it did not drive on


def test_a_new_goal_preempts_the_running_one() -> None:
    async def main() -> tuple[object, MotionResult, float]:
        async with Robot.open("sim://") as robot:
            first = asyncio.create_task(robot.drive_distance(2.0))
            await asyncio.sleep(0.8)
            second = await robot.rotate(math.pi / 4)
            (error,) = await asyncio.gather(first, return_exceptions=True)
            return error, second, robot.sim.pose.yaw

    error, second, yaw = virtual(main)
    assert isinstance(error, MotionPreemptedError)
    assert error.by == "rotate"
    assert second.reason == "arrived"
    assert math.degrees(yaw) == pytest.approx(45, abs=1.0)


def test_an_odometry_reset_ends_a_goal_and_stops_the_robot() -> None:
    async def main() -> tuple[object, bool, float]:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.go_to(2.0, 0.0))
            await asyncio.sleep(1.0)
            robot.reset_odometry()
            (error,) = await asyncio.gather(goal, return_exceptions=True)
            await asyncio.sleep(1.0)
            return error, at_rest(robot), robot.sim.pose.x

    error, rest, x = virtual(main)
    assert isinstance(error, MotionPreemptedError)
    assert error.by == "reset_odometry"
    assert rest
    assert x < 0.5


# -- cancellation, stalls, closing, silence --------------------------------------------------------


def test_cancelling_the_goal_ramps_the_robot_to_rest_and_only_cancels() -> None:
    async def main() -> tuple[asyncio.Task[MotionResult], bool, tuple[int, int], tuple[int, int]]:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.drive_distance(2.0))
            await asyncio.sleep(1.0)
            goal.cancel()
            with pytest.raises(asyncio.CancelledError):
                await goal
            await asyncio.sleep(1.0)
            first = robot.latest("wheel_encoder")
            await asyncio.sleep(0.5)
            later = robot.latest("wheel_encoder")
            assert first is not None
            assert later is not None
            return (
                goal,
                at_rest(robot),
                (first.left_raw, first.right_raw),
                (later.left_raw, later.right_raw),
            )

    goal, rest, counts, counts_later = virtual(main)
    assert goal.cancelled()  # no other error than the cancellation
    assert rest
    assert counts == counts_later  # the wheel counts hold still


def test_cancelling_returns_at_once_with_the_braking_target_set() -> None:
    async def main() -> tuple[float, tuple[float, float]]:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.rotate(3.0))
            await asyncio.sleep(1.0)
            loop = asyncio.get_running_loop()
            goal.cancel()
            cancelled_at = loop.time()
            with pytest.raises(asyncio.CancelledError):
                await goal
            waited = loop.time() - cancelled_at
            await asyncio.sleep(0.1)
            odom = robot.latest("wheel_odom")
            assert odom is not None
            # The ramp is on its way down from the turn toward zero.
            return waited, (odom.commanded_linear_mps, odom.commanded_angular_radps)

    waited, commanded = virtual(main)
    assert waited == 0.0  # nothing waited (virtual time: not a tick)
    assert commanded[0] == 0.0
    assert 0.0 <= commanded[1] < 0.8


def test_a_blocked_wheel_is_a_stall_and_the_robot_is_stopped(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def main() -> tuple[BaseException | None, float, list[tuple[float, int, int]], bool]:
        async with Robot.open("sim://") as robot:
            commands = WheelCommands(robot, monkeypatch)
            robot.sim.block_wheels(left=True, right=False)
            loop = asyncio.get_running_loop()
            started = loop.time()
            try:
                await robot.drive_distance(0.5)
            except MotionError as exc:
                error: BaseException | None = exc
            else:
                error = None
            took = loop.time() - started
            await asyncio.sleep(0.5)
            return error, took, commands.seen, at_rest(robot)

    error, took, commands, rest = virtual(main)
    assert isinstance(error, WheelStallError)
    assert error.wheels == ("left",)
    assert error.result.reason == "stalled"
    assert "the left wheel did not turn for 0.50 s driven at PWM" in str(error)
    assert len(error.pwm) == 1
    assert error.pwm[0] > 100  # the PID pushed against the obstacle
    assert error.stalled_s == pytest.approx(0.5, abs=0.03)
    # Commanded, not turning, for 0.5 s: the error comes well before the goal's time.
    assert took < 2.5
    assert rest
    last_commands = [(left, right) for _, left, right in commands[-5:]]
    assert last_commands == [(0, 0)] * 5


def test_closing_the_robot_ends_a_running_goal_with_an_error() -> None:
    async def main() -> object:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.drive_distance(3.0))
            await asyncio.sleep(0.5)
        async with asyncio.timeout(5):
            (error,) = await asyncio.gather(goal, return_exceptions=True)
        return error

    error = virtual(main)
    assert isinstance(error, MotionAbortedError)
    assert error.result.reason == "closed"
    assert "the Robot closed" in str(error)


def test_wheel_counts_that_stop_coming_end_the_goal() -> None:
    async def main() -> tuple[object, float]:
        async with Robot.open("sim://", stop_timeout_s=0.1) as robot:
            goal = asyncio.create_task(robot.drive_distance(3.0))
            await asyncio.sleep(0.8)
            loop = asyncio.get_running_loop()
            silenced = loop.time()
            robot.bus.transport.line.faults.silent = {0, 1}  # type: ignore[attr-defined]
            (error,) = await asyncio.gather(goal, return_exceptions=True)
            took = loop.time() - silenced
            robot.bus.transport.line.faults.silent = set()  # type: ignore[attr-defined]
            return error, took

    error, took = virtual(main)
    assert isinstance(error, MotionAbortedError)
    assert error.result.reason == "no_counts"
    assert "no wheel counts came for 0.5 s" in str(error)
    assert took == pytest.approx(motion.FEEDBACK_GAP_S, abs=0.05)


def test_a_goal_out_of_time_is_a_timeout_and_the_robot_is_stopped() -> None:
    async def main() -> tuple[BaseException | None, bool]:
        async with Robot.open("sim://") as robot:
            try:
                await robot.drive_distance(1.0, timeout_s=0.5)
            except MotionError as exc:
                return exc, at_rest(robot)
            return None, at_rest(robot)

    error, rest = virtual(main)
    assert isinstance(error, MotionTimeoutError)
    assert isinstance(error, TimeoutError)
    assert error.timeout_s == 0.5
    assert str(error).startswith("the goal was not reached within 0.5 s: went +0.0")
    assert "of +1.000 m by odometry; the robot is stopped" in str(error)
    assert rest


# -- refused ---------------------------------------------------------------------------------------

BAD: list[tuple[str, Callable[[Robot], Awaitable[MotionResult]], type[Exception], str]] = [
    ("nan", lambda r: r.drive_distance(math.nan), InvalidArgumentError, "distance_m=nan"),
    (
        "far",
        lambda r: r.drive_distance(101),
        OutOfRangeError,
        "distance_m=101 is out of range: allowed -100.0..100.0 m",
    ),
    (
        "not a number",
        lambda r: r.drive_distance("1"),  # type: ignore[arg-type]  # the point
        InvalidArgumentError,
        "distance_m must be a number, not '1'",
    ),
    (
        "speed 0",
        lambda r: r.drive_distance(0.5, speed_mps=0),
        OutOfRangeError,
        "speed_mps=0 is out of range: allowed 0.03..1.0 m/s",
    ),
    (
        "speed too fast",
        lambda r: r.drive_distance(0.5, speed_mps=1.5),
        OutOfRangeError,
        "speed_mps=1.5 is out of range: allowed 0.03..1.0 m/s",
    ),
    (
        "negative speed",
        lambda r: r.drive_distance(0.5, speed_mps=-0.3),
        OutOfRangeError,
        "speed_mps=-0.3 is out of range",
    ),
    (
        "negative timeout",
        lambda r: r.drive_distance(0.5, timeout_s=-1),
        OutOfRangeError,
        "timeout_s=-1 is out of range: allowed 0.0..3600.0 s",
    ),
    ("inf turn", lambda r: r.rotate(math.inf), InvalidArgumentError, "angle_rad=inf"),
    (
        "turn too fast",
        lambda r: r.rotate(1.0, speed_radps=9.0),
        OutOfRangeError,
        "speed_radps=9.0 is out of range: allowed 0.2..",
    ),
    ("nan point", lambda r: r.go_to(math.nan, 0.0), InvalidArgumentError, "x_m=nan"),
    ("nan yaw", lambda r: r.go_to(1.0, 0.0, math.inf), InvalidArgumentError, "yaw_rad=inf"),
    (
        "point too far",
        lambda r: r.go_to(0.0, 250.0),
        OutOfRangeError,
        "go_to's distance from the pose (0.000, 0.000) m=250.0 is out of range: allowed 0..100.0 m",
    ),
]


@pytest.mark.parametrize(
    ("call", "error", "message"), [b[1:] for b in BAD], ids=[b[0] for b in BAD]
)
def test_bad_input_is_refused_naming_value_and_range_and_nothing_is_sent(
    monkeypatch: pytest.MonkeyPatch,
    call: Callable[[Robot], Awaitable[MotionResult]],
    error: type[Exception],
    message: str,
) -> None:
    async def main() -> tuple[BaseException | None, int, int, set[tuple[int, int]]]:
        async with Robot.open("sim://") as robot:
            commands = WheelCommands(robot, monkeypatch)
            async with robot.subscribe("wheel_encoder") as ticks:
                await anext(ticks)  # between two control slots
                sent, before = len(commands.seen), robot.stats().streams["wheel_encoder"].samples
                try:
                    await call(robot)
                except Exception as exc:  # judged below
                    refused: BaseException | None = exc
                else:
                    refused = None
                for _ in range(10):
                    await anext(ticks)
                after = robot.stats().streams["wheel_encoder"].samples
                pwm = {(left, right) for _, left, right in commands.seen[sent:]}
                return refused, len(commands.seen) - sent, after - before, pwm

    refused, commands, control_slots, pwm = virtual(main)
    assert isinstance(refused, error)
    assert message in str(refused)
    # One wheel command per control slot, all zero: no command of its own went out.
    assert commands == control_slots == 10
    assert pwm == {(0, 0)}


def test_a_refused_goal_leaves_the_running_one_alone() -> None:
    async def main() -> tuple[MotionResult, float]:
        async with Robot.open("sim://") as robot:
            goal = asyncio.create_task(robot.drive_distance(0.4))
            await asyncio.sleep(0.5)
            with pytest.raises(OutOfRangeError):
                await robot.rotate(1.0, speed_radps=100.0)
            return await goal, robot.sim.pose.x

    result, x = virtual(main)
    assert result.reason == "arrived"
    assert x == pytest.approx(0.4, abs=0.01)


def test_a_goal_is_refused_while_an_emergency_stop_is_latched() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await robot.estop()
            with pytest.raises(StateError, match="emergency stop is latched"):
                await robot.drive_distance(0.3)
            robot.clear_estop()
            result = await robot.drive_distance(0.05)
            assert result.reason == "arrived"

    virtual(main)


def test_the_result_is_exported_and_the_cli_defaults_are_the_goals() -> None:
    assert MotionResult is RobotMotionResult is motion.MotionResult
    assert drive_cli.DEFAULT_LINEAR_MPS == motion.DEFAULT_LINEAR_MPS
    assert drive_cli.DEFAULT_ANGULAR_RADPS == motion.DEFAULT_ANGULAR_RADPS
    assert drive_cli.MIN_GOAL_LINEAR_MPS == motion.MIN_GOAL_LINEAR_MPS
    assert drive_cli.MIN_GOAL_ANGULAR_RADPS == motion.MIN_GOAL_ANGULAR_RADPS


# -- the simulator's obstacle --------------------------------------------------------------------


def test_a_blocked_wheel_does_not_turn_whatever_the_pwm_and_draws_stall_current() -> None:
    async def main() -> tuple[tuple[int, int], tuple[int, int], float, float]:
        async with Robot.open("sim://", controllers=False) as robot:
            await asyncio.sleep(0.1)
            sim = robot.sim
            idle = sim.train.motor_current_a()
            sim.block_wheels(left=True, right=False)
            assert sim.blocked_wheels == (True, False)
            before = robot.latest("wheel_encoder")
            for _ in range(10):
                robot.drive_pwm(600, 600)
                await asyncio.sleep(USER_TICK_S)
            after = robot.latest("wheel_encoder")
            held = sim.train.motor_current_a()
            sim.unblock_wheels()
            for _ in range(10):
                robot.drive_pwm(600, 600)
                await asyncio.sleep(USER_TICK_S)
            freed = robot.latest("wheel_encoder")
            robot.stop()
            assert before is not None
            assert after is not None
            assert freed is not None
            return (
                (after.left_ticks - before.left_ticks, after.right_ticks - before.right_ticks),
                (freed.left_ticks - after.left_ticks, freed.right_ticks - after.right_ticks),
                held - idle,
                sim.train.motor_current_a(),
            )

    blocked, unblocked, extra_a, _ = virtual(main)
    assert blocked[0] == 0  # held still at PWM 600
    assert blocked[1] > 1000  # the other wheel turns
    assert unblocked[0] > 1000  # free again
    # The held motor draws 0.5 A + 6 A at 60 % duty; the turning one less (its back-EMF).
    assert extra_a > 3.0


# -- the neck's waiting move ---------------------------------------------------------------------


def test_a_herkulex_move_with_wait_returns_once_the_neck_is_there() -> None:
    async def main() -> tuple[Any, float, int, Any]:
        async with Robot.open("sim://") as robot:
            loop = asyncio.get_running_loop()
            handle: object = robot.neck  # the HerkuleX or the worm-gear neck's handle
            assert isinstance(handle, ServoHandle)
            started = loop.time()
            sample = await handle.move(400, playtime_s=0.3, wait=True)
            took = loop.time() - started
            neck = robot.sim.neck
            assert isinstance(neck, SimServo)
            reply = neck.handle(ram_read(3, "calibrated_position"), robot.sim.sync())
            assert reply is not None
            position = int(parse_reply(reply).value("calibrated_position"))
            unwaited = await handle.move(450, playtime_s=0.3)
            return sample, took, position, unwaited

    sample, took, position, unwaited = virtual(main)
    assert abs(sample.position_raw - 400) <= 5
    assert not sample.moving
    assert abs(position - 400) <= 5  # the servo's own position, not the read-back
    assert 0.3 <= took < 0.5  # the playtime, and a sample or two after it
    assert unwaited is None  # wait=False (the default) returns at once, as before


def test_a_worm_neck_move_with_wait_returns_once_it_is_there_at_rest() -> None:
    async def main() -> tuple[Any, float, float]:
        async with Robot.open("sim://?neck=worm") as robot:
            loop = asyncio.get_running_loop()
            handle: object = robot.neck  # the HerkuleX or the worm-gear neck's handle
            assert isinstance(handle, WormNeckHandle)
            started = loop.time()
            sample = await handle.move(-50_000, wait=True)
            took = loop.time() - started
            neck = robot.sim.neck
            assert isinstance(neck, SimWormNeck)
            robot.sim.sync()
            return sample, took, neck.position

    sample, took, position = virtual(main)
    assert abs(sample.position_raw - -50_000) <= 1000
    assert not sample.moving
    assert abs(position - -50_000) <= 1000
    assert took > 0.6  # 50000 raw at the simulated 80000 raw/s


def test_a_waiting_move_that_does_not_get_there_in_time_says_so() -> None:
    async def main() -> BaseException | None:
        async with Robot.open("sim://") as robot:
            handle: object = robot.neck  # the HerkuleX or the worm-gear neck's handle
            assert isinstance(handle, ServoHandle)
            try:
                await handle.move(300, playtime_s=1.0, wait=True, timeout_s=0.2)
            except PositionTimeoutError as exc:
                return exc
            return None

    error = virtual(main)
    assert isinstance(error, PositionTimeoutError)
    assert isinstance(error, TimeoutError)
    assert str(error).startswith("the HerkuleX neck did not reach 300 within 0.2 s: it reads back")
    assert (error.sid, error.target_raw) == (3, 300)
    assert error.sample is not None


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"timeout_s": 1.0}, InvalidArgumentError, "give it with wait=True"),
        ({"wait": True, "timeout_s": -1}, OutOfRangeError, "timeout_s=-1 is out of range"),
        ({"wait": 1}, InvalidArgumentError, "wait must be True or False, not 1"),
    ],
)
def test_bad_wait_arguments_are_refused_before_the_move(
    kwargs: dict[str, Any], error: type[Exception], message: str
) -> None:
    async def main() -> int:
        async with Robot.open("sim://") as robot:
            handle: object = robot.neck  # the HerkuleX or the worm-gear neck's handle
            assert isinstance(handle, ServoHandle)
            with pytest.raises(error, match=message):
                await handle.move(400, playtime_s=0.2, **kwargs)
            await asyncio.sleep(0.5)
            sample = robot.latest("servo_neck")
            assert sample is not None
            return sample.position_raw

    assert virtual(main) == 512  # not moved
