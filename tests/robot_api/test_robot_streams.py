"""The Robot's streams on ``sim://``, in virtual time, judged as a user sees them.

Odometry against the simulator's ground truth, every stream at its configured rate with
the bus figures to match, slow or abandoned subscribers that cost the schedule nothing,
devices found (or not) at open and found again later, streams turned on and off, and a
USB adapter's latency that must not slow the control slot.
"""

from __future__ import annotations

import asyncio
import gc
import itertools
import math
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import pytest

from ohmni_tb.errors import InvalidArgumentError, StateError
from ohmni_tb.protocol import Packet, read_request
from ohmni_tb.protocol.core import read_status
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.protocol.worm_neck import read_feedback
from ohmni_tb.robot import (
    STREAM_NAMES,
    LocalRobot,
    RobotStateSample,
    ServoSample,
    WheelEncoderSample,
    WormNeckSample,
)
from ohmni_tb.robot.discovery import DISCOVERY_RETRIES
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.transport import SimTransport

T = TypeVar("T")

#: How often the user's loop re-sends drive(): inside the watchdog, as a user must.
USER_TICK_S = 0.05
#: The polled streams of the default simulated robot and their default rates.
DEFAULT_RATES = {
    "wheel_encoder": 50.0,
    "wheel_odom": 50.0,
    "tbcore_status": 10.0,
    "servo_neck": 30.0,
    "servo_ext1": 30.0,
    "servo_ext2": 30.0,
}
#: HerkuleX feedback block the Robot reads per servo cycle (RAM 48..59).
SERVO_BLOCK = (48, 12)


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


def sim_transport(robot: LocalRobot) -> SimTransport:
    transport = robot.bus.transport
    assert isinstance(transport, SimTransport)
    return transport


def requests_to(robot: LocalRobot, sid: int) -> int:
    device = robot.bus.stats.devices.get(sid)
    return 0 if device is None else device.requests


async def settle(robot: LocalRobot) -> None:
    """Command zero until odometry says the robot stands still."""
    while True:
        robot.drive(0.0, 0.0)
        await asyncio.sleep(USER_TICK_S)
        odom = robot.latest("wheel_odom")
        assert odom is not None
        if odom.linear_mps == 0.0 and odom.angular_radps == 0.0:
            return


async def straight(robot: LocalRobot, distance_m: float, speed_mps: float) -> None:
    """Drive until odometry says ``distance_m`` from where it started, slowing near it."""
    start = robot.latest("wheel_odom")
    assert start is not None
    while True:
        odom = robot.latest("wheel_odom")
        assert odom is not None
        remaining = distance_m - math.hypot(odom.x_m - start.x_m, odom.y_m - start.y_m)
        if remaining <= 0.001:
            break
        robot.drive(min(speed_mps, max(0.02, 1.5 * remaining)), 0.0)
        await asyncio.sleep(USER_TICK_S)
    await settle(robot)


async def turn_to(robot: LocalRobot, heading_rad: float, rate_radps: float) -> None:
    """Turn in place (counter-clockwise) until odometry's heading reaches ``heading_rad``."""
    while True:
        odom = robot.latest("wheel_odom")
        assert odom is not None
        remaining = heading_rad - odom.heading_rad
        if remaining <= math.radians(0.1):
            break
        robot.drive(0.0, min(rate_radps, max(0.05, 2.0 * remaining)))
        await asyncio.sleep(USER_TICK_S)
    await settle(robot)


# -- 1. odometry against the truth -------------------------------------------------------------


def test_a_one_metre_square_by_odometry_matches_the_truth() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(0.2)
            start = robot.sim.pose
            for corner in range(1, 5):
                await straight(robot, 1.0, 0.3)
                await turn_to(robot, corner * math.pi / 2, 0.6)
            await asyncio.sleep(0.5)  # standing: the last samples are of a still robot

            odom = robot.latest("wheel_odom")
            truth = robot.sim.pose
            assert odom is not None
            assert odom.linear_mps == 0.0
            assert odom.angular_radps == 0.0
            assert max(abs(v) for v in robot.sim.wheel_speeds_mps()) == 0.0
            # The odometry pose is the simulator's, within 2 cm and 1°.
            assert math.hypot(odom.x_m - truth.x, odom.y_m - truth.y) < 0.02
            assert abs(odom.heading_rad - truth.yaw) < math.radians(1.0)
            assert odom.heading_rad == pytest.approx(2 * math.pi, abs=math.radians(1.0))
            assert abs(odom.yaw_rad) < math.radians(1.0)  # wrapped into (−π, π]
            # The square closes: the controller did drive a square.
            assert math.hypot(truth.x - start.x, truth.y - start.y) < 0.03
            assert truth.yaw - start.yaw == pytest.approx(2 * math.pi, abs=math.radians(2.0))
            stats = robot.stats()
            assert stats.streams["wheel_encoder"].skipped == 0
            assert stats.streams["wheel_encoder"].missed == 0
            assert stats.bus.rejected_samples == 0

    virtual(main)


# -- 2. every stream at its rate ---------------------------------------------------------------


def _cycle_packets(robot: LocalRobot, name: str) -> list[Packet]:
    """What one cycle of stream ``name`` puts on the bus, built here, not by the Robot."""
    if name == "wheel_encoder":
        return [wheel_command(0, 0), read_count(0), read_count(1)]
    if name == "tbcore_status":
        return [read_status()]
    if name == "new_neck":
        return [read_feedback()]
    sid = {"servo_neck": robot.config.neck_id}
    sid.update(zip(("servo_ext1", "servo_ext2"), robot.config.ext_servo_ids, strict=False))
    return [read_request(sid[name], *SERVO_BLOCK)]


def test_every_stream_runs_at_its_configured_rate() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(6.0)  # the rate window is the last 5 s
            stats = robot.stats()

            for name, hz in DEFAULT_RATES.items():
                s = stats.streams[name]
                assert s.enabled, name
                assert s.requested_hz == hz, name
                assert s.achieved_hz == pytest.approx(hz, rel=0.02), name
                assert s.skipped == 0, name
                assert s.missed == 0, name
                assert s.dropped == 0, name
                assert s.samples >= 5 * hz, name
                if name != "wheel_odom":  # odometry is computed, not polled
                    assert s.jitter_p50_ms is not None, name
                    assert s.jitter_p99_ms is not None, name
                    assert 0.0 <= s.jitter_p50_ms <= s.jitter_p99_ms < 1000 / hz, name
            state = stats.streams["robot_state"]
            assert state.requested_hz == 1.0
            assert state.achieved_hz == pytest.approx(1.0, rel=0.1)
            for name in ("new_neck", "pid_debug"):
                assert not stats.streams[name].enabled, name
                assert stats.streams[name].samples == 0, name

            # The budget is the sum over the schedule of rate × line time per cycle, the
            # line time worked out here from the packets a cycle sends.
            schedule = robot.schedule()
            assert {row[0] for row in schedule} == set(DEFAULT_RATES) - {"wheel_odom"}
            budget = 0.0
            for name, hz, _phase, cost_s in schedule:
                independent = sum(robot.bus.cost_s(p) for p in _cycle_packets(robot, name))
                assert cost_s == pytest.approx(independent), name
                assert hz == DEFAULT_RATES[name], name
                budget += hz * independent
            assert stats.bus.budget_share == pytest.approx(budget)
            assert 0.3 < stats.bus.wire_utilisation < 0.9
            assert stats.bus.wire_utilisation < stats.bus.budget_share
            assert stats.bus.timeouts == 0
            assert stats.bus.deadline_misses == 0
            assert stats.uptime_s == pytest.approx(6.0, abs=0.2)

            text = str(stats)
            for name in (*DEFAULT_RATES, "robot_state"):
                assert name in text, name

    virtual(main)


# -- 3. slow subscribers -----------------------------------------------------------------------


def _wheel_rate(with_subscriber: bool) -> tuple[float, int, int, int]:
    """Run 3 s; (achieved rate, samples since subscribing, the subscription's dropped,
    the stream's dropped)."""

    async def main() -> tuple[float, int, int, int]:
        async with LocalRobot.open("sim://") as robot:
            before = robot.stats().streams["wheel_encoder"].samples
            subscription = robot.subscribe("wheel_encoder", maxlen=8) if with_subscriber else None
            await asyncio.sleep(3.0)
            stats = robot.stats().streams["wheel_encoder"]
            dropped = 0 if subscription is None else subscription.dropped
            if subscription is not None:
                assert subscription.pending == 8
                assert stats.subscribers == 1
            return stats.achieved_hz, stats.samples - before, dropped, stats.dropped

    return virtual(main)


def test_a_subscriber_that_never_reads_does_not_change_the_control_rate() -> None:
    rate_alone, samples_alone, _, _ = _wheel_rate(with_subscriber=False)
    rate, samples, dropped, stream_dropped = _wheel_rate(with_subscriber=True)
    assert rate == rate_alone
    assert samples == samples_alone
    assert rate == pytest.approx(50.0, rel=0.02)
    assert samples >= 145
    assert dropped == samples - 8
    assert stream_dropped == dropped


def test_a_reading_subscriber_gets_every_sample_in_order() -> None:
    async def main() -> None:
        got: list[WheelEncoderSample] = []

        async def read(subscription: Any) -> None:
            got.extend([sample async for sample in subscription])

        async with asyncio.TaskGroup() as tg:
            async with LocalRobot.open("sim://") as robot:
                subscription = robot.subscribe("wheel_encoder", maxlen=8)
                before = robot.stats().streams["wheel_encoder"].samples
                reader = tg.create_task(read(subscription))
                robot.drive(0.2, 0.0)
                for _ in range(30):
                    await asyncio.sleep(0.1)
                    robot.drive(0.2, 0.0)
            # The Robot closed: the reader's `async for` ended by itself.
            assert reader.done()
            stats = robot.stats().streams["wheel_encoder"]

        assert len(got) == stats.samples - before
        assert len(got) >= 145
        assert subscription.dropped == 0
        assert stats.dropped == 0
        stamps = [s.stamp_s for s in got]
        assert all(b > a for a, b in itertools.pairwise(stamps))
        periods = [b - a for a, b in itertools.pairwise(stamps)]
        assert max(periods) < 1.5 / 50  # no gap: no sample was lost
        assert got[-1].left_m > 0.3

    virtual(main)


# -- 4. subscription lifetime ------------------------------------------------------------------


def test_subscriptions_end_when_the_robot_closes() -> None:
    async def main() -> None:
        finished: list[str] = []

        async def read(robot: LocalRobot, name: str) -> None:
            async for _ in robot.subscribe(name):
                pass
            finished.append(name)

        async with asyncio.TaskGroup() as tg:
            async with LocalRobot.open("sim://") as robot:
                for name in ("wheel_encoder", "servo_neck", "robot_state", "pid_debug"):
                    tg.create_task(read(robot, name))
                await asyncio.sleep(1.0)
                assert finished == []
            assert robot.closed
            await asyncio.sleep(0)
        assert sorted(finished) == ["pid_debug", "robot_state", "servo_neck", "wheel_encoder"]

    virtual(main)


def test_a_subscription_taken_after_the_close_ends_at_once() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(0.1)
        async with asyncio.timeout(1.0):
            assert [s async for s in robot.subscribe("wheel_encoder")] == []

    virtual(main)


def test_breaking_out_of_async_for_releases_the_subscription() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            seen = 0
            async for _ in robot.subscribe("wheel_encoder", maxlen=4):
                assert robot.stats().streams["wheel_encoder"].subscribers == 1
                seen += 1
                if seen == 3:
                    break
            gc.collect()
            assert robot.stats().streams["wheel_encoder"].subscribers == 0
            await asyncio.sleep(1.0)
            # Nobody holds it: the samples since are nobody's loss.
            assert robot.stats().streams["wheel_encoder"].dropped == 0

    virtual(main)


def test_latest_is_none_before_the_first_sample() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            for name in STREAM_NAMES:
                if name != "robot_state":  # published at open
                    assert robot.latest(name) is None, name
            opened = robot.latest("robot_state")
            assert isinstance(opened, RobotStateSample)
            assert opened.event == "opened"
            await asyncio.sleep(0.5)
            assert isinstance(robot.latest("wheel_encoder"), WheelEncoderSample)
            assert isinstance(robot.latest("servo_neck"), ServoSample)
            assert robot.latest("new_neck") is None  # no worm neck on this robot
            assert robot.latest("pid_debug") is None  # off by default
            with pytest.raises(InvalidArgumentError, match="wheel_encoder"):
                robot.latest("wheel_encoders")

    virtual(main)


# -- 5. device discovery -----------------------------------------------------------------------


def test_the_default_robot_has_a_herkulex_neck_and_every_device() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(1.5)
            state = robot.latest("robot_state")
            assert state is not None
            assert state.neck == "herkulex"
            assert {0, 1, 3, 11, 12, 20} <= set(state.present)
            assert state.absent == ()
            assert state.faults == ()
            assert robot.neck_kind == "herkulex"
            for name, sid in (("servo_neck", 3), ("servo_ext1", 11), ("servo_ext2", 12)):
                sample = robot.latest(name)
                assert isinstance(sample, ServoSample), name
                assert sample.sid == sid

    virtual(main)


def test_the_core_stream_follows_the_dock() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://?docked=1") as robot:
            await asyncio.sleep(0.5)
            status = robot.latest("tbcore_status")
            assert status is not None
            assert status.docked
            assert status.charging
            assert status.current_a > 0
            assert len(status.cell_v) == 5
            assert status.pack_v == pytest.approx(sum(status.cell_v), abs=0.01)
            robot.sim.set_docked(False)
            await asyncio.sleep(0.3)
            status = robot.latest("tbcore_status")
            assert status is not None
            assert not status.docked
            assert not status.charging
            assert status.current_a < 0

    virtual(main)


def test_a_worm_neck_and_no_external_servos() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://?neck=worm&ext=none") as robot:
            await asyncio.sleep(6.0)
            state = robot.latest("robot_state")
            assert state is not None
            assert state.neck == "worm"
            assert 4 in state.present
            stats = robot.stats()
            worm = stats.streams["new_neck"]
            assert worm.enabled
            assert worm.requested_hz == 30.0
            assert worm.achieved_hz == pytest.approx(30.0, rel=0.02)
            assert isinstance(robot.latest("new_neck"), WormNeckSample)
            for name in ("servo_neck", "servo_ext1", "servo_ext2"):
                assert not stats.streams[name].enabled, name
                assert stats.streams[name].samples == 0, name
                assert robot.latest(name) is None, name
            assert requests_to(robot, 3) <= 1 + DISCOVERY_RETRIES  # asked at open only
            assert {row[0] for row in robot.schedule()} == {
                "wheel_encoder",
                "tbcore_status",
                "new_neck",
            }
            with pytest.raises(StateError, match="servo"):
                robot.servo(3)

    virtual(main)


def test_a_silent_servo_is_not_polled_and_found_again_when_it_answers() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://?silent=11") as robot:
            state = robot.latest("robot_state")
            assert state is not None
            assert 11 in state.absent
            assert 11 not in state.present
            assert 12 in state.present
            with pytest.raises(StateError, match="11"):
                robot.servo(11)
            at_open = requests_to(robot, 11)
            assert 1 <= at_open <= 1 + DISCOVERY_RETRIES  # the discovery (and its retries)

            await asyncio.sleep(4.0)  # before the first re-probe: nothing at all
            assert requests_to(robot, 11) == at_open
            await asyncio.sleep(10.0)  # two re-probes; a 30 Hz poll would be 420
            assert requests_to(robot, 11) <= at_open + 2 * (1 + DISCOVERY_RETRIES)
            ext1 = robot.stats().streams["servo_ext1"]
            assert not ext1.enabled
            assert ext1.samples == 0
            assert robot.latest("servo_ext1") is None
            assert robot.stats().streams["servo_ext2"].achieved_hz == pytest.approx(30, rel=0.02)

            sim_transport(robot).line.faults.silent.clear()
            loop = asyncio.get_running_loop()
            cleared = loop.time()
            while robot.latest("servo_ext1") is None:
                assert loop.time() - cleared < 5.0 + 1.5, "the re-probe did not find servo 11"
                await asyncio.sleep(0.1)
            found = robot.latest("robot_state")
            assert found is not None
            assert 11 in found.present
            assert found.absent == ()
            await asyncio.sleep(6.0)
            ext1 = robot.stats().streams["servo_ext1"]
            assert ext1.enabled
            assert ext1.requested_hz == 30.0
            assert ext1.achieved_hz == pytest.approx(30.0, rel=0.02)
            sample = robot.latest("servo_ext1")
            assert isinstance(sample, ServoSample)
            assert sample.sid == 11
            assert robot.servo(11).sid == 11

    virtual(main)


def test_the_budget_counts_a_servo_found_by_the_reprobe() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://?silent=11") as robot:
            sim_transport(robot).line.faults.silent.clear()
            await asyncio.sleep(7.0)
            assert robot.latest("servo_ext1") is not None
            budget = sum(hz * cost for _, hz, _, cost in robot.schedule())
            assert robot.stats().bus.budget_share == pytest.approx(budget)

    virtual(main)


# -- 6. streams switched at run time -----------------------------------------------------------


def test_enable_stream_stops_and_resumes_a_servo_stream() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(1.0)
            ext2_sid = robot.config.ext_servo_ids[1]

            robot.enable_stream("servo_ext2", False)
            await asyncio.sleep(0.1)  # a cycle already on the wire may still land
            requests = requests_to(robot, ext2_sid)
            samples = robot.stats().streams["servo_ext2"].samples
            await asyncio.sleep(2.0)
            assert requests_to(robot, ext2_sid) == requests
            stats = robot.stats().streams["servo_ext2"]
            assert stats.samples == samples
            assert not stats.enabled
            assert stats.requested_hz == 0.0
            assert stats.achieved_hz < 30.0 / 2  # decaying toward zero
            # The others did not notice.
            assert robot.stats().streams["servo_ext1"].achieved_hz == pytest.approx(30, rel=0.02)

            robot.enable_stream("servo_ext2")
            await asyncio.sleep(6.0)
            assert requests_to(robot, ext2_sid) >= requests + 5 * 30
            stats = robot.stats().streams["servo_ext2"]
            assert stats.enabled
            assert stats.requested_hz == 30.0
            assert stats.achieved_hz == pytest.approx(30.0, rel=0.02)
            assert stats.samples >= samples + 5 * 30

    virtual(main)


def test_turning_off_the_wheel_streams_stops_their_samples_not_the_control() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            full = robot.stats().bus.budget_share
            await asyncio.sleep(0.5)
            robot.enable_stream("wheel_encoder", False)
            robot.enable_stream("wheel_odom", False)
            before = {n: robot.stats().streams[n].samples for n in ("wheel_encoder", "wheel_odom")}
            for _ in range(round(2.0 / USER_TICK_S)):
                robot.drive(0.3, 0.0)
                await asyncio.sleep(USER_TICK_S)
            # The control slot still drives the wheels, and still costs its line time
            # (set_rate makes the Robot sum the budget again).
            assert sum(robot.sim.wheel_speeds_mps()) / 2 == pytest.approx(0.3, abs=0.03)
            robot.set_rate("tbcore_status", 10)
            assert robot.stats().bus.budget_share == pytest.approx(full)
            # ... but publishes nothing.
            for name, samples in before.items():
                assert robot.stats().streams[name].samples == samples, name

    virtual(main)


def test_disabling_a_stream_takes_it_out_of_the_budget() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            full = robot.stats().bus.budget_share
            per_cycle = robot.bus.cost_s(read_request(robot.config.ext_servo_ids[1], *SERVO_BLOCK))
            robot.enable_stream("servo_ext2", False)
            assert robot.stats().bus.budget_share == pytest.approx(full - 30.0 * per_cycle)
            robot.enable_stream("servo_ext2", True)
            assert robot.stats().bus.budget_share == pytest.approx(full)

    virtual(main)


def test_the_schedule_leaves_out_a_stream_turned_off() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            robot.enable_stream("servo_ext2", False)
            assert "servo_ext2" not in {row[0] for row in robot.schedule()}
            budget = sum(hz * cost for _, hz, _, cost in robot.schedule())
            assert robot.stats().bus.budget_share == pytest.approx(budget)

    virtual(main)


def test_set_rate_halves_the_core_stream() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            full = robot.stats().bus.budget_share
            robot.set_rate("tbcore_status", 5)
            assert robot.stats().streams["tbcore_status"].requested_hz == 5.0
            assert robot.stats().bus.budget_share == pytest.approx(
                full - 5.0 * robot.bus.cost_s(read_status())
            )
            assert {row[0]: row[1] for row in robot.schedule()}["tbcore_status"] == 5.0
            await asyncio.sleep(6.0)
            stats = robot.stats()
            assert stats.streams["tbcore_status"].achieved_hz == pytest.approx(5.0, rel=0.02)
            assert stats.streams["tbcore_status"].skipped == 0
            assert stats.streams["wheel_encoder"].achieved_hz == pytest.approx(50.0, rel=0.02)

    virtual(main)


def test_bad_stream_names_and_rates_are_refused() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            for call in (
                lambda: robot.enable_stream("servo_ext3"),
                lambda: robot.set_rate("battery", 5),
                lambda: robot.subscribe("odom"),
                lambda: robot.latest("neck"),
            ):
                with pytest.raises(InvalidArgumentError) as caught:
                    call()
                for name in STREAM_NAMES:
                    assert name in str(caught.value)
            with pytest.raises(InvalidArgumentError):
                robot.set_rate("tbcore_status", 0)
            with pytest.raises(InvalidArgumentError, match="polled"):
                robot.set_rate("robot_state", 2)
            with pytest.raises(StateError, match="new_neck"):
                robot.enable_stream("new_neck")  # no worm neck on this robot
            assert robot.stats().streams["tbcore_status"].requested_hz == 10.0

    virtual(main)


# -- 7. a USB adapter's latency ----------------------------------------------------------------


def test_the_wheel_stream_keeps_50_hz_behind_a_16_ms_usb_latency() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://?usb_latency_ms=16") as robot:
            assert sim_transport(robot).line.usb_latency_s == pytest.approx(0.016)
            await asyncio.sleep(5.5)
            stats = robot.stats()
            wheel = stats.streams["wheel_encoder"]
            assert wheel.achieved_hz == pytest.approx(50.0, rel=0.01)
            assert wheel.skipped == 0
            assert wheel.missed == 0
            assert stats.bus.timeouts == 0
            for name in ("servo_neck", "servo_ext1", "servo_ext2"):
                assert stats.streams[name].achieved_hz == pytest.approx(30.0, rel=0.02), name

    virtual(main)
