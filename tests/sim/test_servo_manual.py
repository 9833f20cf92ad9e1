"""SimServo against the DRS-0101/0201 manual: mode changes, restart, ranges, alarms.

Each test drives the servo through its bytes (the Bench of test_servo_model) and reads
back what a user would: replies, status bytes, registers, and the LEDs a person sees.
"""

from __future__ import annotations

import math

import pytest

from ohmni_tb.herkulex import (
    EEP,
    RAM,
    AckPolicy,
    JogMode,
    JogTarget,
    Led,
    StatusDetail,
    StatusError,
    TorqueControl,
    clear_status,
    eep_read,
    i_jog,
    ram_read,
    ram_write,
    ram_write_many,
    reboot,
    rollback,
    stat,
)
from ohmni_tb.protocol import Command, Memory, Packet, RejectReason, encode_packet, write_request
from ohmni_tb.sim.servo import GARBAGE_TIMEOUT_S, RESTART_S, SimServo

from .test_servo_model import NECK, Bench


@pytest.fixture
def neck() -> Bench:
    return Bench(SimServo(NECK, pos_raw=280))


def torque(bench: Bench, value: TorqueControl, at_s: float | None = None) -> None:
    bench.send(ram_write(NECK, "torque_control", value), at_s)


# -- control mode -----------------------------------------------------------------------


def test_manual_mode_change_torque_off_turn_jog_torque_on(neck: Bench) -> None:
    # Torque off, a turn JOG, torque on: the servo comes up in turn mode, at rest.
    neck.send(i_jog(JogTarget(NECK, 500, mode=JogMode.TURN)), 0.0)
    assert neck.ram("current_control_mode") == JogMode.TURN
    assert neck.ram("calibrated_position", at_s=0.5) == 280  # nothing moved
    torque(neck, TorqueControl.ON, 0.5)
    assert neck.ram("current_control_mode") == JogMode.TURN
    assert neck.status().status_detail == StatusDetail.MOTOR_ON  # on, not moving
    neck.send(i_jog(JogTarget(NECK, 1023, mode=JogMode.TURN)), 1.0)
    assert neck.ram("differential_position", at_s=1.1) == round((60 / 0.166) / 29.09)
    # And back: torque off, a position JOG, torque on.
    torque(neck, TorqueControl.FREE, 2.0)
    neck.send(i_jog(JogTarget(NECK, 500)), 2.0)
    torque(neck, TorqueControl.ON, 2.0)
    assert neck.ram("current_control_mode") == JogMode.POSITION
    assert neck.ram("differential_position") == 0


def test_position_jog_while_spinning_stops_the_spin_and_moves(neck: Bench) -> None:
    torque(neck, TorqueControl.ON)
    neck.send(i_jog(JogTarget(NECK, 600, mode=JogMode.TURN)), 0.0)
    assert neck.status(0.2).status_detail & StatusDetail.MOVING
    neck.send(i_jog(JogTarget(NECK, 500, playtime_ticks=50)), 0.2)
    assert neck.ram("current_control_mode") == JogMode.POSITION
    assert neck.ram("calibrated_position", at_s=2.0) == 500
    assert neck.ram("differential_position") == 0
    assert neck.status().status_detail == StatusDetail.INPOSITION | StatusDetail.MOTOR_ON


def test_brake_does_not_change_the_mode(neck: Bench) -> None:
    torque(neck, TorqueControl.BRAKE)
    neck.send(i_jog(JogTarget(NECK, 500, mode=JogMode.TURN)), 0.0)
    assert neck.ram("current_control_mode") == JogMode.POSITION


# -- restart ------------------------------------------------------------------------


@pytest.mark.parametrize("request_", [reboot(NECK), rollback(NECK)], ids=["reboot", "rollback"])
def test_restart_leaves_the_servo_deaf_for_its_restart_time(neck: Bench, request_: Packet) -> None:
    # A STAT in the same write as the REBOOT arrives while the servo restarts.
    assert neck.send(encode_packet(request_) + encode_packet(stat(NECK)), 1.0) is None
    assert neck.send(stat(NECK), 1.0 + RESTART_S - 0.001) is None
    # Nor does it notice a bad frame meanwhile.
    wire = bytearray(encode_packet(ram_write(NECK, "led_control", Led.RED)))
    wire[-1] ^= 0x02
    neck.send(bytes(wire))
    back = neck.status(1.0 + RESTART_S)
    assert back.status_error == StatusError.NONE
    assert back.status_detail == StatusDetail.NONE
    assert neck.ram("tick") == 0  # the tick counts from the end of the restart


def test_reboot_ack_leaves_before_the_restart(neck: Bench) -> None:
    neck.send(ram_write(NECK, "ack_policy", AckPolicy.ALL))
    reply = neck.send(encode_packet(reboot(NECK)) + encode_packet(stat(NECK)), 1.0)
    assert reply is not None
    assert reply.cmd == Command.REBOOT


# -- register ranges ----------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "raw"),
    [
        ("acceleration_ratio", b"\x33"),  # 51 > 50 %
        ("id", b"\xfe"),  # broadcast cannot be an id
        ("ack_policy", b"\x03"),
        ("torque_control", b"\x20"),  # not free, brake or on
        ("led_control", b"\x08"),
        ("max_pwm", b"\x00\x04"),  # 1024
        ("min_position", b"\x00\x04"),  # 1024
    ],
)
def test_out_of_range_ram_write_is_refused_and_flagged(neck: Bench, name: str, raw: bytes) -> None:
    neck.send(ram_write(NECK, "ack_policy", AckPolicy.ALL))
    before = neck.ask(ram_read(NECK, name)).data
    # The builders refuse these, so they are made with the raw protocol helper.
    ack = neck.ask(write_request(NECK, RAM[name].addr, raw))
    assert ack.status_error == StatusError.INVALID_PACKET
    assert ack.status_detail & StatusDetail.EXCEED_REG_RANGE
    assert neck.ask(ram_read(NECK, name)).data == before


def test_a_write_with_one_bad_register_changes_nothing(neck: Bench) -> None:
    # min_position 300 is fine, max_position 1024 is not: neither is stored.
    neck.send(write_request(NECK, RAM["min_position"].addr, b"\x2c\x01\x00\x04"))
    reply = neck.ask(ram_read(NECK, "min_position", through="max_position"))
    assert (reply.value("min_position"), reply.value("max_position")) == (21, 1002)
    assert reply.status_detail & StatusDetail.EXCEED_REG_RANGE


def test_half_register_write_is_checked_with_the_other_byte(neck: Bench) -> None:
    # max_pwm is 0x03FF: a high byte of 0x04 would make 0x04FF.
    max_pwm = RAM["max_pwm"].addr
    neck.send(write_request(NECK, max_pwm + 1, b"\x04"))
    assert neck.ram("max_pwm") == 1023
    assert neck.status().status_detail & StatusDetail.EXCEED_REG_RANGE
    neck.send(clear_status(NECK))
    neck.send(write_request(NECK, max_pwm, b"\x00"))  # 0x0300: in range
    assert neck.ram("max_pwm") == 0x300
    assert neck.status().status_error == StatusError.NONE


def test_out_of_range_eep_write_is_refused(neck: Bench) -> None:
    neck.send(write_request(NECK, EEP["max_position"].addr, b"\x00\x04", Memory.EEP))
    assert neck.ask(eep_read(NECK, "max_position")).value("max_position") == 1002
    assert neck.status().status_detail & StatusDetail.EXCEED_REG_RANGE


def test_in_range_writes_are_still_stored(neck: Bench) -> None:
    neck.send(ram_write_many(NECK, {"min_position": 0, "max_position": 1023}))
    neck.send(ram_write(NECK, "acceleration_ratio", 50))
    assert neck.ram("max_position") == 1023
    assert neck.ram("acceleration_ratio") == 50
    assert neck.status().status_error == StatusError.NONE


# -- position limits ----------------------------------------------------------------


def test_goal_beyond_the_limits_sets_position_limit_until_cleared(neck: Bench) -> None:
    torque(neck, TorqueControl.ON)
    neck.send(ram_write_many(NECK, {"min_position": 280, "max_position": 650}))
    neck.send(i_jog(JogTarget(NECK, 600, playtime_ticks=20)), 0.0)
    assert neck.status().status_error == StatusError.NONE
    neck.send(i_jog(JogTarget(NECK, 900, playtime_ticks=20)), 1.0)
    assert neck.status().status_error == StatusError.POSITION_LIMIT
    # Still clamped and run; the bit stays after an in-range JOG, until cleared.
    assert neck.ram("calibrated_position", at_s=2.0) == 650
    neck.send(i_jog(JogTarget(NECK, 400, playtime_ticks=20)), 2.0)
    assert neck.status(3.0).status_error == StatusError.POSITION_LIMIT
    assert neck.ram("calibrated_position") == 400
    neck.send(clear_status(NECK))
    assert neck.status().status_error == StatusError.NONE
    # Below the minimum too.
    neck.send(i_jog(JogTarget(NECK, 100, playtime_ticks=20)), 3.0)
    assert neck.status().status_error == StatusError.POSITION_LIMIT


def test_position_limit_in_the_torque_policy_releases_torque(neck: Bench) -> None:
    neck.send(ram_write(NECK, "torque_policy", 0x35 | StatusError.POSITION_LIMIT))
    torque(neck, TorqueControl.ON)
    neck.send(i_jog(JogTarget(NECK, 1010, playtime_ticks=20)), 0.0)
    assert neck.ram("torque_control") == TorqueControl.FREE
    assert neck.ram("calibrated_position", at_s=1.0) == 280  # the JOG was dropped


# -- garbage check ------------------------------------------------------------------


def test_garbage_timeout_is_the_manuals_201_ms() -> None:
    assert math.isclose(GARBAGE_TIMEOUT_S, 0x12 * 0.0112)
    assert RAM["packet_garbage_check_period"].default == 0x12


def test_expired_half_packet_is_flagged_by_the_servo_it_names(neck: Bench) -> None:
    half = encode_packet(ram_write(NECK, "led_control", Led.RED))[:8]
    other = encode_packet(ram_write(4, "led_control", Led.RED))[:8]
    neck.servo.on_rejected(RejectReason.EXPIRED, other, 0.5)
    assert neck.status(0.5).status_error == StatusError.NONE
    expired_s = 0.5 + GARBAGE_TIMEOUT_S
    neck.servo.on_rejected(RejectReason.EXPIRED, half, expired_s)
    status = neck.status(expired_s)
    assert status.status_error == StatusError.INVALID_PACKET
    assert status.status_detail == StatusDetail.GARBAGE_DETECTED
    assert neck.ram("led_control") == Led.NONE


# -- alarm LED ------------------------------------------------------------------------


def overheat(bench: Bench) -> float:
    """Hold full load until the over-temperature alarm latches; return the time."""
    torque(bench, TorqueControl.ON)
    bench.servo.set_load(1.0)
    t = 0.0
    while not bench.status(t).status_error & StatusError.TEMPERATURE:
        t += 5.0
        assert t < 1000, "never overheated"
    return t


def test_led_writes_are_ignored_while_the_alarm_holds(neck: Bench) -> None:
    neck.send(ram_write(NECK, "led_control", Led.BLUE))
    t = overheat(neck)
    neck.send(ram_write(NECK, "led_control", Led.GREEN), t)
    assert neck.ram("led_control") == Led.BLUE
    # Cooled and cleared, the LED obeys again.
    neck.servo.set_load(0.0)
    t += 300.0
    neck.send(clear_status(NECK), t)
    neck.send(ram_write(NECK, "led_control", Led.GREEN), t)
    assert neck.ram("led_control") == Led.GREEN
    assert neck.servo.leds == Led.GREEN


def test_alarm_led_blinks_red_with_the_blink_period(neck: Bench) -> None:
    neck.send(ram_write(NECK, "led_control", Led.GREEN))
    assert neck.servo.leds == Led.GREEN
    # A read past the map is an invalid packet, which the default policy (0x7F) shows.
    neck.send(Packet(NECK, Command.RAM_READ, bytes((RAM.size - 1, 2))), 1.0)
    period_s = neck.ram("led_blink_period") * 0.0112  # 0x2D = 504 ms
    seen: list[Led] = []
    for k in range(8):
        neck.now_s = 1.0 + k * period_s / 4 + 0.01
        neck.servo.advance(neck.now_s)
        seen.append(neck.servo.leds)
    assert set(seen) == {Led.RED, Led.NONE}
    assert seen.count(Led.RED) == 4
    # A JOG's LED bits are ignored too.
    torque(neck, TorqueControl.ON)
    neck.send(i_jog(JogTarget(NECK, 300, led=Led.BLUE)))
    assert neck.ram("led_control") == Led.GREEN


def test_alarm_led_policy_without_the_error_leaves_the_led_alone(neck: Bench) -> None:
    neck.send(ram_write(NECK, "alarm_led_policy", 0x7F & ~StatusError.INVALID_PACKET))
    neck.send(Packet(NECK, Command.RAM_READ, bytes((RAM.size - 1, 2))))
    neck.send(ram_write(NECK, "led_control", Led.BLUE))
    assert neck.ram("led_control") == Led.BLUE
    assert neck.servo.leds == Led.BLUE


# -- time ---------------------------------------------------------------------------


def test_results_do_not_depend_on_how_often_the_servo_is_advanced() -> None:
    def run(steps: int) -> bytes:
        servo = SimServo(NECK, pos_raw=280)
        servo.handle(ram_write(NECK, "torque_control", TorqueControl.ON), 0.0)
        servo.handle(i_jog(JogTarget(NECK, 650, playtime_ticks=200)), 0.0)
        servo.set_load(0.7)
        for k in range(1, steps + 1):
            servo.advance(900.0 * k / steps)
        reply = servo.handle(ram_read(NECK, "status_error", through="desired_velocity"), 900.0)
        assert reply is not None
        return reply.data

    assert run(1) == run(7) == run(5000)
