"""Every topic, service and parameter of tb_control 0.0.13 has a working equivalent.

:data:`ROWS` is tb_control's interface, name by name as the vendor's guide spells it, each
with the library call and the ``ohmni`` command that do the same. The test checks that
docs/robot.md's mapping table has exactly one row for each name, naming that call and that
command, and runs both on ``sim://`` on virtual time: the call through
``Robot.open("sim://")`` and the command through typer's CliRunner, each checked by what a
user would see (a sample arrives, the simulator's truth moved, the servo's register holds
the value, the reply has the fields). A parameter is exercised by opening a robot with its
setting (a keyword for the call, ``OHMNI_*`` in the environment for the command).
"""

from __future__ import annotations

import asyncio
import functools
import json
import math
import re
import threading
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from cli._helpers import invoke, words
from ohmni_tb import Robot
from ohmni_tb.control import PidGains, accel_from_delta_velo_raw
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import ConfigError, StateError
from ohmni_tb.robot import Link, LocalRobot
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.robot import SimRobot

PAGE = Path(__file__).resolve().parents[1] / "docs" / "robot.md"
WORM = "sim://?neck=worm"

Check = Callable[[Robot], Awaitable[None]]


@dataclass(frozen=True)
class Row:
    """One tb_control name and what does it here."""

    name: str  #: tb_control's, exact
    call: str  #: the library call, as docs/robot.md writes it
    cli: str  #: the command, as docs/robot.md writes it (CAPITALS and … are placeholders)
    check: Check  #: runs the call on a robot opened with ``settings`` and checks it
    argv: tuple[str, ...]  #: the command as run (``--port`` added unless given)
    expect: Callable[[str], object]  #: checks the command's output
    settings: dict[str, Any] = field(default_factory=dict)
    url: str = "sim://"
    env: dict[str, str] = field(default_factory=dict)
    code: int = 0  #: the command's exit code
    daemon: bool = False  #: the command acts on ohmni serve's robot only


def truth(robot: Robot) -> SimRobot:
    sim = robot.sim
    assert isinstance(sim, SimRobot)
    return sim


async def first(robot: Robot, stream: str) -> Any:
    """The next sample of ``stream`` (within a second of virtual time)."""
    async with robot.subscribe(stream) as samples:
        return await asyncio.wait_for(anext(samples), 1.0)


async def hold(robot: Robot, seconds: float, send: Callable[[], object]) -> None:
    """``send`` again every 0.05 s for ``seconds``, as a teleop does."""
    loop = asyncio.get_running_loop()
    until = loop.time() + seconds
    while loop.time() < until:
        send()
        await asyncio.sleep(0.05)


def as_json(out: str) -> Any:
    """The JSON a command printed (after any note lines on stderr)."""
    return json.loads(out[out.index("{") :])


async def neck_ram(robot: Robot) -> dict[str, int]:
    return (await robot.servo(3).info())["ram"]


# -- the checks --------------------------------------------------------------------------------


def stream_check(stream: str, test: Callable[[Any], object]) -> Check:
    async def check(robot: Robot) -> None:
        assert test(await first(robot, stream)) is not False

    return check


async def pure_velocity(robot: Robot) -> None:
    await hold(robot, 0.2, lambda: robot.drive(0.3, 0.0, ramped=False))
    assert min(truth(robot).wheel_speeds_mps()) > 0.2


async def ramped_velocity(robot: Robot) -> None:
    await hold(robot, 0.2, lambda: robot.drive(0.3, 0.0))
    assert 0.0 < max(truth(robot).wheel_speeds_mps()) < 0.15


async def pwm(robot: Robot) -> None:
    sent: list[tuple[int, int]] = []
    await hold(robot, 0.4, lambda: sent.append(robot.drive_pwm(300.4, 300, right_enabled=False)))
    assert sent[-1] == (300, 0)
    left, right = truth(robot).wheel_speeds_mps()
    assert left > 0.1
    assert right == 0.0


async def wheel_speeds(robot: Robot) -> None:
    await hold(robot, 1.0, lambda: robot.drive_wheels(0.2, 0.1))
    assert truth(robot).wheel_speeds_mps() == pytest.approx((0.2, 0.1), abs=0.02)


def servo_move(sid: int, raw: int, stream: str) -> Check:
    async def check(robot: Robot) -> None:
        servo = robot.servo(sid)
        await servo.torque("on")
        await servo.move(raw, playtime_s=0.3)
        await asyncio.sleep(0.5)
        sample = robot.latest(stream)
        assert sample is not None
        assert abs(sample.position_raw - raw) <= 5

    return check


async def neck_move(robot: Robot) -> None:
    await robot.neck.move(400, playtime_s=0.3)
    await asyncio.sleep(0.5)
    sample = robot.latest("servo_neck")
    assert sample is not None
    assert abs(sample.position_raw - 400) <= 5


async def worm_move(robot: Robot) -> None:
    await robot.neck.move(-50_000)
    await asyncio.sleep(1.5)
    sample = robot.latest("new_neck")
    assert sample is not None
    assert abs(sample.position_raw - -50_000) <= 1000


def port_of(robot: Robot) -> str | None:
    """``robot.port`` now (a call: it changes under the awaits)."""
    return robot.port


async def connect(robot: Robot) -> None:
    await robot.disconnect()
    assert port_of(robot) is None
    await robot.connect("sim://")
    assert port_of(robot) == "sim://"
    assert robot.state.link is Link.CONNECTED


async def controllers(robot: Robot) -> None:
    robot.enable_controllers(False, wheel="left")
    assert robot.controllers_enabled() == {"left": False, "right": True}
    with pytest.raises(StateError):
        robot.drive(0.2)
    robot.enable_controllers(True)
    robot.drive(0.2)


async def pid_samples(robot: Robot) -> None:
    """The PIDs' state while they drive: a sample a control tick."""
    driving = asyncio.create_task(hold(robot, 0.5, lambda: robot.drive_wheels(0.2, 0.2)))
    try:
        sample = await first(robot, "pid_debug")
    finally:
        await driving
    assert sample.left.setpoint > 0
    assert sample.right.dt_s > 0


async def pid_stream(robot: Robot) -> None:
    robot.enable_stream("pid_debug")
    await pid_samples(robot)


async def sensor_stream(robot: Robot) -> None:
    robot.enable_stream("tbcore_status", False)
    await robot.confirm()
    assert "tbcore_status" not in [row[0] for row in robot.schedule()]
    robot.enable_stream("tbcore_status", True)
    assert (await first(robot, "tbcore_status")).pack_v > 0


async def ports(robot: Robot) -> None:
    listed = await robot.list_ports()
    assert listed == LocalRobot.ports()
    assert all("device" in port for port in listed), listed


async def info(robot: Robot) -> None:
    found = await robot.info()
    assert {0, 1, 3}.issubset(found["present"])
    assert robot.port == "sim://"


async def get_pid(robot: Robot) -> None:
    assert robot.get_pid(wheel="left").kp == robot.config.pid_kp


async def set_pid(robot: Robot) -> None:
    gains = robot.get_pid(wheel="left")
    robot.set_pid(PidGains(500.0, gains.ki, gains.kd, gains.kff, gains.ff_offset), wheel="left")
    assert robot.get_pid(wheel="left").kp == 500.0
    assert robot.get_pid(wheel="right").kp == robot.config.pid_kp


async def servo_info(robot: Robot) -> None:
    registers = await robot.servo(3).info()
    assert registers["ram"]["id"] == registers["eep"]["id"] == 3


async def tbcore(robot: Robot) -> None:
    await asyncio.sleep(0.2)
    sample = robot.latest("tbcore_status")
    assert sample is not None
    assert len(sample.cell_v) == 5


async def servo_id(robot: Robot) -> None:
    await robot.servo(11).set_id(13)
    assert robot.servo(13).sid == 13
    assert robot.config.ext_servo_ids == (13, 12)
    assert [servo.sid for servo in truth(robot).ext_servos] == [13, 12]
    assert (await first(robot, "servo_ext1")).sid == 13


async def reset_odom(robot: Robot) -> None:
    robot.reset_odometry(1.0, -0.5, 1.5)
    await asyncio.sleep(0.1)
    odom = robot.latest("wheel_odom")
    assert odom is not None
    assert (odom.x_m, odom.y_m, odom.yaw_rad) == pytest.approx((1.0, -0.5, 1.5), abs=1e-6)


async def write_eep(robot: Robot) -> None:
    await robot.servo(3).write(30, 200, memory="eep")
    registers = await robot.servo(3).info()
    assert registers["eep"]["position_kp"] == 200
    assert registers["ram"]["position_kp"] != 200  # EEP alone: acts after a reboot


async def zero_offset(robot: Robot) -> None:
    await robot.servo(3).set_zero_offset(-20)
    await asyncio.sleep(0.1)
    sample = robot.latest("servo_neck")
    assert sample is not None
    assert sample.position_raw == 512
    assert sample.angle_rad == pytest.approx(math.radians(20 * 0.325), abs=1e-3)


# -- parameters --------------------------------------------------------------------------------


async def opened_on(robot: Robot) -> None:
    assert robot.port == "sim://"
    assert robot.state.link is Link.CONNECTED


async def baudrate(robot: Robot) -> None:
    assert robot.config.baudrate == 57600
    with pytest.raises(ConfigError, match="baudrate=100 is out of range"):
        async with Robot.open("sim://", baudrate=100):
            pass


def odom_field(name: str, value: object) -> Check:
    return stream_check("wheel_odom", lambda sample: getattr(sample, name) == value)


async def no_tf(robot: Robot) -> None:
    # The transform goes only to Foxglove: the setting is what the bridge and recorder read.
    assert robot.config.enable_broadcast_transform is False


async def half_radius(robot: Robot) -> None:
    # The configured radius is half the simulator's: the odometry counts half the way.
    await hold(robot, 1.0, lambda: robot.drive(0.2, ramped=False))
    robot.stop()
    await asyncio.sleep(0.5)
    odom = robot.latest("wheel_odom")
    assert odom is not None
    assert odom.x_m == pytest.approx(truth(robot).pose.x / 2, rel=0.02)


async def double_separation(robot: Robot) -> None:
    await hold(robot, 1.0, lambda: robot.drive(0.0, 0.5, ramped=False))
    robot.stop()
    await asyncio.sleep(0.5)
    odom = robot.latest("wheel_odom")
    assert odom is not None
    assert odom.heading_rad == pytest.approx(truth(robot).pose.yaw / 2, rel=0.02)


async def linear_limit(robot: Robot) -> None:
    limited = robot.drive(0.5)
    assert limited.limited
    assert limited.twist.linear_mps == pytest.approx(0.2)


async def angular_limit(robot: Robot) -> None:
    limited = robot.drive(0.0, 1.0)
    assert limited.limited
    assert limited.twist.angular_radps == pytest.approx(0.5)


async def fast_ramp(robot: Robot) -> None:
    # Level 10 (2.5 m/s²) is at 0.3 m/s within 0.2 s; the default (0.5 m/s²) is not.
    await hold(robot, 0.3, lambda: robot.drive(0.3))
    assert min(truth(robot).wheel_speeds_mps()) > 0.25


async def no_watchdog(robot: Robot) -> None:
    robot.drive(0.2, ramped=False)
    await asyncio.sleep(1.5)
    assert not robot.state.watchdog_tripped
    assert min(truth(robot).wheel_speeds_mps()) > 0.15
    robot.stop()


async def short_watchdog(robot: Robot) -> None:
    robot.drive(0.2, ramped=False)
    await asyncio.sleep(0.1)
    assert min(truth(robot).wheel_speeds_mps()) > 0.1
    await asyncio.sleep(0.6)
    assert robot.state.watchdog_tripped
    assert truth(robot).wheel_speeds_mps() == pytest.approx((0.0, 0.0), abs=1e-3)


async def neck_id(robot: Robot) -> None:
    assert robot.neck.sid == 12
    await neck_move_to(robot, 12)


async def neck_move_to(robot: Robot, sid: int) -> None:
    await robot.neck.move(400, playtime_s=0.2)
    await asyncio.sleep(0.4)
    sample = robot.latest("servo_neck")
    assert sample is not None
    assert sample.sid == sid
    assert abs(sample.position_raw - 400) <= 5


def neck_register(register: str, value: int, memory: str = "ram") -> Check:
    async def check(robot: Robot) -> None:
        assert (await robot.servo(3).info())[memory][register] == value

    return check


def neck_setting(out: str, register: str, value: int) -> None:
    report = as_json(out)["neck_settings"]
    assert report["ok"] is True
    assert report["read_back"][register] == value


# -- the command's outputs ---------------------------------------------------------------------


def sample_of(*keys: str, test: Callable[[Any], bool]) -> Callable[[str], None]:
    def expect(out: str) -> None:
        value: Any = as_json(out)
        for key in keys:
            value = value[key]
        assert test(value), value

    return expect


def said(text: str) -> Callable[[str], None]:
    def expect(out: str) -> None:
        assert text in words(out), out

    return expect


def recorded(test: Callable[[dict[str, Any], Path], object]) -> Callable[[str], None]:
    def expect(out: str) -> None:
        summary = as_json(out)
        assert test(summary, Path(summary["path"])) is not False

    return expect


def odom_frames(path: Path) -> tuple[str, str]:
    from mcap.reader import make_reader  # the foxglove extra

    with path.open("rb") as file:
        for _, _, message in make_reader(file).iter_messages(
            topics=["/tb_control/wheel_odom/json"]
        ):
            sample = json.loads(message.data)
            return sample["frame_id"], sample["child_frame_id"]
    raise AssertionError("no wheel_odom in the recording")


def record(*more: str) -> tuple[str, ...]:
    return ("record", "{tmp}/run.mcap", "--duration", "0.2", "--overwrite", "--json", *more)


DRIVE = ("drive", "--json")


def _neck_rows() -> list[Row]:
    """tb_control's HerkuleX neck parameters: written to the servo at open, read back."""
    table = [
        ("~servo_neck_min_pos", "neck_min_raw", 300, "min_position"),
        ("~servo_neck_max_pos", "neck_max_raw", 600, "max_position"),
        ("~servo_neck_kp", "neck_kp", 500, "position_kp"),
        ("~servo_neck_ki", "neck_ki", 10, "position_ki"),
        ("~servo_neck_kd", "neck_kd", 7000, "position_kd"),
        ("~servo_neck_v_min", "neck_min_voltage_raw", 80, "min_voltage"),
        ("~servo_neck_v_max", "neck_max_voltage_raw", 140, "max_voltage"),
        ("~servo_neck_overload_pwm", "neck_overload_pwm", 900, "overload_pwm_threshold"),
        ("~servo_neck_max_pwm", "neck_max_pwm", 1000, "max_pwm"),
    ]
    return [
        Row(
            name,
            f"{setting}=…",
            f"OHMNI_{setting.upper()}=… ohmni info",
            neck_register(register, value),
            ("info", "--json"),
            functools.partial(neck_setting, register=register, value=value),
            settings={setting: value},
            env={f"OHMNI_{setting.upper()}": str(value)},
        )
        for name, setting, value, register in table
    ]


ROWS: list[Row] = [
    # -- published topics
    Row(
        "/tb_control/servo/neck",
        'robot.subscribe("servo_neck")',
        "ohmni neck",
        stream_check("servo_neck", lambda s: s.sid == 3 and s.position_raw == 512),
        ("neck", "--json"),
        sample_of("position_raw", test=lambda v: v == 512),
    ),
    Row(
        "/tb_control/tbcore_status",
        'robot.subscribe("tbcore_status")',
        "ohmni status",
        stream_check("tbcore_status", lambda s: len(s.cell_v) == 5 and s.pack_v > 0),
        ("status", "--json"),
        sample_of("battery", "pack_v", test=lambda v: v > 0),
    ),
    Row(
        "/tb_control/wheel_encoder",
        'robot.subscribe("wheel_encoder")',
        "ohmni status",
        stream_check("wheel_encoder", lambda s: 0 <= s.left_pos_raw < 4096),
        ("status", "--json"),
        sample_of("wheels", test=lambda v: {"left_ticks", "right_ticks"} <= set(v)),
    ),
    Row(
        "/tb_control/wheel_odom",
        'robot.subscribe("wheel_odom")',
        "ohmni odom",
        stream_check("wheel_odom", lambda s: len(s.pose_covariance) == 36),
        ("odom", "--count", "1", "--json"),
        sample_of("x_m", test=lambda v: v == 0.0),
    ),
    Row(
        "/tb_control/servo/new_neck",
        'robot.subscribe("new_neck")',
        "ohmni neck",
        stream_check("new_neck", lambda s: isinstance(s.position_raw, int)),
        ("neck", "--json"),
        sample_of("neck", test=lambda v: v == "worm"),
        url=WORM,
    ),
    Row(
        "/tb_control/servo/ext1",
        'robot.subscribe("servo_ext1")',
        "ohmni status",
        stream_check("servo_ext1", lambda s: s.sid == 11),
        ("status", "--json"),
        sample_of("servos", "ext1", "sid", test=lambda v: v == 11),
    ),
    Row(
        "/tb_control/servo/ext2",
        'robot.subscribe("servo_ext2")',
        "ohmni status",
        stream_check("servo_ext2", lambda s: s.sid == 12),
        ("status", "--json"),
        sample_of("servos", "ext2", "sid", test=lambda v: v == 12),
    ),
    Row(
        "/tb_control/robot_state",
        'robot.subscribe("robot_state")',
        "ohmni status",
        stream_check("robot_state", lambda s: s.link is Link.CONNECTED),
        ("status", "--json"),
        sample_of("link", test=lambda v: v == "connected"),
    ),
    Row(
        "/tb_control/motor_pid_debug",
        'robot.subscribe("pid_debug")',
        "OHMNI_PID_DEBUG=true ohmni record FILE.mcap",
        pid_samples,
        record(),
        recorded(lambda s, _: "/tb_control/pid_debug" in s["channels"]),
        settings={"pid_debug": True},
        env={"OHMNI_PID_DEBUG": "true"},
    ),
    # -- subscribed topics
    Row(
        "/tb_cmd_vel",
        "robot.drive(linear, angular, ramped=False)",
        "ohmni drive --linear V --angular W --no-ramp",
        pure_velocity,
        (*DRIVE, "--linear", "0.3", "--angular", "0", "--duration", "0.2", "--no-ramp"),
        sample_of("distance_m", test=lambda v: v > 0.07),
    ),
    Row(
        "/cmd_vel_accel",
        "robot.drive(linear, angular)",
        "ohmni drive --linear V --angular W",
        ramped_velocity,
        (*DRIVE, "--linear", "0.3", "--angular", "0", "--duration", "0.2"),
        sample_of("distance_m", test=lambda v: 0 < v < 0.03),
    ),
    Row(
        "/tb_cmd_motor_pwm",
        "robot.drive_pwm(left, right, left_enabled=…, right_enabled=…)",
        "ohmni drive --pwm L R",
        pwm,
        (*DRIVE, "--pwm", "300", "0", "--duration", "0.4"),
        sample_of("heading_change_deg", test=lambda v: v < -1),  # the left wheel alone
    ),
    Row(
        "/tb_cmd_servo_neck",
        "robot.neck.move(raw, playtime_s=…)",
        "ohmni neck --raw N --playtime S",
        neck_move,
        ("neck", "--raw", "400", "--playtime", "0.3", "--json"),
        sample_of("position_raw", test=lambda v: abs(v - 400) <= 5),
    ),
    Row(
        "/tb_cmd_new_neck",
        "robot.neck.move(raw)",
        "ohmni neck --raw N",
        worm_move,
        ("neck", "--raw", "-50000", "--json"),
        sample_of("position_raw", test=lambda v: abs(v - -50_000) <= 1000),
        url=WORM,
    ),
    Row(
        "/tb_cmd_servo_ext1",
        "robot.servo(11).move(raw, playtime_s=…)",
        "ohmni servo move POS --sid 11 --torque-on",
        servo_move(11, 600, "servo_ext1"),
        ("servo", "move", "600", "--sid", "11", "--torque-on"),
        said("600"),
    ),
    Row(
        "/tb_cmd_servo_ext2",
        "robot.servo(12).move(raw, playtime_s=…)",
        "ohmni servo move POS --sid 12 --torque-on",
        servo_move(12, 450, "servo_ext2"),
        ("servo", "move", "450", "--sid", "12", "--torque-on"),
        said("450"),
    ),
    Row(
        "/tb_cmd_motor_speed_setpoint",
        "robot.drive_wheels(left_mps, right_mps)",
        "ohmni drive --wheels L R",
        wheel_speeds,
        (*DRIVE, "--wheels", "0.2", "0.1", "--duration", "1"),
        sample_of("heading_change_deg", test=lambda v: v < -5),  # the right wheel slower
    ),
    # -- services
    Row(
        "/tb_control/set_servo_pos",
        "robot.servo(sid).move(raw, playtime_s=…)",
        "ohmni servo move POS --sid N --playtime S --torque-on",
        servo_move(3, 400, "servo_neck"),
        ("servo", "move", "400", "--sid", "3", "--playtime", "0.3", "--torque-on"),
        said("400"),
    ),
    Row(
        "/tb_control/connect",
        "robot.connect(port)",
        "ohmni connect PORT",
        connect,
        ("connect", "sim://", "--json"),
        sample_of("is_connected", test=lambda v: v is True),
    ),
    Row(
        "/tb_control/enable_controllers",
        "robot.enable_controllers(enabled, wheel=…)",
        "ohmni pid disable --wheel W",
        controllers,
        ("pid", "disable", "--wheel", "left"),
        said("left"),
    ),
    Row(
        "/tb_control/enable_debug_pid_stream",
        'robot.enable_stream("pid_debug")',
        "ohmni stream enable pid_debug",
        pid_stream,
        ("stream", "enable", "pid_debug", "--json"),
        sample_of("enabled", test=lambda v: v is True),
    ),
    Row(
        "/tb_control/enable_sensor_stream",
        "robot.enable_stream(name, enabled)",
        "ohmni stream disable NAME",
        sensor_stream,
        ("stream", "disable", "tbcore_status", "--json"),
        sample_of("scheduled", test=lambda v: "tbcore_status" not in v and "servo_neck" in v),
    ),
    Row(
        "/tb_control/get_connect_ports",
        "robot.list_ports()",
        "ohmni ports",
        ports,
        ("ports", "--json"),
        lambda out: json.loads(out) == LocalRobot.ports(),
    ),
    Row(
        "/tb_control/get_info",
        "robot.info()",
        "ohmni info",
        info,
        ("info", "--json"),
        sample_of("present", test=lambda v: {0, 1, 3} <= set(v)),
    ),
    Row(
        "/tb_control/get_pid",
        "robot.get_pid(wheel=…)",
        "ohmni pid get",
        get_pid,
        ("pid", "get", "--json"),
        sample_of("wheels", "left", "kp", test=lambda v: v == 600.0),
    ),
    Row(
        "/tb_control/set_pid",
        "robot.set_pid(gains, wheel=…)",
        "ohmni pid set --kp … --wheel W",
        set_pid,
        ("pid", "set", "--kp", "500", "--wheel", "left", "--json"),
        sample_of("wheels", "left", "kp", test=lambda v: v == 500.0),
    ),
    Row(
        "/tb_control/get_servo_info",
        "robot.servo(sid).info()",
        "ohmni servo info --sid N",
        servo_info,
        ("servo", "info", "--sid", "3", "--json"),
        sample_of("ram", "id", test=lambda v: v == 3),
    ),
    Row(
        "/tb_control/get_tbcore_status",
        'robot.latest("tbcore_status")',
        "ohmni status",
        tbcore,
        ("status", "--json"),
        sample_of("battery", "cell_v", test=lambda v: len(v) == 5),
    ),
    Row(
        "/tb_control/reset_servo_id",
        "robot.servo(sid).set_id(new_sid)",
        "ohmni servo set-id NEW --sid N",
        servo_id,
        ("servo", "set-id", "13", "--sid", "11"),
        said("servo 11 is now servo 13"),
    ),
    Row(
        "/tb_control/reset_wheel_odom",
        "robot.reset_odometry(x_m, y_m, yaw_rad)",
        "ohmni odom reset --x M --y M --yaw RAD",
        reset_odom,
        ("odom", "reset", "--x", "1", "--y", "-0.5", "--yaw", "1.5", "--json"),
        sample_of("x_m", test=lambda v: v == 1.0),
    ),
    Row(
        "/tb_control/servo_write_eep",
        'robot.servo(sid).write(address, value, memory="eep")',
        "ohmni servo write ADDR VALUE --eep --sid N",
        write_eep,
        ("servo", "write", "30", "200", "--eep", "--sid", "3"),
        said("200"),
    ),
    Row(
        "/tb_control/set_servo_zero_offset",
        "robot.servo(sid).set_zero_offset(raw)",
        "ohmni servo zero-offset RAW --sid N",
        zero_offset,
        ("servo", "zero-offset", "--sid", "3", "--", "-20"),
        said("servo 3: zero offset -20"),
        daemon=True,
    ),
    # -- parameters
    Row(
        "~port_name",
        "Robot.open(port)",
        "ohmni info --port PORT",
        opened_on,
        ("info", "--json", "--port", "sim://"),
        sample_of("port", test=lambda v: v == "sim://"),
    ),
    Row(
        "~baudrate",
        "baudrate=…",
        "OHMNI_BAUDRATE=… ohmni info",
        baudrate,
        ("info", "--json"),
        said("baudrate=100 is out of range: allowed 1200..4000000 baud"),
        settings={"baudrate": 57600},
        env={"OHMNI_BAUDRATE": "100"},
        code=1,
    ),
    Row(
        "~frame_id_odom",
        "frame_id_odom=…",
        "OHMNI_FRAME_ID_ODOM=… ohmni record FILE.mcap",
        odom_field("frame_id", "map"),
        record(),
        recorded(lambda _, path: odom_frames(path) == ("map", "base_link")),
        settings={"frame_id_odom": "map"},
        env={"OHMNI_FRAME_ID_ODOM": "map"},
    ),
    Row(
        "~frame_id_baselink",
        "frame_id_baselink=…",
        "OHMNI_FRAME_ID_BASELINK=… ohmni record FILE.mcap",
        odom_field("child_frame_id", "base_footprint"),
        record(),
        recorded(lambda _, path: odom_frames(path) == ("odom", "base_footprint")),
        settings={"frame_id_baselink": "base_footprint"},
        env={"OHMNI_FRAME_ID_BASELINK": "base_footprint"},
    ),
    Row(
        "~enable_broadcast_transform",
        "enable_broadcast_transform=…",
        "OHMNI_ENABLE_BROADCAST_TRANSFORM=… ohmni record FILE.mcap",
        no_tf,
        record(),
        recorded(
            lambda s, _: "/tf" not in s["channels"] and "/tb_control/wheel_odom" in s["channels"]
        ),
        settings={"enable_broadcast_transform": False},
        env={"OHMNI_ENABLE_BROADCAST_TRANSFORM": "false"},
    ),
    Row(
        "~wheel_radius",
        "wheel_radius_m=…",
        "OHMNI_WHEEL_RADIUS_M=… ohmni drive",
        half_radius,
        (*DRIVE, "--linear", "0.2", "--duration", "0.5"),
        # The odometry counts half the way the simulator's wheels went.
        sample_of(
            test=lambda v: v["truth"]["x_m"] == pytest.approx(2 * v["pose"]["x_m"], rel=0.05)
        ),
        settings={"wheel_radius_m": 0.038},
        env={"OHMNI_WHEEL_RADIUS_M": "0.038"},
    ),
    Row(
        "~wheel_separation",
        "wheel_separation_m=…",
        "OHMNI_WHEEL_SEPARATION_M=… ohmni drive",
        double_separation,
        (*DRIVE, "--turn", "30"),
        sample_of("truth", "heading_change_deg", test=lambda v: v == pytest.approx(60, abs=3)),
        settings={"wheel_separation_m": 0.66},
        env={"OHMNI_WHEEL_SEPARATION_M": "0.66"},
    ),
    Row(
        "~max_linear_velocity",
        "max_linear_mps=…",
        "OHMNI_MAX_LINEAR_MPS=… ohmni drive",
        linear_limit,
        (*DRIVE, "--distance", "0.1"),
        sample_of("command", "linear_mps", test=lambda v: v == 0.2),
        settings={"max_linear_mps": 0.2},
        env={"OHMNI_MAX_LINEAR_MPS": "0.2"},
    ),
    Row(
        "~max_angular_velocity",
        "max_angular_radps=…",
        "OHMNI_MAX_ANGULAR_RADPS=… ohmni drive",
        angular_limit,
        (*DRIVE, "--turn", "20"),
        sample_of("command", "angular_radps", test=lambda v: v == 0.5),
        settings={"max_angular_radps": 0.5},
        env={"OHMNI_MAX_ANGULAR_RADPS": "0.5"},
    ),
    Row(
        "~delta_velo_raw",
        "linear_accel_mps2=accel_from_delta_velo_raw(level)",
        "OHMNI_LINEAR_ACCEL_MPS2=… ohmni drive",
        fast_ramp,
        (*DRIVE, "--linear", "0.3", "--duration", "0.2"),
        sample_of("distance_m", test=lambda v: v > 0.05),
        settings={"linear_accel_mps2": accel_from_delta_velo_raw(10)},
        env={"OHMNI_LINEAR_ACCEL_MPS2": str(accel_from_delta_velo_raw(10))},
    ),
    Row(
        "~motion_watchdog_enable",
        "watchdog_s=0",
        "OHMNI_WATCHDOG_S=0 ohmni drive",
        no_watchdog,
        ("drive", "--linear", "0.2", "--duration", "0.3"),
        said("re-sent every 0.1 s"),
        settings={"watchdog_s": 0},
        env={"OHMNI_WATCHDOG_S": "0"},
    ),
    Row(
        "~motion_watchdog_period",
        "watchdog_s=…",
        "OHMNI_WATCHDOG_S=… ohmni drive",
        short_watchdog,
        ("drive", "--linear", "0.2", "--duration", "0.3"),
        said("re-sent every 0.05 s"),
        settings={"watchdog_s": 0.15},
        env={"OHMNI_WATCHDOG_S": "0.15"},
    ),
    Row(
        "~servo_neck_id",
        "neck_id=…",
        "OHMNI_NECK_ID=… ohmni info",
        neck_id,
        ("info", "--json"),
        sample_of("servos", test=lambda v: {"sid": 12, "role": "neck", "model": "DRS_0101"} in v),
        settings={"neck_id": 12, "ext_servo_ids": (11,)},
        env={"OHMNI_NECK_ID": "12", "OHMNI_EXT_SERVO_IDS": "11"},
    ),
    Row(
        "~servo_neck_pos_raw_zero_offset",
        "neck_zero_offset_raw=…",
        "OHMNI_NECK_ZERO_OFFSET_RAW=… ohmni neck",
        stream_check("servo_neck", lambda s: s.position_raw == 512 and s.angle_rad > 0.1),
        ("neck", "--json"),
        sample_of("position_deg", test=lambda v: v == pytest.approx(20 * 0.325, abs=0.01)),
        settings={"neck_zero_offset_raw": -20},
        env={"OHMNI_NECK_ZERO_OFFSET_RAW": "-20"},
    ),
    Row(
        "~servo_neck_use_eeprom",
        "neck_use_eeprom=…",
        "OHMNI_NECK_USE_EEPROM=… ohmni info",
        neck_register("position_kp", 500, "eep"),
        ("info", "--json"),
        sample_of("neck_settings", "memory", test=lambda v: v == "eep"),
        settings={"neck_use_eeprom": True, "neck_kp": 500},
        env={"OHMNI_NECK_USE_EEPROM": "true", "OHMNI_NECK_KP": "500"},
    ),
    *_neck_rows(),
]
BY_NAME = {row.name: row for row in ROWS}


# -- the table ---------------------------------------------------------------------------------

#: tb_control's names as /work/shared/reference/tb_control.md lists them, section by section.
SECTIONS = {
    "topics": 9 + 8,
    "services": 15,
    "parameters": 24,
}


def table_rows() -> list[list[str]]:
    """The mapping's rows, cells split (the header and rule rows left out)."""
    text = PAGE.read_text(encoding="utf-8")
    section = text.split("## tb_control to ohmni_tb", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        if not line.startswith("| `"):
            continue
        rows.append([cell.strip() for cell in re.split(r"(?<!\\)\|", line)[1:-1]])
    return rows


def test_the_list_is_tb_controls_whole_interface() -> None:
    names = [row.name for row in ROWS]
    assert len(names) == len(set(names))
    assert len(names) == sum(SECTIONS.values())
    assert sum(name.startswith("~") for name in names) == SECTIONS["parameters"]


def test_the_docs_table_has_one_row_per_name_with_its_call_and_command() -> None:
    seen: list[str] = []
    for cells in table_rows():
        name = re.match(r"`([^`]+)`", cells[0])
        assert name is not None, cells
        seen.append(name[1])
        row = BY_NAME.get(name[1])
        assert row is not None, f"{name[1]} is not tb_control's"
        assert f"`{row.call}`" in cells[1], (row.name, cells[1])
        assert f"`{row.cli}`" in cells[2], (row.name, cells[2])
    assert sorted(seen) == sorted(BY_NAME)


def test_each_command_runs_what_the_table_says() -> None:
    # The placeholders aside, the command as written is the command as run.
    for row in ROWS:
        written = [w for w in row.cli.split() if "=" not in w and w != "ohmni"]
        literal = [w for w in written if not re.fullmatch(r"[A-Z][\w.]*|…", w)]
        ran = iter(row.argv)
        assert all(word in ran for word in literal), (row.name, literal, row.argv)


@pytest.mark.parametrize("row", ROWS, ids=[row.name for row in ROWS])
def test_the_call_works_on_sim(row: Row) -> None:
    async def main() -> None:
        async with Robot.open(row.url, **row.settings) as robot:
            await asyncio.sleep(0.1)
            await row.check(robot)

    run_virtual(main())


class _Daemon:
    """``ohmni serve``'s robot in this process (its own thread, real time)."""

    def __init__(self) -> None:
        self.url = ""
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=asyncio.run, args=(self._main(),), daemon=True)

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with LocalRobot.open("sim://") as robot, RobotServer(robot, port=0) as server:
            self.url = server.url
            self._ready.set()
            await self._stop.wait()

    def __enter__(self) -> _Daemon:
        self._thread.start()
        assert self._ready.wait(30), "the daemon did not start"
        return self

    def __exit__(self, *exc: object) -> None:
        assert self._loop is not None
        assert self._stop is not None
        self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(30)


@pytest.fixture
def daemon_url(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A daemon the commands go through (``OHMNI_DAEMON_URL``)."""
    with _Daemon() as daemon:
        monkeypatch.setenv("OHMNI_DAEMON_URL", daemon.url)
        monkeypatch.delenv("OHMNI_PORT", raising=False)
        yield daemon.url


@pytest.mark.parametrize("row", ROWS, ids=[row.name for row in ROWS])
def test_the_command_works_on_sim(row: Row, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    argv = [arg.replace("{tmp}", str(tmp_path)) for arg in row.argv]
    if row.daemon:
        request.getfixturevalue("daemon_url")  # real time: the daemon has its own thread
    else:
        request.getfixturevalue("virtual_time")
        if "--port" not in argv and row.argv[0] != "ports":
            end = argv.index("--") if "--" in argv else len(argv)
            argv[end:end] = ["--port", row.url]
    result = invoke(*argv, env=row.env)
    assert result.code == row.code, result.out
    row.expect(result.stdout if row.code == 0 else result.out)
