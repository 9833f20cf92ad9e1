"""Physics of the simulated robot: wheels, pose, encoders, battery, worm neck.

Commands and readings go over the Bus on ``sim://`` like a user's would; the robot's
ground truth (``SimTransport.robot``) is what they are checked against. Everything runs
on the virtual clock, so the results are exact and repeatable.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.errors import InvalidArgumentError
from ohmni_tb.protocol import Command, Packet, ReadReply
from ohmni_tb.protocol.core import TbcoreStatus, parse_status, read_status
from ohmni_tb.protocol.drive import (
    parse_count,
    parse_motor_position,
    read_count,
    read_motor_position,
    wheel_command,
)
from ohmni_tb.protocol.worm_neck import (
    WormFeedback,
    WormFlags,
    parse_feedback,
    read_feedback,
    set_target,
)
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.drive import MotorModel, Pose
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport

TICKS_PER_WHEEL_TURN = 16384 * 30 / 11
WHEEL_RADIUS_M = 0.076
WHEEL_SEPARATION_M = 0.330
METRES_PER_TICK = 2 * math.pi * WHEEL_RADIUS_M / TICKS_PER_WHEEL_TURN


def _on_sim(url: str, body: Callable[[Bus, SimRobot, SimTransport], Awaitable[None]]) -> None:
    """Run ``body`` with a Bus on the simulated robot ``url``, on the virtual clock."""

    async def main() -> None:
        sim = await open_transport(url)
        assert isinstance(sim, SimTransport)
        assert sim.robot is not None
        async with Bus(sim) as bus:
            await body(bus, sim.robot, sim)

    run_virtual(main())


async def _read(bus: Bus, request: Packet) -> ReadReply:
    reply = await bus.request(request)
    assert reply is not None
    return ReadReply.parse(reply)


async def _counts(bus: Bus) -> tuple[int, int]:
    """Raw board-frame counts of the left and right boards."""
    left = parse_count(await _read(bus, read_count(0)))
    right = parse_count(await _read(bus, read_count(1)))
    return left, right


async def _status(bus: Bus) -> TbcoreStatus:
    return parse_status(await _read(bus, read_status()))


async def _drive(bus: Bus, left_pwm: int, right_pwm: int, seconds: float) -> None:
    """Send the wheel command at 50 Hz for ``seconds``, as a control loop would."""
    for _ in range(round(seconds * 50)):
        await bus.send(wheel_command(left_pwm, right_pwm))
        await asyncio.sleep(0.02)


async def _stop(bus: Bus) -> None:
    await bus.send(wheel_command(0, 0))
    await asyncio.sleep(0.5)


# -- wheels -------------------------------------------------------------------------------


def test_the_model_top_speed_is_one_metre_a_second() -> None:
    assert MotorModel().top_speed_mps == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("pwm", [1000, 700, 300, -500, -1000])
def test_a_pwm_step_settles_at_the_model_speed(pwm: int) -> None:
    model = MotorModel()
    duty = abs(pwm) / 1000
    expected = math.copysign(model.v_free_mps * (duty - model.dead_band_duty), pwm)

    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, pwm, pwm, 2.0)
        left, right = robot.wheel_speeds_mps()
        assert left == pytest.approx(expected, rel=0.01)
        assert right == pytest.approx(expected, rel=0.01)

    _on_sim("sim://", body)


def test_full_pwm_reaches_the_top_speed() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, 1000, 1000, 2.0)
        assert robot.wheel_speeds_mps()[0] == pytest.approx(1.0, rel=0.01)

    _on_sim("sim://", body)


@pytest.mark.parametrize("pwm", [50, -50, 59])
def test_pwm_inside_the_dead_band_does_not_move_the_wheels(pwm: int) -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, pwm, pwm, 1.0)
        assert robot.wheel_speeds_mps() == (0.0, 0.0)
        assert await _counts(bus) == (0, 0)
        assert robot.pose.x == 0.0

    _on_sim("sim://", body)


def test_a_wheel_coasts_to_a_stop_and_stays_there() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, 600, 600, 1.0)
        await _stop(bus)
        assert robot.wheel_speeds_mps() == (0.0, 0.0)
        before = await _counts(bus)
        await asyncio.sleep(1.0)
        assert await _counts(bus) == before

    _on_sim("sim://", body)


def test_power_cycle_stops_the_wheels() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, 600, 600, 1.0)
        sim.line.power_cycle()
        await asyncio.sleep(0.5)
        assert robot.wheel_speeds_mps() == (0.0, 0.0)

    _on_sim("sim://", body)


def test_an_idle_hour_moves_nothing_and_the_wheels_drive_after_it() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await bus.send(wheel_command(40, 40))  # inside the dead band: held by friction
        await asyncio.sleep(3600.0)
        assert await _counts(bus) == (0, 0)
        assert robot.pose == Pose(0.0, 0.0, 0.0)
        await _drive(bus, 500, 500, 1.0)
        await _stop(bus)
        left, right = await _counts(bus)
        assert left > 0 > right
        assert robot.pose.x == pytest.approx(0.5 * (left - right) * METRES_PER_TICK, rel=1e-3)

    _on_sim("sim://", body)


# -- pose and counts ----------------------------------------------------------------------


def test_driving_straight_the_pose_matches_the_counts() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, 500, 500, 2.0)
        await _stop(bus)
        left, right = await _counts(bus)
        # Forward: the left board counts up, the right board (mirrored) counts down.
        assert left > 0
        assert right < 0
        assert abs(left + right) <= 1  # same motion, floor rounding only
        distance_m = 0.5 * (left - right) * METRES_PER_TICK
        pose = robot.pose
        assert distance_m > 0.5
        assert pose.x == pytest.approx(distance_m, rel=1e-3)
        assert pose.y == pytest.approx(0.0, abs=1e-9)
        assert pose.yaw == pytest.approx(0.0, abs=1e-9)

    _on_sim("sim://", body)


def test_driving_backwards_the_counts_turn_the_other_way() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, -400, -400, 1.0)
        await _stop(bus)
        left, right = await _counts(bus)
        assert left < 0 < right
        assert robot.pose.x == pytest.approx(0.5 * (left - right) * METRES_PER_TICK, rel=1e-3)

    _on_sim("sim://", body)


def test_a_spin_turns_on_the_spot() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        # Robot frame: left forward, right backward, so it turns clockwise (yaw falls).
        await _drive(bus, 400, -400, 1.0)
        await _stop(bus)
        left, right = await _counts(bus)
        assert left > 0
        assert right > 0  # the mirrored right board turned positive: wheel went backwards
        d_left = left * METRES_PER_TICK
        d_right = -right * METRES_PER_TICK
        pose = robot.pose
        assert pose.yaw < -1.0
        assert pose.yaw == pytest.approx((d_right - d_left) / WHEEL_SEPARATION_M, rel=1e-3)
        assert pose.x == pytest.approx(0.0, abs=1e-6)
        assert pose.y == pytest.approx(0.0, abs=1e-6)

    _on_sim("sim://", body)


def test_an_arc_ends_where_the_closed_form_says() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, 300, 600, 1.5)
        await _stop(bus)
        left, right = await _counts(bus)
        d_left, d_right = left * METRES_PER_TICK, -right * METRES_PER_TICK
        yaw = (d_right - d_left) / WHEEL_SEPARATION_M
        assert yaw > 0  # right wheel faster: turns left
        pose = robot.pose
        assert pose.yaw == pytest.approx(yaw, rel=1e-3)
        # Different spin-up times mean the path is not one arc, but it stays near one.
        radius = 0.5 * (d_left + d_right) / yaw
        assert pose.x == pytest.approx(radius * math.sin(yaw), rel=0.05)
        assert pose.y == pytest.approx(radius * (1 - math.cos(yaw)), rel=0.05)

    _on_sim("sim://", body)


# -- traction lost, wheels blocked --------------------------------------------------------


def test_a_wheel_without_traction_turns_but_the_robot_pivots_about_it() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _drive(bus, 400, 400, 1.0)  # straight ahead
        before = robot.pose
        start_left, start_right = await _counts(bus)
        robot.slip(1)  # the right wheel (board 1) loses its grip
        assert robot.slipping_wheels == (False, True)
        await _drive(bus, 400, 400, 1.0)
        left, right = await _counts(bus)
        d_left = (left - start_left) * METRES_PER_TICK
        d_right = -(right - start_right) * METRES_PER_TICK
        # It turns and counts, and faster than the loaded wheel at the same PWM.
        assert d_right > d_left * 1.05
        # The ground under it stands: the robot pivots clockwise about the right wheel.
        after = robot.pose
        assert after.yaw - before.yaw == pytest.approx(-d_left / WHEEL_SEPARATION_M, rel=0.02)
        robot.slip(1, on=False)
        await _drive(bus, 400, 400, 0.5)  # the free-running wheel slows to the other's
        turned = robot.pose.yaw
        await _drive(bus, 400, 400, 1.0)
        assert robot.pose.yaw == pytest.approx(turned, abs=1e-3)  # straight again

    _on_sim("sim://", body)


def test_stall_and_slip_name_the_drive_board_by_its_id() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        robot.stall(0)
        await _drive(bus, 400, 400, 0.5)
        left, right = await _counts(bus)
        assert left == 0  # blocked: it does not turn whatever its PWM
        assert right < -1000
        robot.stall(0, on=False)
        await _drive(bus, 400, 400, 0.5)
        assert (await _counts(bus))[0] > 1000
        with pytest.raises(InvalidArgumentError, match=r"no drive board answers to id 7.*0 \(left"):
            robot.stall(7)
        with pytest.raises(InvalidArgumentError, match="id 20"):
            robot.slip(20)

    _on_sim("sim://", body)


# -- encoder wrap -------------------------------------------------------------------------


def test_the_int32_count_and_the_motor_position_wrap() -> None:
    offset = 2_147_483_000  # 647 ticks below 2**31 - 1

    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        left0, right0 = await _counts(bus)
        assert left0 == right0 == offset
        pos0 = parse_motor_position(await _read(bus, read_motor_position(0)))
        assert pos0 == offset % 16384
        await _drive(bus, 300, 300, 0.5)
        await _stop(bus)
        left, right = await _counts(bus)
        # The left board passed 2**31 - 1 and went on from -2**31.
        assert -(2**31) <= left < -(2**31) + 100_000
        travelled = (left - left0) % 2**32
        assert travelled > 647
        # The right board counted down, away from the wrap.
        assert right < right0
        assert abs(travelled - (right0 - right)) <= 1
        assert robot.pose.x == pytest.approx(travelled * METRES_PER_TICK, rel=1e-3)
        pos = parse_motor_position(await _read(bus, read_motor_position(0)))
        assert pos == (pos0 + travelled) % 16384
        assert pos < pos0  # it wrapped past 16383 as well

    _on_sim(f"sim://?count_offset={offset}", body)


# -- battery ------------------------------------------------------------------------------


def test_the_pack_sags_while_the_motors_draw_current() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await asyncio.sleep(1.0)
        idle = await _status(bus)
        await bus.send(wheel_command(1000, 1000))
        await asyncio.sleep(0.05)  # accelerating: the motors draw the most
        loaded = await _status(bus)
        assert loaded.pack_mv < idle.pack_mv - 100
        assert loaded.charging_current_ma < idle.charging_current_ma < 0
        await _stop(bus)
        await asyncio.sleep(1.0)
        rested = await _status(bus)
        assert rested.pack_mv > loaded.pack_mv
        assert rested.charging_current_ma == idle.charging_current_ma

    _on_sim("sim://", body)


def test_docking_charges_the_pack() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        undocked = await _status(bus)
        assert not undocked.docked
        assert not undocked.charging
        assert not undocked.status[0] & 0x01
        robot.set_docked(True)
        await asyncio.sleep(1.0)
        docked = await _status(bus)
        assert docked.docked
        assert docked.charging
        assert docked.charging_current_ma > 0
        assert docked.pack_mv > undocked.pack_mv
        assert docked.status[0] & 0x01  # docked bit of status 1
        assert docked.fet_status & 0x01  # charge FET on
        robot.set_docked(False)
        await asyncio.sleep(1.0)
        off = await _status(bus)
        assert not off.docked
        assert off.charging_current_ma < 0
        assert off.pack_mv < docked.pack_mv

    _on_sim("sim://", body)


def test_a_full_pack_stops_charging_on_the_dock() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await asyncio.sleep(1.0)
        status = await _status(bus)
        assert status.docked
        assert status.charging_current_ma == 0  # the dock only feeds the load
        assert status.percent == 100

    _on_sim("sim://?soc=100&docked=1", body)


def test_the_pack_discharges_over_time() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        start = await _status(bus)
        await asyncio.sleep(2 * 3600.0)  # two hours idle at ~2.2 A from 8 Ah
        later = await _status(bus)
        assert later.pack_mv < start.pack_mv
        assert (start.percent, later.percent) == (80, 50)

    _on_sim("sim://", body)


# -- worm neck ----------------------------------------------------------------------------


async def _neck(bus: Bus) -> WormFeedback:
    return parse_feedback(await _read(bus, read_feedback()))


async def _raw_target(bus: Bus, position: int) -> None:
    """A target written by hand, past the codec's range check."""
    data = bytes((0x70, 4)) + position.to_bytes(4, "little", signed=True)
    await bus.send(Packet(4, Command.RAM_WRITE, data))


def test_worm_neck_travels_at_a_finite_speed_to_its_target() -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        assert await _neck(bus) == WormFeedback(0, WormFlags.NONE)
        await bus.send(set_target(100_000))
        await asyncio.sleep(0.2)
        on_the_way = await _neck(bus)
        assert on_the_way.moving
        assert 0 < on_the_way.position < 100_000
        await asyncio.sleep(3.0)
        there = await _neck(bus)
        assert there.position == 100_000
        assert not there.moving
        assert not there.stalled
        await bus.send(set_target(-127_000))
        await asyncio.sleep(5.0)
        assert (await _neck(bus)).position == -127_000

    _on_sim("sim://?neck=worm", body)


@pytest.mark.parametrize(("target", "stop"), [(130_000, 120_000), (-200_000, -127_000)])
def test_an_out_of_range_target_stalls_the_neck_until_power_cycle(target: int, stop: int) -> None:
    async def body(bus: Bus, robot: SimRobot, sim: SimTransport) -> None:
        await _raw_target(bus, target)
        await asyncio.sleep(5.0)
        stalled = await _neck(bus)
        assert stalled.stalled
        assert not stalled.moving
        assert stalled.position == stop
        # A valid target is ignored while stalled, however long we wait.
        await bus.send(set_target(0))
        await asyncio.sleep(5.0)
        still = await _neck(bus)
        assert still.stalled
        assert still.position == stop
        sim.line.power_cycle()
        after = await _neck(bus)
        assert not after.stalled
        assert after.position == stop  # it stays where it stalled
        await bus.send(set_target(0))
        await asyncio.sleep(5.0)
        assert await _neck(bus) == WormFeedback(0, WormFlags.NONE)

    _on_sim("sim://?neck=worm", body)
