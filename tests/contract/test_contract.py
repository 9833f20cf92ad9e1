"""The Robot contract, judged the same way on a local robot and on a daemon's: the streams
at their rates, driving, the watchdog, stopping, the gains, the odometry, the rates and
streams, the neck, closing, the motion goals — each through the contract only, with the
simulator's truth to say what the robot really did."""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import (
    MotionPreemptedError,
    OhmniError,
    OutOfRangeError,
    RobotClosedError,
    StateError,
)
from ohmni_tb.herkulex import parse_reply, ram_read, reboot
from ohmni_tb.robot import SampleStream, ServoSample
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import RESTART_S, SimServo

from .conftest import opened, run

#: How far a rate may be from the one asked, by the samples' own stamps.
RATE_TOLERANCE = {"local": 0.01, "remote": 0.03}
#: How close drive_distance(0.5) ends to 0.5 m by the simulator's truth.
DISTANCE_TOLERANCE_M = {"local": 0.01, "remote": 0.02}


def speed(truth: SimRobot) -> float:
    """The simulated body's true forward speed, m/s."""
    left, right = truth.wheel_speeds_mps()
    return (left + right) / 2


async def drive_for(robot: Robot, seconds: float, linear_mps: float = 0.3) -> None:
    """Drive as a teleop does: the command again at 20 Hz, inside the watchdog time."""
    loop = asyncio.get_running_loop()
    until_s = loop.time() + seconds
    while loop.time() < until_s:
        robot.drive(linear_mps, 0.0)
        await asyncio.sleep(0.05)


async def drive_confirmed(robot: Robot) -> None:
    """A drive command, and the daemon's answer to it (a local robot refuses at once)."""
    robot.drive(0.3, 0.0)
    await robot.confirm()


async def wheels_confirmed(robot: Robot) -> None:
    """A drive_wheels command, and the daemon's answer to it."""
    robot.drive_wheels(0.2, 0.2)
    await robot.confirm()


async def until(condition: Callable[[], bool], timeout_s: float = 3.0) -> None:
    """Wait for ``condition()``, looked at every 20 ms."""
    async with asyncio.timeout(timeout_s):
        while not condition():  # noqa: ASYNC110  # the simulator's truth has no event
            await asyncio.sleep(0.02)


async def stamps(subscription: SampleStream[Any], seconds: float) -> list[float]:
    """The stamps of the samples a subscription gets in ``seconds``."""
    got: list[float] = []

    async def read() -> None:
        async for sample in subscription:
            got.append(sample.stamp_s)  # noqa: PERF401  # until the time is up

    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(read(), seconds)
    return got


def rate_hz(got: list[float]) -> float:
    assert len(got) >= 2
    return (len(got) - 1) / (got[-1] - got[0])


def test_every_stream_arrives_at_its_rate(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> dict[str, tuple[float, float]]:
        asked = {
            name: figures.requested_hz
            for name, figures in robot.stats().streams.items()
            if figures.enabled and figures.requested_hz >= 10  # robot_state: 1 Hz, events too
        }
        subscriptions = {name: robot.subscribe(name, maxlen=1000) for name in asked}
        got = await asyncio.gather(*(stamps(s, 3.0) for s in subscriptions.values()))
        assert all(s.dropped == 0 for s in subscriptions.values())
        return {name: (asked[name], rate_hz(g)) for name, g in zip(asked, got, strict=True)}

    rates = run(kind, check)
    assert set(rates) == {
        "wheel_encoder",
        "wheel_odom",
        "tbcore_status",
        "servo_neck",
        "servo_ext1",
        "servo_ext2",
    }
    for name, (asked, got) in rates.items():
        assert got == pytest.approx(asked, rel=RATE_TOLERANCE[kind]), name


def test_drive_moves_the_robot_and_the_watchdog_stops_it(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        limited = robot.drive(0.3, 0.0)
        assert limited.twist.linear_mps == 0.3
        await drive_for(robot, 1.0)
        assert speed(truth) == pytest.approx(0.3, abs=0.03)
        assert truth.pose.x > 0.2
        odom = robot.latest("wheel_odom")
        assert odom is not None
        assert odom.x_m == pytest.approx(truth.pose.x, abs=0.05)
        # No command for watchdog_s: the robot stops by itself, and says why.
        await until(lambda: speed(truth) == 0.0, 2.0)
        await until(lambda: robot.state.watchdog_tripped, 1.0)

    run(kind, check)


def test_stop_ramps_down_and_estop_latches_until_cleared(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await drive_for(robot, 0.6)
        robot.stop()
        await until(lambda: speed(truth) == 0.0, 1.0)
        await drive_for(robot, 0.6)
        await robot.estop()
        await until(lambda: speed(truth) == 0.0, 0.5)
        await until(lambda: robot.state.estopped, 1.0)
        with pytest.raises(StateError, match="an emergency stop is latched"):
            await drive_confirmed(robot)
        robot.clear_estop()
        await robot.confirm()
        await drive_for(robot, 0.6)
        assert speed(truth) > 0.2

    run(kind, check)


def test_the_gains_round_trip_and_the_odometry_resets(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        gains = PidGains(kp=500.0, ki=200.0, kd=1.0, kff=900.0, ff_offset=50.0)
        assert robot.get_pid() != gains
        robot.set_pid(gains)
        robot.reset_odometry(1.0, 2.0, 0.5)
        await robot.confirm()
        assert robot.get_pid() == gains
        async with robot.subscribe("wheel_odom") as odom:
            await anext(odom)  # maybe integrated before the reset reached the robot
            sample = await anext(odom)
        assert (sample.x_m, sample.y_m, sample.yaw_rad) == pytest.approx((1.0, 2.0, 0.5), abs=1e-3)

    run(kind, check)


def test_set_rate_and_enable_stream_change_the_stream_and_the_schedule(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        robot.set_rate("tbcore_status", 5.0)
        await robot.confirm()
        await until(lambda: ("tbcore_status", 5.0) in [row[:2] for row in robot.schedule()])
        async with robot.subscribe("tbcore_status") as status:
            await anext(status)
            assert rate_hz(await stamps(status, 2.0)) == pytest.approx(5.0, rel=0.03)
        robot.enable_stream("tbcore_status", False)
        await robot.confirm()
        await until(lambda: "tbcore_status" not in [row[0] for row in robot.schedule()])
        async with robot.subscribe("tbcore_status") as status:
            assert await stamps(status, 1.0) == []

    run(kind, check)


def test_the_neck_moves_to_its_target(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[object, int]:
        assert robot.neck_kind == "herkulex"
        arrived = await robot.neck.move(400, playtime_s=0.5, wait=True)
        neck = truth.neck
        assert isinstance(neck, SimServo)
        # The servo's true position, asked of the simulated servo, not over the wire.
        reply = neck.handle(ram_read(neck.sid, "calibrated_position"), truth.sync())
        assert reply is not None
        return arrived, parse_reply(reply).value("calibrated_position")

    arrived, true_raw = run(kind, check)
    assert isinstance(arrived, ServoSample)
    assert abs(arrived.position_raw - 400) <= 5
    assert abs(true_raw - 400) <= 5


def test_the_longest_playtime_is_taken_and_one_beyond_it_refused(kind: str) -> None:
    # One playtime range everywhere: 0..2.8448 s (254 ticks of 11.2 ms), both ends in.
    async def check(robot: Robot, truth: SimRobot) -> tuple[float, int, str]:
        loop = asyncio.get_running_loop()
        await robot.neck.move(600, playtime_s=0.3, wait=True)
        start_s = loop.time()
        arrived = await robot.neck.move(400, playtime_s=2.8448, wait=True)
        took_s = loop.time() - start_s
        assert isinstance(arrived, ServoSample)
        with pytest.raises(OutOfRangeError) as refused:
            await robot.neck.move(600, playtime_s=2.85)
        await asyncio.sleep(0.5)
        neck = truth.neck
        assert isinstance(neck, SimServo)
        reply = neck.handle(ram_read(neck.sid, "calibrated_position"), truth.sync())
        assert reply is not None
        return took_s, parse_reply(reply).value("calibrated_position"), str(refused.value)

    took_s, true_raw, message = run(kind, check)
    # The servo took the whole 254 ticks (2.8448 s) to get there, not a clamped or
    # shortened playtime; the read-back comes within a poll or two after.
    assert 2.8448 <= took_s <= 2.8448 + 0.2
    assert "playtime_s=2.85 is out of range: allowed 0.0..2.8448 s" in message
    assert abs(true_raw - 400) <= 5  # the refused move sent nothing


#: tb_control's ~servo_neck_* parameters, as RobotConfig takes them, and the servo's
#: registers they must end up in.
NECK_SETTINGS = {
    "neck_min_raw": ("min_position", 300),
    "neck_max_raw": ("max_position", 600),
    "neck_kp": ("position_kp", 300),
    "neck_ki": ("position_ki", 5),
    "neck_kd": ("position_kd", 4000),
    "neck_min_voltage_raw": ("min_voltage", 80),
    "neck_max_voltage_raw": ("max_voltage", 130),
    "neck_overload_pwm": ("overload_pwm_threshold", 900),
    "neck_max_pwm": ("max_pwm", 1000),
}


def servo_ram(truth: SimRobot) -> dict[str, int]:
    """The simulated neck's settings registers, asked of it, not over the wire."""
    neck = truth.neck
    assert isinstance(neck, SimServo)
    values = {}
    for register, _ in NECK_SETTINGS.values():
        reply = neck.handle(ram_read(neck.sid, register), truth.sync())
        assert reply is not None, "the neck answers"
        values[register] = parse_reply(reply).value(register)
    return values


def test_the_neck_servo_gets_its_settings_at_open_and_again_after_a_reboot(kind: str) -> None:
    wanted = dict(NECK_SETTINGS.values())

    async def check(robot: Robot, truth: SimRobot) -> None:
        assert servo_ram(truth) == wanted
        first = (await robot.info())["neck_settings"]
        assert (first["sid"], first["memory"], first["ok"]) == (3, "ram", True)
        assert first["read_back"] == wanted
        # The servo restarts (a brownout, someone's REBOOT): RAM is EEP's again.
        neck = truth.neck
        assert isinstance(neck, SimServo)
        neck.handle(reboot(neck.sid), truth.sync())
        # As it answers again it holds the factory value (the Robot's check takes a few
        # transactions)...
        await asyncio.sleep(RESTART_S + 0.002)
        assert servo_ram(truth)["min_position"] == 21
        # ... and soon the Robot's again.
        await asyncio.sleep(0.5)
        assert servo_ram(truth) == wanted
        again = (await robot.info())["neck_settings"]
        assert again["loads"] == first["loads"] + 1
        assert "silence" in again["why"]
        assert again["ok"]
        assert not [fault for fault in robot.state.faults if fault.startswith("neck_settings")]

    settings = {name: value for name, (_, value) in NECK_SETTINGS.items()}
    run(kind, check, **settings)


def test_a_closed_robot_refuses_every_call_with_one_error(kind: str) -> None:
    async def check() -> None:
        async with opened(kind) as (robot, _):
            pass
        assert robot.closed
        commands: list[Callable[[], object]] = [
            lambda: robot.drive(0.1, 0.0),
            lambda: robot.drive_pwm(10, 10),
            robot.stop,
            robot.clear_estop,
            lambda: robot.set_rate("tbcore_status", 5.0),
            lambda: robot.enable_stream("tbcore_status", True),
        ]
        for command in commands:
            with pytest.raises(RobotClosedError, match="the robot is closed"):
                command()
        with pytest.raises(RobotClosedError, match="the robot is closed"):
            await robot.estop()
        async for _ in robot.subscribe("wheel_odom"):
            pytest.fail("a closed robot's subscription ends at once")

    run_virtual(check())


def test_drive_distance_ends_at_the_distance_by_the_truth(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[float, str]:
        start = truth.pose.x
        result = await robot.drive_distance(0.5)
        return truth.pose.x - start, result.reason

    travelled, reason = run(kind, check)
    assert reason == "arrived"
    assert travelled == pytest.approx(0.5, abs=DISTANCE_TOLERANCE_M[kind])


def test_rotate_ends_at_the_angle_by_the_truth(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> float:
        start = truth.pose.yaw
        await robot.rotate(math.pi / 2)
        return truth.pose.yaw - start

    turned = run(kind, check)
    assert math.degrees(turned) == pytest.approx(90.0, abs=1.0)


def test_a_goal_cancelled_stops_the_robot(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        goal = asyncio.create_task(robot.drive_distance(2.0))
        await until(lambda: speed(truth) > 0.2)
        goal.cancel()
        with pytest.raises(asyncio.CancelledError):
            await goal
        await until(lambda: speed(truth) == 0.0, 1.5)

    run(kind, check)


def test_a_goal_preempted_raises_the_same_error_with_what_it_did(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        goal = asyncio.create_task(robot.drive_distance(2.0))
        await until(lambda: speed(truth) > 0.2)
        robot.stop()
        with pytest.raises(MotionPreemptedError) as preempted:
            await goal
        assert preempted.value.by == "stop"
        assert preempted.value.result.reason == "preempted"
        assert 0.0 < preempted.value.result.distance_m < 2.0

    run(kind, check)


def test_each_wheel_has_its_own_gains(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        shared = robot.get_pid()
        assert robot.get_pid(wheel="left") == robot.get_pid(wheel="right") == shared
        left = PidGains(kp=500.0, ki=200.0, kd=1.0, kff=900.0, ff_offset=50.0)
        robot.set_pid(left, wheel="left")
        await robot.confirm()
        assert robot.get_pid(wheel="left") == left
        assert robot.get_pid(wheel="right") == shared
        with pytest.raises(StateError, match=r"the wheels' PID gains differ .*get_pid\(wheel="):
            robot.get_pid()
        # The robot still drives straight on them (the sim's wheels are alike).
        await drive_for(robot, 1.0)
        assert speed(truth) == pytest.approx(0.3, abs=0.03)
        robot.set_pid(shared)  # both wheels again
        await robot.confirm()
        assert robot.get_pid() == shared

    run(kind, check)


def test_drive_is_refused_while_a_wheel_controller_is_off(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        assert robot.controllers_enabled() == {"left": True, "right": True}
        robot.enable_controllers(False, wheel="right")
        await robot.confirm()
        assert robot.controllers_enabled() == {"left": True, "right": False}
        with pytest.raises(StateError, match="the right wheel's controller is off"):
            await drive_confirmed(robot)
        with pytest.raises(StateError, match="the right wheel's controller is off"):
            await wheels_confirmed(robot)
        with pytest.raises(StateError, match="the right wheel's controller is off"):
            await robot.drive_distance(0.5)
        await asyncio.sleep(0.3)
        assert truth.wheel_speeds_mps() == (0.0, 0.0)  # nothing moved
        # Open loop still drives.
        assert robot.drive_pwm(250.0, 250.0) == (250, 250)
        await asyncio.sleep(0.3)
        assert min(truth.wheel_speeds_mps()) > 0.05
        robot.stop()
        robot.enable_controllers(True)
        await robot.confirm()
        assert robot.controllers_enabled() == {"left": True, "right": True}
        await drive_for(robot, 1.0)
        assert speed(truth) == pytest.approx(0.3, abs=0.03)

    run(kind, check)


def test_turning_a_controller_off_stops_a_drive(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await drive_for(robot, 0.6)
        robot.enable_controllers(False, wheel="left")
        await until(lambda: truth.wheel_speeds_mps() == (0.0, 0.0), 1.0)
        robot.enable_controllers(True, wheel="left")
        await robot.confirm()
        await asyncio.sleep(0.3)
        assert truth.wheel_speeds_mps() == (0.0, 0.0)  # the old target is not taken up again

    run(kind, check)


def test_drive_unramped_is_the_pure_velocity_command(kind: str) -> None:
    async def after(robot: Robot, truth: SimRobot, *, ramped: bool) -> float:
        robot.drive(0.5, 0.0, ramped=ramped)
        await asyncio.sleep(0.3)
        reached = speed(truth)
        robot.stop()
        await until(lambda: speed(truth) == 0.0, 2.0)
        return reached

    async def check(robot: Robot, truth: SimRobot) -> None:
        ramped = await after(robot, truth, ramped=True)
        pure = await after(robot, truth, ramped=False)
        assert ramped < 0.2  # the acceleration limit: 0.5 m/s² by default
        assert pure > 0.4
        # Still within the limits, and still under the watchdog.
        assert robot.drive(5.0, 0.0, ramped=False).limited
        await until(lambda: robot.state.watchdog_tripped, 1.5)
        await until(lambda: speed(truth) == 0.0, 2.0)

    run(kind, check)


def test_drive_pwm_takes_floats_and_per_motor_enable_flags(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        assert robot.drive_pwm(300.4, 299.5, right_enabled=False) == (300, 0)
        assert robot.drive_pwm(2.5, -0.5) == (2, 0)  # half to even
        assert robot.drive_pwm(300.4, 299.5, right_enabled=False) == (300, 0)
        await asyncio.sleep(0.4)
        left, right = truth.wheel_speeds_mps()
        assert left > 0.05
        assert right == 0.0

    run(kind, check)


# -- bad input: the same error, word for word, on both --------------------------------------

BAD_CALLS: list[tuple[str, Callable[[Robot], object]]] = [
    ("drive nan", lambda r: r.drive(math.nan, 0.0)),
    ("drive text", lambda r: r.drive("fast", 0.0)),  # type: ignore[arg-type]  # on purpose
    ("drive_wheels inf", lambda r: r.drive_wheels(math.inf, 0.0)),
    ("pwm out of range", lambda r: r.drive_pwm(2000, 0)),
    ("pwm not a number", lambda r: r.drive_pwm("1.5", 0)),  # type: ignore[arg-type]  # on purpose
    ("pwm nan", lambda r: r.drive_pwm(math.nan, 0)),
    (
        "pwm of a disabled motor out of range",
        lambda r: r.drive_pwm(0, -1000.5, right_enabled=False),
    ),
    ("pwm enable not bool", lambda r: r.drive_pwm(0, 0, left_enabled=1)),  # type: ignore[arg-type]  # on purpose
    ("drive ramped not bool", lambda r: r.drive(0.1, 0.0, ramped="no")),  # type: ignore[arg-type]  # on purpose
    ("pid of no wheel", lambda r: r.set_pid(PidGains(kp=1.0, ki=0.0, kd=0.0), wheel="middle")),  # type: ignore[arg-type]  # on purpose
    ("get_pid of no wheel", lambda r: r.get_pid(wheel="both")),  # type: ignore[arg-type]  # on purpose
    ("controllers of no wheel", lambda r: r.enable_controllers(False, wheel=0)),  # type: ignore[arg-type]  # on purpose
    ("pid out of range", lambda r: r.set_pid(PidGains(kp=1e9, ki=0.0, kd=0.0))),
    ("pid not gains", lambda r: r.set_pid({"kp": 1})),  # type: ignore[arg-type]  # on purpose
    ("pose too far", lambda r: r.reset_odometry(2e6, 0.0, 0.0)),
    ("rate out of range", lambda r: r.set_rate("wheel_encoder", 500.0)),
    ("rate of an event stream", lambda r: r.set_rate("robot_state", 5.0)),
    ("rate of no stream", lambda r: r.set_rate("odom", 5.0)),
    ("no such stream", lambda r: r.enable_stream("odom", True)),
    ("enabled not bool", lambda r: r.enable_stream("wheel_odom", "yes")),  # type: ignore[arg-type]  # on purpose
    ("controllers not bool", lambda r: r.enable_controllers(1)),  # type: ignore[arg-type]  # on purpose
    ("latest of no stream", lambda r: r.latest("odom")),
    ("subscribe to no stream", lambda r: r.subscribe("odom")),
    ("subscribe maxlen 0", lambda r: r.subscribe("wheel_odom", maxlen=0)),
    ("no such servo", lambda r: r.servo(99)),
]
BAD_AWAITED: list[tuple[str, Callable[[Robot], Any]]] = [
    ("light ring out of range", lambda r: r.light_ring(300, 0, 0)),
    ("neck out of range", lambda r: r.neck.move(2000)),
    ("neck playtime out of range", lambda r: r.neck.move(400, playtime_s=5.0)),
    ("neck torque mode", lambda r: r.neck.torque("loose")),  # type: ignore[attr-defined]  # a HerkuleX neck
    ("release too short", lambda r: r.release_port(0.01)),
    ("goal too far", lambda r: r.drive_distance(1000.0)),
    ("goal too slow", lambda r: r.rotate(1.0, speed_radps=0.01)),
]


def test_bad_input_is_refused_with_the_same_error_on_both() -> None:
    async def refusals(kind: str) -> dict[str, tuple[type[BaseException], str]]:
        got: dict[str, tuple[type[BaseException], str]] = {}
        async with opened(kind) as (robot, truth):
            for name, call in BAD_CALLS:
                with pytest.raises(OhmniError) as raised:
                    call(robot)
                got[name] = (type(raised.value), str(raised.value))
            for name, awaited in BAD_AWAITED:
                with pytest.raises(OhmniError) as raised:
                    await awaited(robot)
                got[name] = (type(raised.value), str(raised.value))
            await robot.confirm()  # nothing refused later: each was refused at once
            assert speed(truth) == 0.0
        return got

    local = run_virtual(refusals("local"))
    remote = run_virtual(refusals("remote"))
    assert remote == local
