"""The health, the odometry set to a pose and the limited twist, judged the same way on a
local robot and on a daemon's: the ``diagnostics`` stream (a device gone silent is ERROR
within 2 s), ``set_odometry``, and ``wheel_odom``'s requested and limited twist."""

from __future__ import annotations

import asyncio
import itertools
import math
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import InvalidArgumentError, MotionPreemptedError, OutOfRangeError
from ohmni_tb.robot import DiagnosticLevel, DiagnosticsSample, LocalRobot
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.robot import SimRobot

from .conftest import run

#: Every entry of a default simulated robot, in order: the devices, then the link.
ENTRIES = ["left_drive", "right_drive", "core", "neck", "ext1", "ext2", "link"]
#: The issue's bound: a device gone silent is reported ERROR within this.
SILENT_REPORTED_S = 2.0


@asynccontextmanager
async def opened_line(kind: str, url: str = "sim://") -> AsyncIterator[tuple[Robot, SimLine]]:
    """A simulated robot through ``kind``, and the simulated line it is on (its faults)."""
    async with LocalRobot.open(url) as served:
        line = served.bus.transport.line  # type: ignore[attr-defined]  # a SimTransport
        if kind == "local":
            yield served, line
            return
        async with RobotServer(served, port=0) as server, Robot.open(server.url) as robot:
            yield robot, line


async def next_diagnostics(
    robot: Robot, test: Callable[[DiagnosticsSample], bool], timeout_s: float
) -> DiagnosticsSample:
    """The first ``diagnostics`` sample from now on that passes ``test``, within ``timeout_s``."""
    async with robot.subscribe("diagnostics") as samples, asyncio.timeout(timeout_s):
        async for sample in samples:
            if test(sample):
                return sample
    raise AssertionError("the stream ended")


def level_of(sample: DiagnosticsSample, name: str) -> DiagnosticLevel:
    entry = sample.entry(name)
    assert entry is not None, name
    return entry.level


def test_diagnostics_has_every_expected_device_and_the_link_at_1_hz(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> list[DiagnosticsSample]:
        got: list[DiagnosticsSample] = []
        async with robot.subscribe("diagnostics") as samples:
            async for sample in samples:
                got.append(sample)
                if len(got) == 3:
                    return got
        raise AssertionError("the stream ended")

    samples = run(kind, check)
    first = samples[0]
    assert [entry.name for entry in first.entries] == ENTRIES
    assert [entry.sid for entry in first.entries] == [0, 1, 20, 3, 11, 12, None]
    assert first.level is DiagnosticLevel.OK
    assert first.event is None
    for entry in first.entries:
        assert entry.level is DiagnosticLevel.OK, entry
        assert entry.message == "ok"
    for name in ("left_drive", "right_drive", "core"):
        values = first.entry(name).values  # type: ignore[union-attr]
        assert str(values["firmware"]).startswith("sim-"), values
        assert values["firmware_known"] is True
        assert values["timeouts"] == 0
        assert 0 < float(values["latency_p50_ms"]) < 25  # type: ignore[arg-type]
    neck = first.entry(3)
    assert neck is not None
    assert neck.values["model"] == "DRS_0101"
    assert neck.values["temperature_raw"] == 160
    assert neck.values["load_pwm"] == 0
    core = first.entry("core")
    assert core is not None
    assert core.values["cell_spread_mv"] == 0
    assert 3200 < int(core.values["lowest_cell_mv"]) < 3400  # type: ignore[arg-type]
    link = first.entry("link")
    assert link is not None
    assert link.values["state"] == "connected"
    assert link.values["checksum_errors"] == 0
    stamps = [sample.stamp_s for sample in samples]
    assert stamps[2] - stamps[1] == pytest.approx(1.0, abs=0.01)
    assert stamps[1] - stamps[0] == pytest.approx(1.0, abs=0.01)


def test_a_device_gone_silent_is_error_within_2_s_and_ok_again_once_it_answers(
    kind: str,
) -> None:
    async def check() -> None:
        async with opened_line(kind) as (robot, line):
            await next_diagnostics(robot, lambda s: s.level is DiagnosticLevel.OK, 2.0)
            loop = asyncio.get_running_loop()
            silenced_s = loop.time()
            line.faults.silent.add(11)  # `silent 11` on the simulator's console
            bad = await next_diagnostics(
                robot, lambda s: level_of(s, "ext1") is DiagnosticLevel.ERROR, 3.0
            )
            assert bad.stamp_s - silenced_s <= SILENT_REPORTED_S
            assert bad.level is DiagnosticLevel.ERROR
            entry = bad.entry(11)
            assert entry is not None
            assert entry.message.startswith("silent: ")
            assert int(entry.values["consecutive_timeouts"]) >= 3  # type: ignore[arg-type]
            assert bad.event is not None
            assert "ext1 ok → error: silent" in bad.event
            # The others did not notice.
            assert [e.name for e in bad.entries if e.level is not DiagnosticLevel.OK] == ["ext1"]
            line.faults.silent.discard(11)  # `talk 11`
            good = await next_diagnostics(robot, lambda s: s.level is DiagnosticLevel.OK, 5.0)
            assert good.event is not None
            assert "ext1 error → ok" in good.event

    run_virtual(check())


def test_a_device_silent_from_the_start_is_error_as_absent(kind: str) -> None:
    async def check() -> None:
        async with opened_line(kind, "sim://?silent=11") as (robot, _):
            sample = await next_diagnostics(robot, lambda s: True, SILENT_REPORTED_S)
            entry = sample.entry("ext1")
            assert entry is not None
            assert entry.level is DiagnosticLevel.ERROR
            assert entry.message.startswith("absent: ")
            assert entry.values["present"] is False
            assert sample.level is DiagnosticLevel.ERROR

    run_virtual(check())


def test_set_odometry_sets_the_pose_and_reset_odometry_goes_back_to_the_origin(
    kind: str,
) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[Any, Any]:
        robot.set_odometry(1.5, -2.0, 3 * math.pi)  # any angle: yaw wraps, heading not
        await robot.confirm()
        async with robot.subscribe("wheel_odom") as odom:
            await anext(odom)  # maybe integrated before the pose reached the robot
            set_to = await anext(odom)
            robot.reset_odometry()
            await robot.confirm()
            await anext(odom)
            reset_to = await anext(odom)
        return set_to, reset_to

    set_to, reset_to = run(kind, check)
    assert (set_to.x_m, set_to.y_m) == pytest.approx((1.5, -2.0), abs=1e-6)
    assert set_to.yaw_rad == pytest.approx(math.pi, abs=1e-6)
    assert set_to.heading_rad == pytest.approx(3 * math.pi, abs=1e-6)
    assert (reset_to.x_m, reset_to.y_m, reset_to.yaw_rad) == pytest.approx((0, 0, 0), abs=1e-6)


def test_set_odometry_ends_a_goal_under_way_and_stops(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> None:
        goal = asyncio.create_task(robot.drive_distance(2.0))
        await asyncio.sleep(1.0)
        robot.set_odometry(0.0, 0.0, 0.0)
        with pytest.raises(MotionPreemptedError) as preempted:
            await goal
        assert preempted.value.by == "set_odometry"
        await asyncio.sleep(1.5)  # the ramp down
        assert truth.wheel_speeds_mps() == (0.0, 0.0)

    run(kind, check)


@pytest.mark.parametrize(
    ("args", "error", "words"),
    [
        ((math.nan, 0.0, 0.0), InvalidArgumentError, "x_m"),
        ((0.0, 2e6, 0.0), OutOfRangeError, "y_m"),
        ((0.0, 0.0, "1"), InvalidArgumentError, "yaw_rad"),
    ],
)
def test_set_odometry_refuses_a_bad_pose_and_keeps_the_one_it_has(
    kind: str, args: tuple[Any, Any, Any], error: type[Exception], words: str
) -> None:
    async def check(robot: Robot, truth: SimRobot) -> Any:
        robot.set_odometry(1.0, 1.0, 0.0)
        with pytest.raises(error, match=words):
            robot.set_odometry(*args)
        await robot.confirm()
        async with robot.subscribe("wheel_odom") as odom:
            await anext(odom)
            return await anext(odom)

    sample = run(kind, check)
    assert (sample.x_m, sample.y_m) == pytest.approx((1.0, 1.0), abs=1e-6)


def test_wheel_odom_shows_the_request_and_what_the_limiter_made_of_it(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> tuple[list[Any], list[Any]]:
        config = robot.config
        assert config.max_linear_mps == 1.0
        assert config.linear_accel_mps2 == 0.5
        driving: list[Any] = []
        async with robot.subscribe("wheel_odom", maxlen=1000) as odom:
            loop = asyncio.get_running_loop()
            until = loop.time() + 1.0
            while loop.time() < until:
                robot.drive(5.0, 0.0)  # five times the limit
                await asyncio.sleep(0.05)
            robot.stop()
            await robot.confirm()
            await asyncio.sleep(0.3)
            while (sample := odom.get_nowait()) is not None:
                driving.append(sample)
        stopping = [s for s in driving if s.requested_linear_mps == 0.0 and s.stamp_s > until]
        driving = [s for s in driving if s.requested_linear_mps == 5.0]
        return driving, stopping

    driving, stopping = run(kind, check)
    # The request as given, and the limiter's twist: under the speed limit, ramping at
    # the acceleration limit (0.5 m/s² at 50 Hz: 0.01 m/s a tick).
    assert len(driving) >= 40
    assert all(s.requested_angular_radps == 0.0 for s in driving)
    commanded = [s.commanded_linear_mps for s in driving]
    assert all(0.0 < c <= 1.0 for c in commanded)
    assert commanded == sorted(commanded)
    steps = [b - a for a, b in itertools.pairwise(commanded) if b > a]
    assert max(steps) == pytest.approx(0.5 / 50, rel=0.05)
    assert 0.4 < commanded[-1] < 0.55  # 1 s at 0.5 m/s²
    # Stopped: nothing requested, and the limiter brakes down to zero.
    assert stopping
    assert stopping[0].commanded_linear_mps < commanded[-1]
    assert stopping[-1].commanded_linear_mps < stopping[0].commanded_linear_mps


def test_an_unramped_drive_shows_the_request_scaled_into_the_limits(kind: str) -> None:
    async def check(robot: Robot, truth: SimRobot) -> Any:
        robot.drive(3.0, 1.0, ramped=False)
        await robot.confirm()
        async with robot.subscribe("wheel_odom") as odom:
            await anext(odom)
            return await anext(odom)

    sample = run(kind, check)
    assert (sample.requested_linear_mps, sample.requested_angular_radps) == (3.0, 1.0)
    # Scaled by one factor into max_linear_mps and max_wheel_mps (the outer wheel goes
    # faster than the body), keeping the curvature, at once: no ramp.
    assert 0.9 < sample.commanded_linear_mps < 1.0
    assert sample.commanded_angular_radps / sample.commanded_linear_mps == pytest.approx(1 / 3)
