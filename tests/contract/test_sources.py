"""Command sources, judged the same way on a local robot and on a daemon's: a higher
source overrides a lower one and hands back after its timeout, the lower one is refused
with nothing reaching the wheels, a stop from any source is obeyed, a goal runs under its
source, and robot_state says which source drives — with the simulator's truth to say
what the wheels really did."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import InvalidArgumentError, MotionPreemptedError, SourceOverriddenError
from ohmni_tb.robot import RobotStateSample, SampleStream
from ohmni_tb.sim.robot import SimRobot

from .conftest import run
from .test_contract import speed, until


async def drive_as(robot: Robot, source: str, seconds: float, linear_mps: float = 0.3) -> None:
    """Drive as ``source`` does: the command again at 20 Hz."""
    loop = asyncio.get_running_loop()
    until_s = loop.time() + seconds
    while loop.time() < until_s:
        robot.drive(linear_mps, 0.0, source=source)
        await asyncio.sleep(0.05)


async def drive_confirmed(robot: Robot, source: str, linear_mps: float) -> None:
    """A drive command of ``source``, and the daemon's answer to it (a local robot answers
    at once)."""
    robot.drive(linear_mps, 0.0, source=source)
    await robot.confirm()


async def refused(robot: Robot, source: str, linear_mps: float = 0.3) -> SourceOverriddenError:
    """A drive command of ``source`` that the robot refuses."""
    with pytest.raises(SourceOverriddenError) as raised:
        await drive_confirmed(robot, source, linear_mps)
    return raised.value


def events(states: SampleStream[Any]) -> list[str]:
    """The events of the robot_state samples queued so far."""
    got: list[str] = []
    while (sample := states.get_nowait()) is not None:
        assert isinstance(sample, RobotStateSample)
        if sample.event is not None:
            got.append(sample.event)
    return got


def test_local_overrides_remote_refusing_it_and_hands_back_after_its_timeout(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        loop = asyncio.get_running_loop()
        states = robot.subscribe("robot_state", maxlen=1000)
        await drive_as(robot, "remote", 1.0)
        assert speed(truth) == pytest.approx(0.3, abs=0.03)
        await until(lambda: robot.state.active_source == "remote", 1.0)
        # A person at the robot takes over: a stop held at 20 Hz, while the remote
        # script goes on asking for 0.3 m/s between its commands.
        until_s = loop.time() + 1.0
        while loop.time() < until_s:
            robot.drive(0.0, 0.0, source="local")
            await asyncio.sleep(0.025)
            error = await refused(robot, "remote")
            await asyncio.sleep(0.025)
        assert (error.source, error.active) == ("remote", "local")
        assert error.lapses_in_s is not None
        assert 0.0 < error.lapses_in_s <= 0.5
        assert "drive() from source 'remote' refused: source 'local'" in str(error)
        assert "nothing was sent" in str(error)
        # None of the script's commands reached the wheels: they came to rest and stayed.
        assert speed(truth) == pytest.approx(0.0, abs=0.005)
        assert robot.state.active_source == "local"
        # The person lets go: within local's timeout (0.5 s) the script is still refused…
        await asyncio.sleep(0.3)
        await refused(robot, "remote")
        assert speed(truth) == pytest.approx(0.0, abs=0.005)
        # …after it, its next command drives again.
        await asyncio.sleep(0.4)
        await drive_as(robot, "remote", 1.0)
        await robot.confirm()
        assert speed(truth) == pytest.approx(0.3, abs=0.03)
        await until(lambda: robot.state.active_source == "remote", 1.0)
        await asyncio.sleep(0.1)  # the daemon's last samples in
        said = events(states)
        assert "command source remote drives" in said
        assert "command source local drives (over remote)" in said
        assert any(e.startswith("command source local lapsed (no command for 0.5 s)") for e in said)
        # And when nobody commands any more, nobody drives: the source lapses as the
        # watchdog stops the wheels (both 0.5 s after the last command).
        await until(lambda: robot.state.active_source is None, 2.0)
        assert robot.state.watchdog_tripped
        await until(lambda: speed(truth) == 0.0, 0.5)

    run(kind, check)


def test_a_stop_from_a_lower_source_is_obeyed(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        await drive_as(robot, "local", 1.0)
        assert speed(truth) == pytest.approx(0.3, abs=0.03)
        robot.drive(0.3, 0.0, source="local")  # the person's last command
        robot.stop(source="autonomy")  # a script sees a problem: never refused
        await robot.confirm()
        # Stopped by the stop, well before the watchdog would have (0.5 s).
        await until(lambda: speed(truth) == 0.0, 0.45)
        # It did not take over: the person's next command is taken.
        assert robot.state.active_source == "local"
        robot.drive(0.2, 0.0, source="local")
        await robot.confirm()
        await until(lambda: speed(truth) > 0.1, 1.0)

    run(kind, check)


def test_a_goal_runs_under_its_source_and_a_higher_one_cancels_it(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        goal = asyncio.create_task(robot.drive_distance(2.0, source="remote"))
        await until(lambda: speed(truth) > 0.2)
        await until(lambda: robot.state.active_source == "remote", 1.0)
        # A lower source, during the goal: refused, and the goal goes on.
        error = await refused(robot, "autonomy", -0.3)
        assert (error.active, error.lapses_in_s) == ("remote", None)  # while its goal runs
        assert "while its motion goal runs" in str(error)
        with pytest.raises(SourceOverriddenError):
            await robot.rotate(1.0, source="autonomy")
        await asyncio.sleep(0.3)
        assert not goal.done()
        assert speed(truth) > 0.2
        # A higher one takes over: the goal ends, saying by what.
        robot.drive(0.0, 0.0, source="local")
        with pytest.raises(MotionPreemptedError) as preempted:
            await goal
        assert (preempted.value.by, preempted.value.source) == ("drive", "local")
        assert "preempted by drive() of command source 'local'" in str(preempted.value)
        assert 0.0 < preempted.value.result.distance_m < 2.0
        await until(lambda: speed(truth) == 0.0, 1.5)
        # A goal of a lower source is refused before it moves anything.
        robot.drive(0.0, 0.0, source="local")
        with pytest.raises(SourceOverriddenError, match="source 'local'"):
            await robot.drive_distance(0.5, source="remote")
        assert speed(truth) == 0.0

    run(kind, check)


def test_a_source_that_lapses_before_the_watchdog_leaves_the_robot_stopped(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        states = robot.subscribe("robot_state", maxlen=1000)
        await drive_as(robot, "local", 1.0)
        assert speed(truth) == pytest.approx(0.3, abs=0.03)
        # local lapses 0.2 s after its last command, before the watchdog (0.5 s): no
        # source is live, and the robot stops then — no watchdog trip.
        await until(lambda: robot.state.active_source is None, 0.35)
        await until(lambda: speed(truth) == 0.0, 0.6)
        assert not robot.state.watchdog_tripped
        await asyncio.sleep(0.1)
        assert (
            "command source local lapsed (no command for 0.2 s), stopping: no source drives"
            in events(states)
        )

    run(kind, check, command_sources="safety:0.5,local:0.2,remote:0.5,autonomy:1")


def test_the_robot_default_source_and_a_bad_source(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        assert robot.source == "autonomy"
        robot.drive(0.2, 0.0)
        await robot.confirm()
        await until(lambda: robot.state.active_source == "autonomy", 1.0)
        with pytest.raises(InvalidArgumentError) as bad:
            robot.drive(0.2, 0.0, source="operator")
        assert str(bad.value) == (
            "source='operator' is not a command source: allowed safety, local, remote, autonomy"
        )
        with pytest.raises(InvalidArgumentError, match="source='operator'"):
            robot.stop(source="operator")

    run(kind, check)
