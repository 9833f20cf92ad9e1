"""Nothing a caller sets and no load makes the robot drive on (docs/safety.md's table).

- the control tick's rate has one range, with a floor; the watchdog has a timer of its
  own and acts ``watchdog_s`` after the last command whatever the tick's rate;
- ``stop()`` puts the braking command on the wire at once, not at the next tick;
- a loop too busy for the control slots to start on time still gets the braking command
  out;
- whatever the PID gains or the open-loop PWM, a wheel is held near ``max_wheel_mps``;
- a closed Robot refuses every command with one error.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import pytest

from ohmni_tb import RobotConfig
from ohmni_tb.control.defaults import CONTROL_HZ_RANGE, WHEEL_GAIN_RANGES
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import ConfigError, OutOfRangeError, RobotClosedError, StateError
from ohmni_tb.robot import LocalRobot
from ohmni_tb.sim.clock import VirtualClockLoop

from .test_robot_safety import (
    STOPPED,
    WATCHDOG_S,
    Wire,
    fastest,
    keep_commanding,
    next_event,
    virtual,
)

#: The slowest control tick allowed, and its period.
SLOWEST_HZ = CONTROL_HZ_RANGE[0]
SLOW_PERIOD_S = 1.0 / SLOWEST_HZ
#: The default braking ramp from 0.5 m/s at linear_decel_mps2 = 1.
RAMP_S = 0.5


@pytest.mark.parametrize("hz", [0.1, 1.0, 9.9, 100.5])
def test_the_control_tick_has_one_range_with_a_floor(hz: float) -> None:
    async def main() -> tuple[str, float]:
        async with LocalRobot.open("sim://") as robot:
            with pytest.raises(OutOfRangeError) as caught:
                robot.set_rate("wheel_encoder", hz)
            return str(caught.value), robot.stats().streams["wheel_encoder"].requested_hz

    message, requested = virtual(main)
    assert f"wheel_encoder rate={hz!r} is out of range: allowed 10.0..100.0 Hz" in message
    assert requested == 50.0  # unchanged
    with pytest.raises(ConfigError, match=r"wheel_hz=.* allowed 10\.\.100 Hz"):
        RobotConfig(wheel_hz=hz)


def test_at_the_slowest_tick_the_watchdog_stops_the_wheels_on_time() -> None:
    async def main() -> tuple[float, float, list[tuple[float, tuple[int, int]]], float]:
        async with LocalRobot.open("sim://") as robot:
            robot.set_rate("wheel_encoder", SLOWEST_HZ)
            states = robot.subscribe("robot_state")
            wire = Wire(robot)
            # Silent from a moment between two ticks: the watchdog must not wait for one.
            last = await keep_commanding(lambda: robot.drive_pwm(600, 600), 1.03)
            trip = await next_event(states, "watchdog")
            await asyncio.sleep(0.6)
            return last, trip.stamp_s, wire.wheel_commands(last), fastest(robot)

    last, trip_s, commands, speed = virtual(main)
    assert trip_s == pytest.approx(last + WATCHDOG_S, abs=1e-6)
    stop_s = next(t for t, pwm in commands if pwm == STOPPED)
    assert stop_s - trip_s < 0.005  # on the wire at once, not up to a tick later
    assert speed == 0.0


def test_stop_puts_the_brake_on_the_wire_at_once_whatever_the_tick() -> None:
    async def main() -> tuple[float, list[tuple[float, tuple[int, int]]]]:
        async with LocalRobot.open("sim://", watchdog_s=0) as robot:
            robot.set_rate("wheel_encoder", SLOWEST_HZ)
            wire = Wire(robot)
            robot.drive_pwm(600, 600)
            await asyncio.sleep(1.03)  # between two ticks of the slow control slot
            loop = asyncio.get_running_loop()
            asked = loop.time()
            robot.stop()
            await asyncio.sleep(0.3)
            return asked, wire.wheel_commands(asked)

    asked, commands = virtual(main)
    assert commands[0][1] == STOPPED
    assert commands[0][0] - asked < 0.005


def _hog(loop: VirtualClockLoop, busy_s: float, until_s: float) -> None:
    """Keep the loop busy: each pass through it spends ``busy_s`` in one callback (the
    virtual clock moves on meanwhile, as the real one does under a flood of clients)."""

    def spin() -> None:
        if loop.time() < until_s:
            loop.advance(busy_s)
            loop.call_soon(spin)

    loop.call_soon(spin)


def test_a_saturated_loop_still_gets_the_watchdogs_stop_out() -> None:
    """Every pass of the loop takes 30 ms (longer than the control slot's slack): the
    control cycles are skipped, but the braking command goes anyway, late not never."""

    async def main() -> tuple[float, float, float, int]:
        async with LocalRobot.open("sim://") as robot:
            loop = asyncio.get_running_loop()
            assert isinstance(loop, VirtualClockLoop)
            last = await keep_commanding(lambda: robot.drive(0.5, 0.0), 2.0)
            moving = fastest(robot)
            _hog(loop, 0.03, until_s=last + 5.0)
            await asyncio.sleep(WATCHDOG_S + RAMP_S + 0.5)
            stopped = fastest(robot)
            skipped = robot.stats().streams["wheel_encoder"].skipped
            await asyncio.sleep(5.0)
            return moving, stopped, last, skipped

    moving, stopped, _, skipped = virtual(main)
    assert moving > 0.45
    assert skipped > 10  # the loop really was too busy for the control slots
    assert stopped < 0.01


def _pid_gains(**changes: float) -> PidGains:
    config = RobotConfig()
    gains = config.pid_gains()
    values = {name: getattr(gains, name) for name in WHEEL_GAIN_RANGES}
    values.update(changes)
    return PidGains(**values)


@pytest.mark.parametrize(
    ("gain", "value"), [("ff_offset", 1e6), ("kp", 1e12), ("kff", 20_000.0), ("kd", 1e4)]
)
def test_every_gain_has_one_range_everywhere(gain: str, value: float) -> None:
    low, high = WHEEL_GAIN_RANGES[gain]

    async def main() -> tuple[str, PidGains, PidGains]:
        async with LocalRobot.open("sim://") as robot:
            before = robot.get_pid()
            with pytest.raises(OutOfRangeError) as caught:
                robot.set_pid(_pid_gains(**{gain: value}))
            return str(caught.value), before, robot.get_pid()

    message, before, after = virtual(main)
    assert f"pid {gain}={value!r} is out of range: allowed {low}..{high}" in message
    assert after == before
    settings: dict[str, Any] = {f"pid_{gain}": value}
    with pytest.raises(ConfigError, match=f"pid_{gain}="):
        RobotConfig(**settings)


def _top_speed(act: Callable[[LocalRobot], object], **settings: Any) -> float:
    async def main() -> float:
        async with LocalRobot.open("sim://", **settings) as robot:
            top = 0.0
            for _ in range(60):  # 3 s
                act(robot)
                await asyncio.sleep(0.05)
                top = max(top, fastest(robot))
            return top

    return virtual(main)


@pytest.mark.parametrize(
    ("why", "act", "settings"),
    [
        ("the highest gains", lambda r: r.drive(0.3, 0.0), {}),
        ("open-loop PWM", lambda r: r.drive_pwm(1000, 1000), {}),
        ("fast wheels asked", lambda r: r.drive_wheels(2.0, 2.0), {}),
    ],
)
def test_the_wheels_are_held_to_max_wheel_mps_after_the_pid(
    why: str, act: Callable[[LocalRobot], object], settings: dict[str, Any]
) -> None:
    limit = 0.3

    def act_with_gains(robot: LocalRobot) -> object:
        if why == "the highest gains":
            highest = {name: high for name, (_, high) in WHEEL_GAIN_RANGES.items()}
            robot.set_pid(PidGains(**highest))
        return act(robot)

    top = _top_speed(act_with_gains, max_wheel_mps=limit, **settings)
    # The governor caps the PWM at what 1.1 x the limit needs and cuts a wheel's power
    # above 1.1 x the limit + 0.03 m/s.
    assert top < limit * 1.1 + 0.03, why


# -- a closed Robot ------------------------------------------------------------------------

COMMANDS: list[tuple[str, Callable[[LocalRobot], object]]] = [
    ("drive", lambda r: r.drive(0.1, 0.0)),
    ("drive_wheels", lambda r: r.drive_wheels(0.1, 0.1)),
    ("drive_pwm", lambda r: r.drive_pwm(100, 100)),
    ("stop", lambda r: r.stop()),
    ("estop", lambda r: r.estop()),
    ("clear_estop", lambda r: r.clear_estop()),
    ("set_pid", lambda r: r.set_pid(_pid_gains())),
    ("reset_odometry", lambda r: r.reset_odometry(1.0, 0.0, 0.0)),
    ("set_rate", lambda r: r.set_rate("tbcore_status", 5.0)),
    ("enable_stream", lambda r: r.enable_stream("tbcore_status", False)),
    ("enable_controllers", lambda r: r.enable_controllers(False)),
    ("info", lambda r: r.info()),
    ("light_ring", lambda r: r.light_ring(1, 2, 3)),
    ("neck.move", lambda r: r.neck.move(400, playtime_s=0.5)),
    ("release_port", lambda r: r.release_port(1.0)),
]


async def _perform(command: Callable[[LocalRobot], object], robot: LocalRobot) -> None:
    result = command(robot)
    if asyncio.iscoroutine(result):
        await result


@pytest.mark.parametrize(("name", "command"), COMMANDS, ids=[name for name, _ in COMMANDS])
def test_a_closed_robot_refuses_every_command_with_one_error(
    name: str, command: Callable[[LocalRobot], object]
) -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            neck = robot.neck
        assert robot.closed
        with pytest.raises(RobotClosedError, match="the robot is closed"):
            await _perform(command, robot)
        if name == "neck.move":  # a handle kept from before the close, too
            with pytest.raises(RobotClosedError):
                await neck.move(400, playtime_s=0.5)

    virtual(main)
    assert issubclass(RobotClosedError, StateError)  # code catching StateError still does
