"""A servo's status bytes and its latched errors through the contract, local and through the
daemon alike: asked now, cleared (the torque stays as the fault left it) — judged by the
simulator's truth."""

from __future__ import annotations

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import StateError
from ohmni_tb.herkulex import TorqueControl, parse_reply, ram_read
from ohmni_tb.protocol import StatusError
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import SimServo

from .conftest import run


def _ram(truth: SimRobot, servo: SimServo, name: str) -> int:
    reply = servo.handle(ram_read(servo.sid, name), truth.sync())
    assert reply is not None
    return parse_reply(reply).value(name)


def test_a_latched_error_is_read_then_cleared_and_the_torque_stays_off(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        servo = robot.servo(11)
        sim = truth.ext_servos[0]
        await servo.move(700, playtime_s=0.1, wait=True)
        status = await servo.status()
        assert status.ok
        assert status.torque_on
        # 12 V is above max_voltage (10.1 V): the servo latches the error and, by its
        # torque policy, lets go.
        truth.sync()
        sim.set_supply_voltage(12.0)
        status = await servo.status()
        assert status.error & StatusError.INPUT_VOLTAGE
        assert not status.torque_on
        truth.sync()
        sim.set_supply_voltage(7.4)
        assert (await servo.status()).error & StatusError.INPUT_VOLTAGE  # latched
        cleared = await servo.clear_errors()
        assert cleared.ok
        assert not cleared.torque_on
        assert _ram(truth, sim, "status_error") == 0
        assert _ram(truth, sim, "torque_control") == TorqueControl.FREE
        await servo.move(600, playtime_s=0.1, wait=True)  # it takes moves again
        assert abs(_ram(truth, sim, "calibrated_position") - 600) <= 5

    run(kind, check)


def test_the_status_of_a_released_port_is_refused(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await robot.release_port()
        with pytest.raises(StateError, match="released"):
            await robot.servo(11).status()
        with pytest.raises(StateError, match="released"):
            await robot.servo(11).clear_errors()
        await robot.reclaim_port()

    run(kind, check)
