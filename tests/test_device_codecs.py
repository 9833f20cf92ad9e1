"""The Ohmni board codecs (drive, core, worm neck, device map), sans-IO."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb import control, monitor
from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.herkulex import JogMode, JogTarget, decode_jog
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Memory,
    Packet,
    PacketDecoder,
    ReadReply,
    core,
    drive,
    encode_packet,
    worm_neck,
)
from ohmni_tb.protocol.devices import DEVICE_MAP, DeviceId, device_name
from ohmni_tb.protocol.drive import DriveProfile, WheelJogForm
from ohmni_tb.sim import drive as sim_drive

SRC = Path(control.__file__).resolve().parent.parent
I_JOG_PROFILE = DriveProfile(wheel_form=WheelJogForm.I_JOG)
UNMIRRORED = DriveProfile(right_mirrored=False)


def _read_reply(
    sid: int, addr: int, data: bytes, memory: Memory = Memory.RAM, status: bytes = b"\0\0"
) -> ReadReply:
    """A read reply as a device sends it, parsed the way the bus parses it."""
    packet = Packet(sid, memory.read_cmd | REPLY_FLAG, bytes((addr, len(data))) + data + status)
    return ReadReply.parse(packet)


def _decode_every_way(wire: bytes) -> list[list[Packet]]:
    """Decode ``wire`` whole, in halves and byte by byte."""
    results = []
    for chunk in (len(wire), (len(wire) + 1) // 2, 1):
        decoder = PacketDecoder()
        packets: list[Packet] = []
        for i in range(0, len(wire), chunk):
            packets += decoder.feed(wire[i : i + chunk])
        results.append(packets)
    return results


# -- device map --------------------------------------------------------------------------


def test_device_ids_match_the_vendor_map() -> None:
    assert (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE) == (0, 1)
    assert (DeviceId.HERKULEX_NECK, DeviceId.WORM_NECK, DeviceId.CORE) == (3, 4, 20)
    assert DeviceId.BROADCAST == BROADCAST_ID == 0xFE


@pytest.mark.parametrize(
    ("sid", "name"),
    [(0, "left"), (1, "right"), (3, "neck"), (4, "worm-neck"), (20, "core"), (11, "ext1")],
)
def test_device_name_of_known_ids(sid: int, name: str) -> None:
    assert device_name(sid) == name


def test_device_name_of_an_unknown_id() -> None:
    assert device_name(77) == "sid77"


def test_only_the_external_servo_ids_are_marked_assumed() -> None:
    assumed = sorted(sid for sid, info in DEVICE_MAP.items() if not info.confirmed)
    assert assumed == [11, 12]


# -- drive boards: counts and motor position ----------------------------------------------


def test_read_count_is_the_published_left_wheel_vector() -> None:
    wire = bytes.fromhex("FF FF 09 00 04 32 CC 3B 04")
    assert encode_packet(drive.read_count(0)) == wire
    for packets in _decode_every_way(wire):
        assert packets == [drive.read_count(0)]


def test_read_count_of_the_right_board() -> None:
    assert drive.read_count(1) == Packet(1, Command.RAM_READ, bytes((59, 4)))


@pytest.mark.parametrize("sid", [2, 3, 20, BROADCAST_ID])
def test_read_count_refuses_a_non_drive_sid(sid: int) -> None:
    with pytest.raises(OutOfRangeError, match="drive sid"):
        drive.read_count(sid)
    with pytest.raises(OutOfRangeError, match="drive sid"):
        drive.read_motor_position(sid)


@pytest.mark.parametrize("count", [0, 1, -1, 123_456, -123_456, 2**31 - 1, -(2**31)])
def test_parse_count_is_int32_little_endian(count: int) -> None:
    reply = _read_reply(0, 59, count.to_bytes(4, "little", signed=True))
    assert drive.parse_count(reply) == count


def test_parse_count_of_known_bytes() -> None:
    assert drive.parse_count(_read_reply(1, 59, bytes.fromhex("C0 1D FE FF"))) == -123_456


@pytest.mark.parametrize(
    ("addr", "data"),
    [(58, b"\0\0\0\0"), (59, b"\0\0"), (59, b"\0\0\0\0\0")],
    ids=["wrong addr", "short", "long"],
)
def test_parse_count_refuses_a_reply_of_another_shape(addr: int, data: bytes) -> None:
    with pytest.raises(MalformedReplyError):
        drive.parse_count(_read_reply(0, addr, data))


def test_read_motor_position_packet() -> None:
    assert drive.read_motor_position(0) == Packet(0, Command.RAM_READ, bytes((58, 2)))


@pytest.mark.parametrize("position", [0, 1, 8192, 16383])
def test_parse_motor_position_is_14_bits(position: int) -> None:
    reply = _read_reply(0, 58, position.to_bytes(2, "little"))
    assert drive.parse_motor_position(reply) == position


def test_parse_motor_position_refuses_a_value_beyond_14_bits() -> None:
    with pytest.raises(MalformedReplyError, match="16384"):
        drive.parse_motor_position(_read_reply(0, 58, (16384).to_bytes(2, "little")))


@pytest.mark.parametrize(("addr", "data"), [(59, b"\0\0"), (58, b"\0\0\0\0")])
def test_parse_motor_position_refuses_a_reply_of_another_shape(addr: int, data: bytes) -> None:
    with pytest.raises(MalformedReplyError):
        drive.parse_motor_position(_read_reply(0, addr, data))


def test_read_firmware_tag_asks_eep_f1_with_length_zero() -> None:
    assert drive.read_firmware_tag(20) == Packet(20, Command.EEP_READ, bytes((0xF1, 0)))


def test_set_torque_may_broadcast() -> None:
    packet = drive.set_torque(BROADCAST_ID, drive.DriveTorque.BRAKE)
    assert packet == Packet(BROADCAST_ID, Command.RAM_WRITE, bytes((52, 1, 0x40)))


def test_set_torque_refuses_a_non_drive_sid() -> None:
    with pytest.raises(OutOfRangeError):
        drive.set_torque(20, drive.DriveTorque.ON)


# -- drive boards: the wheel command ------------------------------------------------------


def test_wheel_command_forward_is_left_plus_right_minus() -> None:
    packet = drive.wheel_command(250, 250)
    assert packet.sid == BROADCAST_ID
    assert packet.cmd == Command.S_JOG
    # playtime, then per board: JOG LSB, JOG MSB (0x40 = negative), SET (0x02 turn), id.
    assert packet.data == bytes.fromhex("00 FA 00 02 00 FA 40 02 01")


def test_wheel_command_reverse_sets_the_left_sign_bit() -> None:
    packet = drive.wheel_command(-1000, -1000)
    # -1000 left: 1000 | 0x4000 = 0x43E8; right mirrored to +1000 = 0x03E8.
    assert packet.data == bytes.fromhex("00 E8 43 02 00 E8 03 02 01")


def test_wheel_command_follows_the_profile_mirror() -> None:
    packet = drive.wheel_command(100, 100, UNMIRRORED)
    assert packet.data == bytes.fromhex("00 64 00 02 00 64 00 02 01")
    assert drive.decode_wheel_command(packet, UNMIRRORED) == {0: 100, 1: 100}


def test_wheel_command_as_one_i_jog_with_two_five_byte_tags() -> None:
    packet = drive.wheel_command(250, 250, I_JOG_PROFILE)
    assert packet.sid == BROADCAST_ID
    assert packet.cmd == Command.I_JOG
    # Per board: JOG LSB, JOG MSB, SET (0x02 turn), id, playtime 0.
    assert packet.data == bytes.fromhex("FA 00 02 00 00 FA 40 02 01 00")
    wire = encode_packet(packet)
    assert len(wire) == 7 + 2 * 5
    for packets in _decode_every_way(wire):
        assert packets == [packet]


@pytest.mark.parametrize(
    ("profile", "wire_hex"),
    [
        (drive.DRIVE_PROFILE, "FF FF 10 FE 06 A8 56 00 2C 01 02 00 2C 41 02 01"),
        (I_JOG_PROFILE, "FF FF 11 FE 05 AA 54 2C 01 02 00 00 2C 41 02 01 00"),
    ],
    ids=["S_JOG", "I_JOG"],
)
def test_the_wheel_command_examples_of_the_hardware_page(
    profile: DriveProfile, wire_hex: str
) -> None:
    # docs/hardware.md shows these bytes for wheel_command(300, 300).
    assert encode_packet(drive.wheel_command(300, 300, profile)) == bytes.fromhex(wire_hex)
    page = (Path(__file__).parent.parent / "docs" / "hardware.md").read_text(encoding="utf-8")
    assert wire_hex in " ".join(page.split())  # the page spaces the fields apart


def test_the_wheel_forms_are_the_jog_command_codes() -> None:
    assert int(WheelJogForm.S_JOG) == Command.S_JOG
    assert int(WheelJogForm.I_JOG) == Command.I_JOG
    assert drive.DRIVE_PROFILE.wheel_form is WheelJogForm.S_JOG


@pytest.mark.parametrize(
    ("field", "value"),
    [("wheel_form", "S_JOG"), ("wheel_form", 6), ("wheel_form", True), ("right_mirrored", 1)],
)
def test_a_drive_profile_with_a_bad_entry_is_refused(field: str, value: object) -> None:
    with pytest.raises(InvalidArgumentError, match=field):
        DriveProfile(**{field: value})  # type: ignore[arg-type]  # what a hand edit might hold


@given(
    st.integers(-1000, 1000),
    st.integers(-1000, 1000),
    st.sampled_from(WheelJogForm),
    st.booleans(),
)
def test_every_profile_round_trips_through_the_wire(
    left: int, right: int, form: WheelJogForm, mirrored: bool
) -> None:
    profile = DriveProfile(wheel_form=form, right_mirrored=mirrored)
    (packet,) = PacketDecoder().feed(encode_packet(drive.wheel_command(left, right, profile)))
    assert drive.decode_wheel_command(packet, profile) == {
        0: left,
        1: -right if mirrored else right,
    }


@pytest.mark.parametrize(
    ("built_with", "read_with"),
    [(drive.DRIVE_PROFILE, I_JOG_PROFILE), (I_JOG_PROFILE, drive.DRIVE_PROFILE)],
    ids=["S_JOG read as I_JOG", "I_JOG read as S_JOG"],
)
def test_a_wheel_command_of_another_form_is_not_read(
    built_with: DriveProfile, read_with: DriveProfile
) -> None:
    with pytest.raises(MalformedReplyError, match=read_with.wheel_form.name):
        drive.decode_wheel_command(drive.wheel_command(100, 100, built_with), read_with)


def test_the_bus_monitor_reads_the_wheel_command_in_either_form() -> None:
    # A capture shows which form the vendor sends: the monitor reads both, with the
    # profile's mirror.
    i_jog_packet = drive.wheel_command(300, 300, I_JOG_PROFILE)
    assert monitor.describe(i_jog_packet) == (
        "I_JOG wheels: left pwm +300, right pwm -300 (board frame)"
    )
    assert monitor.describe(drive.wheel_command(300, 300, UNMIRRORED)) == (
        "S_JOG wheels: left pwm +300, right pwm +300 (board frame)"
    )


def test_the_wheel_command_is_a_herkulex_turn_jog() -> None:
    # Both codecs read the same tags the same way: one jog codec, protocol.jog.
    for profile in (drive.DRIVE_PROFILE, I_JOG_PROFILE):
        targets = decode_jog(drive.wheel_command(300, 200, profile))
        assert targets == (
            JogTarget(0, 300, mode=JogMode.TURN),
            JogTarget(1, -200, mode=JogMode.TURN),
        )


def test_wheel_command_is_one_frame_on_the_wire() -> None:
    wire = encode_packet(drive.wheel_command(300, -200))
    assert len(wire) == 7 + 1 + 2 * 4
    for packets in _decode_every_way(wire):
        assert packets == [drive.wheel_command(300, -200)]


@given(st.integers(-1000, 1000), st.integers(-1000, 1000))
def test_decode_wheel_command_round_trip(left: int, right: int) -> None:
    decoded = drive.decode_wheel_command(drive.wheel_command(left, right))
    # The decoder gives the board frame: the right wheel stays mirrored.
    assert decoded == {0: left, 1: -right}


@pytest.mark.parametrize(("left", "right", "bad"), [(1001, 0, 1001), (0, -1001, -1001)])
def test_wheel_command_refuses_pwm_out_of_range(left: int, right: int, bad: int) -> None:
    with pytest.raises(OutOfRangeError) as info:
        drive.wheel_command(left, right)
    assert info.value.value == bad
    assert str(bad) in str(info.value)
    assert (info.value.low, info.value.high) == (-1000, 1000)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_wheel_command_refuses_non_finite(value: float) -> None:
    with pytest.raises(OutOfRangeError):
        drive.wheel_command(value, 0)  # type: ignore[arg-type]  # what a caller might pass


@pytest.mark.parametrize("value", [0.5, 100.0, True, "100", None])
def test_wheel_command_refuses_non_integers(value: object) -> None:
    with pytest.raises(InvalidArgumentError, match="right_pwm"):
        drive.wheel_command(0, value)  # type: ignore[arg-type]  # what a caller might pass


def test_decode_wheel_command_ignores_other_tags() -> None:
    # A jog for servo 11 in position mode (SET 0x00) shares the packet with the left wheel.
    data = bytes.fromhex("00 64 00 02 00 00 02 00 0B")
    assert drive.decode_wheel_command(Packet(BROADCAST_ID, Command.S_JOG, data)) == {0: 100}


def test_decode_wheel_command_skips_invalid_and_position_tags_of_the_boards() -> None:
    # Left: "jog invalid" (SET 0x22); right: position mode (SET 0x00).
    data = bytes.fromhex("00 64 00 22 00 64 00 00 01")
    assert drive.decode_wheel_command(Packet(BROADCAST_ID, Command.S_JOG, data)) == {}


@pytest.mark.parametrize("tag", ["64 80 02 00", "64 00 42 00"], ids=["word bit 15", "SET bit 6"])
def test_decode_wheel_command_refuses_reserved_bits_in_a_board_tag(tag: str) -> None:
    packet = Packet(BROADCAST_ID, Command.S_JOG, bytes.fromhex("00 " + tag))
    with pytest.raises(MalformedReplyError, match="reserved"):
        drive.decode_wheel_command(packet)


@pytest.mark.parametrize(
    "packet",
    [
        Packet(BROADCAST_ID, Command.I_JOG, bytes.fromhex("64 00 02 00 00")),
        Packet(BROADCAST_ID, Command.S_JOG, bytes.fromhex("00 64 00 02")),
    ],
    ids=["not S_JOG", "cut tag"],
)
def test_decode_wheel_command_refuses_other_packets(packet: Packet) -> None:
    with pytest.raises(MalformedReplyError):
        drive.decode_wheel_command(packet)


# -- drive boards: device facts defined once ----------------------------------------------


def test_the_drive_facts_have_one_value_everywhere() -> None:
    assert control.PWM_LIMIT == drive.PWM_LIMIT == 1000
    assert control.MOTOR_TICKS_PER_REV == drive.MOTOR_POSITION_MODULUS == 2**14
    assert sim_drive.TICKS_PER_MOTOR_TURN == drive.MOTOR_POSITION_MODULUS
    assert control.DEFAULT_TICKS_PER_REV == drive.MOTOR_POSITION_MODULUS * 30 / 11


def _literal_definitions(names: set[str]) -> list[str]:
    """Every module-level ``NAME = <number>`` for ``names`` in the package source."""
    found: list[str] = []
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Assign):
                targets, value = node.targets, node.value
            elif isinstance(node, ast.AnnAssign) and node.value is not None:
                targets, value = [node.target], node.value
            else:
                continue
            # A definition computes a number from literals; an alias names another constant.
            if any(isinstance(n, ast.Name) for n in ast.walk(value)):
                continue
            found.extend(
                f"{path.relative_to(SRC)}:{t.id}"
                for t in targets
                if isinstance(t, ast.Name) and t.id in names
            )
    return found


def test_the_drive_facts_are_defined_once_in_the_drive_codec() -> None:
    # control and the simulator alias these; only protocol/drive.py writes the numbers.
    names = {"PWM_LIMIT", "MOTOR_POSITION_MODULUS", "MOTOR_TICKS_PER_REV", "TICKS_PER_MOTOR_TURN"}
    assert sorted(_literal_definitions(names)) == [
        "protocol/drive.py:MOTOR_POSITION_MODULUS",
        "protocol/drive.py:PWM_LIMIT",
    ]


# -- core board ---------------------------------------------------------------------------


def _status(cells: tuple[int, int, int, int, int], current_ma: int = -1200) -> core.TbcoreStatus:
    return core.TbcoreStatus(
        cell_mv=cells,
        charging_current_ma=current_ma,
        docked=True,
        fet_status=3,
        status=(1, 2, 3, 4),
    )


def test_read_status_is_ram_a0_len_18() -> None:
    assert core.read_status() == Packet(20, Command.RAM_READ, bytes((0xA0, 18)))


def test_status_round_trip() -> None:
    status = _status((3301, 3302, 3290, 3310, 3305), -2345)
    block = core.encode_status(status)
    assert len(block) == 18
    assert core.parse_status(_read_reply(20, 0xA0, block)) == status


def test_status_bytes_layout() -> None:
    block = core.encode_status(_status((3300, 3300, 3300, 3300, 3300), -1))
    assert block[:2] == (3300).to_bytes(2, "little")
    assert block[10:12] == b"\xff\xff"  # i16 LE current
    assert block[12:] == bytes((1, 3, 1, 2, 3, 4))  # docked, fet, status 1..4


def test_status_derived_fields() -> None:
    status = _status((3300, 3310, 3320, 3330, 3140), 500)
    assert status.pack_mv == 3300 + 3310 + 3320 + 3330 + 3140
    assert status.min_cell_mv == 3140
    assert status.percent == 20
    assert status.charging
    assert not _status((3300,) * 5, 0).charging


@pytest.mark.parametrize(
    ("lowest_mv", "percent"),
    [(3149, 20), (3150, 50), (3249, 50), (3250, 80), (3379, 80), (3380, 100), (2500, 20)],
)
def test_vendor_percent_rule_edges(lowest_mv: int, percent: int) -> None:
    cells = (3400, lowest_mv, 3450, 3400, 3500)
    assert core.percent_from_cells(cells) == percent
    assert _status(cells).percent == percent


@pytest.mark.parametrize(("addr", "size"), [(0xA1, 18), (0xA0, 17)])
def test_parse_status_refuses_a_reply_of_another_shape(addr: int, size: int) -> None:
    with pytest.raises(MalformedReplyError):
        core.parse_status(_read_reply(20, addr, bytes(size)))


@pytest.mark.parametrize(
    ("cells", "current"),
    [
        ((70_000, 3300, 3300, 3300, 3300), 0),
        ((3300,) * 5, 40_000),
        ((-1, 3300, 3300, 3300, 3300), 0),
    ],
)
def test_encode_status_refuses_fields_that_do_not_fit(cells: tuple[int, ...], current: int) -> None:
    status = _status(cells, current)  # type: ignore[arg-type]
    with pytest.raises(OutOfRangeError):
        core.encode_status(status)


def test_light_ring_is_the_published_vector() -> None:
    wire = bytes.fromhex("FF FF 0C 14 03 D8 26 C1 03 00 FF FF")
    assert encode_packet(core.set_light_ring(0, 255, 255)) == wire
    for packets in _decode_every_way(wire):
        assert packets == [core.set_light_ring(0, 255, 255)]


@pytest.mark.parametrize(("h", "s", "v"), [(256, 0, 0), (0, -1, 0)])
def test_light_ring_refuses_components_out_of_range(h: int, s: int, v: int) -> None:
    with pytest.raises(OutOfRangeError):
        core.set_light_ring(h, s, v)


@pytest.mark.parametrize("bad", [1.5, True])
def test_light_ring_refuses_components_that_are_not_ints(bad: object) -> None:
    with pytest.raises(InvalidArgumentError, match="value must be an int"):
        core.set_light_ring(0, 0, bad)  # type: ignore[arg-type]  # the wrong type on purpose


# -- worm neck ----------------------------------------------------------------------------


@pytest.mark.parametrize("position", [-127_000, -1, 0, 1, 120_000])
def test_set_target_in_range(position: int) -> None:
    packet = worm_neck.set_target(position)
    assert packet == Packet(
        4, Command.RAM_WRITE, bytes((0x70, 4)) + position.to_bytes(4, "little", signed=True)
    )


@pytest.mark.parametrize("position", [-127_001, 120_001, 2**31, -(2**40)])
def test_set_target_refuses_out_of_range(position: int) -> None:
    with pytest.raises(OutOfRangeError) as info:
        worm_neck.set_target(position)
    assert info.value.value == position
    assert (info.value.low, info.value.high) == (worm_neck.WORM_MIN, worm_neck.WORM_MAX)


@pytest.mark.parametrize("position", [1.0, True, math.nan, "0"])
def test_set_target_refuses_non_integers(position: object) -> None:
    with pytest.raises(InvalidArgumentError):
        worm_neck.set_target(position)  # type: ignore[arg-type]  # what a caller might pass


def test_read_feedback_packet() -> None:
    assert worm_neck.read_feedback() == Packet(4, Command.RAM_READ, bytes((0x74, 5)))


@pytest.mark.parametrize(
    ("position", "flags"),
    [
        (0, worm_neck.WormFlags.NONE),
        (-127_000, worm_neck.WormFlags.MOVING),
        (120_000, worm_neck.WormFlags.STALLED),
    ],
)
def test_feedback_round_trip(position: int, flags: worm_neck.WormFlags) -> None:
    feedback = worm_neck.WormFeedback(position, flags)
    reply = _read_reply(4, 0x74, worm_neck.encode_feedback(feedback))
    parsed = worm_neck.parse_feedback(reply)
    assert parsed == feedback
    assert parsed.moving == bool(flags & worm_neck.WormFlags.MOVING)
    assert parsed.stalled == bool(flags & worm_neck.WormFlags.STALLED)


def test_parse_feedback_of_known_bytes_ignores_unknown_flag_bits() -> None:
    reply = _read_reply(4, 0x74, bytes.fromhex("30 39 FF FF FD"))  # -50896, flags 0xFD
    feedback = worm_neck.parse_feedback(reply)
    assert feedback.position == -50_896
    assert feedback.moving
    assert not feedback.stalled


@pytest.mark.parametrize(("addr", "size"), [(0x70, 5), (0x74, 4)])
def test_parse_feedback_refuses_a_reply_of_another_shape(addr: int, size: int) -> None:
    with pytest.raises(MalformedReplyError):
        worm_neck.parse_feedback(_read_reply(4, addr, bytes(size)))
