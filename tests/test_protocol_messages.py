"""Read/write requests, their replies, and which requests get a reply."""

from __future__ import annotations

from typing import cast

import pytest

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.protocol import (
    BROADCAST_ID,
    MAX_PACKET_SIZE,
    REPLY_FLAG,
    AckPolicy,
    Command,
    Memory,
    Packet,
    ReadReply,
    StatusDetail,
    StatusError,
    StatusReply,
    encode_packet,
    read_request,
    reply_expected,
    reply_matches,
    write_request,
)
from ohmni_tb.protocol.messages import MAX_READ_LENGTH

# -- requests -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("request_packet", "wire"),
    [
        (read_request(0xFD, 0x35, 1), "FF FF 09 FD 04 C4 3A 35 01"),
        (read_request(0, 59, 4), "FF FF 09 00 04 32 CC 3B 04"),
        (read_request(0xFD, 0x1E, 4, Memory.EEP), "FF FF 09 FD 02 EC 12 1E 04"),
        (write_request(0xFD, 0x35, b"\x01"), "FF FF 0A FD 03 C0 3E 35 01 01"),
        (write_request(0xFD, 0x34, b"\x60"), "FF FF 0A FD 03 A0 5E 34 01 60"),
        (write_request(0x14, 0xC1, bytes([0, 255, 255])), "FF FF 0C 14 03 D8 26 C1 03 00 FF FF"),
        (
            write_request(0xFD, 0x1E, bytes([0xC8, 0x00, 0xE8, 0x03]), Memory.EEP),
            "FF FF 0D FD 01 C8 36 1E 04 C8 00 E8 03",
        ),
    ],
    ids=["ram-read-led", "wheel-count", "eep-read-gains", "led-green", "torque-on", "ring", "eep"],
)
def test_requests_encode_to_the_golden_bytes(request_packet: Packet, wire: str) -> None:
    assert encode_packet(request_packet) == bytes.fromhex(wire)


def test_memory_picks_the_commands() -> None:
    assert (Memory.RAM.read_cmd, Memory.RAM.write_cmd) == (Command.RAM_READ, Command.RAM_WRITE)
    assert (Memory.EEP.read_cmd, Memory.EEP.write_cmd) == (Command.EEP_READ, Command.EEP_WRITE)


def test_read_request_limits() -> None:
    assert read_request(0, 0, 0).data == b"\x00\x00"
    assert read_request(0xFD, 0xFF, MAX_READ_LENGTH).data == bytes([0xFF, MAX_READ_LENGTH])
    # The longest read's reply still fits in one packet.
    data = bytes([0, MAX_READ_LENGTH]) + bytes(MAX_READ_LENGTH + 2)
    reply = Packet(0, Command.RAM_READ.reply, data)
    assert len(encode_packet(reply)) == MAX_PACKET_SIZE


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((BROADCAST_ID, 0x35, 1), "sid"),
        ((0xFF, 0x35, 1), "sid"),
        ((-1, 0x35, 1), "sid"),
        ((3, -1, 1), "addr"),
        ((3, 0x100, 1), "addr"),
        ((3, 0x35, -1), "length"),
        ((3, 0x35, MAX_READ_LENGTH + 1), "length"),
    ],
    ids=["broadcast", "sid-FF", "sid-negative", "addr-negative", "addr-256", "len-neg", "len-big"],
)
def test_read_request_refuses(args: tuple[int, int, int], name: str) -> None:
    with pytest.raises(OutOfRangeError) as info:
        read_request(*args)
    assert info.value.name == name
    assert str(info.value).startswith(f"{name}={args[('sid', 'addr', 'length').index(name)]}")


def test_broadcast_read_names_the_allowed_ids() -> None:
    with pytest.raises(OutOfRangeError, match=r"sid=254 .*0\.\.253"):
        read_request(BROADCAST_ID, 0x35, 1)


def test_write_request_to_broadcast_is_allowed() -> None:
    packet = write_request(BROADCAST_ID, 0x34, b"\x60")
    assert (packet.sid, packet.cmd, packet.data) == (0xFE, Command.RAM_WRITE, b"\x34\x01\x60")


@pytest.mark.parametrize(
    ("args", "name"),
    [
        ((0xFF, 0x35, b"\x01"), "sid"),
        ((3, 0x100, b"\x01"), "addr"),
        ((3, 0x35, b""), "len(data)"),
        ((3, 0x35, bytes(215)), "len(data)"),
    ],
    ids=["sid-FF", "addr-256", "empty", "too-long"],
)
def test_write_request_refuses(args: tuple[int, int, bytes], name: str) -> None:
    with pytest.raises(OutOfRangeError) as info:
        write_request(*args)
    assert info.value.name == name


def test_write_request_limits_and_types() -> None:
    assert len(encode_packet(write_request(3, 0, bytes(214)))) == 223
    assert write_request(3, 0x35, bytearray(b"\x01")).data == b"\x35\x01\x01"
    with pytest.raises(InvalidArgumentError, match="data must be bytes"):
        write_request(3, 0x35, cast("bytes", [1]))


# -- replies ------------------------------------------------------------------------------

KP_KD_REPLY = Packet(0xFD, Command.EEP_READ | REPLY_FLAG, bytes.fromhex("1E 04 B8 01 40 1F 00 00"))


def test_read_reply_parses_the_golden_reply() -> None:
    reply = ReadReply.parse(KP_KD_REPLY)
    assert reply == ReadReply(
        sid=0xFD,
        memory=Memory.EEP,
        addr=0x1E,
        data=bytes.fromhex("B8 01 40 1F"),
        status_error=StatusError.NONE,
        status_detail=StatusDetail.NONE,
    )
    assert reply.length == 4
    assert int.from_bytes(reply.data[:2], "little") == 440
    assert int.from_bytes(reply.data[2:], "little") == 8000


def test_read_reply_carries_the_status_flags() -> None:
    packet = Packet(3, Command.RAM_READ.reply, bytes([0x35, 1, 0x01, 0x18, 0x44]))
    reply = ReadReply.parse(packet)
    assert reply.memory is Memory.RAM
    assert reply.data == b"\x01"
    assert reply.status_error == StatusError.INVALID_PACKET | StatusError.OVERLOAD
    assert StatusDetail.CHECKSUM_ERROR in reply.status_detail
    assert StatusDetail.MOTOR_ON in reply.status_detail
    assert StatusDetail.MOVING not in reply.status_detail


def test_read_reply_of_length_zero_request_takes_what_came() -> None:
    tag = b"stable"
    packet = Packet(20, Command.EEP_READ.reply, bytes([0xF1, len(tag)]) + tag + b"\x00\x00")
    assert ReadReply.parse(packet).data == tag
    empty = Packet(20, Command.EEP_READ.reply, bytes([0xF1, 0, 0, 0]))
    assert ReadReply.parse(empty).data == b""


@pytest.mark.parametrize(
    "packet",
    [
        Packet(3, Command.RAM_READ.reply, bytes([0x35, 4, 1, 2, 3, 0, 0])),
        Packet(3, Command.RAM_READ.reply, bytes([0x35, 1, 1, 2, 0, 0])),
        Packet(3, Command.RAM_READ.reply, bytes([0x35, 1, 0])),
        Packet(3, Command.RAM_READ.reply, b""),
        Packet(3, Command.RAM_READ, bytes([0x35, 1, 1, 0, 0])),
        Packet(3, Command.RAM_WRITE.reply, bytes([0x35, 1, 1, 0, 0])),
        Packet(3, Command.STAT.reply, b"\x00\x00"),
    ],
    ids=["short", "long", "truncated", "empty", "request", "write-reply", "stat-reply"],
)
def test_read_reply_refuses_a_packet_that_does_not_fit(packet: Packet) -> None:
    with pytest.raises(MalformedReplyError):
        ReadReply.parse(packet)


def test_read_reply_length_mismatch_says_so() -> None:
    packet = Packet(3, Command.RAM_READ.reply, bytes([0x35, 4, 1, 2, 3, 0, 0]))
    with pytest.raises(MalformedReplyError, match="says 4 bytes but carries 3"):
        ReadReply.parse(packet)


def test_status_reply_parses() -> None:
    reply = StatusReply.parse(Packet(3, Command.STAT.reply, b"\x08\x04"))
    assert reply == StatusReply(3, 0x47, StatusError.INVALID_PACKET, StatusDetail.CHECKSUM_ERROR)
    write_ack = StatusReply.parse(Packet(3, Command.RAM_WRITE.reply, b"\x00\x42"))
    assert write_ack.cmd == Command.RAM_WRITE | REPLY_FLAG
    assert write_ack.status_detail == StatusDetail.INPOSITION | StatusDetail.MOTOR_ON


@pytest.mark.parametrize(
    "packet",
    [
        Packet(3, Command.STAT, b"\x00\x00"),
        Packet(3, Command.STAT.reply, b"\x00"),
        Packet(3, Command.STAT.reply, b"\x00\x00\x00"),
    ],
    ids=["request", "one-byte", "three-bytes"],
)
def test_status_reply_refuses(packet: Packet) -> None:
    with pytest.raises(MalformedReplyError):
        StatusReply.parse(packet)


# -- which requests get a reply -----------------------------------------------------------

READS = (Command.RAM_READ, Command.EEP_READ)
QUIET_UNLESS_ALL = (
    Command.EEP_WRITE,
    Command.RAM_WRITE,
    Command.I_JOG,
    Command.S_JOG,
    Command.ROLLBACK,
    Command.REBOOT,
)
#: (command, ACK policy, sid) -> reply expected, from reference/herkulex.md "Commands".
REPLY_TABLE: dict[tuple[Command, int, int], bool] = {}
for _policy in (0, 1, 2):
    REPLY_TABLE[Command.STAT, _policy, 3] = True
    REPLY_TABLE[Command.STAT, _policy, BROADCAST_ID] = True
    for _cmd in READS:
        REPLY_TABLE[_cmd, _policy, 3] = _policy >= 1
        REPLY_TABLE[_cmd, _policy, BROADCAST_ID] = False
    for _cmd in QUIET_UNLESS_ALL:
        REPLY_TABLE[_cmd, _policy, 3] = _policy == 2
        REPLY_TABLE[_cmd, _policy, BROADCAST_ID] = False


def test_reply_table_covers_every_command() -> None:
    assert {cmd for cmd, _, _ in REPLY_TABLE} == set(Command)
    assert len(REPLY_TABLE) == len(Command) * 3 * 2


@pytest.mark.parametrize(
    ("cmd", "policy", "sid"),
    list(REPLY_TABLE),
    ids=[
        f"{c.name}-policy{p}-{'bcast' if s == BROADCAST_ID else 'sid3'}" for c, p, s in REPLY_TABLE
    ],
)
def test_reply_expected(cmd: Command, policy: int, sid: int) -> None:
    assert reply_expected(cmd, sid, policy) is REPLY_TABLE[cmd, policy, sid]


def test_reply_expected_defaults_to_policy_1() -> None:
    assert [int(p) for p in AckPolicy] == [0, 1, 2]
    assert reply_expected(Command.RAM_READ, 3)
    assert not reply_expected(Command.RAM_WRITE, 3)


# -- pairing a reply with its request -----------------------------------------------------

READ_LED = read_request(3, 0x35, 1)
LED_REPLY = Packet(3, Command.RAM_READ.reply, bytes([0x35, 1, 0x01, 0, 0]))


def test_reply_matches_its_read() -> None:
    assert reply_matches(READ_LED, LED_REPLY)


@pytest.mark.parametrize(
    "reply",
    [
        Packet(4, Command.RAM_READ.reply, bytes([0x35, 1, 0x01, 0, 0])),
        Packet(3, Command.RAM_READ.reply, bytes([0x36, 1, 0x01, 0, 0])),
        Packet(3, Command.RAM_READ.reply, bytes([0x35, 2, 0x01, 0x02, 0, 0])),
        Packet(3, Command.EEP_READ.reply, bytes([0x35, 1, 0x01, 0, 0])),
        Packet(3, Command.RAM_READ, bytes([0x35, 1])),
        Packet(3, Command.RAM_READ.reply, bytes([0x35])),
        # A bit-0 error in the size byte passes both checksums (they ignore bit 0): the
        # length byte then disagrees with the bytes carried.
        Packet(3, Command.RAM_READ.reply, bytes([0x35, 1, 0x01, 0])),
    ],
    ids=[
        "wrong-sid",
        "wrong-addr",
        "wrong-length",
        "eep-not-ram",
        "echo",
        "too-short",
        "length-byte-disagrees",
    ],
)
def test_reply_matches_refuses(reply: Packet) -> None:
    assert not reply_matches(READ_LED, reply)


def test_length_zero_read_accepts_any_length() -> None:
    tag_read = read_request(20, 0xF1, 0, Memory.EEP)
    for tag in (b"", b"stable", b"2019-08-01-abcdef"):
        reply = Packet(20, Command.EEP_READ.reply, bytes([0xF1, len(tag)]) + tag + b"\0\0")
        assert reply_matches(tag_read, reply)
    other_addr = Packet(20, Command.EEP_READ.reply, bytes([0xF0, 1, 0x41, 0, 0]))
    assert not reply_matches(tag_read, other_addr)


def test_status_reply_matches_a_write_and_stat() -> None:
    write = write_request(3, 0x35, b"\x01")
    assert reply_matches(write, Packet(3, Command.RAM_WRITE.reply, b"\x00\x00"))
    assert not reply_matches(write, Packet(3, Command.EEP_WRITE.reply, b"\x00\x00"))
    assert not reply_matches(write, Packet(2, Command.RAM_WRITE.reply, b"\x00\x00"))
    assert reply_matches(Packet(3, Command.STAT), Packet(3, Command.STAT.reply, b"\x00\x00"))
