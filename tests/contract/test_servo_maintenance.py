"""Servo maintenance through the contract, local and through the daemon alike: reading
every register, writing one, the zero offset, a servo's new id (the robot follows it) and
a drive board's new id (only when confirmed) — judged by the simulator's truth."""

from __future__ import annotations

import asyncio

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, StateError
from ohmni_tb.sim.robot import SimRobot

from .conftest import run
from .test_contract import drive_for


def test_servo_info_and_a_register_write_reach_the_servo(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        servo = robot.servo(11)
        before = await servo.info()
        assert before["ram"]["id"] == 11
        assert before["eep"]["id"] == 11
        await servo.write("led_control", 2)
        await servo.write("max_pwm", 900, persist=True)
        after = await servo.info()
        assert after["ram"]["led_control"] == 2
        assert after["ram"]["max_pwm"] == 900
        assert after["eep"]["max_pwm"] == 900
        with pytest.raises(OutOfRangeError, match="max_pwm"):
            await servo.write("max_pwm", 5000)
        with pytest.raises(InvalidArgumentError, match="set_id"):
            await servo.write("id", 13)
        assert (await servo.info())["ram"]["id"] == 11  # nothing was sent

    run(kind, check)


def test_the_zero_offset_moves_the_angle_of_the_samples(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await robot.neck.move(512, playtime_s=0.2, wait=True)
        await robot.servo(3).set_zero_offset(100)
        assert robot.servo(3).zero_offset_raw == 100
        assert robot.config.neck_zero_offset_raw == 100
        await asyncio.sleep(0.2)
        sample = robot.latest("servo_neck")
        assert sample is not None
        # 512 is now 100 counts below the zero: about −0.33 rad (0.325 ° a count).
        assert sample.angle_rad == pytest.approx(-100 * 0.325 * 3.14159265 / 180, abs=0.01)
        with pytest.raises(OutOfRangeError, match="zero_offset_raw"):
            await robot.servo(3).set_zero_offset(600)

    run(kind, check)


def test_a_servo_given_a_new_id_keeps_its_stream_and_handle(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await asyncio.sleep(0.5)
        missed = robot.stats().streams["servo_ext1"].missed
        handle = robot.servo(11)
        await handle.set_id(13)
        assert handle.sid == 13
        assert [servo.sid for servo in truth.ext_servos] == [13, 12]
        assert robot.servo(13).sid == 13
        with pytest.raises(StateError, match="given id 13"):
            robot.servo(11)
        assert robot.config.ext_servo_ids == (13, 12)
        await asyncio.sleep(1.0)
        latest = robot.latest("servo_ext1")
        assert latest is not None
        assert latest.sid == 13
        assert latest.stamp_s > asyncio.get_running_loop().time() - 0.1
        await robot.confirm()
        assert robot.stats().streams["servo_ext1"].missed == missed
        await robot.servo(13).move(700, playtime_s=0.2, wait=True)

    run(kind, check)


def test_a_new_id_another_device_answers_to_is_refused_with_nothing_sent(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        for taken, who in ((12, "servo 12"), (20, "core"), (3, "servo 3"), (0, "drive")):
            with pytest.raises(StateError, match=f"cannot take id {taken}: .*{who}"):
                await robot.servo(11).set_id(taken)
        with pytest.raises(OutOfRangeError, match="254"):
            await robot.servo(11).set_id(254)
        assert [servo.sid for servo in truth.ext_servos] == [11, 12]
        assert robot.servo(11).sid == 11

    run(kind, check)


def test_a_drive_board_id_changes_only_when_confirmed(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        with pytest.raises(InvalidArgumentError, match="confirm=True"):
            await robot.reset_board_id(1, 7)
        with pytest.raises(InvalidArgumentError, match="not a drive board"):
            await robot.reset_board_id(11, 7, confirm=True)
        with pytest.raises(StateError, match="cannot take id 20"):
            await robot.reset_board_id(1, 20, confirm=True)
        assert truth.right.sid == 1
        await robot.reset_board_id(1, 7, confirm=True)
        assert truth.right.sid == 7
        await asyncio.sleep(0.2)
        assert 1 not in robot.state.present
        assert "drive_absent:1" in robot.state.faults
        await robot.reset_board_id(7, 1, confirm=True)  # back, so the stop on leaving confirms
        assert truth.right.sid == 1
        await asyncio.sleep(0.2)
        assert 1 in robot.state.present
        assert "drive_absent:1" not in robot.state.faults
        await drive_for(robot, 0.5)
        left, right = truth.wheel_speeds_mps()
        assert left > 0.1
        assert right > 0.1

    run(kind, check)


def test_a_drive_board_keeps_its_new_id_over_a_power_cycle() -> None:
    truth = SimRobot()
    from ohmni_tb.protocol.drive import set_board_id

    for packet in set_board_id(0, 9):
        truth.left.handle(packet, 0.0)
    assert truth.left.sid == 9
    truth.left.power_cycle(1.0)
    assert truth.left.sid == 9
