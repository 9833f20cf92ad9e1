"""Port hand-off: ``release_port()`` gives the serial port to another program and
``reclaim_port()`` takes it back, on the same Robot.

On ``sim://`` in virtual time, each test judges the Robot by what a user sees — the
``robot_state`` events, the streams, the errors — and by the simulator's ground truth:
its line's byte counters (nothing crosses a released line), its wheels and its neck's
registers, asked off the wire. On a pseudo-terminal, with ``ohmni sim --pty`` in its own
process, a second opener of the same path proves the port (its descriptor and its
exclusive lock) is free while released, and that a reclaim waits while it is held.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from typing import Any, TypeVar

import pytest

from cli._helpers import needs_pty, sim_on_pty
from ohmni_tb.bus import Bus
from ohmni_tb.errors import (
    InvalidArgumentError,
    OutOfRangeError,
    StateError,
    StopNotConfirmedError,
    TransportError,
)
from ohmni_tb.herkulex import TorqueControl, parse_reply, ram_read
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import parse_count, read_count
from ohmni_tb.robot import Link, LocalRobot, RobotStateSample, SampleStream, ServoHandle
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import SimServo
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.sim.url import build_line
from ohmni_tb.transport import MemoryTransport

T = TypeVar("T")

#: What drive commands say while the port is released.
RELEASED_MESSAGE = r"the port is released to another program; reclaim_port\(\) first"
#: Float slack for comparing loop times.
EPS_S = 1e-6


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


def sim_line(robot: LocalRobot) -> SimLine:
    transport = robot.bus.transport
    assert isinstance(transport, SimTransport)
    return transport.line


def sim_robot(robot: LocalRobot) -> SimRobot:
    assert isinstance(robot.sim, SimRobot)
    return robot.sim


def line_bytes(line: SimLine) -> tuple[int, int]:
    """Bytes the devices and the host have received on ``line`` so far."""
    return line.stats.bytes_to_devices, line.stats.bytes_to_host


def link(robot: LocalRobot) -> Link:
    """The Robot's link now (a call, so a type checker does not narrow it)."""
    return robot.state.link


def fastest(robot: LocalRobot) -> float:
    """The faster of the simulated robot's true wheel speeds, m/s."""
    return max(abs(v) for v in sim_robot(robot).wheel_speeds_mps())


def neck_torque(robot: LocalRobot) -> TorqueControl:
    """The simulated neck's torque mode now, asked of the servo, not over the wire."""
    sim = sim_robot(robot)
    neck = sim.neck
    assert isinstance(neck, SimServo)
    reply = neck.handle(ram_read(neck.sid, "torque_control"), sim.sync())
    assert reply is not None
    return TorqueControl(parse_reply(reply).value("torque_control"))


def drain(subscription: SampleStream[T]) -> list[T]:
    out = []
    while (item := subscription.get_nowait()) is not None:
        out.append(item)
    return out


def events(samples: list[RobotStateSample], words: str) -> list[RobotStateSample]:
    """The robot_state samples whose event text holds ``words``."""
    return [s for s in samples if s.event is not None and words in s.event]


async def next_event(states: SampleStream[RobotStateSample], words: str) -> RobotStateSample:
    """Wait for the next robot_state event holding ``words``."""
    async with asyncio.timeout(30):
        async for sample in states:
            if sample.event is not None and words in sample.event:
                return sample
    raise AssertionError(f"robot_state ended before an event with {words!r}")


async def keep_driving(robot: LocalRobot, seconds: float) -> None:
    """drive(0.3, 0) every 50 ms (a teleop loop) for ``seconds``."""
    for _ in range(round(seconds / 0.05)):
        robot.drive(0.3, 0.0)
        await asyncio.sleep(0.05)


async def encoder_samples_in(robot: LocalRobot, seconds: float) -> int:
    """How many wheel_encoder samples arrive in the next ``seconds``."""
    encoder = robot.subscribe("wheel_encoder", maxlen=1000)
    await asyncio.sleep(seconds)
    return len(drain(encoder))


# -- on sim://, in virtual time ------------------------------------------------------------


def test_a_released_port_is_silent_refuses_driving_and_comes_back_on_reclaim() -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state", maxlen=1000)
            await keep_driving(robot, 1.0)
            out: dict[str, Any] = {"moving": fastest(robot), "before": robot.stats().bus}
            line = sim_line(robot)
            await robot.release_port()
            # The stop was confirmed by the counts before the port went.
            out["at_release"] = fastest(robot)
            out["state"] = robot.state
            out["released"] = events(drain(states), "released")
            quiet_from = line_bytes(line)
            last_encoder = robot.latest("wheel_encoder")
            refused = []
            for command in (
                lambda: robot.drive(0.3, 0.0),
                lambda: robot.drive_wheels(0.2, 0.2),
                lambda: robot.drive_pwm(300, 300),
            ):
                with pytest.raises(StateError, match=RELEASED_MESSAGE) as error:
                    command()
                refused.append(str(error.value))
            out["refused"] = refused
            # Longer than the watchdog, a reconnect's backoff and the reprobe interval.
            await asyncio.sleep(6.0)
            out["quiet"] = tuple(b - a for a, b in zip(quiet_from, line_bytes(line), strict=True))
            out["still"] = robot.state.link
            out["during"] = robot.stats()
            out["latest_kept"] = robot.latest("wheel_encoder") == last_encoder
            out["periodic"] = [s.link for s in drain(states) if s.event is None]
            out["rolled"] = fastest(robot)
            await robot.reclaim_port()
            out["back"] = robot.state
            out["reclaimed"] = events(drain(states), "port reclaimed")
            await asyncio.sleep(0.1)
            out["encoder_samples"] = await encoder_samples_in(robot, 1.0)
            await keep_driving(robot, 1.0)
            out["driven_again"] = fastest(robot)
            return out

    out = virtual(main)
    assert out["moving"] > 0.25
    assert out["at_release"] == 0.0
    state: RobotStateSample = out["state"]
    assert state.link is Link.RELEASED
    assert str(state.link) == "released"
    (released,) = out["released"]
    assert released.link is Link.RELEASED
    assert released.event == "port released to another program until reclaim_port()"
    assert len(out["refused"]) == 3
    # Nothing crossed the line, and nothing tried to reopen it on its own.
    assert out["quiet"] == (0, 0)
    assert out["still"] is Link.RELEASED
    during = out["during"]
    assert during.bus.link_losses == out["before"].link_losses
    assert during.bus.reconnects == out["before"].reconnects
    assert during.streams["wheel_encoder"].samples > 0
    assert out["latest_kept"]
    # robot_state keeps its periodic samples, showing the release.
    assert len(out["periodic"]) >= 5
    assert set(out["periodic"]) == {Link.RELEASED}
    assert out["rolled"] == 0.0
    back: RobotStateSample = out["back"]
    assert back.link is Link.CONNECTED
    assert back.faults == ()
    (reclaimed,) = out["reclaimed"]
    assert reclaimed.link is Link.CONNECTED
    assert 48 <= out["encoder_samples"] <= 51
    assert out["driven_again"] > 0.25


@pytest.mark.parametrize(
    ("on_exit_neck", "expected"), [("free", TorqueControl.FREE), ("keep", TorqueControl.ON)]
)
def test_releasing_does_with_the_neck_what_closing_does_and_neck_commands_are_refused(
    on_exit_neck: str, expected: TorqueControl
) -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://", on_exit_neck=on_exit_neck) as robot:
            await robot.neck.move(raw=400, playtime_s=0.3)
            await asyncio.sleep(0.5)
            out: dict[str, Any] = {"holding": neck_torque(robot)}
            await robot.release_port()
            out["released"] = neck_torque(robot)
            line = sim_line(robot)
            quiet_from = line_bytes(line)
            neck = robot.neck
            assert isinstance(neck, ServoHandle)
            errors = []
            commands: list[Callable[[], Awaitable[object]]] = [
                lambda: neck.move(raw=450),
                lambda: neck.torque("on"),
                lambda: robot.servo(11).free(),
                lambda: robot.light_ring(0, 255, 255),
                robot.info,
            ]
            for command in commands:
                with pytest.raises(StateError, match=RELEASED_MESSAGE) as error:
                    async with asyncio.timeout(1.0):  # a refusal, not a hang
                        await command()
                errors.append(error.value)
            out["errors"] = errors
            out["quiet"] = line_bytes(line) == quiet_from
            await robot.reclaim_port()
            await robot.neck.move(raw=450, playtime_s=0.3)
            await asyncio.sleep(0.5)
            out["after"] = neck_torque(robot)
            return out

    out = virtual(main)
    assert out["holding"] is TorqueControl.ON
    assert out["released"] is expected
    assert len(out["errors"]) == 5
    assert out["quiet"]
    assert out["after"] is TorqueControl.ON


def test_a_cancelled_release_still_stops_the_wheels_and_releases_the_port() -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            await keep_driving(robot, 1.0)
            out: dict[str, Any] = {"moving": fastest(robot)}
            releasing = asyncio.create_task(robot.release_port())
            await asyncio.sleep(0.01)  # inside the confirmed stop
            releasing.cancel()
            with pytest.raises(asyncio.CancelledError):
                await releasing
            out["at_cancel"] = fastest(robot)
            out["link"] = robot.state.link
            out["attached"] = sim_line(robot).attached
            return out

    out = virtual(main)
    assert out["moving"] > 0.25
    assert out["at_cancel"] == 0.0
    assert out["link"] is Link.RELEASED
    assert not out["attached"]


def test_a_stream_turned_off_stays_off_after_a_reclaim() -> None:
    async def main() -> tuple[int, int]:
        async with LocalRobot.open("sim://") as robot:
            robot.enable_stream("servo_ext1", False)
            await robot.release_port()
            await robot.reclaim_port()
            ext1 = robot.subscribe("servo_ext1", maxlen=1000)
            ext2 = robot.subscribe("servo_ext2", maxlen=1000)
            await asyncio.sleep(1.0)
            return len(drain(ext1)), len(drain(ext2))

    off, on = virtual(main)
    assert off == 0
    assert 28 <= on <= 31


def test_a_timed_release_takes_the_port_back_by_itself() -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state", maxlen=1000)
            loop = asyncio.get_running_loop()
            await robot.release_port(duration_s=2.0)
            out: dict[str, Any] = {"released_s": loop.time()}
            out["released"] = events(drain(states), "released")
            await asyncio.sleep(1.9)
            out["before_due"] = robot.state.link
            out["back"] = await next_event(states, "port reclaimed")
            out["encoder_samples"] = await encoder_samples_in(robot, 1.0)
            return out

    out = virtual(main)
    (released,) = out["released"]
    assert released.event == "port released to another program for 2 s"
    assert out["before_due"] is Link.RELEASED
    back: RobotStateSample = out["back"]
    assert back.link is Link.CONNECTED
    assert out["released_s"] + 2.0 - EPS_S <= back.stamp_s <= out["released_s"] + 2.1
    assert 48 <= out["encoder_samples"] <= 51


@pytest.mark.parametrize("again_s", [3.0, None])
def test_releasing_again_replaces_the_timer(again_s: float | None) -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state", maxlen=1000)
            loop = asyncio.get_running_loop()
            await robot.release_port(duration_s=1.0)
            await asyncio.sleep(0.5)
            await robot.release_port(duration_s=again_s)  # no error
            out: dict[str, Any] = {"again_s": loop.time()}
            out["renewed"] = events(drain(states), "renewed")
            await asyncio.sleep(2.0)  # past the first timer
            out["after_first_timer"] = robot.state.link
            await asyncio.sleep(2.0)
            out["reclaimed"] = events(drain(states), "port reclaimed")
            out["link"] = robot.state.link
            await robot.reclaim_port()
            await robot.reclaim_port()  # not released: nothing to do
            out["end"] = robot.state.link
            return out

    out = virtual(main)
    (renewed,) = out["renewed"]
    assert renewed.link is Link.RELEASED
    assert out["after_first_timer"] is Link.RELEASED
    if again_s is None:
        assert renewed.event == "port release renewed: until reclaim_port()"
        assert out["reclaimed"] == []
        assert out["link"] is Link.RELEASED
    else:
        assert renewed.event == "port release renewed: for 3 s"
        (reclaimed,) = out["reclaimed"]
        assert out["again_s"] + again_s - EPS_S <= reclaimed.stamp_s <= out["again_s"] + 3.1
        assert out["link"] is Link.CONNECTED
    assert out["end"] is Link.CONNECTED


def test_a_stop_the_counts_do_not_confirm_is_raised_after_the_port_is_released() -> None:
    # As on exit: the robot may be moving, so the caller hears of it; the port goes all
    # the same (the other program may be what is needed to deal with it).
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state", maxlen=1000)
            await asyncio.sleep(0.2)
            line = sim_line(robot)
            line.faults.silent = {int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE)}
            with pytest.raises(StopNotConfirmedError) as error:
                await robot.release_port()
            out: dict[str, Any] = {"error": error.value, "link": robot.state.link}
            out["attached"] = line.attached
            out["released"] = events(drain(states), "released")
            line.faults.silent = set()
            await robot.reclaim_port()
            out["back"] = robot.state.link
            return out

    out = virtual(main)
    assert out["link"] is Link.RELEASED
    assert not out["attached"]
    (released,) = out["released"]
    assert released.event is not None
    assert "the wheel stop was not confirmed" in released.event
    assert out["back"] is Link.CONNECTED


def test_closing_a_released_robot_is_quick_and_sends_nothing() -> None:
    async def main() -> dict[str, Any]:
        loop = asyncio.get_running_loop()
        async with LocalRobot.open("sim://") as robot:
            line = sim_line(robot)
            await robot.release_port(duration_s=2.0)
            quiet_from = line_bytes(line)
            closing_s = loop.time()
        out: dict[str, Any] = {"took_s": loop.time() - closing_s}
        await asyncio.sleep(3.0)  # past the release's timer: nothing reopens the port
        out["quiet"] = line_bytes(line) == quiet_from
        out["attached"] = line.attached
        out["link"] = robot.state.link
        out["exit_error"] = robot.exit_error
        out["left_running"] = asyncio.all_tasks() - {asyncio.current_task()}
        for call in (robot.release_port(), robot.reclaim_port()):
            with pytest.raises(StateError, match="closed"):
                await call
        return out

    out = virtual(main)
    assert out["took_s"] < 0.01
    assert out["quiet"]
    assert not out["attached"]
    assert out["link"] is Link.CLOSED
    assert out["exit_error"] is None
    assert not out["left_running"]


@pytest.mark.parametrize(
    ("duration_s", "error"),
    [
        (0.05, OutOfRangeError),
        (3600.5, OutOfRangeError),
        (-1.0, OutOfRangeError),
        (math.nan, OutOfRangeError),
        (math.inf, OutOfRangeError),
        ("5", InvalidArgumentError),
        (True, InvalidArgumentError),
    ],
)
def test_a_bad_duration_is_refused_by_value_and_range_and_nothing_changes(
    duration_s: Any, error: type[Exception]
) -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state", maxlen=1000)
            line = sim_line(robot)
            with pytest.raises(error) as refused:
                await robot.release_port(duration_s=duration_s)
            sent = line_bytes(line)
            out: dict[str, Any] = {"message": str(refused.value), "link": robot.state.link}
            robot.drive(0.3, 0.0)  # still allowed
            out["encoder_samples"] = await encoder_samples_in(robot, 1.0)
            out["sent_more"] = line_bytes(line) > sent
            out["events"] = events(drain(states), "release")
            return out

    out = virtual(main)
    assert f"duration_s={duration_s!r}" in out["message"]
    assert "0.1..3600.0 s" in out["message"]
    assert out["link"] is Link.CONNECTED
    assert 48 <= out["encoder_samples"] <= 51
    assert out["sent_more"]
    assert out["events"] == []


def test_a_robot_on_an_injected_transport_that_cannot_reopen_refuses_to_release() -> None:
    async def main() -> dict[str, Any]:
        line, _ = build_line({})
        host, device = MemoryTransport.pair("injected")
        serving = asyncio.create_task(line.serve(device))
        try:
            async with LocalRobot.open(host) as robot:
                await asyncio.sleep(0.2)
                sent = line.stats.bytes_to_devices
                with pytest.raises(StateError, match="cannot reopen its port") as refused:
                    await robot.release_port(duration_s=1.0)
                out: dict[str, Any] = {"message": str(refused.value), "link": robot.state.link}
                out["encoder_samples"] = await encoder_samples_in(robot, 1.0)
                out["sent_more"] = line.stats.bytes_to_devices > sent
                await robot.reclaim_port()  # not released: nothing to do
                out["after_reclaim"] = robot.state.link
        finally:
            serving.cancel()
            await asyncio.gather(serving, return_exceptions=True)
            await device.aclose()
        return out

    out = virtual(main)
    assert "injected transport" in out["message"]
    assert out["link"] is Link.CONNECTED
    assert 48 <= out["encoder_samples"] <= 51
    assert out["sent_more"]
    assert out["after_reclaim"] is Link.CONNECTED


# -- on a pseudo-terminal, in real time ----------------------------------------------------


@pytest.fixture
def pty_path() -> Iterator[str]:
    """``ohmni sim --pty`` in its own process (started outside the test's event loop)."""
    with sim_on_pty() as (path, _proc):
        yield path


async def left_count(bus: Bus) -> int:
    return parse_count(await bus.query(read_count(DeviceId.LEFT_DRIVE)))


@needs_pty
@pytest.mark.real_time  # a pseudo-terminal keeps real time
async def test_on_a_pty_another_program_uses_the_released_port_then_the_robot_takes_it_back(
    pty_path: str,
) -> None:
    async with LocalRobot.open(pty_path) as robot:
        states = robot.subscribe("robot_state", maxlen=1000)
        # While the Robot holds it, the port's exclusive lock refuses a second opener.
        with pytest.raises(TransportError):
            await Bus.open(pty_path)
        await robot.release_port()
        assert link(robot) is Link.RELEASED
        # The other program opens the same port and talks to the robot.
        async with await Bus.open(pty_path, timeout_s=1.0) as other:
            assert await left_count(other) == 0
        await robot.reclaim_port()
        assert link(robot) is Link.CONNECTED
        assert events(drain(states), "port reclaimed")
        # Real time on a shared machine: the stream is back, not a rate to the sample.
        assert await encoder_samples_in(robot, 1.0) >= 25
        # And the Robot holds the port again.
        with pytest.raises(TransportError):
            await Bus.open(pty_path)


@needs_pty
@pytest.mark.real_time  # a pseudo-terminal keeps real time
async def test_on_a_pty_a_reclaim_waits_while_another_program_holds_the_port(
    pty_path: str,
) -> None:
    loop = asyncio.get_running_loop()
    async with LocalRobot.open(pty_path, reconnect_max_backoff_s=0.2) as robot:
        states = robot.subscribe("robot_state", maxlen=1000)
        await robot.release_port()
        async with await Bus.open(pty_path, timeout_s=1.0) as other:
            await robot.reclaim_port()  # returns after the first attempt
            assert link(robot) is Link.RELEASED
            (waiting,) = events(drain(states), "another program still holds it")
            assert waiting.link is Link.RELEASED
            with pytest.raises(StateError, match="another program still holds it"):
                robot.drive(0.3, 0.0)
            await asyncio.sleep(1.0)
            assert link(robot) is Link.RELEASED
            # Its retries never took the port from the program that holds it.
            assert await left_count(other) == 0
            await robot.reclaim_port()  # already waiting: returns at once
            freed_s = loop.time()
        back = await next_event(states, "port reclaimed")
        assert back.link is Link.CONNECTED
        assert back.stamp_s - freed_s < 2.0  # backoff at most 0.2 s, plus the open
        assert await encoder_samples_in(robot, 1.0) >= 25
