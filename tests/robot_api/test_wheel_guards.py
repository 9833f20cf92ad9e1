"""The stall and slip guards on ``sim://`` in virtual time, judged by what a user sees —
``robot_state``'s faults and events, the errors — and by the simulator's truth: normal
driving raises neither; open-loop PWM against an obstacle stalls too; ``stop()`` ends a
stall's hold; a slip clears once the wheels stand; ``stall_s=0`` and ``slip_s=0`` turn
the guards off; bad settings and simulator options are refused with one clear error."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from ohmni_tb import Robot, RobotConfig
from ohmni_tb.errors import ConfigError
from ohmni_tb.robot import RobotStateSample
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport

#: How often a teleop loop sends its command again (inside the watchdog's 0.5 s).
TICK_S = 0.05
#: The guards' faults.
GUARD_FAULTS = ("wheel_stall", "wheel_slip")


async def keep(robot: Robot, seconds: float, command: Callable[[], object]) -> None:
    """Give ``command`` again every tick for ``seconds``, as a teleop loop does."""
    for _ in range(round(seconds / TICK_S)):
        command()
        await asyncio.sleep(TICK_S)


def drive(robot: Robot, linear: float, angular: float) -> Callable[[], object]:
    return lambda: robot.drive(linear, angular)


def with_robot(body: Callable[[Robot, SimRobot], Awaitable[Any]], **settings: Any) -> Any:
    """``body(robot, truth)`` on a fresh ``sim://`` robot, in virtual time; its result and
    every ``robot_state`` sample published meanwhile."""

    async def main() -> tuple[Any, list[RobotStateSample]]:
        async with Robot.open("sim://", **settings) as robot:
            states = robot.subscribe("robot_state", maxlen=10_000)
            result = await body(robot, robot.sim)
            seen = []
            while (state := states.get_nowait()) is not None:
                seen.append(state)
            return result, seen

    return run_virtual(main())


def guard_faults(states: list[RobotStateSample]) -> set[str]:
    return {fault for state in states for fault in state.faults if fault.startswith(GUARD_FAULTS)}


def events(states: list[RobotStateSample]) -> list[str]:
    return [state.event for state in states if state.event is not None]


# -- no false alarm ------------------------------------------------------------------------------


async def _turns_in_place(robot: Robot) -> None:
    await keep(robot, 2.0, drive(robot, 0.0, 1.0))
    await keep(robot, 2.0, drive(robot, 0.0, -0.2))


async def _ramps(robot: Robot) -> None:
    for speed in (0.1, 0.3, 0.6, 0.9, 0.4, 0.05):
        await keep(robot, 0.6, drive(robot, speed, 0.3 * speed))


async def _reverses(robot: Robot) -> None:
    await keep(robot, 1.2, drive(robot, 0.5, 0.0))
    await keep(robot, 1.2, drive(robot, -0.5, 0.0))
    await keep(robot, 1.2, drive(robot, 0.0, 2.0))
    await keep(robot, 1.2, drive(robot, 0.0, -2.0))


async def _jumps(robot: Robot) -> None:
    # The pure velocity command: the setpoints jump, the PIDs catch up.
    await keep(robot, 1.5, lambda: robot.drive(0.4, 1.0, ramped=False))
    await keep(robot, 1.5, lambda: robot.drive(-0.4, -1.0, ramped=False))


async def _goals(robot: Robot) -> None:
    await robot.drive_distance(0.4)
    await robot.rotate(math.pi / 2)
    await robot.drive_distance(-0.1, speed_mps=0.05)


async def _open_loop(robot: Robot) -> None:
    await keep(robot, 1.5, lambda: robot.drive_pwm(400, 380))
    await keep(robot, 1.0, lambda: robot.drive_pwm(-150, -150))


NORMAL: dict[str, Callable[[Robot], Awaitable[None]]] = {
    "drive": lambda robot: keep(robot, 3.0, drive(robot, 0.3, 0.0)),
    "crawl": lambda robot: keep(robot, 3.0, drive(robot, 0.03, 0.0)),
    "arc": lambda robot: keep(robot, 3.0, drive(robot, 0.4, 0.8)),
    "turn_in_place": _turns_in_place,
    "ramp": _ramps,
    "reversal": _reverses,
    "unramped": _jumps,
    "goals": _goals,
    "open_loop": _open_loop,
}


@pytest.mark.parametrize("motion", NORMAL)
def test_normal_motions_raise_neither_fault(motion: str) -> None:
    async def body(robot: Robot, truth: SimRobot) -> None:
        await NORMAL[motion](robot)
        robot.stop()
        await asyncio.sleep(0.5)

    _, states = with_robot(body)
    assert guard_faults(states) == set()
    assert not [event for event in events(states) if event.startswith(GUARD_FAULTS)]


# -- the stall guard -----------------------------------------------------------------------------


Speeds = tuple[float, float]


def test_open_loop_pwm_against_an_obstacle_stalls_and_stop_ends_the_hold() -> None:
    async def body(
        robot: Robot, truth: SimRobot
    ) -> tuple[tuple[str, ...], Speeds, tuple[str, ...], Speeds]:
        truth.block_wheels(left=True, right=False)
        await keep(robot, 1.0, lambda: robot.drive_pwm(500, 500))
        faults, wheels = robot.state.faults, truth.wheel_speeds_mps()
        robot.stop()  # stop() ends the hold at once
        stopped = robot.state.faults
        truth.unblock_wheels()
        await keep(robot, 0.5, lambda: robot.drive_pwm(500, 500))  # the same PWM again
        again = truth.wheel_speeds_mps()
        robot.stop()
        return faults, wheels, stopped, again

    (faults, wheels, stopped, (left, right)), states = with_robot(body)
    assert faults == ("wheel_stall:0",)
    assert wheels == (0.0, 0.0)  # the right wheel's power is cut too
    assert stopped == ()
    assert left > 0.2
    assert right > 0.2
    said = events(states)
    stall = next(event for event in said if event.startswith("wheel_stall:"))
    assert "the left wheel (drive board 0) driven at PWM 500" in stall
    assert "did not turn for 0.50 s" in stall
    assert "wheel_stall cleared by stop()" in said


def test_a_wheel_that_moves_slowly_under_load_is_not_a_stall() -> None:
    # Creeping at 0.03 m/s the wheel moves a few tenths of a millimetre a tick: turning.
    async def body(robot: Robot, truth: SimRobot) -> float:
        await keep(robot, 2.0, drive(robot, 0.03, 0.0))
        left, _ = truth.wheel_speeds_mps()
        return left

    left, states = with_robot(body)
    assert left > 0.02
    assert guard_faults(states) == set()


def test_stall_s_zero_turns_the_stall_guard_off() -> None:
    async def body(robot: Robot, truth: SimRobot) -> tuple[float, float]:
        truth.block_wheels(left=True, right=False)
        await keep(robot, 1.5, lambda: robot.drive_pwm(500, 500))
        return truth.wheel_speeds_mps()

    (left, right), states = with_robot(body, stall_s=0)
    assert left == 0.0
    assert right > 0.2  # nothing cut the power
    assert guard_faults(states) == set()


# -- the slip guard ------------------------------------------------------------------------------


def test_a_slip_is_a_fault_while_it_lasts_and_the_wheels_keep_their_command() -> None:
    async def body(
        robot: Robot, truth: SimRobot
    ) -> tuple[tuple[str, ...], Speeds, tuple[str, ...]]:
        await keep(robot, 1.0, drive(robot, 0.3, 0.0))
        truth.slip_wheels(left=True, right=False)
        await keep(robot, 1.5, drive(robot, 0.3, 0.0))
        faults, wheels = robot.state.faults, truth.wheel_speeds_mps()
        robot.stop()
        await asyncio.sleep(1.0)
        return faults, wheels, robot.state.faults

    (faults, (left, right), standing), states = with_robot(body)
    assert faults == ("wheel_slip:0",)
    assert left > 0.3  # still driven: the slip guard does not stop the wheels
    assert right > 0.25
    assert standing == ()
    said = events(states)
    slip = next(event for event in said if event.startswith("wheel_slip:"))
    assert "the left wheel (drive board 0) ran at" in slip
    assert "off the commanded curve" in slip
    assert "wheel_slip cleared: the wheels stand" in said


def test_slip_s_zero_turns_the_slip_guard_off() -> None:
    async def body(robot: Robot, truth: SimRobot) -> None:
        await keep(robot, 1.0, drive(robot, 0.3, 0.0))
        truth.slip_wheels(left=True, right=False)
        await keep(robot, 2.0, drive(robot, 0.3, 0.0))

    _, states = with_robot(body, slip_s=0)
    assert guard_faults(states) == set()


# -- settings and simulator options --------------------------------------------------------------


@pytest.mark.parametrize(
    ("setting", "value", "allowed"),
    [
        ("stall_s", 0.05, "0 (off) or 0.1..10 s"),
        ("stall_s", -1, "0 (off) or 0.1..10 s"),
        ("stall_s", 11, "0 (off) or 0.1..10 s"),
        ("slip_s", 0.3, "0 (off) or 0.5..10 s"),
        ("slip_s", 60, "0 (off) or 0.5..10 s"),
    ],
)
def test_bad_guard_settings_are_refused_naming_the_range(
    setting: str, value: float, allowed: str
) -> None:
    settings: dict[str, Any] = {setting: value}
    with pytest.raises(ConfigError) as caught:
        RobotConfig(**settings)
    assert f"{setting}={value}" in str(caught.value)
    assert f"allowed {allowed}" in str(caught.value)


def test_the_guard_settings_default_to_half_a_second_and_a_second() -> None:
    config = RobotConfig()
    assert (config.stall_s, config.slip_s) == (0.5, 1.0)
    assert RobotConfig(stall_s=0, slip_s=0).stall_s == 0


def test_sim_url_options_start_a_wheel_blocked_or_without_grip() -> None:
    async def main() -> tuple[tuple[bool, bool], tuple[bool, bool]]:
        transport = await open_transport("sim://?stall=0&slip=1")
        assert isinstance(transport, SimTransport)
        assert transport.robot is not None
        async with transport:
            return transport.robot.blocked_wheels, transport.robot.slipping_wheels

    assert run_virtual(main()) == ((True, False), (False, True))


@pytest.mark.parametrize(
    ("url", "message"),
    [
        (
            "sim://?stall=5",
            "option stall: id 5 is not a drive board's: allowed 0 (left), 1 (right)",
        ),
        ("sim://?slip=20", "option slip: id 20 is not a drive board's"),
        ("sim://?slip=left", "option slip: 'left' is not a device id"),
    ],
)
def test_bad_sim_options_are_refused_naming_the_value(url: str, message: str) -> None:
    async def main() -> None:
        await open_transport(url)

    with pytest.raises(ConfigError) as caught:
        run_virtual(main())
    assert message in str(caught.value)
