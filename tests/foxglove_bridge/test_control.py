"""Parameters and services in the Foxglove app: read always, changed only with control,
and a refused change is a message to the client with nothing sent — judged on the Robot
(its PIDs, rates, odometry) and on the simulator's neck, with the Robot on ``sim://`` in
real time (the SDK's server runs in its own threads)."""

from __future__ import annotations

import asyncio
import secrets
from collections.abc import AsyncIterator
from typing import Any

import pytest

from ohmni_tb import Robot
from ohmni_tb.control.pid import PidGains
from ohmni_tb.foxglove import FoxgloveBridge
from ohmni_tb.foxglove.access import UNLOCK_SERVICE
from ohmni_tb.foxglove.control import (
    LIMIT_PARAMETERS,
    NECK_MOVE_SERVICE,
    PID_PARAMETERS,
    RESET_ODOM_SERVICE,
    SET_ODOMETRY_SERVICE,
    RobotControl,
)

from ._wire import FoxgloveClient

P = "/tb_control/"
#: The token a client unlocks control with.
TOKEN = secrets.token_urlsafe(32)


@pytest.fixture
async def robot() -> AsyncIterator[Robot]:
    async with Robot.open("sim://", on_exit_neck="keep") as opened:
        yield opened


async def connected(robot: Robot, *, writable: bool) -> tuple[FoxgloveBridge, FoxgloveClient]:
    """A bridge and a client of it; with control, the client unlocked it."""
    bridge = FoxgloveBridge(
        robot,
        port=0,
        control=RobotControl(robot, writable=writable),
        token=TOKEN if writable else None,
    )
    await bridge.start()
    client = await FoxgloveClient.connect(bridge.url)
    if writable:
        assert await client.unlock(TOKEN) == {"unlocked": True}
    return bridge, client


async def next_sample(robot: Robot, stream: str) -> Any:
    """The stream's next sample (the Robot publishes its first ones a moment after opening,
    later on a loaded machine)."""
    async with robot.subscribe(stream) as samples, asyncio.timeout(10.0):
        return await anext(samples)


async def test_every_parameter_reads_what_the_robot_runs_with(robot: Robot) -> None:
    bridge, client = await connected(robot, writable=False)
    try:
        values = await client.get_parameters()
        assert "parameters" in client.server_info["capabilities"]
        assert "services" not in client.server_info["capabilities"]  # read only: none
        assert client.services == {}
        gains = robot.get_pid()
        for name, field in PID_PARAMETERS.items():
            assert values[P + name] == pytest.approx(getattr(gains, field))
        for stream in ("wheel_encoder", "servo_neck", "servo_ext1", "servo_ext2"):
            assert values[f"{P}rate/{stream}"] == robot.stats().streams[stream].requested_hz
        assert values[P + "rate/tbcore_status"] == 10.0
        assert f"{P}rate/new_neck" not in values  # a HerkuleX neck here: not polled
        for name in LIMIT_PARAMETERS:
            assert values[P + name] == pytest.approx(getattr(robot.config, name))
        # Asked by name: those alone.
        assert await client.get_parameters(P + "pid_kp", request_id="one") == {
            P + "pid_kp": pytest.approx(gains.kp)
        }
    finally:
        await client.close()
        await bridge.aclose()


async def test_a_read_only_server_refuses_a_change_and_says_why(robot: Robot) -> None:
    before = robot.get_pid()
    bridge, client = await connected(robot, writable=False)
    try:
        answered = await client.set_parameters({P + "pid_kp": 1.0})
        assert answered[P + "pid_kp"] == pytest.approx(before.kp)  # unchanged
        assert robot.get_pid() == before
        assert any("read only" in s["message"] for s in client.statuses)
    finally:
        await client.close()
        await bridge.aclose()


async def test_with_control_the_pid_gains_and_a_rate_change_on_the_robot(robot: Robot) -> None:
    bridge, client = await connected(robot, writable=True)
    try:
        answered = await client.set_parameters(
            {P + "pid_kp": 450.0, P + "pid_ki": 120.0, P + "rate/servo_neck": 15.0}
        )
        assert robot.get_pid() == PidGains(
            kp=450.0,
            ki=120.0,
            kd=robot.config.pid_kd,
            kff=robot.config.pid_kff,
            ff_offset=robot.config.pid_ff_offset,
        )
        assert robot.stats().streams["servo_neck"].requested_hz == 15.0
        assert answered[P + "pid_kp"] == 450.0
        assert answered[P + "rate/servo_neck"] == 15.0
        # The neck's samples over 2 s at the new rate: about 30, not 60.
        await asyncio.sleep(0.2)
        async with robot.subscribe("servo_neck", maxlen=1000) as samples:
            await asyncio.sleep(2.0)
            assert 20 <= samples.pending <= 40
    finally:
        await client.close()
        await bridge.aclose()


@pytest.mark.parametrize(
    ("name", "value", "words"),
    [
        (P + "rate/servo_neck", 500.0, "0.1"),  # the range is named
        (P + "max_linear_mps", 3.0, "read only"),
        (P + "no_such_thing", 1.0, "no parameter"),
        (P + "pid_kp", -1.0, "kp"),
    ],
)
async def test_a_refused_value_is_told_and_changes_nothing(
    robot: Robot, name: str, value: float, words: str
) -> None:
    gains, rates = robot.get_pid(), robot.schedule()
    bridge, client = await connected(robot, writable=True)
    try:
        await client.set_parameters({name: value})
        messages = [s["message"] for s in client.statuses]
        assert any(words in m for m in messages), messages
        assert robot.get_pid() == gains
        assert robot.schedule() == rates
    finally:
        await client.close()
        await bridge.aclose()


async def test_the_services_reset_odometry_and_move_the_neck(robot: Robot) -> None:
    assert robot.sim is not None
    bridge, client = await connected(robot, writable=True)
    try:
        assert "services" in client.server_info["capabilities"]
        assert set(client.services) == {
            UNLOCK_SERVICE,
            RESET_ODOM_SERVICE,
            SET_ODOMETRY_SERVICE,
            NECK_MOVE_SERVICE,
        }
        request_schema = client.services[RESET_ODOM_SERVICE]["request"]
        assert request_schema["encoding"] == "json"
        assert request_schema["schemaEncoding"] == "jsonschema"

        pose = {"x_m": 1.5, "y_m": -0.25, "yaw_rad": 0.5}
        assert await client.call_service(RESET_ODOM_SERVICE, pose) == pose
        # The next sample, 20 ms on (later on a loaded machine), is at the new pose.
        odom = await next_sample(robot, "wheel_odom")
        assert (odom.x_m, odom.y_m, odom.yaw_rad) == pytest.approx((1.5, -0.25, 0.5), abs=1e-3)

        answer = await client.call_service(
            NECK_MOVE_SERVICE, {"raw": 420, "playtime_s": 0.2}, call_id=2
        )
        assert answer == {"moved": True}
        await asyncio.sleep(0.6)  # the move's playtime, and the servo settling
        neck = await next_sample(robot, "servo_neck")
        assert neck.position_raw == pytest.approx(420, abs=3)
    finally:
        await client.close()
        await bridge.aclose()


async def test_set_odometry_sets_the_pose_given_whole(robot: Robot) -> None:
    bridge, client = await connected(robot, writable=True)
    try:
        schema = client.services[SET_ODOMETRY_SERVICE]["request"]
        assert schema["encoding"] == "json"
        pose = {"x_m": -2.0, "y_m": 0.75, "yaw_rad": -1.0}
        assert await client.call_service(SET_ODOMETRY_SERVICE, pose) == pose
        odom = await next_sample(robot, "wheel_odom")
        assert (odom.x_m, odom.y_m, odom.yaw_rad) == pytest.approx((-2.0, 0.75, -1.0), abs=1e-3)
        # Not the whole pose: refused, naming what is missing, and the pose stays.
        refused = await client.call_service(SET_ODOMETRY_SERVICE, {"x_m": 5.0}, call_id=2)
        assert "missing y_m, yaw_rad" in refused["failure"], refused
        odom = await next_sample(robot, "wheel_odom")
        assert odom.x_m == pytest.approx(-2.0, abs=1e-3)
    finally:
        await client.close()
        await bridge.aclose()


@pytest.mark.parametrize(
    ("request_json", "words"),
    [
        ({"raw": 9000}, "650"),  # beyond the neck's range: the range is named
        ({"raw": 400, "rad": 0.1}, "one of them"),
        ({"angle": 3}, "takes a JSON object"),
    ],
)
async def test_a_refused_service_call_fails_with_the_reason_and_sends_nothing(
    robot: Robot, request_json: dict[str, float], words: str
) -> None:
    bridge, client = await connected(robot, writable=True)
    try:
        before = await next_sample(robot, "servo_neck")
        answer = await client.call_service(NECK_MOVE_SERVICE, request_json)
        assert words in answer["failure"]
        await asyncio.sleep(0.5)  # a move sent would show by now
        after = await next_sample(robot, "servo_neck")
        assert after.position_raw == before.position_raw
        assert after.torque == before.torque
    finally:
        await client.close()
        await bridge.aclose()


async def test_tb_cmd_vel_is_the_pure_command_and_cmd_vel_accel_the_ramped_one(
    robot: Robot,
) -> None:
    got: list[tuple[float, float, bool]] = []
    arrived = asyncio.Event()

    def teleop(linear: float, angular: float, ramped: bool) -> None:
        got.append((linear, angular, ramped))
        if len(got) == 3:
            arrived.set()

    bridge = FoxgloveBridge(robot, port=0, teleop=teleop, token=TOKEN)
    await bridge.start()
    client = await FoxgloveClient.connect(bridge.url)
    try:
        assert await client.unlock(TOKEN) == {"unlocked": True}
        for channel, topic in enumerate(("/tb_cmd_vel", "/cmd_vel_accel", "/cmd_vel"), 1):
            await client.advertise_twist(channel, topic)
        for channel, linear in ((1, 0.1), (2, 0.2), (3, 0.3)):
            await client.send_twist(linear, channel_id=channel)
        async with asyncio.timeout(5.0):
            await arrived.wait()
    finally:
        await client.close()
        await bridge.aclose()
    assert sorted(got) == [(0.1, 0.0, False), (0.2, 0.0, True), (0.3, 0.0, True)]
