"""The Robot's safety behaviour, end to end on ``sim://`` in virtual time.

Each test uses a Robot the way a user would and judges it by what a user could see: the
``robot_state`` events and the streams, the packets on the wire (a spy on the simulated
line, which outlives a reconnect), and the simulated robot's own truth — its wheels and
its servos' registers, asked directly, off the wire. The guards covered: the motion
watchdog, a cancelled or failing user, an unplugged cable, stale wheel feedback, the
thermal and hold guards of the servos, the emergency stop, and the checks that refuse
bad input before anything is sent.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

import pytest

from ohmni_tb.errors import (
    InvalidArgumentError,
    OutOfRangeError,
    StateError,
    StopNotConfirmedError,
)
from ohmni_tb.herkulex import TorqueControl, parse_reply, ram_read, ram_write
from ohmni_tb.protocol import BROADCAST_ID, Command, Packet, PacketDecoder
from ohmni_tb.protocol.connection import DEFAULT_PROBE_INTERVAL_S
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import DRIVE_PROFILE, decode_wheel_command
from ohmni_tb.robot import Link, LocalRobot, RobotStateSample, SampleStream, WheelOdomSample
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import (
    AMBIENT_TEMP_RAW,
    TEMP_RISE_FULL_LOAD_RAW,
    THERMAL_TIME_CONSTANT_S,
    SimServo,
)
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.sim.url import build_line

T = TypeVar("T")

#: The control tick at the default ``wheel_hz`` of 50.
PERIOD_S = 0.02
#: The default ``watchdog_s``.
WATCHDOG_S = 0.5
#: The default ``linear_decel_mps2``.
DECEL_MPS2 = 1.0
#: The default ``servo_hz``: how often the guards see a servo's feedback.
SERVO_PERIOD_S = 1 / 30
#: The default ``neck_rest_raw``.
NECK_REST_RAW = 465
#: Float slack for comparing loop times.
EPS_S = 1e-6

WheelPwm = tuple[int, int]
STOPPED: WheelPwm = (0, 0)


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


# -- what a test looks at ------------------------------------------------------------------


class Wire:
    """Every packet the host writes on the robot's simulated line, with the loop time."""

    def __init__(self, robot: LocalRobot) -> None:
        self.packets: list[tuple[float, Packet]] = []
        line = sim_line(robot)
        write = line.host_write
        decoder = PacketDecoder()
        loop = asyncio.get_running_loop()

        def record(data: bytes) -> None:
            now = loop.time()
            self.packets.extend((now, packet) for packet in decoder.feed(bytes(data)))
            write(data)

        # On the line, not the transport: a reconnect opens a new transport on it.
        setattr(line, "host_write", record)  # noqa: B010 - mypy forbids assigning a method

    def mark(self) -> int:
        """A bookmark for :meth:`since`."""
        return len(self.packets)

    def since(self, mark: int) -> list[Packet]:
        """The packets written after ``mark``."""
        return [packet for _, packet in self.packets[mark:]]

    def wheel_commands(
        self, after_s: float = -math.inf, *, mark: int = 0
    ) -> list[tuple[float, WheelPwm]]:
        """Each wheel command written at or after ``after_s`` (and after ``mark``): its time
        and forward PWM per wheel."""
        out = []
        for t, packet in self.packets[mark:]:
            if t >= after_s and is_wheel_command(packet):
                pwm = decode_wheel_command(packet)
                right = -pwm[1] if DRIVE_PROFILE.right_mirrored else pwm[1]
                out.append((t, (pwm[0], right)))
        return out

    def last_wheel_command_s(self) -> float:
        """When the newest wheel command was written."""
        return self.wheel_commands()[-1][0]


def is_wheel_command(packet: Packet) -> bool:
    return packet.sid == BROADCAST_ID and packet.cmd == DRIVE_PROFILE.wheel_form


def is_read(packet: Packet) -> bool:
    return packet.cmd in (Command.RAM_READ, Command.EEP_READ)


def idle_schedule(packet: Packet) -> bool:
    """Whether a standing robot's own schedule sends this: reads and zero wheel commands."""
    if is_wheel_command(packet):
        return set(decode_wheel_command(packet).values()) == {0}
    return is_read(packet)


def sim_transport(robot: LocalRobot) -> SimTransport:
    transport = robot.bus.transport
    assert isinstance(transport, SimTransport)
    return transport


def sim_line(robot: LocalRobot) -> SimLine:
    return sim_transport(robot).line


def sim_robot(robot: LocalRobot) -> SimRobot:
    sim = robot.sim
    assert isinstance(sim, SimRobot)
    return sim


def sim_neck(robot: LocalRobot) -> SimServo:
    neck = sim_robot(robot).neck
    assert isinstance(neck, SimServo)
    return neck


def sim_servo(robot: LocalRobot, sid: int) -> SimServo:
    sim = sim_robot(robot)
    found = [servo for servo in (sim.neck, *sim.ext_servos) if servo.sid == sid]
    assert len(found) == 1
    assert isinstance(found[0], SimServo)
    return found[0]


def register(robot: LocalRobot, servo: SimServo, name: str) -> int:
    """A servo register's true value now, asked of the simulated servo, not over the wire."""
    now_s = sim_robot(robot).sync()
    reply = servo.handle(ram_read(servo.sid, name), now_s)
    assert reply is not None
    return parse_reply(reply).value(name)


def torque(robot: LocalRobot, servo: SimServo) -> TorqueControl:
    return TorqueControl(register(robot, servo, "torque_control"))


def position(robot: LocalRobot, servo: SimServo) -> int:
    return register(robot, servo, "calibrated_position")


def fastest(robot: LocalRobot) -> float:
    """The faster of the simulated robot's true wheel speeds, m/s."""
    return max(abs(v) for v in sim_robot(robot).wheel_speeds_mps())


def drain(subscription: SampleStream[T]) -> list[T]:
    out = []
    while (item := subscription.get_nowait()) is not None:
        out.append(item)
    return out


def events(samples: list[RobotStateSample], words: str) -> list[RobotStateSample]:
    """The robot_state samples whose event text holds ``words``."""
    return [s for s in samples if s.event is not None and words in s.event]


async def keep_commanding(command: Callable[[], object], seconds: float) -> float:
    """Call ``command`` every 50 ms (a teleop loop) for ``seconds``; when it was last called."""
    loop = asyncio.get_running_loop()
    last = loop.time()
    for _ in range(round(seconds / 0.05)):
        last = loop.time()
        command()
        await asyncio.sleep(0.05)
    return last


async def sleep_until(t_s: float) -> None:
    await asyncio.sleep(max(0.0, t_s - asyncio.get_running_loop().time()))


async def next_event(states: SampleStream[RobotStateSample], words: str) -> RobotStateSample:
    """Wait for the next robot_state event holding ``words``."""
    async with asyncio.timeout(30):
        async for sample in states:
            if sample.event is not None and words in sample.event:
                return sample
    raise AssertionError(f"robot_state ended before an event with {words!r}")


# -- 1. the motion watchdog ----------------------------------------------------------------


def test_the_watchdog_stops_the_wheels_half_a_second_after_the_last_drive_command() -> None:
    async def main() -> tuple[float, float, RobotStateSample, list[WheelOdomSample], float]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state")
            odom = robot.subscribe("wheel_odom", maxlen=1000)
            last = await keep_commanding(lambda: robot.drive(0.3, 0.0), 1.5)
            moving = fastest(robot)
            trip = await next_event(states, "watchdog")
            await sleep_until(trip.stamp_s + 0.3 / DECEL_MPS2 + 0.3)
            stopped = fastest(robot)
            await asyncio.sleep(0.5)
            assert not events(drain(states), "watchdog")  # it tripped once
            return last, moving, trip, drain(odom), stopped

    last, moving, trip, odom, stopped = virtual(main)
    assert moving > 0.25
    # Tripped by its own timer, watchdog_s after the last command (not at a later tick).
    assert last + WATCHDOG_S - EPS_S <= trip.stamp_s <= last + WATCHDOG_S + EPS_S
    assert trip.watchdog_tripped
    assert trip.event is not None
    assert "0.5 s" in trip.event
    # The command the wheels follow ramps down at the deceleration limit, to zero.
    before = [s.commanded_linear_mps for s in odom if s.stamp_s < trip.stamp_s]
    after = [s for s in odom if s.stamp_s >= trip.stamp_s]
    # (The last sample before the trip may already carry the first braking step.)
    assert before[-1] == pytest.approx(0.3, abs=DECEL_MPS2 * PERIOD_S)
    commanded = [s.commanded_linear_mps for s in after]
    assert all(b <= a for a, b in itertools.pairwise(commanded))
    first_zero = next(s for s in after if s.commanded_linear_mps == 0.0)
    assert first_zero.stamp_s <= trip.stamp_s + 0.3 / DECEL_MPS2 + PERIOD_S + EPS_S
    # And the robot itself stands still soon after.
    assert stopped < 0.01


def test_with_the_watchdog_off_the_robot_keeps_driving_without_commands() -> None:
    async def main() -> tuple[float, list[RobotStateSample], list[WheelPwm], RobotStateSample]:
        async with LocalRobot.open("sim://", watchdog_s=0) as robot:
            states = robot.subscribe("robot_state")
            wire = Wire(robot)
            last = await keep_commanding(lambda: robot.drive(0.3, 0.0), 1.0)
            await asyncio.sleep(2.0)
            pwm = [p for _, p in wire.wheel_commands(last + WATCHDOG_S + PERIOD_S)]
            return fastest(robot), drain(states), pwm, robot.state

    speed, states, pwm, state = virtual(main)
    assert speed > 0.25
    assert not events(states, "watchdog")
    assert not state.watchdog_tripped
    assert pwm
    assert all(left > 0 and right > 0 for left, right in pwm)


def test_the_watchdog_stops_open_loop_pwm_too() -> None:
    async def main() -> tuple[
        float, float, float, RobotStateSample, list[tuple[float, WheelPwm]], float
    ]:
        async with LocalRobot.open("sim://") as robot:
            states = robot.subscribe("robot_state")
            wire = Wire(robot)
            started = asyncio.get_running_loop().time()
            last = await keep_commanding(lambda: robot.drive_pwm(300, 300), 1.0)
            moving = fastest(robot)
            trip = await next_event(states, "watchdog")
            await asyncio.sleep(1.5)
            return started, last, moving, trip, wire.wheel_commands(), fastest(robot)

    started, last, moving, trip, commands, stopped = virtual(main)
    assert moving > 0.2
    assert last + WATCHDOG_S - EPS_S <= trip.stamp_s <= last + WATCHDOG_S + EPS_S
    assert trip.watchdog_tripped
    assert {pwm for t, pwm in commands if started + PERIOD_S < t < trip.stamp_s} == {(300, 300)}
    after = [(t, pwm) for t, pwm in commands if t >= trip.stamp_s]
    # The stop goes on the wire at once, not at the next control tick.
    assert after[0][0] <= trip.stamp_s + PERIOD_S / 4
    assert {pwm for _, pwm in after} == {STOPPED}
    assert stopped == 0.0


# -- 2. a cancelled user -------------------------------------------------------------------


@pytest.mark.parametrize("offset_s", [0.0, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.01, 0.0199])
def test_cancelling_the_task_that_runs_the_robot_mid_tick_still_stops_the_wheels(
    offset_s: float,
) -> None:
    """``offset_s``: when the cancel lands after a control tick is due (its slot on the
    wire for the first few ms, then the line carrying feedback reads, then idle)."""

    async def main() -> dict[str, Any]:
        ready: asyncio.Future[tuple[LocalRobot, Wire]] = asyncio.get_running_loop().create_future()

        async def user() -> None:
            async with LocalRobot.open("sim://") as robot:
                ready.set_result((robot, Wire(robot)))
                await robot.neck.move(raw=400, playtime_s=0.2)
                while True:
                    robot.drive(0.5, 0.0)
                    await asyncio.sleep(0.05)

        task = asyncio.create_task(user())
        robot, wire = await ready
        await asyncio.sleep(2.0)
        out: dict[str, Any] = {"moving": fastest(robot), "holding": torque(robot, sim_neck(robot))}
        loop = asyncio.get_running_loop()
        cancel_at = wire.last_wheel_command_s() + offset_s
        while cancel_at <= loop.time():
            cancel_at += PERIOD_S
        loop.call_at(cancel_at, task.cancel)
        with pytest.raises(asyncio.CancelledError):
            await task
        out["cancel_at"] = cancel_at
        out["cancelled"] = task.cancelled()
        out["closed"] = robot.closed and robot.bus.closed
        out["left_running"] = asyncio.all_tasks() - {asyncio.current_task()}
        await asyncio.sleep(1.0)
        out["commands"] = wire.wheel_commands()
        out["after"] = fastest(robot)
        out["neck"] = torque(robot, sim_neck(robot))
        return out

    out = virtual(main)
    assert out["moving"] > 0.45
    assert out["cancelled"]
    assert out["closed"]
    assert not out["left_running"]
    commands: list[tuple[float, WheelPwm]] = out["commands"]
    assert commands[-1][1] == STOPPED
    # The first stop goes out at once, behind at most the transaction on the wire, and
    # nothing but stops follows it.
    cancel_at: float = out["cancel_at"]
    first_stop = next(i for i, (t, pwm) in enumerate(commands) if t >= cancel_at and pwm == STOPPED)
    assert commands[first_stop][0] - cancel_at < 0.005
    assert {pwm for _, pwm in commands[first_stop:]} == {STOPPED}
    assert out["after"] == 0.0
    # The neck is let go on the way out too (on_exit_neck="free").
    assert out["holding"] is TorqueControl.ON
    assert out["neck"] is TorqueControl.FREE


# -- 3. leaving the async with on an error -----------------------------------------------


@pytest.mark.parametrize(
    ("on_exit_neck", "neck_torque", "neck_raw"),
    [
        ("free", TorqueControl.FREE, 400),
        ("rest", TorqueControl.FREE, 500),  # neck_rest_raw=500 below
        ("keep", TorqueControl.ON, 400),
    ],
)
def test_an_error_in_the_user_code_stops_the_wheels_and_leaves_the_neck_as_configured(
    on_exit_neck: str, neck_torque: TorqueControl, neck_raw: int
) -> None:
    async def main() -> tuple[float, float, TorqueControl, int, TorqueControl, int, bool, bool]:
        opened: list[LocalRobot] = []

        async def user() -> None:
            async with LocalRobot.open(
                "sim://", on_exit_neck=on_exit_neck, neck_rest_raw=500
            ) as robot:
                opened.append(robot)
                await robot.neck.move(raw=400, playtime_s=0.5)
                await keep_commanding(lambda: robot.drive(0.5, 0.0), 1.5)
                raise RuntimeError("user code failed")

        with pytest.raises(RuntimeError, match="user code failed"):
            await user()
        (robot,) = opened
        neck = sim_neck(robot)
        at_exit = fastest(robot)
        at_exit_torque, at_exit_raw = torque(robot, neck), position(robot, neck)
        left_running = bool(asyncio.all_tasks() - {asyncio.current_task()})
        await asyncio.sleep(2.0)
        return (
            at_exit,
            fastest(robot),
            at_exit_torque,
            at_exit_raw,
            torque(robot, neck),
            position(robot, neck),
            robot.closed,
            left_running,
        )

    at_exit, later, exit_torque, exit_raw, final_torque, final_raw, closed, left_running = virtual(
        main
    )
    assert closed
    assert not left_running
    # The stop was confirmed by the wheel counts before the context manager let go.
    assert at_exit == 0.0
    assert later == 0.0
    # The neck was done with before the port closed, not left to happen later.
    assert (exit_torque, exit_raw) == (neck_torque, neck_raw)
    assert (final_torque, final_raw) == (neck_torque, neck_raw)


# -- 4. an unplugged cable -----------------------------------------------------------------


def test_an_unplugged_cable_stops_the_drive_and_reconnects_without_driving_on() -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            wire = Wire(robot)
            states = robot.subscribe("robot_state")
            await keep_commanding(lambda: robot.drive(0.3, 0.0), 1.5)
            loop = asyncio.get_running_loop()
            out: dict[str, Any] = {"moving": fastest(robot), "unplugged_s": loop.time()}
            sim_transport(robot).unplug_usb()
            out["lost"] = await next_event(states, "link lost")
            out["back"] = await next_event(states, "link back")
            # No drive command from here on: the streams come back at their rates.
            await asyncio.sleep(0.1)
            encoder = robot.subscribe("wheel_encoder", maxlen=1000)
            neck = robot.subscribe("servo_neck", maxlen=1000)
            odom = robot.subscribe("wheel_odom", maxlen=1000)
            await asyncio.sleep(1.0)
            out["encoder_samples"] = len(drain(encoder))
            out["neck_samples"] = len(drain(neck))
            out["commanded"] = {s.commanded_linear_mps for s in drain(odom)}
            await asyncio.sleep(0.5)
            out["after"] = fastest(robot)
            out["commands"] = wire.wheel_commands(out["unplugged_s"])
            out["stats"] = robot.stats().bus
            out["state"] = robot.state
            # A new command drives again, on the new link.
            await keep_commanding(lambda: robot.drive(0.3, 0.0), 1.5)
            out["driven_again"] = fastest(robot)
            return out

    out = virtual(main)
    assert out["moving"] > 0.25
    lost: RobotStateSample = out["lost"]
    assert lost.stamp_s >= out["unplugged_s"]
    assert lost.link is Link.LOST
    assert "link_lost" in lost.faults
    back: RobotStateSample = out["back"]
    assert back.stamp_s >= lost.stamp_s
    assert back.link is Link.CONNECTED
    assert "link_lost" not in back.faults
    assert out["state"].link is Link.CONNECTED
    assert out["stats"].link_losses >= 1
    assert out["stats"].reconnects >= 1
    assert 48 <= out["encoder_samples"] <= 51
    assert 28 <= out["neck_samples"] <= 31
    # The drive target was dropped with the link: nothing drives the wheels after it.
    assert out["commanded"] == {0.0}
    commands: list[tuple[float, WheelPwm]] = out["commands"]
    assert commands
    assert {pwm for _, pwm in commands} == {STOPPED}
    assert out["after"] == 0.0
    assert out["driven_again"] > 0.25


# -- 5. stale wheel feedback ---------------------------------------------------------------


@pytest.mark.parametrize("stale_ticks", [3, 5, 10])
def test_silent_drive_boards_stop_the_wheels_after_stale_ticks_and_clear_when_back(
    stale_ticks: int,
) -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://", stale_ticks=stale_ticks) as robot:
            wire = Wire(robot)
            states = robot.subscribe("robot_state")

            def drive() -> None:  # the user's teleop command
                robot.drive(0.3, 0.0)

            await keep_commanding(drive, 1.5)
            loop = asyncio.get_running_loop()
            out: dict[str, Any] = {"moving": fastest(robot), "silent_s": loop.time()}
            line = sim_line(robot)
            line.faults.silent = {int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE)}
            # The user keeps commanding: it is the missing feedback that stops the robot.
            stale = asyncio.create_task(next_event(states, "stale feedback"))
            await keep_commanding(drive, 1.5)
            out["stale"] = await stale
            out["state"] = robot.state
            out["stopped"] = fastest(robot)
            out["commands"] = wire.wheel_commands(out["silent_s"])
            out["back_s"] = loop.time()
            line.faults.silent = set()
            back = asyncio.create_task(next_event(states, "feedback is back"))
            await keep_commanding(drive, 1.5)
            out["back"] = await back
            out["after"] = robot.state
            out["driven_again"] = fastest(robot)
            return out

    out = virtual(main)
    assert out["moving"] > 0.25
    silent_s: float = out["silent_s"]
    stale: RobotStateSample = out["stale"]
    assert "stale_feedback" in stale.faults
    assert f"{stale_ticks} ticks" in (stale.event or "")
    # Each missed tick waits for its reads to time out: measured ~35 ms a tick.
    assert silent_s + (stale_ticks - 1) * PERIOD_S <= stale.stamp_s
    assert stale.stamp_s <= silent_s + stale_ticks * 0.05 + 0.05
    assert "stale_feedback" in out["state"].faults
    # The control slot keeps going out, with zero PWM from the fault on, and the boards
    # (silent, not deaf) stop.
    commands: list[tuple[float, WheelPwm]] = out["commands"]
    during = [pwm for t, pwm in commands if stale.stamp_s <= t < out["back_s"]]
    assert len(during) >= 10
    assert set(during) == {STOPPED}
    assert all(pwm != STOPPED for t, pwm in commands if t < silent_s + PERIOD_S)
    assert out["stopped"] == 0.0
    back: RobotStateSample = out["back"]
    # The bus stopped asking the silent boards (its breaker) and probes them again once
    # a probe interval: the fault clears at the first answered control slot after that.
    assert back.stamp_s - out["back_s"] <= DEFAULT_PROBE_INTERVAL_S + 2 * PERIOD_S
    assert "stale_feedback" not in back.faults
    assert "stale_feedback" not in out["after"].faults
    assert out["driven_again"] > 0.25


# -- 6. the thermal guard ------------------------------------------------------------------

#: A limit just above room temperature, so a servo holding a full load reaches it in
#: seconds; far below the servos' own max_temperature (222), so no servo frees itself.
THERMAL_LIMIT_RAW = 165


def crossing_s(limit_raw: float, load: float) -> float:
    """When a servo at room temperature holding ``load`` reaches ``limit_raw`` (the
    simulator's first-order model)."""
    rise = TEMP_RISE_FULL_LOAD_RAW * load**2
    return THERMAL_TIME_CONSTANT_S * math.log(rise / (rise - (limit_raw - AMBIENT_TEMP_RAW)))


@pytest.mark.parametrize(
    ("sid", "target_raw", "final_raw"),
    [
        (3, 400, NECK_REST_RAW),  # the neck is rested, then freed
        (11, 600, 600),  # an external servo is freed where it is
    ],
)
def test_the_thermal_guard_frees_a_hot_servo(sid: int, target_raw: int, final_raw: int) -> None:
    async def main() -> tuple[float, list[RobotStateSample], RobotStateSample, TorqueControl, int]:
        async with LocalRobot.open("sim://", thermal_limit_raw=THERMAL_LIMIT_RAW) as robot:
            states = robot.subscribe("robot_state")
            await robot.servo(sid).move(raw=target_raw, playtime_s=0.5)
            await asyncio.sleep(0.6)
            servo = sim_servo(robot, sid)
            assert torque(robot, servo) is TorqueControl.ON
            servo.set_load(1.0)
            loaded_s = asyncio.get_running_loop().time()
            await asyncio.sleep(crossing_s(THERMAL_LIMIT_RAW, 1.0) + 3.0)
            return (
                loaded_s,
                drain(states),
                robot.state,
                torque(robot, servo),
                position(robot, servo),
            )

    loaded_s, states, state, final_torque, raw = virtual(main)
    [trip] = events(states, "thermal guard")
    assert trip.event is not None
    assert f"servo {sid}" in trip.event
    assert f"thermal:{sid}" in trip.faults
    assert f"thermal:{sid}" in state.faults
    # Seen at the first feedback read after the servo got that hot.
    crossed_s = loaded_s + crossing_s(THERMAL_LIMIT_RAW, 1.0)
    # (A sample's stamp is when its read went on the wire, a request's time before the
    # servo measured.)
    assert crossed_s - 0.002 <= trip.stamp_s <= crossed_s + SERVO_PERIOD_S + 0.01
    assert final_torque is TorqueControl.FREE
    assert abs(raw - final_raw) <= 1


def test_with_the_thermal_guard_off_a_hot_servo_keeps_its_torque() -> None:
    async def main() -> tuple[list[RobotStateSample], RobotStateSample, TorqueControl, int, int]:
        async with LocalRobot.open(
            "sim://", thermal_limit_raw=THERMAL_LIMIT_RAW, thermal_guard=False
        ) as robot:
            states = robot.subscribe("robot_state")
            await robot.neck.move(raw=400, playtime_s=0.5)
            await asyncio.sleep(0.6)
            neck = sim_neck(robot)
            neck.set_load(1.0)
            await asyncio.sleep(crossing_s(THERMAL_LIMIT_RAW, 1.0) + 3.0)
            sample = robot.latest("servo_neck")
            assert sample is not None
            return (
                drain(states),
                robot.state,
                torque(robot, neck),
                position(robot, neck),
                sample.temperature_raw,
            )

    states, state, neck_torque, raw, temperature = virtual(main)
    assert temperature >= THERMAL_LIMIT_RAW  # it did get that hot
    assert not events(states, "thermal")
    assert not [fault for fault in state.faults if fault.startswith("thermal")]
    assert neck_torque is TorqueControl.ON
    assert raw == 400


# -- 7. the hold guard ---------------------------------------------------------------------


def test_the_hold_guard_rests_then_frees_a_neck_left_holding() -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://", neck_hold_s=2) as robot:
            states = robot.subscribe("robot_state")
            neck = sim_neck(robot)
            loop = asyncio.get_running_loop()
            out: dict[str, Any] = {"moved_s": loop.time()}
            await robot.neck.move(raw=400, playtime_s=0.5)
            await asyncio.sleep(1.9)
            out["holding"] = (torque(robot, neck), position(robot, neck))
            guard = await next_event(states, "hold guard")
            out["guard"] = guard
            await sleep_until(guard.stamp_s + 0.5)
            out["resting"] = (torque(robot, neck), position(robot, neck))
            await sleep_until(guard.stamp_s + 1.5)
            out["rested"] = (torque(robot, neck), position(robot, neck))
            await asyncio.sleep(3.0)
            out["later"] = drain(states)
            return out

    out = virtual(main)
    assert out["holding"] == (TorqueControl.ON, 400)
    guard: RobotStateSample = out["guard"]
    moved_s: float = out["moved_s"]
    assert moved_s + 2.0 < guard.stamp_s <= moved_s + 2.0 + SERVO_PERIOD_S + 0.01
    # Rested first (torque on, on its way to the rest position), then freed there.
    resting_torque, resting_raw = out["resting"]
    assert resting_torque is TorqueControl.ON
    assert 400 < resting_raw < NECK_REST_RAW
    assert out["rested"] == (TorqueControl.FREE, NECK_REST_RAW)
    assert not events(out["later"], "hold guard")  # a free neck is not held


def test_the_hold_guard_leaves_a_neck_that_keeps_being_commanded() -> None:
    async def main() -> tuple[list[RobotStateSample], TorqueControl]:
        async with LocalRobot.open("sim://", neck_hold_s=2) as robot:
            states = robot.subscribe("robot_state")
            for raw in (400, 420, 400, 420, 400):
                await robot.neck.move(raw=raw, playtime_s=0.5)
                await asyncio.sleep(1.5)
            return drain(states), torque(robot, sim_neck(robot))

    states, neck_torque = virtual(main)
    assert not events(states, "hold guard")
    assert neck_torque is TorqueControl.ON


def test_the_hold_guard_counts_a_neck_found_holding_from_the_open() -> None:
    # Left holding by an earlier process (`ohmni neck up`): a Robot that opens is not the
    # one to move it at once (a read-only command would), but rests it neck_hold_s later.
    async def main() -> dict[str, Any]:
        line, sim = build_line({})
        neck = sim.neck
        assert isinstance(neck, SimServo)
        transport = SimTransport(line, robot=sim)
        neck.handle(ram_write(3, "torque_control", TorqueControl.ON), sim.sync())
        loop = asyncio.get_running_loop()
        out: dict[str, Any] = {"opening_s": loop.time()}
        async with LocalRobot.open(transport, neck_hold_s=2) as robot:
            states = robot.subscribe("robot_state")
            await asyncio.sleep(1.5)
            out["holding"] = (torque(robot, neck), position(robot, neck))
            out["guard"] = await next_event(states, "hold guard")
            return out

    out = virtual(main)
    assert out["holding"] == (TorqueControl.ON, 512)
    opening_s: float = out["opening_s"]
    assert opening_s + 2.0 < out["guard"].stamp_s <= opening_s + 2.0 + 0.2


# -- 8. the emergency stop -----------------------------------------------------------------


@pytest.mark.parametrize("offset_s", [0.008, 0.015])
def test_estop_sends_a_stop_at_once_and_refuses_driving_until_cleared(offset_s: float) -> None:
    async def main() -> dict[str, Any]:
        async with LocalRobot.open("sim://") as robot:
            wire = Wire(robot)
            states = robot.subscribe("robot_state")
            await keep_commanding(lambda: robot.drive(0.5, 0.0), 1.5)
            out: dict[str, Any] = {"moving": fastest(robot)}
            loop = asyncio.get_running_loop()
            # Between two control ticks: the stop must not wait for the next one.
            estop_s = wire.last_wheel_command_s() + offset_s
            while estop_s <= loop.time():
                estop_s += PERIOD_S
            await sleep_until(estop_s)
            out["estop_s"] = loop.time()
            out["mark"] = wire.mark()
            await robot.estop()
            out["returned_s"] = loop.time()
            out["state"] = robot.state
            refusals = []
            for refused in (
                lambda: robot.drive(0.3, 0.0),
                lambda: robot.drive_wheels(0.3, 0.3),
                lambda: robot.drive_pwm(300, 300),
            ):
                with pytest.raises(StateError) as caught:
                    refused()
                refusals.append(str(caught.value))
            out["refusals"] = refusals
            await asyncio.sleep(1.5)
            out["stopped"] = fastest(robot)
            out["cleared_s"] = loop.time()
            robot.clear_estop()
            await keep_commanding(lambda: robot.drive(0.3, 0.0), 1.5)
            out["driven_again"] = fastest(robot)
            out["commands"] = wire.wheel_commands(mark=out["mark"])
            out["events"] = drain(states)
            return out

    out = virtual(main)
    assert out["moving"] > 0.45
    estop_s: float = out["estop_s"]
    commands: list[tuple[float, WheelPwm]] = out["commands"]
    latched = [(t, pwm) for t, pwm in commands if t < out["cleared_s"]]
    # The next wheel command is the stop, sent ahead of the schedule (a tick is at most
    # every 20 ms; this one leaves behind at most the transaction on the wire).
    assert latched[0][1] == STOPPED
    assert latched[0][0] - estop_s < 0.004
    assert out["returned_s"] - estop_s < 0.004
    assert {pwm for _, pwm in latched} == {STOPPED}
    assert out["state"].estopped
    for message in out["refusals"]:
        assert "emergency stop" in message
        assert "clear_estop()" in message
    assert out["stopped"] == 0.0
    [latch] = events(out["events"], "emergency stop latched")
    assert latch.estopped
    [clear] = events(out["events"], "emergency stop cleared")
    assert not clear.estopped
    assert out["driven_again"] > 0.25


@pytest.mark.parametrize("moment", ["after_a_tick", "after_a_drive_command"])
def test_no_wheel_command_goes_out_after_the_estops_stop(moment: str) -> None:
    """Forty estops each, across the beat of the 50, 30 and 10 Hz streams, so that some land
    while a wheel command waits behind a transaction on the wire: just after a control
    tick (its slot waits behind a feedback read), or right after a changed drive command
    (its early write waits behind the control slot)."""

    async def main() -> list[tuple[float, list[WheelPwm]]]:
        async with LocalRobot.open("sim://") as robot:
            wire = Wire(robot)
            loop = asyncio.get_running_loop()
            overtaken = []
            for attempt in range(40):
                robot.clear_estop()
                await keep_commanding(lambda: robot.drive(0.5, 0.0), 0.25 + attempt * 0.0031)
                if moment == "after_a_tick":
                    estop_s = wire.last_wheel_command_s() + PERIOD_S * (attempt % 4) / 8
                    while estop_s <= loop.time():
                        estop_s += PERIOD_S
                    await sleep_until(estop_s)
                else:
                    robot.drive(0.6, 0.0)
                estop_s = loop.time()
                mark = wire.mark()
                await robot.estop()
                await asyncio.sleep(0.1)
                # A drive command queued before the estop may go out ahead of its stop;
                # after the stop, nothing but stops until clear_estop().
                commands = [pwm for _, pwm in wire.wheel_commands(mark=mark)]
                assert STOPPED in commands
                driven = [pwm for pwm in commands[commands.index(STOPPED) :] if pwm != STOPPED]
                if driven:
                    overtaken.append((estop_s, driven))
            return overtaken

    overtaken = virtual(main)
    assert not overtaken, f"{len(overtaken)} of 40 estops were followed by a drive: {overtaken}"


# -- 9. bad input is refused before the wire -----------------------------------------------

Act = Callable[[LocalRobot], object]
#: Typed Any: these are the mistakes mypy would catch, made at run time.
A_STRING: Any = "1"
A_FLOAT: Any = 1.5


async def perform(act: Act, robot: LocalRobot) -> None:
    """Do ``act``, awaiting it if it is a coroutine."""
    result = act(robot)
    if isinstance(result, Awaitable):
        await result


def refused(id_: str, act: Act, error: type[Exception], *words: str, url: str = "sim://") -> Any:
    return pytest.param(url, act, error, list(words), id=id_)


@pytest.mark.parametrize(
    ("url", "act", "error", "words"),
    [
        refused("drive-nan", lambda r: r.drive(math.nan), InvalidArgumentError, "linear_mps=nan"),
        refused(
            "drive-str", lambda r: r.drive(A_STRING), InvalidArgumentError, "linear_mps", "'1'"
        ),
        refused("drive-bool", lambda r: r.drive(True), InvalidArgumentError, "True"),
        refused("drive-inf", lambda r: r.drive(math.inf, 0), InvalidArgumentError, "=inf"),
        refused(
            "drive-angular-inf",
            lambda r: r.drive(0.1, -math.inf),
            InvalidArgumentError,
            "angular_radps=-inf",
        ),
        refused(
            "drive_wheels-nan",
            lambda r: r.drive_wheels(math.nan, 0),
            InvalidArgumentError,
            "left_mps=nan",
        ),
        refused(
            "drive_pwm-1001",
            lambda r: r.drive_pwm(1001, 0),
            OutOfRangeError,
            "PWM=1001",
            "-1000..1000",
        ),
        refused(
            "drive_pwm-right--1001",
            lambda r: r.drive_pwm(0, -1001),
            OutOfRangeError,
            "right PWM=-1001",
            "-1000..1000",
        ),
        refused("drive_pwm-nan", lambda r: r.drive_pwm(math.nan, 0), InvalidArgumentError, "nan"),
        refused(
            "drive_pwm-1000.5",
            lambda r: r.drive_pwm(1000.5, 0),
            OutOfRangeError,
            "PWM=1000.5",
            "-1000..1000",
        ),
        refused("neck-700", lambda r: r.neck.move(raw=700), OutOfRangeError, "=700", "280..650"),
        refused("neck-279", lambda r: r.neck.move(raw=279), OutOfRangeError, "=279", "280..650"),
        refused(
            "neck-playtime--1",
            lambda r: r.neck.move(raw=400, playtime_s=-1),
            OutOfRangeError,
            "playtime_s=-1",
            "0.0..2.8448 s",
        ),
        refused(
            "neck-playtime-nan",
            lambda r: r.neck.move(raw=400, playtime_s=math.nan),
            InvalidArgumentError,
            "playtime_s=nan",
            "0.0..2.8448 s",
        ),
        refused(
            "worm-beyond-down",
            lambda r: r.neck.move(raw=130_000),
            OutOfRangeError,
            "=130000",
            "-127000..120000",
            url="sim://?neck=worm",
        ),
        refused(
            "worm-beyond-up",
            lambda r: r.neck.move(raw=-200_000),
            OutOfRangeError,
            "=-200000",
            "-127000..120000",
            url="sim://?neck=worm",
        ),
        refused(
            "worm-float",
            lambda r: r.neck.move(raw=A_FLOAT),
            InvalidArgumentError,
            "1.5",
            url="sim://?neck=worm",
        ),
        refused(
            "light_ring-hue",
            lambda r: r.light_ring(256, 0, 0),
            OutOfRangeError,
            "hue=256",
            "0..255",
        ),
        refused(
            "light_ring-value",
            lambda r: r.light_ring(0, 0, -1),
            OutOfRangeError,
            "value=-1",
            "0..255",
        ),
        refused(
            "set_rate-0",
            lambda r: r.set_rate("servo_neck", 0),
            OutOfRangeError,
            "rate=0",
            "0.1..50.0",
        ),
        refused(
            "subscribe-nope",
            lambda r: r.subscribe("nope"),
            InvalidArgumentError,
            "'nope'",
            "wheel_odom",
        ),
        refused(
            "latest-nope", lambda r: r.latest("nope"), InvalidArgumentError, "'nope'", "wheel_odom"
        ),
        refused(
            "reset_odometry-nan",
            lambda r: r.reset_odometry(math.nan),
            InvalidArgumentError,
            "x_m=nan",
        ),
    ],
)
def test_bad_input_is_refused_with_the_value_and_range_and_nothing_reaches_the_wire(
    url: str, act: Act, error: type[Exception], words: list[str]
) -> None:
    async def main() -> tuple[str, list[Packet], list[Packet], float, bool]:
        async with LocalRobot.open(url) as robot:
            wire = Wire(robot)
            await asyncio.sleep(0.1)
            mark = wire.mark()
            with pytest.raises(error) as caught:
                await perform(act, robot)
            # Anything it had queued would be on the wire by now.
            await asyncio.sleep(0.2)
            odom = robot.latest("wheel_odom")
            assert odom is not None
            return (
                str(caught.value),
                wire.since(mark),
                wire.since(0),
                robot.stats().streams["servo_neck"].requested_hz,
                math.isfinite(odom.x_m),
            )

    message, after, everything, neck_hz, odometry_finite = virtual(main)
    for word in words:
        assert word in message
    # A standing robot's schedule only reads and sends zero wheel commands: anything
    # else after the refusal would be the refused command's.
    assert after
    assert all(idle_schedule(packet) for packet in after), [
        p for p in after if not idle_schedule(p)
    ]
    assert all(idle_schedule(packet) for packet in everything)
    # And nothing changed.
    assert neck_hz in (30.0, 0.0)  # 0: the worm-neck robot has no servo_neck stream
    assert odometry_finite


@pytest.mark.parametrize(
    ("url", "act"),
    [
        ("sim://", lambda r: r.drive(0.3)),
        ("sim://", lambda r: r.drive_wheels(0.2, 0.2)),
        ("sim://", lambda r: r.drive_pwm(200, 0)),
        ("sim://", lambda r: r.neck.move(raw=400)),
        ("sim://?neck=worm", lambda r: r.neck.move(raw=1000)),
        ("sim://", lambda r: r.light_ring(10, 20, 30)),
    ],
    ids=["drive", "drive_wheels", "drive_pwm", "neck", "worm_neck", "light_ring"],
)
def test_the_same_commands_with_good_input_do_reach_the_wire(url: str, act: Act) -> None:
    """The control for the test above: its check sees each command's packet."""

    async def main() -> list[Packet]:
        async with LocalRobot.open(url) as robot:
            wire = Wire(robot)
            await asyncio.sleep(0.1)
            mark = wire.mark()
            await perform(act, robot)
            await asyncio.sleep(0.2)
            return wire.since(mark)

    after = virtual(main)
    assert not all(idle_schedule(packet) for packet in after)


def test_a_robot_whose_drive_boards_never_answered_closes_cleanly(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger="ohmni_tb")

    # `ohmni status` on a bus without drive boards must still show what does answer:
    # nothing was driven, and no count could ever confirm a stop.
    async def main() -> tuple[tuple[int, ...], BaseException | None, list[WheelPwm]]:
        async with LocalRobot.open("sim://?silent=0,1") as robot:
            wire = Wire(robot)
            await asyncio.sleep(0.5)
            absent = robot.state.absent
        return absent, robot.exit_error, [pwm for _, pwm in wire.wheel_commands()]

    absent, exit_error, commands = virtual(main)
    assert absent == (0, 1)
    assert exit_error is None
    assert commands[-1] == (0, 0)  # the zero command went out all the same
    assert "drive boards never answered" in caplog.text


def test_a_robot_whose_drive_boards_went_silent_still_raises_on_a_clean_exit() -> None:
    async def main() -> None:
        async with LocalRobot.open("sim://") as robot:
            await asyncio.sleep(0.2)
            sim_line(robot).faults.silent = {int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE)}

    with pytest.raises(StopNotConfirmedError):
        virtual(main)
