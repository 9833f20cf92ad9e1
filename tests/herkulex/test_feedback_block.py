"""The servo feedback block (RAM 48..59) a Robot polls, decoded in the codec layer."""

from __future__ import annotations

import pytest

from ohmni_tb.errors import MalformedReplyError
from ohmni_tb.herkulex import (
    JogTarget,
    StatusDetail,
    StatusError,
    TorqueControl,
    parse_reply,
    ram_read,
    ram_write,
    s_jog,
)
from ohmni_tb.herkulex.registers import (
    FEEDBACK_ADDR,
    FEEDBACK_SIZE,
    ServoFeedback,
    decode_feedback,
)
from ohmni_tb.protocol import read_request
from ohmni_tb.sim.servo import SimServo

# RAM 48 error, 49 detail, 50-51 reserved, 52 torque, 53 LED, 54 voltage, 55 temperature,
# 56 current control mode, 57 tick, 58-59 calibrated position (little-endian).
BLOCK = bytes([0x04, 0x22, 0, 0, 0x60, 0x01, 0x64, 0x2D, 0x00, 0x7F, 0x90, 0x01])


def test_the_block_is_ram_48_through_the_calibrated_position() -> None:
    assert (FEEDBACK_ADDR, FEEDBACK_SIZE) == (48, 12)
    assert ram_read(3, "status_error", through="calibrated_position") == read_request(
        3, FEEDBACK_ADDR, FEEDBACK_SIZE
    )


def test_a_block_decodes_field_by_field() -> None:
    assert decode_feedback(BLOCK) == ServoFeedback(
        status_error=StatusError(0x04),
        status_detail=StatusDetail(0x22),
        torque=TorqueControl.ON,
        voltage_raw=0x64,
        temperature_raw=0x2D,
        position_raw=0x190,
    )


def test_the_position_is_ten_bits() -> None:
    block = bytearray(BLOCK)
    block[11] = 0xFC | 0x01  # bits above the 10-bit position
    assert decode_feedback(bytes(block)).position_raw == 0x190


@pytest.mark.parametrize("size", [0, 11, 13])
def test_a_block_of_another_size_is_malformed(size: int) -> None:
    with pytest.raises(MalformedReplyError, match=f"12 bytes, got {size}"):
        decode_feedback((BLOCK * 2)[:size])


def test_a_torque_byte_that_is_no_mode_is_malformed() -> None:
    block = bytearray(BLOCK)
    block[4] = 0x20
    with pytest.raises(MalformedReplyError, match="torque byte 0x20"):
        decode_feedback(block)


def test_a_simulated_servo_s_block_agrees_with_its_registers_read_one_by_one() -> None:
    servo = SimServo(3, pos_raw=300.0)
    servo.set_supply_voltage(8.1)
    servo.handle(ram_write(3, "torque_control", TorqueControl.ON), 0.0)
    servo.handle(s_jog(60, JogTarget(3, 450)), 0.01)
    reply = servo.handle(read_request(3, FEEDBACK_ADDR, FEEDBACK_SIZE), 0.4)  # mid-move
    assert reply is not None
    parsed = parse_reply(reply)
    block = decode_feedback(parsed.data)

    def register(name: str, t_s: float = 0.4) -> int:
        answer = servo.handle(ram_read(3, name), t_s)
        assert answer is not None
        return parse_reply(answer).value(name)

    assert block.torque is TorqueControl.ON
    assert block.status_error == StatusError(register("status_error"))
    assert block.status_detail == StatusDetail(register("status_detail"))
    assert block.status_detail & StatusDetail.MOVING
    assert block.voltage_raw == register("voltage") == round(8.1 / 0.074)
    assert block.temperature_raw == register("temperature")
    assert 300 < block.position_raw == register("calibrated_position") < 450
