"""One test for each mistake other HerkuleX drivers made (reference/herkulex.md)."""

from __future__ import annotations

import pytest

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import (
    RAM,
    AckPolicy,
    JogMode,
    JogTarget,
    Model,
    TorqueControl,
    decode_jog,
    eep_read,
    i_jog,
    model_read,
    parse_model,
    parse_reply,
    playtime_s_from_ticks,
    playtime_ticks_from_s,
    ram_read,
    ram_write,
    s_jog,
)
from ohmni_tb.protocol import BROADCAST_ID, Command, PacketDecoder, encode_packet
from ohmni_tb.sim.servo import SimServo

GOLDEN_REPLY = bytes.fromhex("FF FF 0F FD 42 4C B2 1E 04 B8 01 40 1F 00 00")


def test_ack_policy_is_ram_1_not_0x34() -> None:
    assert RAM["ack_policy"].addr == 1
    assert ram_write(3, "ack_policy", AckPolicy.ALL).data == bytes((1, 1, 2))
    # 0x34 is the torque register: "policy 2" there is not even a legal torque value.
    assert RAM.by_addr(0x34).name == "torque_control"
    with pytest.raises(InvalidArgumentError):
        ram_write(3, RAM.by_addr(0x34), AckPolicy.ALL)
    # And the servo obeys RAM 1: after it, even a write is acknowledged.
    servo = SimServo(3)
    assert servo.handle(ram_write(3, "led_control", 1), 0.0) is None
    servo.handle(ram_write(3, "ack_policy", AckPolicy.ALL), 0.0)
    assert servo.handle(ram_write(3, "led_control", 2), 0.0) is not None


def test_reply_survives_stray_bytes_before_and_inside_a_frame() -> None:
    stray = b"\x00" + GOLDEN_REPLY
    # A driver reading at fixed offsets from the first byte gets Kp wrong here.
    assert int.from_bytes(stray[9:11], "little") != 440
    # A corrupted copy (one byte inserted mid-frame) followed by the good reply.
    corrupted = GOLDEN_REPLY[:10] + b"\x55" + GOLDEN_REPLY[10:]
    decoder = PacketDecoder()
    packets = decoder.feed(stray) + decoder.feed(corrupted + GOLDEN_REPLY)
    replies = [parse_reply(p) for p in packets]
    assert [(r.value("position_kp"), r.value("position_kd")) for r in replies] == [
        (440, 8000),
        (440, 8000),
    ]
    assert decoder.stats.checksum_errors + decoder.stats.bad_sizes >= 1


@pytest.mark.parametrize(
    "build",
    [
        lambda: ram_read(BROADCAST_ID, "absolute_position"),
        lambda: eep_read(BROADCAST_ID, "id"),
        lambda: model_read(BROADCAST_ID),
    ],
    ids=["ram_read", "eep_read", "model_read"],
)
def test_reads_to_broadcast_are_refused(build: object) -> None:
    with pytest.raises(OutOfRangeError) as info:
        build()  # type: ignore[operator]
    assert info.value.name == "sid"
    assert info.value.high == BROADCAST_ID - 1


def test_model_bytes_are_read_in_order() -> None:
    servo = SimServo(3, model=Model.DRS_0201)
    answer = servo.handle(model_read(3), 0.0)
    assert answer is not None
    reply = parse_reply(answer)
    assert reply.data == b"\x02\x01"
    # The wrong order (second byte as the model) would call this a DRS-0101.
    assert Model(reply.data[1]) is Model.DRS_0101
    assert parse_model(reply) is Model.DRS_0201


def test_playtime_is_ticks_not_ms_and_never_wraps() -> None:
    # 672 ms is 60 ticks; passing the milliseconds as ticks is refused, not truncated.
    assert playtime_ticks_from_s(0.672) == 60
    with pytest.raises(OutOfRangeError):
        JogTarget(3, 512, playtime_ticks=672)
    # 255 is outside the manual's range, and 256 must not wrap to 0.
    for ticks in (255, 256):
        with pytest.raises(OutOfRangeError):
            JogTarget(3, 512, playtime_ticks=ticks)
        with pytest.raises(OutOfRangeError):
            s_jog(ticks, JogTarget(3, 512))
        with pytest.raises(OutOfRangeError):
            playtime_s_from_ticks(ticks)
    with pytest.raises(OutOfRangeError):
        playtime_ticks_from_s(2.87)  # 256.25 ticks
    assert playtime_ticks_from_s(2.8448) == 254
    # Seconds passed where ticks belong are caught by type.
    with pytest.raises(InvalidArgumentError, match="playtime_ticks_from_s"):
        JogTarget(3, 512, playtime_ticks=0.5)  # type: ignore[arg-type]


def test_turn_pwm_uses_the_sign_bit_and_feedback_is_signed() -> None:
    backwards = JogTarget(3, -512, mode=JogMode.TURN)
    assert backwards.jog_word == 0x4200
    assert i_jog(backwards).data[:2] == b"\x00\x42"
    assert JogTarget(3, 512, mode=JogMode.TURN).jog_word == 0x0200
    assert JogTarget(3, -1023, mode=JogMode.TURN).jog_word == 0x43FF
    assert decode_jog(i_jog(backwards)) == (backwards,)
    with pytest.raises(OutOfRangeError):
        JogTarget(3, -1024, mode=JogMode.TURN)
    # Feedback registers are two's complement, not sign-magnitude and not unsigned.
    assert RAM["pwm"].decode(b"\x00\xfe") == -512
    assert RAM["differential_position"].decode(b"\xfe\xff") == -2
    # And a servo spinning backwards reports negative speed and PWM.
    servo = SimServo(3)
    servo.handle(ram_write(3, "torque_control", TorqueControl.ON), 0.0)
    servo.handle(i_jog(backwards), 0.0)
    reply = servo.handle(ram_read(3, "differential_position", through="pwm"), 0.5)
    assert reply is not None
    parsed = parse_reply(reply)
    assert parsed.value("differential_position") < 0
    assert parsed.value("pwm") < 0


def test_calibrated_and_absolute_positions_are_distinct() -> None:
    assert (RAM["calibrated_position"].addr, RAM["absolute_position"].addr) == (58, 60)
    servo = SimServo(3)
    servo.handle(ram_write(3, "calibration_difference", 10), 0.0)
    servo.handle(ram_write(3, "torque_control", TorqueControl.ON), 0.0)
    servo.handle(i_jog(JogTarget(3, 500, playtime_ticks=50)), 0.0)
    reply = servo.handle(ram_read(3, "calibrated_position", through="absolute_position"), 1.0)
    assert reply is not None
    parsed = parse_reply(reply)
    # The JOG goal is in the calibrated coordinate; the pot reads calibrated + difference.
    assert parsed.value("calibrated_position") == 500
    assert parsed.value("absolute_position") == 510


def test_policy_2_acknowledges_writes_so_the_bus_must_consume_them() -> None:
    # A driver that ignores these acks leaves them in the buffer for the next read.
    servo = SimServo(3)
    servo.handle(ram_write(3, "ack_policy", AckPolicy.ALL), 0.0)
    ack = servo.handle(ram_write(3, "led_control", 1), 0.0)
    assert ack is not None
    assert ack.cmd == Command.RAM_WRITE | 0x40
    assert len(encode_packet(ack)) == 9
