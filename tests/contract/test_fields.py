"""The fields tb_control's messages have, on a local robot and on a daemon's: the wheels'
speed in ticks per 50 Hz period and position on 0..4095, the odometry's frames,
quaternion and 6×6 covariances, and the servos' last commands."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.herkulex import TorqueControl
from ohmni_tb.herkulex.units import angle_rad_from_raw
from ohmni_tb.robot import (
    LocalRobot,
    ServoSample,
    WheelEncoderSample,
    WheelOdomSample,
    WormNeckSample,
)
from ohmni_tb.sim.clock import run_virtual

from .conftest import run


async def drive_for(robot: Robot, seconds: float, linear: float, angular: float = 0.0) -> None:
    """Drive as a teleop does: the command again at 20 Hz."""
    loop = asyncio.get_running_loop()
    until_s = loop.time() + seconds
    while loop.time() < until_s:
        robot.drive(linear, angular)
        await asyncio.sleep(0.05)


async def samples_for(robot: Robot, stream: str, seconds: float) -> list[Any]:
    """Every sample of ``stream`` in the next ``seconds``."""
    got: list[Any] = []
    async with robot.subscribe(stream, maxlen=1000) as subscription:
        loop = asyncio.get_running_loop()
        until_s = loop.time() + seconds
        while (left_s := until_s - loop.time()) > 0:
            try:
                got.append(await asyncio.wait_for(anext(subscription), left_s))
            except TimeoutError:
                break
    return got


def test_wheel_encoder_speeds_and_positions_follow_the_counts(kind: str) -> None:
    async def check(robot: Robot, _: object) -> list[WheelEncoderSample]:
        driving = asyncio.create_task(drive_for(robot, 2.0, 0.3))
        await asyncio.sleep(1.0)  # at speed
        got = await samples_for(robot, "wheel_encoder", 0.6)
        await driving
        return got

    got = run(kind, check)
    assert len(got) >= 25
    first, last = got[0], got[-1]
    periods = (last.stamp_s - first.stamp_s) * 50
    # What the counts rolled per 50 Hz period, in each board's own sense: the left counts
    # up, the right (mirrored) down while the robot drives forward.
    left_per_period = (last.left_raw - first.left_raw) / periods
    right_per_period = (last.right_raw - first.right_raw) / periods
    assert left_per_period > 400
    assert right_per_period < -400
    for sample in got[len(got) // 2 :]:
        assert sample.left_vel_raw == pytest.approx(left_per_period, rel=0.03)
        assert sample.right_vel_raw == pytest.approx(right_per_period, rel=0.03)
    for sample in got:
        assert 0 <= sample.left_pos_raw < 4096
        assert 0 <= sample.right_pos_raw < 4096
        assert sample.left_pos_raw == sample.left_raw % 4096
        assert sample.right_pos_raw == sample.right_raw % 4096
    assert len({sample.left_pos_raw for sample in got}) > 10  # it moves on 0..4095


def test_wheel_encoder_speeds_are_per_50_hz_period_whatever_the_control_rate(kind: str) -> None:
    async def check(robot: Robot, _: object) -> tuple[WheelEncoderSample, WheelEncoderSample]:
        driving = asyncio.create_task(drive_for(robot, 1.6, 0.3))
        await asyncio.sleep(1.0)
        got = await samples_for(robot, "wheel_encoder", 0.4)
        await driving
        return got[0], got[-1]

    first, last = run(kind, check, wheel_hz=25.0)
    per_period = (last.left_raw - first.left_raw) / ((last.stamp_s - first.stamp_s) * 50)
    assert last.left_vel_raw == pytest.approx(per_period, rel=0.03)


def test_wheel_odom_carries_the_configured_frames_quaternion_and_covariances(kind: str) -> None:
    async def check(robot: Robot, _: object) -> WheelOdomSample | None:
        await drive_for(robot, 1.0, 0.2, 0.8)
        return robot.latest("wheel_odom")

    odom = run(kind, check, frame_id_odom="map", frame_id_baselink="base_footprint")
    assert odom is not None
    assert (odom.frame_id, odom.child_frame_id) == ("map", "base_footprint")
    assert odom.yaw_rad > 0.3  # it turned
    qx, qy, qz, qw = odom.orientation
    assert (qx, qy) == (0.0, 0.0)
    assert math.hypot(qz, qw) == pytest.approx(1.0)
    assert 2 * math.atan2(qz, qw) == pytest.approx(odom.yaw_rad)

    pose = odom.pose_covariance
    assert len(pose) == 36
    matrix = [pose[row * 6 : row * 6 + 6] for row in range(6)]
    assert all(matrix[r][c] == matrix[c][r] for r in range(6) for c in range(6))
    # x, y and yaw are the odometry's own covariance, which grew with the distance ...
    for i, r in enumerate((0, 1, 5)):
        for j, c in enumerate((0, 1, 5)):
            assert matrix[r][c] == odom.covariance[i * 3 + j]
    assert 0 < matrix[0][0] < 0.01
    assert 0 < matrix[5][5] < 0.01
    # ... z, roll and pitch cannot be seen by wheels: large, and uncorrelated.
    for r in (2, 3, 4):
        assert matrix[r][r] == 1e6
        assert [v for c, v in enumerate(matrix[r]) if c != r] == [0.0] * 5

    twist = odom.twist_covariance
    assert len(twist) == 36
    diagonal = [twist[i * 7] for i in range(6)]
    assert diagonal[2:5] == [1e6] * 3
    assert 0 < diagonal[0] < 0.01
    assert 0 < diagonal[5] < 0.1
    assert sum(twist) == sum(diagonal)


def test_wheel_odom_frames_default_to_odom_and_base_link(kind: str) -> None:
    async def check(robot: Robot, _: object) -> WheelOdomSample | None:
        await asyncio.sleep(0.1)
        return robot.latest("wheel_odom")

    odom = run(kind, check)
    assert odom is not None
    assert (odom.frame_id, odom.child_frame_id) == ("odom", "base_link")
    # Standing where it opened: a filter that inverts the pose covariance still can.
    assert min(odom.pose_covariance[i * 7] for i in range(6)) > 0


def test_servo_samples_carry_the_last_position_and_torque_commanded(kind: str) -> None:
    async def check(robot: Robot, _: object) -> tuple[ServoSample, ServoSample, ServoSample]:
        await asyncio.sleep(0.1)
        before = robot.latest("servo_neck")
        assert before is not None
        await robot.neck.move(400, playtime_s=0.3, wait=True)
        moved = (await samples_for(robot, "servo_neck", 0.1))[-1]
        neck: Any = robot.neck
        await neck.free()
        await asyncio.sleep(0.1)
        freed = (await samples_for(robot, "servo_neck", 0.1))[-1]
        return before, moved, freed

    before, moved, freed = run(kind, check, neck_zero_offset_raw=12)
    assert (before.position_raw_cmd, before.pos_rad_cmd, before.torque_cmd) == (None, None, None)
    assert moved.position_raw_cmd == 400
    assert moved.pos_rad_cmd == pytest.approx(angle_rad_from_raw(400, zero_offset_raw=12))
    assert moved.pos_rad_cmd == pytest.approx(moved.angle_rad, abs=0.03)  # it is there
    assert moved.torque_cmd is TorqueControl.ON
    assert freed.torque_cmd is TorqueControl.FREE
    assert freed.position_raw_cmd == 400  # the last target sent, still


def test_an_external_servo_sample_carries_its_own_commands(kind: str) -> None:
    async def check(robot: Robot, _: object) -> tuple[ServoSample, ServoSample]:
        servo: Any = robot.servo(11)
        await servo.move(600, playtime_s=0.2, wait=True)
        ext = (await samples_for(robot, "servo_ext1", 0.1))[-1]
        neck = (await samples_for(robot, "servo_neck", 0.1))[-1]
        return ext, neck

    ext, neck = run(kind, check)
    assert (ext.sid, ext.position_raw_cmd, ext.torque_cmd) == (11, 600, TorqueControl.ON)
    assert (neck.position_raw_cmd, neck.torque_cmd) == (None, None)


@asynccontextmanager
async def worm_robot(kind: str) -> AsyncIterator[Robot]:
    """A robot with the worm-gear neck, local or through a daemon."""
    if kind == "local":
        async with Robot.open("sim://?neck=worm") as robot:
            yield robot
        return
    async with (
        LocalRobot.open("sim://?neck=worm") as served,
        RobotServer(served, port=0) as server,
        Robot.open(server.url) as robot,
    ):
        yield robot


def test_new_neck_samples_carry_the_last_target_and_no_angle(kind: str) -> None:
    async def check() -> tuple[WormNeckSample, WormNeckSample]:
        async with worm_robot(kind) as robot:
            await asyncio.sleep(0.1)
            before = robot.latest("new_neck")
            assert before is not None
            await robot.neck.move(-50_000, wait=True)
            after = (await samples_for(robot, "new_neck", 0.1))[-1]
            return before, after

    before, after = run_virtual(check())
    assert before.position_raw_cmd is None
    assert after.position_raw_cmd == -50_000
    assert abs(after.position_raw - -50_000) <= 1000
    # No angle is known for the worm gear's units, and it has no torque mode.
    for sample in (before, after):
        assert (sample.pos_rad, sample.pos_rad_cmd, sample.torque_cmd) == (None, None, None)
