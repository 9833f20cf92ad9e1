"""The JOG tag codec (sans-IO): the one place the bits of an I_JOG or S_JOG tag live.

HerkuleX servos take their moves as tags inside an I_JOG or S_JOG, and the drive boards
are assumed to take their wheel command the same way (see :mod:`ohmni_tb.protocol.drive`),
so both :mod:`ohmni_tb.herkulex.commands` and the drive codec build and read tags here::

    jog word (16 bits, little-endian)
      position mode   bits 0..14 = goal position
      turn mode       bit 14 (0x4000) = negative, bits 0..13 = PWM magnitude
      bit 15 is reserved (always 0)
    SET byte
      bit 0 stop   bit 1 mode (0 position, 1 turn)   bits 2..4 LED green/blue/red
      bit 5 "jog invalid" (the device skips the tag)  bits 6..7 reserved (always 0)
    I_JOG  per device: jog_lsb jog_msb set id playtime
    S_JOG  playtime, then per device: jog_lsb jog_msb set id

The ranges a *device* accepts (a HerkuleX takes PWM and positions up to 1023, a drive
board PWM up to 1000) are its own codec's business; this module only refuses what does
not fit the bits.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, ProtocolError
from ohmni_tb.protocol.framing import Command, Packet

__all__ = [
    "I_JOG_TAG_SIZE",
    "MAX_JOG_POSITION",
    "MAX_TURN_MAGNITUDE",
    "S_JOG_TAG_SIZE",
    "TURN_SIGN_BIT",
    "JogSet",
    "JogTag",
    "decode_jog_word",
    "encode_jog_word",
    "jog_data",
    "jog_tags",
]

#: Turn-mode jog words carry the sign here and the magnitude below it.
TURN_SIGN_BIT: Final = 0x4000
#: The largest PWM magnitude the turn-mode word can carry (bits 0..13).
MAX_TURN_MAGNITUDE: Final = TURN_SIGN_BIT - 1
#: The largest position the position-mode word can carry (bits 0..14).
MAX_JOG_POSITION: Final = 0x7FFF
#: Bytes of one I_JOG tag: jog word (2), SET, id, playtime.
I_JOG_TAG_SIZE: Final = 5
#: Bytes of one S_JOG tag (the playtime is shared, in front of the tags).
S_JOG_TAG_SIZE: Final = 4

_JOG_RESERVED: Final = 0x8000
_SET_STOP: Final = 0x01
_SET_TURN: Final = 0x02
_SET_LED_SHIFT: Final = 2
_SET_LED_MASK: Final = 0x07
_SET_JOG_INVALID: Final = 0x20
_SET_RESERVED: Final = 0xC0


def encode_jog_word(value: int, *, turn: bool) -> int:
    """The 16-bit jog word for a position, or for a signed PWM in turn mode.

    Raises:
        InvalidArgumentError: ``value`` is not an int.
        OutOfRangeError: The value does not fit the word's bits (turn: ±16383, position:
            0..32767); nothing is built.
    """
    _check_int("jog value", value)
    if turn:
        if not -MAX_TURN_MAGNITUDE <= value <= MAX_TURN_MAGNITUDE:
            raise OutOfRangeError("pwm", value, -MAX_TURN_MAGNITUDE, MAX_TURN_MAGNITUDE)
        # Sign and magnitude, not two's complement: -1 is 0x4001.
        return TURN_SIGN_BIT | -value if value < 0 else value
    if not 0 <= value <= MAX_JOG_POSITION:
        raise OutOfRangeError("position", value, 0, MAX_JOG_POSITION, "count")
    return value


def decode_jog_word(word: int, *, turn: bool) -> int:
    """The position, or the signed PWM in turn mode, of a jog word read off the wire.

    Raises:
        InvalidArgumentError: ``word`` is not an int.
        ProtocolError: The reserved bit 15 is set (or the word is not 16 bits).
    """
    _check_int("jog word", word)
    if not 0 <= word <= 0xFFFF or word & _JOG_RESERVED:
        raise ProtocolError(f"jog word 0x{word:04X} sets reserved bits")
    if not turn:
        return word
    magnitude = word & MAX_TURN_MAGNITUDE
    return -magnitude if word & TURN_SIGN_BIT else magnitude


@dataclass(frozen=True, slots=True)
class JogSet:
    """The SET byte of a jog tag.

    Attributes:
        turn: Continuous rotation (the word is a signed PWM) instead of a position.
        stop: Stop and hold (the word is ignored).
        led: The three LED bits, green 1, blue 2, red 4 (HerkuleX RAM 53's layout).
        invalid: "Jog invalid": the device skips this tag.

    Raises:
        InvalidArgumentError: A field has the wrong type.
        OutOfRangeError: ``led`` is not 0..7.
    """

    turn: bool = False
    stop: bool = False
    led: int = 0
    invalid: bool = False

    def __post_init__(self) -> None:
        for name in ("turn", "stop", "invalid"):
            if not isinstance(getattr(self, name), bool):
                raise InvalidArgumentError(f"{name} must be a bool, not {getattr(self, name)!r}")
        if isinstance(self.led, bool) or not isinstance(self.led, int):
            raise InvalidArgumentError(f"led must be LED bits 0..7, not {self.led!r}")
        if not 0 <= self.led <= _SET_LED_MASK:
            raise OutOfRangeError("led", self.led, 0, _SET_LED_MASK)

    def to_byte(self) -> int:
        """The SET byte as sent."""
        return (
            (_SET_STOP if self.stop else 0)
            | (_SET_TURN if self.turn else 0)
            | (self.led << _SET_LED_SHIFT)
            | (_SET_JOG_INVALID if self.invalid else 0)
        )

    @classmethod
    def from_byte(cls, byte: int) -> JogSet:
        """Decode a SET byte read off the wire.

        Raises:
            InvalidArgumentError: ``byte`` is not an int.
            ProtocolError: The reserved bits 6..7 are set (or it is not a byte).
        """
        _check_int("SET byte", byte)
        if not 0 <= byte <= 0xFF or byte & _SET_RESERVED:
            raise ProtocolError(f"jog SET byte 0x{byte:02X} sets reserved bits")
        return cls(
            turn=bool(byte & _SET_TURN),
            stop=bool(byte & _SET_STOP),
            led=(byte >> _SET_LED_SHIFT) & _SET_LED_MASK,
            invalid=bool(byte & _SET_JOG_INVALID),
        )


@dataclass(frozen=True, slots=True)
class JogTag:
    """One tag as it sits on the wire, its fields not yet interpreted.

    Attributes:
        word: The 16-bit jog word (:func:`encode_jog_word`).
        set_byte: The SET byte (:meth:`JogSet.to_byte`).
        sid: The device the tag is for.
        playtime_ticks: The tag's playtime (I_JOG), or the shared one (S_JOG).

    Raises:
        InvalidArgumentError: A field is not an int.
        OutOfRangeError: A field does not fit its byte (the word its 16 bits).
    """

    word: int
    set_byte: int
    sid: int
    playtime_ticks: int = 0

    def __post_init__(self) -> None:
        _check_byte("word", self.word, 0xFFFF)
        _check_byte("set_byte", self.set_byte)
        _check_byte("sid", self.sid)
        _check_byte("playtime_ticks", self.playtime_ticks)


def jog_data(cmd: Command, tags: Sequence[JogTag], *, playtime_ticks: int = 0) -> bytes:
    """The data bytes of an I_JOG or S_JOG carrying ``tags``.

    Args:
        cmd: ``Command.I_JOG`` (each tag with its own playtime) or ``Command.S_JOG``.
        tags: The tags, in order.
        playtime_ticks: S_JOG's shared playtime; an I_JOG ignores it.

    Raises:
        InvalidArgumentError: ``cmd`` is not a jog, or there are no tags.
        OutOfRangeError: ``playtime_ticks`` does not fit a byte.
    """
    _check_byte("playtime_ticks", playtime_ticks)
    if not tags:
        raise InvalidArgumentError("a jog needs at least one tag")
    if cmd == Command.I_JOG:
        data = bytearray()
        for t in tags:
            data += bytes((t.word & 0xFF, t.word >> 8, t.set_byte, t.sid, t.playtime_ticks))
        return bytes(data)
    if cmd == Command.S_JOG:
        data = bytearray((playtime_ticks,))
        for t in tags:
            data += bytes((t.word & 0xFF, t.word >> 8, t.set_byte, t.sid))
        return bytes(data)
    raise InvalidArgumentError(f"cmd must be I_JOG or S_JOG, not {cmd!r}")


def jog_tags(packet: Packet) -> tuple[JogTag, ...]:
    """Split an I_JOG or S_JOG into its tags (S_JOG's shared playtime goes into each).

    Raises:
        ProtocolError: Not a jog, an S_JOG without its playtime byte, or data that is not
            whole tags.
    """
    d = packet.data
    if packet.cmd == Command.I_JOG:
        playtime, tags, size = None, d, I_JOG_TAG_SIZE
    elif packet.cmd == Command.S_JOG:
        if not d:
            raise ProtocolError(f"S_JOG without a playtime byte: {packet!r}")
        playtime, tags, size = d[0], d[1:], S_JOG_TAG_SIZE
    else:
        raise ProtocolError(f"not a jog: {packet!r}")
    if not tags or len(tags) % size:
        raise ProtocolError(f"jog data is not whole {size}-byte tags: {packet!r}")
    return tuple(
        JogTag(
            word=tags[i] | tags[i + 1] << 8,
            set_byte=tags[i + 2],
            sid=tags[i + 3],
            playtime_ticks=tags[i + 4] if playtime is None else playtime,
        )
        for i in range(0, len(tags), size)
    )


def _check_int(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidArgumentError(f"{name} must be an int, not {type(value).__name__}")


def _check_byte(name: str, value: int, high: int = 0xFF) -> None:
    _check_int(name, value)
    if not 0 <= value <= high:
        raise OutOfRangeError(name, value, 0, high)
