"""The Ohmni board codecs (drive, core, worm neck, device map), sans-IO."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
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


def test_wheel_command_without_mirroring() -> None:
    packet = drive.wheel_command(100, 100, mirror_right=False)
    assert drive.decode_wheel_command(packet) == {0: 100, 1: 100}


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
