"""The register maps against the reference table, lookups, and value encoding."""

from __future__ import annotations

import itertools

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import EEP, RAM, BaudRate, Model, Register, model_from_bytes
from ohmni_tb.protocol import Memory

# (name, EEP address, RAM address, size, default) copied from reference/herkulex.md.
REFERENCE = [
    ("id", 6, 0, 1, 0xFD),
    ("ack_policy", 7, 1, 1, 1),
    ("alarm_led_policy", 8, 2, 1, 0x7F),
    ("torque_policy", 9, 3, 1, 0x35),
    ("max_temperature", 11, 5, 1, 0xDE),
    ("min_voltage", 12, 6, 1, 0x5B),
    ("max_voltage", 13, 7, 1, 0x89),
    ("acceleration_ratio", 14, 8, 1, 25),
    ("max_acceleration_time", 15, 9, 1, 0x2D),
    ("dead_zone", 16, 10, 1, 0),
    ("saturator_offset", 17, 11, 1, 0),
    ("saturator_slope", 18, 12, 2, 0),
    ("pwm_offset", 20, 14, 1, 0),
    ("min_pwm", 21, 15, 1, 0),
    ("max_pwm", 22, 16, 2, 1023),
    ("overload_pwm_threshold", 24, 18, 2, 1022),
    ("min_position", 26, 20, 2, 21),
    ("max_position", 28, 22, 2, 1002),
    ("position_kp", 30, 24, 2, 440),
    ("position_kd", 32, 26, 2, 8000),
    ("position_ki", 34, 28, 2, 0),
    ("position_feedforward_gain1", 36, 30, 2, 0),
    ("position_feedforward_gain2", 38, 32, 2, 0),
    ("led_blink_period", 44, 38, 1, 0x2D),
    ("adc_fault_check_period", 45, 39, 1, 0x2D),
    ("packet_garbage_check_period", 46, 40, 1, 0x12),
    ("stop_detection_period", 47, 41, 1, 0x1B),
    ("overload_detection_period", 48, 42, 1, 0x96),
    ("stop_threshold", 49, 43, 1, 3),
    ("inposition_margin", 50, 44, 1, 3),
    ("calibration_difference", 53, 47, 1, 0),
]
# (name, RAM address, size, read-only, signed) for the RAM-only registers.
RAM_ONLY = [
    ("status_error", 48, 1, False, False),
    ("status_detail", 49, 1, False, False),
    ("torque_control", 52, 1, False, False),
    ("led_control", 53, 1, False, False),
    ("voltage", 54, 1, True, False),
    ("temperature", 55, 1, True, False),
    ("current_control_mode", 56, 1, True, False),
    ("tick", 57, 1, True, False),
    ("calibrated_position", 58, 2, True, False),
    ("absolute_position", 60, 2, True, False),
    ("differential_position", 62, 2, True, True),
    ("pwm", 64, 2, True, True),
    ("absolute_goal_position", 68, 2, True, False),
    ("absolute_desired_trajectory_position", 70, 2, True, False),
    ("desired_velocity", 72, 2, True, True),
]


@pytest.mark.parametrize(("name", "eep", "ram", "size", "default"), REFERENCE)
def test_shared_registers_match_the_reference(
    name: str, eep: int, ram: int, size: int, default: int
) -> None:
    e, r = EEP[name], RAM[name]
    assert (e.addr, e.size, e.default, e.memory) == (eep, size, default, Memory.EEP)
    assert (r.addr, r.size, r.default, r.memory) == (ram, size, default, Memory.RAM)
    assert not e.read_only
    assert not r.read_only


@pytest.mark.parametrize(("name", "addr", "size", "read_only", "signed"), RAM_ONLY)
def test_ram_only_registers_match_the_reference(
    name: str, addr: int, size: int, read_only: bool, signed: bool
) -> None:
    reg = RAM[name]
    assert (reg.addr, reg.size, reg.read_only, reg.signed) == (addr, size, read_only, signed)
    assert name not in EEP


def test_eep_only_registers() -> None:
    assert [(r.name, r.addr, r.read_only) for r in EEP if r.addr < 6] == [
        ("model_no1", 0, True),
        ("model_no2", 1, True),
        ("firmware_version", 2, True),
        ("baud_rate", 4, False),
    ]
    assert EEP["baud_rate"].default == 0x10
    assert BaudRate(0x10) is BaudRate.B115200
    assert BaudRate.B115200.bps == 115_200


def test_every_register_appears_once_and_none_overlap() -> None:
    for table in (EEP, RAM):
        regs = list(table)
        assert [r.addr for r in regs] == sorted(r.addr for r in regs)
        for a, b in itertools.pairwise(regs):
            assert a.end <= b.addr, (a.name, b.name)
        assert regs[-1].end <= table.size


def test_signed_settings_take_negative_values() -> None:
    assert (RAM["pwm_offset"].low, RAM["pwm_offset"].high) == (-128, 127)
    assert RAM["calibration_difference"].encode(-1) == b"\xff"
    assert RAM["calibration_difference"].decode(b"\x80") == -128


def test_lookup_by_address() -> None:
    assert RAM.by_addr(52) is RAM["torque_control"]
    assert EEP.by_addr(30) is EEP["position_kp"]
    with pytest.raises(InvalidArgumentError, match="starts at address 59"):
        RAM.by_addr(59)  # the second byte of the calibrated position
    with pytest.raises(InvalidArgumentError, match="starts at address 4"):
        RAM.by_addr(4)  # reserved


def test_unknown_name_lists_the_known_ones() -> None:
    with pytest.raises(InvalidArgumentError, match="known: id, ack_policy"):
        RAM.by_name("ack")


def test_writable_spans() -> None:
    assert RAM.writable(48, 2)
    assert RAM.writable(50, 4)  # reserved 50..51 are stored, 52/53 writable
    assert not RAM.writable(53, 2)  # 54 is the voltage reading
    assert not RAM.writable(72, 4)  # runs past the end
    assert not EEP.writable(0, 1)
    assert EEP.writable(4, 50)


def test_read_only_write_refused_before_encoding() -> None:
    with pytest.raises(InvalidArgumentError, match="read-only"):
        RAM["temperature"].encode(0)
    with pytest.raises(InvalidArgumentError, match="read-only"):
        EEP["model_no1"].encode(2)


@pytest.mark.parametrize("bad", [True, 1.0, "1", None])
def test_non_int_values_are_refused(bad: object) -> None:
    with pytest.raises(InvalidArgumentError, match="takes an int"):
        RAM["ack_policy"].encode(bad)  # type: ignore[arg-type]


def test_decode_checks_length() -> None:
    with pytest.raises(InvalidArgumentError, match="2 byte"):
        RAM["absolute_position"].decode(b"\x00")


writable = [r for table in (EEP, RAM) for r in table if not r.read_only]


@pytest.mark.parametrize("reg", writable, ids=lambda r: f"{r.memory.name}-{r.name}")
def test_range_edges(reg: Register) -> None:
    for value in (reg.low, reg.high):
        if reg.choices is None or value in reg.choices:
            assert reg.decode(reg.encode(value)) == value
    for value in (reg.low - 1, reg.high + 1):
        with pytest.raises(OutOfRangeError) as info:
            reg.encode(value)
        assert (info.value.low, info.value.high) == (reg.low, reg.high)


@given(st.data())
def test_encode_decode_round_trip(data: st.DataObject) -> None:
    reg = data.draw(st.sampled_from(writable))
    values = (
        st.sampled_from(sorted(reg.choices))
        if reg.choices is not None
        else st.integers(reg.low, reg.high)
    )
    value = data.draw(values)
    encoded = reg.encode(value)
    assert len(encoded) == reg.size
    assert reg.decode(encoded) == value


def test_model_detection_uses_the_first_byte() -> None:
    assert model_from_bytes(b"\x01\x01") is Model.DRS_0101
    assert model_from_bytes(b"\x02\x01") is Model.DRS_0201
    with pytest.raises(InvalidArgumentError, match="unknown HerkuleX model"):
        model_from_bytes(b"\x06\x01")
    with pytest.raises(InvalidArgumentError, match="2 bytes"):
        model_from_bytes(b"\x02")
