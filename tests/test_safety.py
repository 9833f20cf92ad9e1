"""A wheel stop that is delivered: repeated, and confirmed by the wheel counts.

Against ``sim://`` in virtual time, judged by the simulated robot's own wheels and pose:
on a line that loses 3 % of its bytes a single unacknowledged stop can be lost and the
robot drives on; :func:`~ohmni_tb.safety.stop_wheels` stops it on every seed, says loudly
when the drive boards cannot confirm it, and keeps sending stops the whole time.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import re
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

import pytest
import typer
from typer.testing import CliRunner

from ohmni_tb import Robot
from ohmni_tb.bus import Bus
from ohmni_tb.cli import app
from ohmni_tb.errors import (
    DeviceError,
    OhmniError,
    OutOfRangeError,
    StopNotConfirmedError,
    TransportError,
)
from ohmni_tb.protocol import Packet, ReadReply
from ohmni_tb.protocol.drive import decode_wheel_command, parse_count, read_count, wheel_command
from ohmni_tb.robot import LocalRobot
from ohmni_tb.safety import DEFAULT_REPEAT_S, StopReport, stop_wheels
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport

T = TypeVar("T")

#: The issue's line: 3 % of the bytes lost, each way.
SEEDS = range(1, 7)
Stop = Callable[[Bus], Awaitable[object]]


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


async def sim(query: str = "") -> tuple[SimTransport, SimRobot]:
    transport = await open_transport(f"sim://?{query}")
    assert isinstance(transport, SimTransport)
    assert transport.robot is not None
    return transport, transport.robot


async def drive(bus: Bus, pwm: int = 400, seconds: float = 1.0) -> None:
    """The demo's drive: the wheel command re-sent at 10 Hz."""
    for _ in range(round(seconds * 10)):
        await bus.send(wheel_command(pwm, pwm))
        await asyncio.sleep(0.1)


def fastest(robot: SimRobot) -> float:
    return max(abs(v) for v in robot.wheel_speeds_mps())


async def single_stop(bus: Bus) -> None:
    """The demo's old stop: one wheel command of 0, which nothing acknowledges."""
    await bus.send(wheel_command(0, 0))


def drive_and_stop(seed: int, stop: Stop) -> tuple[float, float, float]:
    """Drive 1 s on the lossy line, stop, and look at the robot: (speed while driving,
    speed 1 s after the stop, metres travelled in the second after that)."""

    async def main() -> tuple[float, float, float]:
        transport, robot = await sim(f"drop=0.03&seed={seed}")
        async with Bus(transport) as bus:
            await drive(bus)
            moving = fastest(robot)
            await stop(bus)
            await asyncio.sleep(1.0)
            after = fastest(robot)
            x = robot.pose.x
            await asyncio.sleep(1.0)
            return moving, after, robot.pose.x - x

    return virtual(main)


def test_a_single_unacknowledged_stop_is_lost_on_a_lossy_line_and_the_robot_drives_on() -> None:
    results = {seed: drive_and_stop(seed, single_stop) for seed in SEEDS}
    assert all(moving > 0.3 for moving, _, _ in results.values())
    drove_on = [seed for seed, (_, after, travelled) in results.items() if after > 0.3]
    # The failure the issue reports: some seed loses the stop and the robot keeps going.
    assert drove_on, results
    assert all(results[seed][2] > 0.3 for seed in drove_on)


@pytest.mark.parametrize("seed", SEEDS)
def test_stop_wheels_stops_the_robot_on_a_lossy_line(seed: int) -> None:
    outcome: list[StopReport | StopNotConfirmedError] = []

    async def stop(bus: Bus) -> None:
        # On a line this lossy the count reads may not confirm it in time: then it must
        # say so (and have kept stopping); either way the wheels must stop.
        try:
            outcome.append(await stop_wheels(bus))
        except StopNotConfirmedError as exc:
            outcome.append(exc)

    moving, after, travelled = drive_and_stop(seed, stop)
    assert moving > 0.3
    assert after == 0.0
    assert travelled == 0.0
    [result] = outcome
    if isinstance(result, StopNotConfirmedError):
        assert result.report.stops_sent >= 30  # stopping all the while
    else:
        assert result.confirmed


def test_stop_wheels_confirms_on_most_seeds_of_a_lossy_line() -> None:
    async def confirmed(seed: int) -> bool:
        transport, _ = await sim(f"drop=0.03&seed={seed}")
        async with Bus(transport) as bus:
            await drive(bus)
            try:
                await stop_wheels(bus, timeout_s=2.0)
            except StopNotConfirmedError:
                return False
            return True

    results = [run_virtual(confirmed(seed)) for seed in range(1, 21)]
    # Measured: 19 of 20 (a 3 % byte loss costs over half of the count reads).
    assert sum(results) >= 17, results


def test_stop_wheels_returns_once_the_wheels_stand_still_with_the_counts_they_stand_at() -> None:
    async def main() -> tuple[StopReport, tuple[float, float], int, int, float]:
        transport, robot = await sim("drop=0.03&seed=4")
        async with Bus(transport) as bus:
            await drive(bus)
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            report = await stop_wheels(bus)
            took = loop.time() - t0
            speeds = robot.wheel_speeds_mps()
            train = robot.train
            return report, speeds, train.count(0), train.count(1), took

    report, speeds, left, right, took = virtual(main)
    assert speeds == (0.0, 0.0)  # stopped when it returns, not just soon after
    assert report.confirmed
    assert report.counts == (left, right)
    assert report.stops_sent >= 2  # repeated while the wheels ran down
    assert report.reads >= 3
    assert 0.1 < report.elapsed_s == pytest.approx(took, abs=1e-6)
    assert report.elapsed_s < 1.0


def test_a_robot_at_rest_confirms_in_a_few_readings() -> None:
    async def main() -> StopReport:
        transport, _ = await sim()
        async with Bus(transport) as bus:
            return await stop_wheels(bus)

    report = virtual(main)
    assert report.confirmed
    assert report.counts == (0, 0)
    assert report.missed_reads == 0
    assert 0.06 <= report.elapsed_s < 0.1
    assert report.stops_sent >= 2  # the first at once, then every 30 ms while reading


def test_silent_drive_boards_raise_loudly_and_the_stops_go_out_the_whole_time(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A silent board still acts on what it hears (a dead transmitter): count the stops
    # the left board received, and when.
    heard: list[float] = []

    async def main() -> tuple[StopNotConfirmedError, float, float, tuple[float, float]]:
        transport, robot = await sim("silent=0,1")
        board = robot.left
        original = board.handle_jog

        def spy(packet: Packet, now_s: float) -> None:
            if decode_wheel_command(packet).get(0) == 0:
                heard.append(now_s)
            original(packet, now_s)

        monkeypatch.setattr(board, "handle_jog", spy)
        async with Bus(transport) as bus:
            await drive(bus)
            assert fastest(robot) > 0.3
            t0 = transport.line.now_s()
            with pytest.raises(StopNotConfirmedError) as caught:
                await stop_wheels(bus, timeout_s=0.5)
            t1 = transport.line.now_s()
            return caught.value, t0, t1, robot.wheel_speeds_mps()

    error, t0, t1, speeds = virtual(main)
    message = str(error)
    assert "WHEEL STOP NOT CONFIRMED" in message
    assert "may still be moving" in message
    assert "the left drive board (sid 0) answered none of" in message
    assert "the right drive board (sid 1) answered none of" in message
    assert "the bus presumes it gone" in message
    assert isinstance(error, DeviceError)
    assert error.sid == 0
    assert not error.report.confirmed
    assert error.report.reads == 0
    assert error.report.counts is None
    assert t1 - t0 == pytest.approx(0.5, abs=0.05)
    # Every stop sent reached the board, from the start to the end of the half second.
    assert error.report.stops_sent == len(heard)
    assert len(heard) >= 0.5 / DEFAULT_REPEAT_S
    assert heard[0] - t0 < 0.005
    assert t1 - heard[-1] <= DEFAULT_REPEAT_S + 0.005
    assert max(b - a for a, b in itertools.pairwise(heard)) <= DEFAULT_REPEAT_S + 0.005
    assert speeds == (0.0, 0.0)  # the stops acted, though nothing could confirm it


def test_wheels_that_keep_being_driven_are_not_confirmed_as_stopped() -> None:
    async def main() -> StopNotConfirmedError:
        transport, _ = await sim()
        async with Bus(transport) as bus:

            async def rogue() -> None:  # another task that keeps driving
                while True:
                    await bus.send(wheel_command(400, 400))
                    await asyncio.sleep(0.005)

            task = asyncio.create_task(rogue())
            await asyncio.sleep(0.5)
            try:
                with pytest.raises(StopNotConfirmedError) as caught:
                    await stop_wheels(bus, timeout_s=0.3)
            finally:
                task.cancel()
                await asyncio.wait([task])
            return caught.value

    error = virtual(main)
    # Forward: the left count goes up, the right (mirrored) one down.
    assert re.search(r"the left drive board \(sid 0\)'s count moved \+\d+ ticks", str(error))
    assert re.search(r"the right drive board \(sid 1\)'s count moved -\d+ ticks", str(error))
    assert error.report.reads >= 6
    assert error.report.stops_sent >= 0.3 / DEFAULT_REPEAT_S - 1


def test_a_lost_link_is_not_a_confirmed_stop() -> None:
    async def main() -> StopNotConfirmedError:
        transport, _ = await sim()
        async with Bus(transport) as bus:
            await drive(bus, seconds=0.3)
            asyncio.get_running_loop().call_later(0.01, transport.unplug_usb)
            with pytest.raises(StopNotConfirmedError) as caught:
                await stop_wheels(bus)
            return caught.value

    error = virtual(main)
    assert "the link failed" in str(error)
    assert isinstance(error.__cause__, TransportError)
    assert error.report.elapsed_s < 0.1  # said at once, not after the whole second


def test_a_cancelled_caller_still_stops_the_wheels() -> None:
    async def main() -> tuple[float, float, set[asyncio.Task[Any]]]:
        transport, robot = await sim()
        async with Bus(transport) as bus:
            await drive(bus)
            # The line is busy with a slow slot: the stop has to wait for it.
            busy = asyncio.ensure_future(bus.transact([read_count(0), read_count(1)]))
            await asyncio.sleep(0)
            task = asyncio.create_task(stop_wheels(bus))
            await asyncio.sleep(0)  # it has started: the stop is queued
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            await busy
            moving = fastest(robot)
            await asyncio.sleep(1.0)
            others = asyncio.all_tasks() - {asyncio.current_task()}
            return moving, fastest(robot), {t for t in others if t is not None}

    _moving, after, others = virtual(main)
    assert after == 0.0
    assert not others  # the repeat task is gone with its caller


@pytest.mark.parametrize(
    ("kwargs", "name", "allowed"),
    [
        ({"timeout_s": 0.0}, "timeout_s", "0.05..60.0 s"),
        ({"timeout_s": math.nan}, "timeout_s", "0.05..60.0 s"),
        ({"timeout_s": 61}, "timeout_s", "0.05..60.0 s"),
        ({"repeat_s": 0.0}, "repeat_s", "0.005..1.0 s"),
        ({"repeat_s": math.inf}, "repeat_s", "0.005..1.0 s"),
        ({"settle_s": 0.01}, "settle_s", "0.02..0.5 s"),
        ({"settle_s": 0.6}, "settle_s", "0.02..0.5 s"),
        ({"settle_s": 0.2, "timeout_s": 0.3}, "settle_s", "0.02..0.15 s"),
        ({"tolerance_ticks": -1}, "tolerance_ticks", "0..1000 ticks"),
        ({"tolerance_ticks": 1.5}, "tolerance_ticks", "0..1000 ticks"),
        ({"tolerance_ticks": True}, "tolerance_ticks", "0..1000 ticks"),
    ],
)
def test_bad_arguments_name_the_value_and_range_and_send_nothing(
    kwargs: dict[str, Any], name: str, allowed: str
) -> None:
    async def main() -> int:
        transport, _ = await sim()
        async with Bus(transport) as bus:
            with pytest.raises(OutOfRangeError) as caught:
                await stop_wheels(bus, **kwargs)
            assert caught.value.name == name
            assert f"allowed {allowed}" in str(caught.value)
            return bus.stats.bytes_out

    assert virtual(main) == 0


def test_counts_that_wrap_through_int32_are_read_as_a_small_change() -> None:
    # Boards near the int32 wrap: a robot at rest across it still confirms.
    async def main() -> tuple[StopReport, int]:
        transport, _ = await sim(f"count_offset={2**31 - 10}")
        async with Bus(transport) as bus:
            await drive(bus, seconds=0.3)
            report = await stop_wheels(bus)
            left = parse_count(ReadReply.parse(await bus.request(read_count(0)) or _no_reply()))
            return report, left

    report, left = virtual(main)
    assert report.confirmed
    assert report.counts is not None
    assert report.counts[0] == left < 0  # wrapped while driving forward


def _no_reply() -> Packet:
    raise AssertionError("no reply")


# -- the demo ------------------------------------------------------------------------------

runner = CliRunner()


def _words(text: str) -> str:
    """The output with rich's line wrapping undone."""
    return " ".join(text.split())


@pytest.mark.usefixtures("virtual_time")
def test_the_demo_does_not_drive_when_no_drive_board_answers() -> None:
    # The Robot finds no drive board: the demo says so and does not drive; the Robot,
    # which never heard from them, sends the stop and has nothing to confirm it with.
    result = runner.invoke(app, ["demo", "--port", "sim://?silent=0,1"])
    assert result.exit_code == 0, result.output
    out = _words(result.stdout)
    assert "faults: drive_absent:0, drive_absent:1" in out
    assert "drive skipped: drive boards 0 and 1 do not answer" in out
    assert "drive: forward" not in result.stdout
    assert "Traceback" not in result.output


@pytest.mark.usefixtures("virtual_time")
def test_the_demo_says_loudly_when_the_drive_boards_go_silent_mid_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Boards that answered and then went silent may be driving: one bold line, exit 1.
    from ohmni_tb.cli import demo as demo_cli
    from ohmni_tb.sim.transport import SimTransport

    real = demo_cli._drive

    async def drive_then_silence(robot: Any) -> None:
        await real(robot)
        transport = robot.bus.transport
        assert isinstance(transport, SimTransport)
        transport.line.faults.silent = {0, 1}

    monkeypatch.setattr(demo_cli, "_drive", drive_then_silence)
    result = runner.invoke(app, ["demo", "--port", "sim://"])
    assert result.exit_code == 1, result.output
    err = _words(result.stderr)
    assert "WHEEL STOP NOT CONFIRMED, the robot may still be moving" in err
    assert err.count("NOT CONFIRMED") == 1  # one line, not a traceback
    assert "Traceback" not in result.output


#: Seeds of the lossy line's fault generator: each a different pattern of lost bytes.
_LOSSY_SEEDS = range(1, 7)


@pytest.mark.parametrize("seed", _LOSSY_SEEDS)
def test_on_a_lossy_line_the_robot_stops_and_never_claims_a_stop_it_did_not_see(
    seed: int,
) -> None:
    # A line losing 3 % of its bytes loses about half its transactions. Whatever the
    # pattern, the wheels stop when the robot closes; the stop is either confirmed by the
    # counts or said not to be (StopNotConfirmedError), never claimed without them.
    async def main() -> tuple[bool, tuple[float, float], float]:
        robot_truth: SimRobot | None = None
        confirmed = True
        try:
            async with Robot.open(f"sim://?drop=0.03&seed={seed}&ext=none") as robot:
                assert isinstance(robot, LocalRobot)
                robot_truth = robot.sim
                await asyncio.sleep(0.3)
                loop = asyncio.get_running_loop()
                started = loop.time()
                while loop.time() - started < 1.0:
                    robot.drive(0.3, 0.0)
                    await asyncio.sleep(0.1)
        except StopNotConfirmedError:
            confirmed = False
        assert robot_truth is not None
        await asyncio.sleep(0.5)
        return confirmed, robot_truth.wheel_speeds_mps(), robot_truth.pose.x

    confirmed, speeds, went = run_virtual(main())
    # Stopped in truth (the stale-feedback guard may have stopped it before the second
    # was up: `went` is not checked), and seen so: the confirmation's count reads go even
    # to a board whose breaker the lost replies opened.
    assert speeds == (0.0, 0.0), (seed, confirmed, went)
    assert confirmed, seed


def test_the_demo_on_a_lossy_line_reports_its_stop_either_way(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from ohmni_tb.cli.demo import _demo

    for seed in _LOSSY_SEEDS:
        # The neck's part, after the drive, may lose its commands on this line too; a
        # stop not confirmed ends the demo with exit code 1 (after saying so).
        with contextlib.suppress(OhmniError, typer.Exit):
            run_virtual(_demo(f"sim://?drop=0.03&seed={seed}&ext=none", True))
        out = _words(capsys.readouterr().out)
        confirmed = re.search(
            r"stop confirmed \d\.\d{3} s after the stop by both wheel counts", out
        )
        assert "drive: forward at 0.30 m/s" in out, out
        if confirmed:
            # What it then says of the odometry holds against the truth.
            assert "wheels 0.000 m/s, 0.000 m/s" in out, out
            error = re.search(r"odometry is (\d+\.\d) mm from the truth", out)
            assert error is not None, out
            assert float(error.group(1)) < 10.0, out
        else:
            assert "odometry is" not in out, out  # no figure from a run it did not finish
