"""Commands through the daemon: one driver at a time (the control lease), any number of
readers, nothing reaching the wire without the lease, the Robot's safety still in charge.

Real asyncio on ``sim://``; the simulator's ground truth says whether the robot moved.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterator
from typing import Any

import pytest
from websockets.asyncio.client import ClientConnection, connect

from ohmni_tb import Robot
from ohmni_tb.client import RobotClient
from ohmni_tb.control.pid import PidGains
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import InvalidArgumentError, LeaseError, OutOfRangeError, StateError
from ohmni_tb.protocol import Command, Packet


def speed(robot: Robot) -> float:
    """The simulated body's forward speed, m/s (ground truth)."""
    left, right = robot.sim.wheel_speeds_mps()
    return float(left + right) / 2


async def drive_for(client: RobotClient, seconds: float, linear_mps: float = 0.3) -> None:
    """Drive as a teleop does: the command again at 20 Hz, inside the watchdog time."""
    loop = asyncio.get_running_loop()
    until = loop.time() + seconds
    while loop.time() < until:
        client.drive(linear_mps, 0.0)
        await asyncio.sleep(0.05)


async def until(condition: Any, timeout_s: float = 3.0) -> None:
    """Wait for ``condition()`` (the simulator's ground truth has no event to wait on)."""
    async with asyncio.timeout(timeout_s):
        while not condition():  # noqa: ASYNC110  # polled: ground truth, no event
            await asyncio.sleep(0.02)


class NeckSpy:
    """Every packet the simulated neck servo receives that would move it or change torque."""

    def __init__(self, robot: Robot, monkeypatch: pytest.MonkeyPatch) -> None:
        self.commands: list[Packet] = []
        neck = robot.sim.neck
        original = neck.handle

        def spy(packet: Packet, now_s: float) -> Packet | None:
            if packet.cmd in (Command.S_JOG, Command.I_JOG, Command.RAM_WRITE):
                self.commands.append(packet)
            reply: Packet | None = original(packet, now_s)
            return reply

        monkeypatch.setattr(neck, "handle", spy)


async def raw_call(ws: ClientConnection, id: int, method: str, **args: Any) -> dict[str, Any]:
    """Send a call on a bare WebSocket; return its answer (other messages skipped)."""
    await ws.send(json.dumps({"op": "call", "id": id, "method": method, "args": args}))
    while True:
        message: dict[str, Any] = json.loads(await ws.recv())
        if message.get("id") == id:
            return message


@pytest.fixture
async def driver(server: RobotServer) -> AsyncIterator[RobotClient]:
    async with RobotClient.connect(server.url) as client:
        await client.acquire()
        yield client


async def test_one_driver_moves_the_robot_while_readers_watch_it_move(
    robot: Robot, server: RobotServer, driver: RobotClient
) -> None:
    async with (
        RobotClient.connect(server.url) as reader1,
        RobotClient.connect(server.url) as reader2,
        reader1.subscribe("wheel_odom") as odom,
    ):
        assert driver.has_lease
        assert driver.lease_holder == driver.peer
        assert reader1.lease_holder == driver.peer
        assert not reader1.has_lease
        await drive_for(driver, 1.0)
        assert speed(robot) == pytest.approx(0.3, abs=0.03)
        assert robot.sim.pose.x > 0.1
        # The readers see it move in the Robot's own samples.
        seen = [await anext(odom) for _ in range(odom.pending)]
        assert max(sample.linear_mps for sample in seen) > 0.2
        latest = reader2.latest("wheel_odom")
        assert latest is not None
        assert latest.x_m > 0.1
        # A reader's command is refused here, before anything is sent.
        with pytest.raises(LeaseError, match=f"drive needs the control lease: {driver.peer}"):
            reader2.drive(-0.3, 0.0)
        await driver.confirm()


async def test_a_command_without_the_lease_is_refused_to_that_client_and_moves_nothing(
    robot: Robot, server: RobotServer, monkeypatch: pytest.MonkeyPatch
) -> None:
    neck = NeckSpy(robot, monkeypatch)
    before = bytes(robot.sim.core.light_ring)
    async with (
        connect(server.url) as intruder,
        RobotClient.connect(server.url) as bystander,
        bystander.subscribe("robot_state") as state,
    ):
        await intruder.recv()  # hello
        commands: list[tuple[str, dict[str, Any]]] = [
            ("drive", {"linear_mps": 0.5}),
            ("drive_pwm", {"left": 400, "right": 400}),
            ("drive_wheels", {"left_mps": 0.3, "right_mps": 0.3}),
            ("move", {"target": "neck", "raw": 300}),
            ("torque", {"target": "neck", "mode": "on"}),
            ("light_ring", {"hue": 1, "saturation": 2, "value": 3}),
            ("set_pid", {"kp": 1.0, "ki": 0.0, "kd": 0.0}),
            ("reset_odometry", {"x_m": 5.0}),
            ("set_odometry", {"x_m": 5.0, "y_m": 1.0, "yaw_rad": 0.5}),
            ("enable_stream", {"topic": "tbcore_status", "enabled": False}),
            ("release", {}),
        ]
        for id, (method, args) in enumerate(commands, start=1):
            answer = await raw_call(intruder, id, method, **args)
            assert answer["op"] == "error", method
            assert answer["code"] == "no_lease", method
            assert f"{method} needs the control lease" in answer["message"]
        await asyncio.sleep(0.3)
        assert speed(robot) == 0.0
        assert robot.sim.pose.x == 0.0
        assert neck.commands == []
        assert bytes(robot.sim.core.light_ring) == before
        assert robot.get_pid() != PidGains(kp=1.0)
        assert robot.stats().streams["tbcore_status"].achieved_hz > 5
        # The bystander got no error of the intruder's, and its stream went on.
        await anext(state)
        assert bystander.latest("robot_state") is not None


async def test_acquire_is_refused_while_another_holds_the_lease_and_steal_takes_it(
    robot: Robot, server: RobotServer, driver: RobotClient, caplog: pytest.LogCaptureFixture
) -> None:
    async with RobotClient.connect(server.url) as operator:
        with pytest.raises(LeaseError, match=f"held by {driver.peer}.*steal") as refused:
            await operator.acquire()
        assert refused.value.holder == driver.peer
        await drive_for(driver, 0.8)
        assert speed(robot) > 0.2
        with caplog.at_level(logging.WARNING, logger="ohmni_tb"):
            assert await operator.acquire(steal=True) == driver.peer
            # The loser is told, and the robot stops although nobody sent a stop.
            await until(lambda: not driver.has_lease)
        assert driver.lease_holder == operator.peer
        assert f"lost the control lease at {server.url}: stolen by {operator.peer}" in caplog.text
        await until(lambda: speed(robot) == 0.0, 2.0)
        with pytest.raises(LeaseError, match=f"{operator.peer} holds it"):
            driver.drive(0.3, 0.0)
        assert server.lease_holder == operator.peer
        await drive_for(operator, 0.5, linear_mps=-0.2)
        assert speed(robot) < -0.1


async def test_the_driver_leaving_releases_the_lease_and_stops_the_robot() -> None:
    # The watchdog off: only the lease's release can stop the wheels in this test.
    async with (
        Robot.open("sim://", watchdog_s=0) as robot,
        RobotServer(robot, port=0) as server,
        RobotClient.connect(server.url) as reader,
    ):
        async with RobotClient.connect(server.url) as driver:
            await driver.acquire()
            driver.drive(0.3, 0.0)
            await driver.confirm()
            await until(lambda: speed(robot) > 0.25)
        await until(lambda: reader.lease_holder is None)
        assert server.lease_holder is None
        await until(lambda: speed(robot) == 0.0, 2.0)
        # Anyone may take it now.
        await reader.acquire()
        assert reader.has_lease


async def test_release_hands_the_lease_back_and_stops_the_robot() -> None:
    async with (
        Robot.open("sim://", watchdog_s=0) as robot,
        RobotServer(robot, port=0) as server,
        RobotClient.connect(server.url) as driver,
        RobotClient.connect(server.url) as next_one,
    ):
        async with driver.lease():
            driver.drive(0.3, 0.0)
            await until(lambda: speed(robot) > 0.25)
        assert not driver.has_lease
        await until(lambda: speed(robot) == 0.0, 2.0)
        await until(lambda: next_one.lease_holder is None)
        await next_one.acquire()


async def test_the_watchdog_still_stops_a_driver_that_goes_quiet(
    robot: Robot, server: RobotServer, driver: RobotClient
) -> None:
    await drive_for(driver, 0.6)
    assert speed(robot) > 0.2
    assert driver.has_lease
    # Holding the lease is not driving: no command for watchdog_s, and the wheels stop.
    await until(lambda: speed(robot) == 0.0, 2.0)
    state = driver.latest("robot_state")
    assert state is not None
    assert state.watchdog_tripped
    assert driver.has_lease


async def test_anyone_may_stop_and_estop_and_the_driver_then_hears_why(
    robot: Robot, server: RobotServer, driver: RobotClient
) -> None:
    async with RobotClient.connect(server.url) as reader:
        await drive_for(driver, 0.6)
        reader.stop()
        await reader.confirm()
        await reader.estop()
        await until(lambda: speed(robot) == 0.0, 2.0)
        # The driver's next command is refused by the daemon's Robot: raised on confirm().
        driver.drive(0.3, 0.0)
        with pytest.raises(StateError, match="emergency stop is latched"):
            await driver.confirm()
        assert speed(robot) == 0.0
        # Clearing it needs the lease.
        with pytest.raises(LeaseError):
            reader.clear_estop()
        driver.clear_estop()
        await drive_for(driver, 0.6)
        assert speed(robot) > 0.2
        await driver.confirm()


async def test_bad_values_are_refused_with_the_allowed_range_and_nothing_is_sent(
    robot: Robot, server: RobotServer, driver: RobotClient, monkeypatch: pytest.MonkeyPatch
) -> None:
    neck = NeckSpy(robot, monkeypatch)
    with pytest.raises(
        OutOfRangeError, match=r"left PWM=5000 is out of range: allowed -1000..1000"
    ):
        driver.drive_pwm(5000, 0)
    with pytest.raises(InvalidArgumentError, match="linear_mps"):
        driver.drive(float("nan"), 0.0)
    config = robot.config
    with pytest.raises(
        InvalidArgumentError,
        match=rf"position=2000 is out of range: allowed {config.neck_min_raw}\.\."
        rf"{config.neck_max_raw}",
    ):
        await driver.neck.move(raw=2000)
    with pytest.raises(InvalidArgumentError, match=r"0\.\.255"):
        await driver.light_ring(300, 0, 0)
    with pytest.raises(StateError, match="no HerkuleX servo 42"):
        await driver.servo(42).move(raw=512)
    await asyncio.sleep(0.2)
    assert neck.commands == []
    assert speed(robot) == 0.0
    await driver.confirm()  # none of those was a deferred command


async def test_the_driver_drives_the_neck_servos_pid_odometry_streams_and_light(
    robot: Robot, server: RobotServer, driver: RobotClient
) -> None:
    target = (robot.config.neck_min_raw + robot.config.neck_max_raw) // 2 + 30
    await driver.neck.move(raw=target, playtime_s=0.3)

    def at_target() -> bool:
        sample = robot.latest("servo_neck")
        return sample is not None and abs(sample.position_raw - target) <= 3

    await until(at_target)
    await driver.servo(11).torque("brake")
    await driver.light_ring(10, 200, 255)
    assert bytes(robot.sim.core.light_ring) == bytes((10, 200, 255))
    gains = PidGains(kp=500.0, ki=200.0, kd=0.0, kff=900.0, ff_offset=50.0)
    driver.set_pid(gains)
    driver.reset_odometry(1.0, 2.0, 0.5)
    driver.enable_stream("tbcore_status", False)
    await driver.confirm()
    assert robot.get_pid() == gains
    assert driver.get_pid() == gains
    odom = robot.latest("wheel_odom")
    await until(lambda: (s := robot.latest("wheel_odom")) is not None and s is not odom)
    sample = robot.latest("wheel_odom")
    assert sample is not None
    assert (sample.x_m, sample.y_m, sample.yaw_rad) == pytest.approx((1.0, 2.0, 0.5), abs=1e-3)
    assert robot.stats().streams["tbcore_status"].enabled is False


async def test_the_clients_drive_returns_what_the_robot_will_drive(
    robot: Robot, server: RobotServer, driver: RobotClient
) -> None:
    limited = driver.drive(3.0, 1.0)  # beyond the speed limits: scaled, curvature kept
    assert limited.limited
    assert limited == robot.drive(3.0, 1.0)
    assert driver.drive_wheels(2.0, 1.0) == robot.drive_wheels(2.0, 1.0)
    driver.stop()
    await driver.confirm()


async def test_a_read_only_daemon_refuses_commands_but_not_stops(robot: Robot) -> None:
    async with (
        RobotServer(robot, port=0, read_only=True) as server,
        RobotClient.connect(server.url) as client,
    ):
        assert client.hello.read_only
        with pytest.raises(StateError, match="takes no commands"):
            await client.acquire()
        client.stop()
        await client.estop()
        await client.confirm()
        assert robot.state.estopped
