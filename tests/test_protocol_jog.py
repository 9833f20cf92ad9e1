"""The jog tag codec, protocol.jog: the one place the bits of a JOG tag are written."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb import herkulex
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, ProtocolError
from ohmni_tb.protocol import BROADCAST_ID, Command, Packet
from ohmni_tb.protocol import jog as jog_codec
from ohmni_tb.protocol.jog import (
    MAX_JOG_POSITION,
    MAX_TURN_MAGNITUDE,
    TURN_SIGN_BIT,
    JogSet,
    JogTag,
    decode_jog_word,
    encode_jog_word,
    jog_data,
    jog_tags,
)

SRC = Path(jog_codec.__file__).resolve().parent.parent


# -- the jog word ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "word"),
    [(0, 0x0000), (1, 0x0001), (-1, 0x4001), (512, 0x0200), (-1000, 0x43E8), (-16383, 0x7FFF)],
)
def test_turn_words_are_sign_and_magnitude(value: int, word: int) -> None:
    assert encode_jog_word(value, turn=True) == word
    assert decode_jog_word(word, turn=True) == value


def test_position_words_are_the_value() -> None:
    assert encode_jog_word(650, turn=False) == 650
    assert decode_jog_word(0x4000, turn=False) == 0x4000  # bit 14 is a position bit here


@given(st.integers(-MAX_TURN_MAGNITUDE, MAX_TURN_MAGNITUDE), st.booleans())
def test_words_round_trip(value: int, turn: bool) -> None:
    value = value if turn else abs(value)
    assert decode_jog_word(encode_jog_word(value, turn=turn), turn=turn) == value


@pytest.mark.parametrize(
    ("value", "turn", "low", "high"),
    [
        (16384, True, -16383, 16383),
        (-16384, True, -16383, 16383),
        (-1, False, 0, MAX_JOG_POSITION),
        (0x8000, False, 0, MAX_JOG_POSITION),
    ],
)
def test_a_value_that_does_not_fit_the_word_is_refused(
    value: int, turn: bool, low: int, high: int
) -> None:
    with pytest.raises(OutOfRangeError) as info:
        encode_jog_word(value, turn=turn)
    assert (info.value.value, info.value.low, info.value.high) == (value, low, high)


@pytest.mark.parametrize("word", [0x8000, 0xFFFF, 0x10000, -1])
@pytest.mark.parametrize("turn", [True, False])
def test_a_word_with_reserved_bits_is_a_protocol_error(word: int, turn: bool) -> None:
    with pytest.raises(ProtocolError, match="reserved"):
        decode_jog_word(word, turn=turn)


# -- the SET byte ---------------------------------------------------------------------------


def test_set_byte_layout() -> None:
    # bit 0 stop, bit 1 turn, bits 2..4 LED green/blue/red, bit 5 jog invalid.
    assert JogSet(stop=True).to_byte() == 0x01
    assert JogSet(turn=True).to_byte() == 0x02
    assert JogSet(led=0b101).to_byte() == 0b1_0100
    assert JogSet(invalid=True).to_byte() == 0x20
    assert JogSet(turn=True, stop=True, led=7, invalid=True).to_byte() == 0x3F


@pytest.mark.parametrize("byte", range(0x40))
def test_every_valid_set_byte_round_trips(byte: int) -> None:
    assert JogSet.from_byte(byte).to_byte() == byte


@pytest.mark.parametrize("byte", [0x40, 0x80, 0xC2, 0x100, -1])
def test_a_set_byte_with_reserved_bits_is_a_protocol_error(byte: int) -> None:
    with pytest.raises(ProtocolError, match="reserved"):
        JogSet.from_byte(byte)


def test_a_bad_set_field_is_refused() -> None:
    with pytest.raises(OutOfRangeError, match=r"led=8 .*0\.\.7"):
        JogSet(led=8)
    with pytest.raises(InvalidArgumentError, match="turn"):
        JogSet(turn=1)  # type: ignore[arg-type]  # what a caller might pass
    with pytest.raises(InvalidArgumentError, match="led"):
        JogSet(led=True)


# -- tags in a packet -----------------------------------------------------------------------


TAGS = (JogTag(0x0200, 0x02, 0, 5), JogTag(0x4200, 0x06, 1, 7))


def test_i_jog_data_is_five_bytes_a_tag_with_its_own_playtime() -> None:
    data = jog_data(Command.I_JOG, TAGS)
    assert data == bytes.fromhex("00 02 02 00 05 00 42 06 01 07")
    assert jog_tags(Packet(BROADCAST_ID, Command.I_JOG, data)) == TAGS


def test_s_jog_data_is_a_shared_playtime_then_four_bytes_a_tag() -> None:
    data = jog_data(Command.S_JOG, TAGS, playtime_ticks=9)
    assert data == bytes.fromhex("09 00 02 02 00 00 42 06 01")
    # The shared playtime goes into every tag.
    assert jog_tags(Packet(BROADCAST_ID, Command.S_JOG, data)) == (
        JogTag(0x0200, 0x02, 0, 9),
        JogTag(0x4200, 0x06, 1, 9),
    )


def test_jog_data_refuses_no_tags_and_other_commands() -> None:
    with pytest.raises(InvalidArgumentError, match="at least one"):
        jog_data(Command.I_JOG, [])
    with pytest.raises(InvalidArgumentError, match="I_JOG or S_JOG"):
        jog_data(Command.RAM_WRITE, TAGS)


@pytest.mark.parametrize(
    ("packet", "message"),
    [
        (Packet(3, Command.STAT), "not a jog"),
        (Packet(3, Command.S_JOG), "playtime"),
        (Packet(3, Command.S_JOG, b"\x00"), "whole 4-byte"),
        (Packet(3, Command.I_JOG, bytes(6)), "whole 5-byte"),
    ],
)
def test_jog_tags_refuses_what_is_not_whole_tags(packet: Packet, message: str) -> None:
    with pytest.raises(ProtocolError, match=message):
        jog_tags(packet)


# -- one codec for both users ---------------------------------------------------------------


def test_herkulex_keeps_its_names_from_the_one_codec() -> None:
    assert herkulex.TURN_SIGN_BIT == TURN_SIGN_BIT == 0x4000
    target = herkulex.JogTarget(3, -5, mode=herkulex.JogMode.TURN, stop=True)
    assert target.jog_word == encode_jog_word(-5, turn=True)
    assert target.set_byte == JogSet(turn=True, stop=True).to_byte()


@pytest.mark.parametrize("module", ["protocol/drive.py", "herkulex/commands.py"])
def test_jog_bits_are_not_written_again_elsewhere(module: str) -> None:
    # A module-level constant named like a jog bit and set from a literal is a second copy
    # of the codec; it belongs in protocol/jog.py.
    copies = []
    for node in ast.parse((SRC / module).read_text(encoding="utf-8")).body:
        target: ast.expr
        if isinstance(node, ast.AnnAssign) and node.value is not None:
            target, value = node.target, node.value
        elif isinstance(node, ast.Assign) and len(node.targets) == 1:
            target, value = node.targets[0], node.value
        else:
            continue
        if not isinstance(target, ast.Name):
            continue
        named_like_a_bit = any(w in target.id for w in ("JOG", "SET", "SIGN", "TURN"))
        from_literals = not any(isinstance(n, ast.Name | ast.Call) for n in ast.walk(value))
        if named_like_a_bit and from_literals:
            copies.append(target.id)
    assert copies == []
