"""The Robot runs with the bus profile it is given: on a robot whose boards differ from the
assumed profile, the right profile makes it work with no other change."""

from __future__ import annotations

import asyncio

import pytest

from ohmni_tb import Robot
from ohmni_tb.config import RobotConfig
from ohmni_tb.errors import ConfigError, MotionError
from ohmni_tb.protocol.profile import DEFAULT_PROFILE, BusProfile
from ohmni_tb.robot import LocalRobot

#: A robot whose boards take I_JOG, keep the battery block at 0xB0 as five cells alone,
#: and whose external servos are 13 and 14.
VARIANT_URL = (
    "sim://?wheel_form=i_jog&battery_addr=0xB0&battery_layout=cells&battery_length=10"
    "&ext_servos=13,14"
)
VARIANT = BusProfile.from_settings(
    {
        "wheel_form": "i_jog",
        "battery_addr": 0xB0,
        "battery_layout": "cells",
        "battery_length": 10,
        "ext_servo_ids": (13, 14),
    }
)


async def test_with_its_profile_the_robot_drives_reads_the_battery_and_finds_its_servos() -> None:
    async with Robot.open(VARIANT_URL, profile=VARIANT) as robot:
        info = await robot.info()
        assert {13, 14} <= set(info["present"])
        assert info["profile"]["battery_addr"] == 0xB0
        assert info["profile"]["ext_servo_ids"] == [13, 14]
        await asyncio.sleep(0.5)
        battery = robot.latest("tbcore_status")
        assert battery is not None
        assert all(3.0 < v < 3.5 for v in battery.cell_v)
        result = await robot.drive_distance(0.3)
        assert result.distance_m == pytest.approx(0.3, abs=0.01)
        assert isinstance(robot, LocalRobot)
        assert robot.sim.pose.x == pytest.approx(0.3, abs=0.02)


async def test_with_the_assumed_profile_the_same_robot_does_not_drive() -> None:
    async with Robot.open(VARIANT_URL) as robot:
        await asyncio.sleep(0.5)
        battery = robot.latest("tbcore_status")
        assert battery is None or battery.pack_v == 0.0  # nothing at 0xA0
        with pytest.raises(MotionError, match=r"ohmni probe --allow-motion"):
            await robot.drive_distance(0.3)
        assert isinstance(robot, LocalRobot)
        assert robot.sim.pose.x == 0.0


async def test_the_settings_give_the_same_profile_as_the_object(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for name, value in VARIANT.as_json().items():
        shown = ",".join(map(str, value)) if isinstance(value, list) else str(value)
        monkeypatch.setenv(f"OHMNI_{name.upper()}", shown)
    async with Robot.open(VARIANT_URL, config=RobotConfig()) as robot:
        assert robot.config.profile() == VARIANT
        result = await robot.drive_distance(0.2)
        assert result.distance_m == pytest.approx(0.2, abs=0.01)


async def test_the_profile_is_fixed_while_the_robot_is_open() -> None:
    async with Robot.open("sim://") as robot:
        with pytest.raises(ConfigError, match=r"bus profile \(wheel_form\) is fixed"):
            robot.config = robot.config.replace(wheel_form="i_jog")
        # The servo ids are not: the Robot follows an id change.
        robot.config = robot.config.replace(ext_servo_ids=(11,))
        assert robot.config.ext_servo_ids == (11,)


async def test_a_profile_and_a_profile_setting_at_once_are_refused() -> None:
    with pytest.raises(ConfigError, match="wheel_form given both alone and in profile"):
        async with Robot.open("sim://", profile=DEFAULT_PROFILE, wheel_form="i_jog"):
            pass
    with pytest.raises(ConfigError, match="profile must be a BusProfile"):
        async with Robot.open("sim://", profile={"wheel_form": "i_jog"}):  # type: ignore[arg-type]  # a user's mistake
            pass


async def test_a_remote_robot_takes_no_profile() -> None:
    with pytest.raises(ConfigError, match="profile cannot be given to a remote robot"):
        async with Robot.open("ws://127.0.0.1:9", profile=DEFAULT_PROFILE):
            pass


async def test_a_battery_block_that_is_not_a_pack_is_a_fault_that_names_the_probe() -> None:
    events: list[str] = []
    async with Robot.open(VARIANT_URL) as robot:  # the assumed profile: nothing at 0xA0
        states = robot.subscribe("robot_state")
        await asyncio.sleep(1.0)
        assert "battery_implausible" in robot.state.faults
        while (sample := states.get_nowait()) is not None:
            if sample.event:
                events.append(sample.event)
    assert any("battery block at RAM 0xA0 reads cells 0/0/0/0/0 mV" in e for e in events), events
    assert any("ohmni probe" in e for e in events)
    async with Robot.open(VARIANT_URL, profile=VARIANT) as robot:
        await asyncio.sleep(1.0)
        assert "battery_implausible" not in robot.state.faults
