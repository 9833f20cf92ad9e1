"""The Robot's commands on ``sim://``, in virtual time: what reaches the wire and what the
simulated robot does with it.

Motion is judged by the simulator's ground truth (its wheels and pose) and by the wheel
commands the drive boards decode; the neck and servos by their feedback streams; the
light ring by the core board's register.
"""

from __future__ import annotations

import asyncio
import itertools
import math
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

import pytest

from ohmni_tb import Robot
from ohmni_tb.control.pid import PidGains
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, StateError
from ohmni_tb.herkulex import (
    JogTarget,
    StatusError,
    TorqueControl,
    eep_read,
    parse_reply,
    ram_read,
    s_jog,
)
from ohmni_tb.protocol import Packet
from ohmni_tb.protocol.drive import decode_wheel_command
from ohmni_tb.robot import LocalRobot, PidDebugSample, ServoHandle, ServoSample, WormNeckSample
from ohmni_tb.robot.discovery import REPROBE_S
from ohmni_tb.sim.clock import run_virtual

T = TypeVar("T")

#: How often a user's loop re-sends drive(): inside the 0.5 s watchdog.
USER_TICK_S = 0.05


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


class WheelTap:
    """The wheel commands the left and right drive boards decode, as they arrive.

    ``left`` and ``right`` are ``(time, PWM)``, forward positive for both wheels (the
    right board's mirrored sign is undone here).
    """

    def __init__(self, robot: Robot, monkeypatch: pytest.MonkeyPatch) -> None:
        self.left: list[tuple[float, int]] = []
        self.right: list[tuple[float, int]] = []
        board = robot.sim.left
        original = board.handle_jog

        def spy(packet: Packet, now_s: float) -> None:
            pwm = decode_wheel_command(packet)
            if 0 in pwm:
                self.left.append((now_s, pwm[0]))
            if 1 in pwm:
                self.right.append((now_s, -pwm[1]))
            original(packet, now_s)

        monkeypatch.setattr(board, "handle_jog", spy)

    def since(self, t: float) -> list[tuple[int, int]]:
        """(left, right) PWM of every command since ``t``."""
        rights = [p for at, p in self.right if at >= t]
        lefts = [p for at, p in self.left if at >= t]
        return list(zip(lefts, rights, strict=True))


async def keep_driving(robot: Robot, seconds: float, linear: float, angular: float = 0.0) -> None:
    for _ in range(round(seconds / USER_TICK_S)):
        robot.drive(linear, angular)
        await asyncio.sleep(USER_TICK_S)


async def wait_for(
    what: Callable[[], bool], timeout_s: float, step_s: float = 0.02, message: str = ""
) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not what():
        assert loop.time() < end, message or "condition not met in time"
        await asyncio.sleep(step_s)


# -- 8. drive commands -------------------------------------------------------------------------


def test_drive_is_clamped_counted_and_reaches_the_speed_limit_within_the_ramp() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.2)
            limited = robot.drive(2.0, 0.0)
            assert limited.limited
            assert limited.twist.linear_mps == 1.0
            assert limited.twist.angular_radps == 0.0
            assert limited.scale == pytest.approx(0.5)
            assert robot.stats().bus.clamped_commands == 1
            inside = robot.drive(0.5, 0.0)
            assert not inside.limited
            assert robot.stats().bus.clamped_commands == 1

            # 0 → 1 m/s at 0.5 m/s² takes 2 s; allow the wheel loop half a second more.
            await keep_driving(robot, 2.5, 2.0)
            left, right = robot.sim.wheel_speeds_mps()
            assert left == pytest.approx(1.0, abs=0.02)
            assert right == pytest.approx(1.0, abs=0.02)
            assert robot.sim.pose.yaw == pytest.approx(0.0, abs=math.radians(0.5))
            assert robot.stats().bus.clamped_commands == 1 + round(2.5 / USER_TICK_S)
            odom = robot.latest("wheel_odom")
            assert odom is not None
            assert odom.commanded_linear_mps == pytest.approx(1.0)

    virtual(main)


def test_the_speed_follows_the_acceleration_limit() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.2)
            await keep_driving(robot, 1.0, 1.0)
            # After 1 s at 0.5 m/s² the limited command is 0.5 m/s, not the 1 m/s asked.
            speed = sum(robot.sim.wheel_speeds_mps()) / 2
            assert 0.35 < speed < 0.6

    virtual(main)


def test_drive_wheels_turns_left_when_the_right_wheel_is_faster() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.2)
            yaw0 = robot.sim.pose.yaw
            for _ in range(round(2.0 / USER_TICK_S)):
                wheels = robot.drive_wheels(0.2, 0.4)
                assert (wheels.left_mps, wheels.right_mps) == (0.2, 0.4)
                await asyncio.sleep(USER_TICK_S)
            left, right = robot.sim.wheel_speeds_mps()
            assert left == pytest.approx(0.2, abs=0.02)
            assert right == pytest.approx(0.4, abs=0.02)
            # (0.4 - 0.2) / 0.33 ≈ 0.6 rad/s: well over half a radian in 2 s.
            assert robot.sim.pose.yaw - yaw0 > 0.5
            assert robot.stats().bus.clamped_commands == 0
            clamped = robot.drive_wheels(3.0, 1.5)  # scaled by one factor: same curvature
            assert (clamped.left_mps, clamped.right_mps) == pytest.approx((1.0, 0.5))
            assert robot.stats().bus.clamped_commands == 1

    virtual(main)


def test_drive_pwm_moves_forward_open_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            tap = WheelTap(robot, monkeypatch)
            await asyncio.sleep(0.2)
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            for _ in range(round(2.0 / USER_TICK_S)):
                robot.drive_pwm(300, 300)
                await asyncio.sleep(USER_TICK_S)
            sent = tap.since(t0)
            assert len(sent) >= 2.0 * 50
            assert set(sent) == {(300, 300)}  # exactly as asked: no controller in between
            left, right = robot.sim.wheel_speeds_mps()
            assert left > 0.15
            assert right == pytest.approx(left, rel=0.01)
            assert robot.sim.pose.x > 0.2
            with pytest.raises(OutOfRangeError):
                robot.drive_pwm(1001, 0)

    virtual(main)


def test_without_the_controllers_drive_does_not_move(monkeypatch: pytest.MonkeyPatch) -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            tap = WheelTap(robot, monkeypatch)
            await asyncio.sleep(0.2)
            robot.enable_controllers(False)
            t0 = asyncio.get_running_loop().time()
            with pytest.raises(StateError, match="both wheels' controllers are off"):
                robot.drive(0.3, 0.0)
            await asyncio.sleep(0.5)
            assert set(tap.since(t0)) == {(0, 0)}
            assert robot.sim.wheel_speeds_mps() == (0.0, 0.0)
            assert robot.sim.pose.x == 0.0
            # drive_pwm still works without them.
            for _ in range(round(1.0 / USER_TICK_S)):
                robot.drive_pwm(300, 300)
                await asyncio.sleep(USER_TICK_S)
            assert robot.sim.pose.x > 0.05
            # And with them back, drive() moves again.
            robot.enable_controllers(True)
            await keep_driving(robot, 1.5, 0.3)
            assert sum(robot.sim.wheel_speeds_mps()) / 2 == pytest.approx(0.3, abs=0.03)

    virtual(main)


# -- 9. the wheel PIDs ---------------------------------------------------------------------------


def test_set_pid_round_trips_and_the_pwm_does_not_jump(monkeypatch: pytest.MonkeyPatch) -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            tap = WheelTap(robot, monkeypatch)
            old = robot.get_pid()
            assert old == robot.config.pid_gains()
            loop = asyncio.get_running_loop()
            await keep_driving(robot, 3.0, 0.3)  # cruising
            cruise = tap.since(loop.time() - 1.0)
            steps = [abs(b[0] - a[0]) for a, b in itertools.pairwise(cruise)]
            before = tap.left[-1][1]

            # A change of feed-forward alone is worth (1300 − 940) × 0.3 ≈ 108 PWM.
            new = PidGains(kp=800.0, ki=1000.0, kd=0.0, kff=1300.0, ff_offset=60.0)
            robot.set_pid(new)
            assert robot.get_pid() == new
            changed_at = loop.time()
            await keep_driving(robot, 0.1, 0.3)
            after = [p for at, p in tap.left if at >= changed_at]
            assert after, "no wheel command after the change"
            assert abs(after[0] - before) <= max(steps) + 5, (before, after[:3], max(steps))

            # The new gains hold the speed as well as the old ones.
            await keep_driving(robot, 2.0, 0.3)
            assert sum(robot.sim.wheel_speeds_mps()) / 2 == pytest.approx(0.3, abs=0.02)

    virtual(main)


def test_pid_debug_is_off_by_default_and_publishes_when_enabled() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await keep_driving(robot, 1.0, 0.3)
            assert robot.latest("pid_debug") is None
            assert not robot.stats().streams["pid_debug"].enabled
            assert robot.stats().streams["pid_debug"].samples == 0

            robot.enable_stream("pid_debug")
            subscription = robot.subscribe("pid_debug")
            await keep_driving(robot, 1.0, 0.3)
            stats = robot.stats().streams["pid_debug"]
            assert stats.enabled
            assert stats.achieved_hz == pytest.approx(50.0, rel=0.05)
            sample = robot.latest("pid_debug")
            assert isinstance(sample, PidDebugSample)
            assert sample.left.setpoint == pytest.approx(0.3)
            assert sample.right.setpoint == pytest.approx(0.3)
            assert sample.left.feedback == pytest.approx(0.3, abs=0.03)
            assert subscription.pending >= 45

            robot.enable_stream("pid_debug", False)
            count = robot.stats().streams["pid_debug"].samples
            await keep_driving(robot, 0.5, 0.3)
            assert robot.stats().streams["pid_debug"].samples == count

    virtual(main)


# -- 10. odometry reset ------------------------------------------------------------------------


def test_reset_odometry_starts_the_next_sample_from_there() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.5)
            robot.reset_odometry(1.0, 2.0, 0.5)
            subscription = robot.subscribe("wheel_odom")
            first = await anext(subscription)
            assert (first.x_m, first.y_m, first.yaw_rad) == pytest.approx((1.0, 2.0, 0.5))
            assert first.heading_rad == pytest.approx(0.5)

            # Driving straight on from there moves along the new heading.
            truth0 = robot.sim.pose
            await keep_driving(robot, 2.0, 0.2)
            await keep_driving(robot, 1.0, 0.0)
            odom = robot.latest("wheel_odom")
            truth = robot.sim.pose
            assert odom is not None
            travelled = math.hypot(truth.x - truth0.x, truth.y - truth0.y)
            assert travelled > 0.2
            assert odom.x_m == pytest.approx(1.0 + travelled * math.cos(0.5), abs=0.01)
            assert odom.y_m == pytest.approx(2.0 + travelled * math.sin(0.5), abs=0.01)
            assert odom.yaw_rad == pytest.approx(0.5 + truth.yaw - truth0.yaw, abs=0.01)

    virtual(main)


# -- 11. the neck and servos -------------------------------------------------------------------


def test_neck_move_and_free_show_in_its_stream() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.2)
            neck_handle = robot.neck
            assert isinstance(neck_handle, ServoHandle)
            await neck_handle.move(raw=600, playtime_s=0.5)

            def neck() -> ServoSample:
                sample = robot.latest("servo_neck")
                assert isinstance(sample, ServoSample)
                return sample

            await wait_for(lambda: abs(neck().position_raw - 600) <= 3, 1.5, message="neck")
            assert neck().torque is TorqueControl.ON
            assert neck().sid == 3

            await neck_handle.free()
            await wait_for(lambda: neck().torque is TorqueControl.FREE, 0.5, message="free")

            await robot.servo(11).move(raw=300, playtime_s=0.3)

            def ext1() -> ServoSample:
                sample = robot.latest("servo_ext1")
                assert isinstance(sample, ServoSample)
                return sample

            await wait_for(lambda: abs(ext1().position_raw - 300) <= 3, 1.5, message="servo 11")
            assert ext1().torque is TorqueControl.ON
            assert robot.servo(3) is neck_handle
            with pytest.raises(StateError, match="99"):
                robot.servo(99)
            with pytest.raises(OutOfRangeError):
                await neck_handle.move(raw=1000)  # outside the neck's range: nothing sent

    virtual(main)


def test_the_worm_neck_moves_toward_its_target() -> None:
    async def main() -> None:
        async with Robot.open("sim://?neck=worm") as robot:
            await asyncio.sleep(0.2)
            assert robot.neck_kind == "worm"
            await robot.neck.move(raw=50_000)
            positions: list[int] = []
            async for sample in robot.subscribe("new_neck"):
                assert isinstance(sample, WormNeckSample)
                positions.append(sample.position_raw)
                if sample.position_raw == 50_000 and not sample.moving:
                    break
                assert len(positions) < 60, positions[-5:]
            assert positions == sorted(positions)  # on its way, never back
            assert positions[0] < 50_000
            last = robot.latest("new_neck")
            assert last is not None
            assert not last.stalled
            with pytest.raises(StateError):
                robot.servo(3)

    virtual(main)


# -- 12. light ring and info ---------------------------------------------------------------------


def test_the_light_ring_reaches_the_core_board() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await robot.light_ring(10, 200, 255)
            await asyncio.sleep(0.05)
            assert bytes(robot.sim.core.light_ring) == bytes((10, 200, 255))
            with pytest.raises(OutOfRangeError):
                await robot.light_ring(256, 0, 0)
            assert bytes(robot.sim.core.light_ring) == bytes((10, 200, 255))

    virtual(main)


def test_info_reports_firmware_tags_and_servo_models() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            info = await robot.info()
            assert info["firmware"] == {
                "left_drive": "sim-drive-1.0",
                "right_drive": "sim-drive-1.0",
                "core": "sim-core-1.0",
            }
            assert info["servos"] == {3: "DRS_0101", 11: "DRS_0101", 12: "DRS_0101"}
            assert info["neck"] == "herkulex"
            assert info["absent"] == []
        async with Robot.open("sim://?neck=0201&ext=12&silent=20") as robot:
            info = await robot.info()
            assert info["servos"] == {3: "DRS_0201", 12: "DRS_0101"}
            assert info["present"] == [0, 1, 3, 12]
            assert info["firmware"]["core"] is None
            assert info["absent"] == [11, 20]

    virtual(main)


# -- 13. commands beside the control slot -------------------------------------------------------


def test_commands_keep_the_control_slot_on_time() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            await asyncio.sleep(0.5)
            loop = asyncio.get_running_loop()
            before = robot.stats().streams["wheel_encoder"]
            end = loop.time() + 2.0
            sent = {"neck": 0, "ring": 0}

            async def necks() -> None:
                while loop.time() < end:
                    await robot.neck.move(raw=400 + 200 * (sent["neck"] % 2), playtime_s=0.1)
                    sent["neck"] += 1

            async def rings() -> None:
                while loop.time() < end:
                    await robot.light_ring(sent["ring"] % 256, 200, 255)
                    sent["ring"] += 1

            async with asyncio.TaskGroup() as tg:
                tg.create_task(necks())
                tg.create_task(rings())
                for _ in range(round(2.0 / USER_TICK_S)):
                    robot.drive(0.3, 0.0)
                    await asyncio.sleep(USER_TICK_S)

            after = robot.stats().streams["wheel_encoder"]
            assert sent["neck"] > 100
            assert sent["ring"] > 100
            assert after.samples - before.samples == pytest.approx(100, abs=1)
            assert after.skipped == 0
            assert after.missed == 0
            assert after.achieved_hz == pytest.approx(50.0, rel=0.01)
            assert after.jitter_p99_ms is not None
            assert after.jitter_p99_ms < 5.0
            assert sum(robot.sim.wheel_speeds_mps()) / 2 == pytest.approx(0.3, abs=0.03)

    virtual(main)


def test_a_zero_offset_moves_where_zero_radians_is() -> None:
    async def main() -> tuple[int, float]:
        async with Robot.open("sim://") as robot:
            neck = robot.neck
            assert isinstance(neck, ServoHandle)
            with pytest.raises(OutOfRangeError, match="512"):
                neck.zero_offset_raw = 512
            neck.zero_offset_raw = 40  # 0 rad is now raw 552
            await neck.move(rad=0.0, playtime_s=0.3)
            await asyncio.sleep(0.6)
            sample = robot.latest("servo_neck")
            assert sample is not None
            return sample.position_raw, sample.angle_rad

    position, angle = virtual(main)
    assert position == 552
    assert angle == pytest.approx(0.0, abs=0.01)


def test_a_number_too_large_for_a_float_is_refused_by_name() -> None:
    async def main() -> None:
        async with Robot.open("sim://") as robot:
            with pytest.raises(OutOfRangeError, match=r"linear_mps=1000.*is out of range"):
                robot.drive(10**400)
            with pytest.raises(OutOfRangeError, match=r"y_m=1000"):
                robot.reset_odometry(0.0, 10**400)

    virtual(main)


def test_a_servo_register_is_written_by_address_eep_or_ram() -> None:
    async def main() -> tuple[int, int, int]:
        async with Robot.open("sim://") as robot:
            servo = robot.servo(11)
            assert isinstance(servo, ServoHandle)  # a local robot's handle
            sim_servo = robot.sim.ext_servos[0]
            # tb_control's servo_write_eep: EEP 30 (position_kp) by its address.
            await servo.write(30, 200, memory="eep")
            with pytest.raises(InvalidArgumentError, match=r"31 \(it is byte 2 of position_kp"):
                await servo.write(31, 1, memory="eep")
            with pytest.raises(OutOfRangeError, match=r"position_kp=40000"):
                await servo.write(30, 40_000, memory="eep")
            await servo.write(0x35, 1)  # RAM 53: led_control
            now = robot.sim.sync()
            eep = sim_servo.handle(eep_read(11, "position_kp"), now)
            ram = sim_servo.handle(ram_read(11, "position_kp"), now)
            led = sim_servo.handle(ram_read(11, "led_control"), now)
            assert eep is not None
            assert ram is not None
            assert led is not None
            return (
                parse_reply(eep).value("position_kp"),
                parse_reply(ram).value("position_kp"),
                parse_reply(led).value("led_control"),
            )

    # The EEP copy took it (it acts after a reboot); RAM still runs the factory gain.
    assert virtual(main) == (200, 440, 1)


def _neck_register(robot: LocalRobot, name: str, memory: str = "ram") -> int:
    """A register of the simulated neck, asked of it, not over the wire."""
    neck = robot.sim.neck
    build = eep_read if memory == "eep" else ram_read
    reply = neck.handle(build(neck.sid, name), robot.sim.sync())
    assert reply is not None, "the neck answers"
    return parse_reply(reply).value(name)


def test_the_servo_holds_its_own_limits_when_the_host_does_not() -> None:
    async def main() -> tuple[int, StatusError]:
        async with LocalRobot.open("sim://", neck_min_raw=300, neck_max_raw=600) as robot:
            neck = robot.neck
            assert isinstance(neck, ServoHandle)
            await neck.move(400, playtime_s=0.2, wait=True)
            # A program bypassing the Robot's checks jogs the neck to 250 on the bus.
            await robot.bus.request(s_jog(0, JogTarget(3, 250)), expect_reply=False)
            await asyncio.sleep(1.0)
            sample = robot.latest("servo_neck")
            assert sample is not None
            return sample.position_raw, sample.status_error

    position, errors = virtual(main)
    assert position == 300  # the servo stopped at its own min_position
    assert errors & StatusError.POSITION_LIMIT


def test_use_eeprom_makes_the_servo_power_up_with_the_settings() -> None:
    async def main() -> tuple[tuple[int, int], int, list[str]]:
        settings: dict[str, Any] = {"neck_min_raw": 300, "neck_kp": 250, "neck_use_eeprom": True}
        async with LocalRobot.open("sim://", **settings) as robot:
            report = (await robot.info())["neck_settings"]
            assert (report["memory"], report["ok"]) == ("eep", True)
            # A power cut too short to miss a read: the servo comes up from its EEP.
            robot.sim.neck.power_cycle(robot.sim.sync())
            after_power = (
                _neck_register(robot, "min_position"),
                _neck_register(robot, "position_kp"),
            )
            return after_power, _neck_register(robot, "position_kp", "eep"), report["eep_written"]

    after_power, eep_kp, written = virtual(main)
    assert after_power == (300, 250)
    assert eep_kp == 250
    # Only the EEP registers that differed from the settings were written (EEP wears).
    assert sorted(written) == ["max_position", "min_position", "position_kp"]


def test_a_neck_found_late_gets_its_settings_then() -> None:
    async def main() -> tuple[int, int, str]:
        async with LocalRobot.open("sim://?silent=3", neck_min_raw=300) as robot:
            assert robot.neck_kind == "none"
            assert (await robot.info())["neck_settings"] is None
            line = robot.bus.transport.line  # type: ignore[attr-defined]  # sim://
            line.faults.silent.discard(3)
            before = _neck_register(robot, "min_position")
            await asyncio.sleep(REPROBE_S + 1.0)
            report = (await robot.info())["neck_settings"]
            return before, _neck_register(robot, "min_position"), report["why"]

    before, after, why = virtual(main)
    assert (before, after) == (21, 300)
    assert why == "the neck answered"
