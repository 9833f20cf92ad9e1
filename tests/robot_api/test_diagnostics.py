"""What each ``diagnostics`` entry says of a device in trouble, on the simulator: an unknown
firmware tag, a battery low, out of balance or not read as a pack, a hot or loaded servo,
a wheel whose PID sits at its limit, the watchdog, a released port, faults, and the
stream turned off."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

import numpy as np
import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import StateError
from ohmni_tb.robot import DiagnosticEntry, DiagnosticLevel, DiagnosticsSample, LocalRobot
from ohmni_tb.robot.diagnostics import (
    CELL_SPREAD_WARN_MV,
    LOW_CELL_WARN_MV,
    UNKNOWN_FIRMWARE,
)
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import SimServo
from ohmni_tb.transport import open_transport

OK, WARN, ERROR = DiagnosticLevel.OK, DiagnosticLevel.WARN, DiagnosticLevel.ERROR


async def health(
    robot: Robot,
    test: Callable[[DiagnosticsSample], bool] = lambda _: True,
    timeout_s: float = 3.0,
) -> DiagnosticsSample:
    """The first ``diagnostics`` sample from now on that passes ``test``."""
    async with robot.subscribe("diagnostics") as samples, asyncio.timeout(timeout_s):
        async for sample in samples:
            if test(sample):
                return sample
    raise AssertionError("the stream ended")


def entry(sample: DiagnosticsSample, key: str | int) -> DiagnosticEntry:
    found = sample.entry(key)
    assert found is not None, key
    return found


def not_ok(sample: DiagnosticsSample) -> dict[str, DiagnosticLevel]:
    return {e.name: e.level for e in sample.entries if e.level is not OK}


def truth(robot: LocalRobot) -> SimRobot:
    assert isinstance(robot.sim, SimRobot)
    return robot.sim


async def test_an_unknown_firmware_tag_is_warn_and_says_how_to_report_it() -> None:
    transport = await open_transport("sim://")
    sim = transport.simulated
    assert isinstance(sim, SimRobot)
    sim.right.tag = "2021-03-04-rc2"  # a board the project has not seen
    async with Robot.open(transport) as robot:
        sample = await health(robot)
    right = entry(sample, "right_drive")
    assert right.level is WARN
    assert right.message == f"firmware tag '2021-03-04-rc2' is {UNKNOWN_FIRMWARE}"
    assert "`ohmni probe --share FILE`" in right.message
    assert right.values["firmware"] == "2021-03-04-rc2"
    assert right.values["firmware_known"] is False
    assert entry(sample, "left_drive").values["firmware_known"] is True
    assert not_ok(sample) == {"right_drive": WARN}
    assert sample.level is WARN


async def test_a_battery_low_and_out_of_balance_is_warn_with_its_cells() -> None:
    async with LocalRobot.open("sim://?soc=8") as robot:
        truth(robot).core.pack.soc = np.array([0.08, 0.08, 0.08, 0.30, 0.08])
        await asyncio.sleep(0.5)  # the battery read again
        core = entry(await health(robot), "core")
    assert core.level is WARN
    lowest, spread = core.values["lowest_cell_mv"], core.values["cell_spread_mv"]
    assert isinstance(lowest, int)
    assert isinstance(spread, int)
    assert lowest < LOW_CELL_WARN_MV
    assert spread > CELL_SPREAD_WARN_MV
    assert f"battery low: a cell at {lowest} mV" in core.message
    assert f"cells {spread} mV apart" in core.message


async def test_a_battery_block_that_is_not_a_pack_is_error() -> None:
    # The battery block is elsewhere on this (simulated) robot: the Robot reads zeros.
    async with Robot.open("sim://?battery_addr=0xB0") as robot:
        core = entry(await health(robot, lambda s: entry(s, "core").level is ERROR), "core")
    assert core.message.startswith("fault battery_implausible")
    assert core.values["faults"] == "battery_implausible"
    assert core.values["lowest_cell_mv"] == 0


async def test_a_loaded_servo_is_warn_then_error_once_the_thermal_guard_frees_it() -> None:
    async with LocalRobot.open("sim://", thermal_limit_raw=175) as robot:
        servo = robot.servo(11)
        await servo.torque("on")
        await servo.move(raw=600, playtime_s=0.3)
        await asyncio.sleep(0.5)
        sim = next(s for s in truth(robot).ext_servos if s.sid == 11)
        assert isinstance(sim, SimServo)
        sim.set_load(1.0)
        loaded = await health(robot, lambda s: entry(s, 11).level is not OK)
        hot = await health(robot, lambda s: entry(s, 11).level is ERROR, timeout_s=120.0)
    ext1 = entry(loaded, "ext1")
    assert ext1.level is WARN
    assert ext1.message.startswith("loaded: PWM ")
    assert ext1.values["load_share"] == pytest.approx(1.0, abs=0.01)
    hot_ext1 = entry(hot, "ext1")
    assert hot_ext1.message.startswith("fault thermal:11")
    assert hot_ext1.values["thermal_limit_raw"] == 175
    assert hot.event is not None
    assert "ext1 warn → error: fault thermal:11" in hot.event


async def test_a_servo_near_its_thermal_limit_is_warm() -> None:
    async with Robot.open("sim://", thermal_limit_raw=165) as robot:  # the room is at 160
        neck = entry(await health(robot), "neck")
    assert neck.level is WARN
    assert neck.message == "warm: temperature 160 raw, the limit 165"


async def test_a_blocked_wheel_sits_at_the_pwm_limit_and_says_so() -> None:
    # The stall guard off: it would cut the wheel's power after stall_s.
    async with LocalRobot.open("sim://", stall_s=0) as robot:
        truth(robot).block_wheels(left=True, right=False)
        loop = asyncio.get_running_loop()
        until = loop.time() + 2.6
        while loop.time() < until:
            robot.drive_wheels(0.8, 0.8)
            await asyncio.sleep(0.05)
        sample = robot.latest("diagnostics")
        assert sample is not None
    left, right = entry(sample, "left_drive"), entry(sample, "right_drive")
    assert left.level is WARN
    assert left.values["pid_saturated_share"] == pytest.approx(1.0, abs=0.05)
    assert "PID at the PWM limit" in left.message
    assert right.level is OK
    assert right.values["pid_saturated_share"] == 0.0


async def test_the_link_counts_watchdog_trips() -> None:
    async with Robot.open("sim://") as robot:
        for trip in (1, 2):
            robot.drive(0.2, 0.0)
            await asyncio.sleep(1.0)  # watchdog_s 0.5: it stops the wheels
            link = entry(await health(robot), "link")
            assert link.values["watchdog_trips"] == trip
            assert link.values["watchdog_tripped"] is True
            assert link.level is OK  # the watchdog doing its job is no fault


async def test_a_released_port_is_warn_and_reads_nothing_of_the_servos() -> None:
    async with LocalRobot.open("sim://") as robot:
        await health(robot)
        await robot.release_port()
        before = robot.bus.stats.devices[11].requests
        released = await health(robot)
        assert robot.bus.stats.devices[11].requests == before
        await robot.reclaim_port()
        back = await health(robot, lambda s: s.level is OK)
    link = entry(released, "link")
    assert link.level is WARN
    assert link.values["state"] == "released"
    assert "released to another program" in link.message
    assert entry(back, "link").values["state"] == "connected"


async def test_a_drive_board_absent_at_open_is_error_with_its_fault() -> None:
    async with LocalRobot.open("sim://?silent=0") as robot:
        sample = await health(robot)
        robot.bus.transport.line.faults.silent.clear()  # type: ignore[attr-defined]  # so the stop on the way out is confirmed
    left = entry(sample, 0)
    assert left.level is ERROR
    assert left.message == (
        "fault drive_absent:0; absent: it does not answer (asked again every 5 s)"
    )
    assert left.values["present"] is False


async def test_stale_feedback_is_an_error_of_the_link_and_each_silent_board() -> None:
    async with LocalRobot.open("sim://") as robot:
        await health(robot)
        robot.bus.transport.line.faults.silent |= {0, 1}  # type: ignore[attr-defined]  # a SimTransport
        sample = await health(robot, lambda s: entry(s, "link").level is ERROR)
        robot.bus.transport.line.faults.silent.clear()  # type: ignore[attr-defined]  # so the stop on the way out is confirmed
    assert entry(sample, "link").message == "fault stale_feedback"
    assert entry(sample, "left_drive").message.startswith("silent: ")
    assert entry(sample, "right_drive").message.startswith("silent: ")
    assert set(not_ok(sample)) == {"left_drive", "right_drive", "link"}


async def test_the_stream_turned_off_sends_no_sample_and_on_again_does() -> None:
    async with Robot.open("sim://") as robot:
        await health(robot)
        robot.enable_stream("diagnostics", False)
        assert not robot.stats().streams["diagnostics"].enabled
        async with robot.subscribe("diagnostics") as samples:
            await asyncio.sleep(3.0)
            assert samples.pending == 0
        robot.enable_stream("diagnostics")
        await health(robot, timeout_s=1.1)


async def test_diagnostics_hz_0_turns_it_off_and_it_cannot_be_turned_on() -> None:
    async with Robot.open("sim://", diagnostics_hz=0) as robot:
        await asyncio.sleep(2.0)
        assert robot.latest("diagnostics") is None
        figures = robot.stats().streams["diagnostics"]
        assert not figures.enabled
        assert figures.samples == 0
        with pytest.raises(StateError, match="diagnostics_hz=0"):
            robot.enable_stream("diagnostics")


async def test_diagnostics_hz_sets_the_rate() -> None:
    async with Robot.open("sim://", diagnostics_hz=4) as robot:
        first = await health(robot)
        second = await health(robot)
        assert robot.stats().streams["diagnostics"].requested_hz == 4
    assert second.stamp_s - first.stamp_s == pytest.approx(0.25, abs=0.005)
