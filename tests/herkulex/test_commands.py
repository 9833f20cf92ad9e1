"""HerkuleX builders and reply parsing against the manual's golden vectors, byte for byte."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.errors import (
    InvalidArgumentError,
    MalformedReplyError,
    OutOfRangeError,
    ProtocolError,
)
from ohmni_tb.herkulex import (
    EEP,
    MAX_I_JOG_TARGETS,
    MAX_S_JOG_TARGETS,
    RAM,
    JogMode,
    JogTarget,
    Led,
    Model,
    StatusDetail,
    StatusError,
    TorqueControl,
    clear_status,
    decode_jog,
    eep_read,
    eep_write,
    eep_write_many,
    i_jog,
    model_read,
    parse_model,
    parse_reply,
    ram_read,
    ram_write,
    ram_write_many,
    reboot,
    rollback,
    s_jog,
    stat,
)
from ohmni_tb.protocol import (
    BROADCAST_ID,
    Command,
    Memory,
    Packet,
    PacketDecoder,
    encode_packet,
)

# (name, builder, wire bytes) from reference/herkulex.md; the REBOOT vector is from
# reference/ohmni-bus.md.
GOLDEN_REQUESTS: list[tuple[str, Callable[[], Packet], str]] = [
    (
        "EEP_READ Kp+Kd",
        lambda: eep_read(0xFD, "position_kp", through="position_kd"),
        "FF FF 09 FD 02 EC 12 1E 04",
    ),
    (
        "EEP_WRITE Kp=200 Kd=1000",
        lambda: eep_write_many(0xFD, {"position_kp": 200, "position_kd": 1000}),
        "FF FF 0D FD 01 C8 36 1E 04 C8 00 E8 03",
    ),
    (
        "RAM_WRITE LED green",
        lambda: ram_write(0xFD, "led_control", Led.GREEN),
        "FF FF 0A FD 03 C0 3E 35 01 01",
    ),
    (
        "RAM_WRITE torque on",
        lambda: ram_write(0xFD, "torque_control", TorqueControl.ON),
        "FF FF 0A FD 03 A0 5E 34 01 60",
    ),
    ("RAM_READ LED", lambda: ram_read(0xFD, "led_control"), "FF FF 09 FD 04 C4 3A 35 01"),
    (
        "I_JOG 512 green 60 ticks",
        lambda: i_jog(JogTarget(0xFD, 512, led=Led.GREEN, playtime_ticks=60)),
        "FF FF 0C FD 05 32 CC 00 02 04 FD 3C",
    ),
    (
        "S_JOG 60 ticks 512 green",
        lambda: s_jog(60, JogTarget(0xFD, 512, led=Led.GREEN)),
        "FF FF 0C FD 06 30 CE 3C 00 02 04 FD",
    ),
    ("REBOOT", lambda: reboot(0xFD), "FF FF 07 FD 09 F2 0C"),
]
GOLDEN_REPLY = bytes.fromhex("FF FF 0F FD 42 4C B2 1E 04 B8 01 40 1F 00 00")


def chunkings(wire: bytes) -> dict[str, list[bytes]]:
    """The same bytes whole, in two halves, and one byte at a time."""
    half = len(wire) // 2
    return {
        "whole": [wire],
        "halves": [wire[:half], wire[half:]],
        "bytewise": [wire[i : i + 1] for i in range(len(wire))],
    }


def decode_all(chunks: list[bytes]) -> list[Packet]:
    decoder = PacketDecoder()
    out: list[Packet] = []
    for chunk in chunks:
        out += decoder.feed(chunk)
    assert decoder.pending == 0
    return out


@pytest.mark.parametrize(("name", "build", "wire_hex"), GOLDEN_REQUESTS, ids=lambda v: v)
def test_builder_matches_golden_bytes(
    name: str, build: Callable[[], Packet], wire_hex: str
) -> None:
    assert encode_packet(build()) == bytes.fromhex(wire_hex), name


@pytest.mark.parametrize(("name", "build", "wire_hex"), GOLDEN_REQUESTS, ids=lambda v: v)
@pytest.mark.parametrize("how", ["whole", "halves", "bytewise"])
def test_golden_request_decodes_to_the_built_packet(
    name: str, build: Callable[[], Packet], wire_hex: str, how: str
) -> None:
    packets = decode_all(chunkings(bytes.fromhex(wire_hex))[how])
    assert packets == [build()], name


@pytest.mark.parametrize("how", ["whole", "halves", "bytewise"])
def test_golden_reply_decodes_and_parses(how: str) -> None:
    (packet,) = decode_all(chunkings(GOLDEN_REPLY)[how])
    reply = parse_reply(packet)
    assert reply.sid == 0xFD
    assert reply.cmd is Command.EEP_READ
    assert reply.memory is Memory.EEP
    assert reply.addr == 0x1E
    assert reply.data == bytes.fromhex("B8 01 40 1F")
    assert reply.value("position_kp") == 440
    assert reply.value(EEP["position_kd"]) == 8000
    assert reply.status_error == StatusError.NONE
    assert reply.status_detail == StatusDetail.NONE


def test_golden_jogs_decode_to_their_target() -> None:
    target = JogTarget(0xFD, 512, led=Led.GREEN, playtime_ticks=60)
    i_packet = decode_all([bytes.fromhex("FF FF 0C FD 05 32 CC 00 02 04 FD 3C")])[0]
    s_packet = decode_all([bytes.fromhex("FF FF 0C FD 06 30 CE 3C 00 02 04 FD")])[0]
    assert decode_jog(i_packet) == (target,)
    assert decode_jog(s_packet) == (target,)


def test_status_reply_has_no_register_bytes() -> None:
    reply = parse_reply(Packet(3, Command.STAT | 0x40, bytes((0x04, 0x42))))
    assert reply.cmd is Command.STAT
    assert reply.addr is None
    assert reply.memory is None
    assert reply.data == b""
    assert reply.status_error == StatusError.TEMPERATURE
    assert reply.status_detail == StatusDetail.MOTOR_ON | StatusDetail.INPOSITION
    with pytest.raises(InvalidArgumentError, match="no register bytes"):
        reply.value("led_control")


def test_write_ack_under_policy_2_parses_as_status() -> None:
    reply = parse_reply(Packet(3, Command.RAM_WRITE | 0x40, bytes((0x08, 0x10))))
    assert reply.cmd is Command.RAM_WRITE
    assert reply.status_error == StatusError.INVALID_PACKET
    assert reply.status_detail == StatusDetail.EXCEED_REG_RANGE


@pytest.mark.parametrize(
    "packet",
    [
        Packet(3, Command.RAM_READ, bytes((52, 1))),  # a request, not a reply
        Packet(3, 0x4F, bytes((0, 0))),  # reply to an unknown command
        Packet(3, Command.RAM_READ | 0x40, bytes((52, 2, 0x60, 0, 0))),  # length disagrees
        Packet(3, Command.STAT | 0x40, bytes((0,))),  # one status byte
    ],
    ids=["request", "unknown-command", "bad-length", "short-status"],
)
def test_parse_reply_refuses_malformed(packet: Packet) -> None:
    with pytest.raises(MalformedReplyError):
        parse_reply(packet)


def test_reply_value_outside_the_bytes_read_is_refused() -> None:
    reply = parse_reply(Packet(3, Command.RAM_READ | 0x40, bytes((58, 2, 0x00, 0x02, 0, 0))))
    assert reply.value("calibrated_position") == 512
    with pytest.raises(InvalidArgumentError, match="not in this reply"):
        reply.value("absolute_position")


def test_block_read_covers_from_first_to_last_register() -> None:
    packet = ram_read(3, "calibrated_position", through="pwm")
    assert packet.data == bytes((58, 66 - 58))
    with pytest.raises(InvalidArgumentError, match="comes before"):
        ram_read(3, "pwm", through="calibrated_position")


def test_write_many_needs_adjacent_registers() -> None:
    assert ram_write_many(3, {"min_position": 280, "max_position": 650}).data == bytes(
        (20, 4, 0x18, 0x01, 0x8A, 0x02)
    )
    with pytest.raises(InvalidArgumentError, match="gapless"):
        ram_write_many(3, {"min_position": 280, "position_kp": 100})
    with pytest.raises(InvalidArgumentError, match="nothing to write"):
        ram_write_many(3, {})


def test_clear_status_is_the_documented_write() -> None:
    assert clear_status(3) == Packet(3, Command.RAM_WRITE, bytes((48, 2, 0, 0)))


def test_memory_mismatch_is_refused() -> None:
    with pytest.raises(InvalidArgumentError, match="not a RAM register"):
        ram_read(3, EEP["id"])
    with pytest.raises(InvalidArgumentError, match="no EEP register named 'torque_control'"):
        eep_write(3, "torque_control", 0x60)


def test_writes_check_the_value_before_building() -> None:
    with pytest.raises(InvalidArgumentError, match="read-only"):
        ram_write(3, "absolute_position", 512)
    with pytest.raises(OutOfRangeError) as info:
        ram_write(3, "acceleration_ratio", 51)
    assert (info.value.name, info.value.low, info.value.high) == ("acceleration_ratio", 0, 50)
    with pytest.raises(InvalidArgumentError, match="not one of"):
        ram_write(3, "torque_control", 0x20)


def test_two_byte_signed_and_unsigned_writes_are_little_endian() -> None:
    assert ram_write(3, "max_position", 1002).data == bytes((22, 2, 0xEA, 0x03))
    assert ram_write(3, "calibration_difference", -3).data == bytes((47, 1, 0xFD))


def test_stat_reboot_rollback_layouts() -> None:
    assert stat(3) == Packet(3, Command.STAT)
    assert stat(BROADCAST_ID).sid == BROADCAST_ID
    assert reboot(BROADCAST_ID) == Packet(BROADCAST_ID, Command.REBOOT)
    assert rollback(3) == Packet(3, Command.ROLLBACK, b"\x01\x01")
    assert rollback(3, keep_id=False, keep_baud=True).data == b"\x00\x01"
    with pytest.raises(OutOfRangeError):
        stat(0xFF)


def test_model_read_and_parse() -> None:
    assert model_read(3) == Packet(3, Command.EEP_READ, bytes((0, 2)))
    reply = parse_reply(Packet(3, Command.EEP_READ | 0x40, bytes((0, 2, 0x01, 0x01, 0, 0))))
    assert parse_model(reply) is Model.DRS_0101
    other = parse_reply(Packet(3, Command.EEP_READ | 0x40, bytes((4, 1, 0x10, 0, 0))))
    with pytest.raises(InvalidArgumentError, match="model_read"):
        parse_model(other)


# -- jogs -----------------------------------------------------------------------------


def test_set_byte_layout() -> None:
    t = JogTarget(1, 100, mode=JogMode.TURN, led=Led.RED | Led.BLUE, stop=True)
    # bit0 stop, bit1 turn, bits 2..4 = green/blue/red
    assert t.set_byte == 0b0001_1011


def test_several_servos_go_to_broadcast_each_with_its_own_tag() -> None:
    packet = i_jog(
        JogTarget(3, 650, playtime_ticks=100),
        JogTarget(11, 200, led=Led.BLUE, playtime_ticks=50),
    )
    assert packet.sid == BROADCAST_ID
    assert packet.data == bytes((0x8A, 0x02, 0x00, 3, 100, 0xC8, 0x00, 0x08, 11, 50))


def test_s_jog_refuses_a_conflicting_target_playtime() -> None:
    assert s_jog(30, JogTarget(3, 500, playtime_ticks=30)).data[0] == 30
    with pytest.raises(InvalidArgumentError, match="one playtime"):
        s_jog(30, JogTarget(3, 500, playtime_ticks=60))


def test_jog_target_limits() -> None:
    with pytest.raises(InvalidArgumentError, match="at least one"):
        i_jog()
    with pytest.raises(InvalidArgumentError, match="same servo"):
        i_jog(JogTarget(3, 500), JogTarget(3, 600))
    with pytest.raises(OutOfRangeError):
        JogTarget(BROADCAST_ID, 500)  # a tag names a real servo
    with pytest.raises(OutOfRangeError):
        JogTarget(3, 1024)
    with pytest.raises(OutOfRangeError):
        JogTarget(3, -1)
    with pytest.raises(InvalidArgumentError, match="int"):
        JogTarget(3, 512.0)  # type: ignore[arg-type]
    with pytest.raises(OutOfRangeError):
        i_jog(*(JogTarget(i, 512) for i in range(MAX_I_JOG_TARGETS + 1)))
    with pytest.raises(OutOfRangeError):
        s_jog(0, *(JogTarget(i, 512) for i in range(MAX_S_JOG_TARGETS + 1)))
    # The largest jogs still fit one packet.
    assert len(encode_packet(i_jog(*(JogTarget(i, 512) for i in range(MAX_I_JOG_TARGETS)))))
    assert len(encode_packet(s_jog(0, *(JogTarget(i, 512) for i in range(MAX_S_JOG_TARGETS)))))


def test_decode_jog_skips_invalid_tags_and_refuses_malformed() -> None:
    invalid_tag = bytes((0x00, 0x02, 0x20, 3, 10))
    valid_tag = bytes((0x00, 0x01, 0x00, 4, 10))
    assert decode_jog(Packet(BROADCAST_ID, Command.I_JOG, invalid_tag + valid_tag)) == (
        JogTarget(4, 256, playtime_ticks=10),
    )
    with pytest.raises(ProtocolError, match="whole"):
        decode_jog(Packet(3, Command.I_JOG, valid_tag[:4]))
    with pytest.raises(ProtocolError, match="reserved"):
        decode_jog(Packet(3, Command.I_JOG, bytes((0x00, 0x80, 0x00, 3, 10))))
    with pytest.raises(ProtocolError, match="out of range"):
        decode_jog(Packet(3, Command.I_JOG, bytes((0x00, 0x02, 0x00, 3, 0xFF))))
    with pytest.raises(ProtocolError, match="not a jog"):
        decode_jog(stat(3))


jog_targets = st.builds(
    lambda sid, mode, pos, pwm, led, stop, ticks: JogTarget(
        sid, pwm if mode == JogMode.TURN else pos, mode, Led(led), stop, ticks
    ),
    st.integers(0, 0xFD),
    st.sampled_from(JogMode),
    st.integers(0, 1023),
    st.integers(-1023, 1023),
    st.integers(0, 7),
    st.booleans(),
    st.integers(0, 254),
)


@given(st.lists(jog_targets, min_size=1, max_size=10, unique_by=lambda t: t.sid))
def test_i_jog_round_trips_through_the_wire(targets: list[JogTarget]) -> None:
    (packet,) = PacketDecoder().feed(encode_packet(i_jog(*targets)))
    assert decode_jog(packet) == tuple(targets)


@given(
    st.integers(0, 254),
    st.lists(jog_targets, min_size=1, max_size=10, unique_by=lambda t: t.sid),
)
def test_s_jog_round_trips_through_the_wire(ticks: int, targets: list[JogTarget]) -> None:
    shared = [
        JogTarget(t.sid, t.value, t.mode, t.led, t.stop, playtime_ticks=ticks) for t in targets
    ]
    (packet,) = PacketDecoder().feed(encode_packet(s_jog(ticks, *shared)))
    assert decode_jog(packet) == tuple(shared)


def test_led_bits_match_ram_53() -> None:
    # The SET byte's LED bits are RAM 53's bits shifted by two, so one flag type serves both.
    assert ram_write(3, "led_control", Led.RED).data[-1] == 0x04
    assert JogTarget(3, 0, led=Led.RED).set_byte == 0x04 << 2
    assert RAM["led_control"].high == int(Led.GREEN | Led.BLUE | Led.RED)
