"""Switching the port at run time (tb_control's ``connect``), local and through the daemon
alike: ``port_of(robot)`` says which port is open, ``disconnect()`` stops the wheels and closes
it, ``connect(port)`` opens another one (or the same again)."""

from __future__ import annotations

import asyncio

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import InvalidArgumentError, StateError, TransportError
from ohmni_tb.robot import Link
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.transport.ports import list_ports

from .conftest import run
from .test_contract import drive_for, speed


def port_of(robot: Robot) -> str | None:
    """``robot.port`` now (a call: it changes under the awaits)."""
    return robot.port


def link_of(robot: Robot) -> Link:
    """The link now."""
    return robot.state.link


def test_port_says_which_port_is_open(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        assert port_of(robot) == "sim://"
        await robot.disconnect()
        assert port_of(robot) is None
        await robot.connect()
        assert port_of(robot) == "sim://"

    run(kind, check)


def test_disconnect_stops_the_wheels_and_commands_wait_for_connect(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await drive_for(robot, 0.5)
        assert speed(truth) > 0.1
        await robot.disconnect()
        assert speed(truth) == 0.0
        assert link_of(robot) is Link.RELEASED
        with pytest.raises(StateError, match="disconnected from its port; connect"):
            await robot.light_ring(0, 0, 0)
        await robot.connect()
        await asyncio.sleep(0.3)
        assert link_of(robot) is Link.CONNECTED
        assert robot.latest("wheel_encoder") is not None
        await drive_for(robot, 0.5)
        assert speed(truth) > 0.1

    run(kind, check)


def test_connect_switches_to_another_port_and_the_streams_follow(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        assert robot.neck_kind == "herkulex"
        await drive_for(robot, 0.5)
        await robot.connect("sim://?ext=none")
        assert port_of(robot) == "sim://?ext=none"
        assert speed(truth) == 0.0  # the old port's wheels stopped before it closed
        await asyncio.sleep(0.5)
        before = robot.latest("wheel_odom")
        assert before is not None
        await drive_for(robot, 0.5)
        after = robot.latest("wheel_odom")
        assert after is not None
        assert after.x_m > before.x_m + 0.02  # the robot on the new port drove
        assert speed(truth) == 0.0  # and not the old one

    run(kind, check)


def test_a_port_that_cannot_open_leaves_the_robot_disconnected(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        with pytest.raises(TransportError):
            await robot.connect("/dev/ohmni-no-such-port")
        assert port_of(robot) is None
        await robot.connect()  # the port it had
        assert port_of(robot) == "sim://"
        with pytest.raises(InvalidArgumentError, match="serial device or URL"):
            await robot.connect("ws://127.0.0.1:1")

    run(kind, check)


def test_list_ports_names_the_computers_serial_ports_even_while_disconnected(kind: str) -> None:
    # tb_control's get_connect_ports. The daemon in these tests runs on this computer, so
    # both kinds list the same ports as the computer's own list.
    here = [port.as_dict() for port in list_ports()]

    async def check(robot: Robot, truth: SimRobot) -> None:
        assert await robot.list_ports() == here
        await robot.disconnect()
        assert await robot.list_ports() == here
        await robot.connect()

    run(kind, check)
