"""HerkuleX request builders and reply parsing (sans-IO): every builder returns a Packet.

Nothing here touches a port or a clock; every argument is checked before a
:class:`~ohmni_tb.protocol.Packet` exists, so a bad value never reaches the wire.

JOG tags (I_JOG: 5 bytes per servo, S_JOG: 4 bytes after one shared playtime byte) are
encoded by :mod:`ohmni_tb.protocol.jog`, the one place their bits are written down (the
drive boards' wheel command uses the same codec). On these models a position is
0..1023 and a turn-mode PWM -1023..1023.

Whether a request gets a reply is decided in one place, :func:`reply_expected`
(re-exported from :mod:`ohmni_tb.protocol`).
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final

from ohmni_tb._checks import show
from ohmni_tb.errors import (
    InvalidArgumentError,
    MalformedReplyError,
    OutOfRangeError,
    ProtocolError,
)
from ohmni_tb.herkulex.registers import Led, Model, Register, model_from_bytes, resolve
from ohmni_tb.herkulex.units import check_playtime_ticks
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Memory,
    Packet,
    ReadReply,
    StatusDetail,
    StatusError,
    StatusReply,
    check_sid,
    read_request,
    write_request,
)
from ohmni_tb.protocol.framing import MAX_DATA_SIZE
from ohmni_tb.protocol.jog import (
    I_JOG_TAG_SIZE,
    S_JOG_TAG_SIZE,
    TURN_SIGN_BIT,
    JogSet,
    JogTag,
    decode_jog_word,
    encode_jog_word,
    jog_data,
    jog_tags,
)

__all__ = [
    "MAX_I_JOG_TARGETS",
    "MAX_PWM",
    "MAX_S_JOG_TARGETS",
    "TURN_SIGN_BIT",
    "JogMode",
    "JogTarget",
    "Reply",
    "clear_status",
    "decode_jog",
    "eep_read",
    "eep_write",
    "eep_write_many",
    "i_jog",
    "model_read",
    "parse_model",
    "parse_reply",
    "ram_read",
    "ram_write",
    "ram_write_many",
    "reboot",
    "rollback",
    "s_jog",
    "stat",
]

#: The largest PWM magnitude (and position) a jog word carries on these models.
MAX_PWM: Final = 1023
_MAX_POSITION: Final = 1023
#: As many 5-byte tags as fit in one packet's data.
MAX_I_JOG_TARGETS: Final = MAX_DATA_SIZE // I_JOG_TAG_SIZE
#: As many 4-byte tags as fit after the shared playtime byte.
MAX_S_JOG_TARGETS: Final = (MAX_DATA_SIZE - 1) // S_JOG_TAG_SIZE

_READS: Final = frozenset({Command.RAM_READ, Command.EEP_READ})


class JogMode(enum.IntEnum):
    """What a jog's value means; RAM 56 (control mode) reports the same codes."""

    #: The value is a goal position (calibrated, 0..1023) reached over the playtime.
    POSITION = 0
    #: Continuous rotation: the value is a signed PWM, -1023..1023.
    TURN = 1


@dataclass(frozen=True, slots=True)
class JogTarget:
    """One servo's part of an I_JOG or S_JOG.

    Attributes:
        sid: The servo's id (0..0xFD; a tag cannot name broadcast).
        value: The goal position (0..1023, the calibrated coordinate of RAM 58) in
            position mode, or the signed PWM (-1023..1023) in turn mode.
        mode: Position or continuous turn.
        led: LEDs to light while the jog runs.
        stop: Stop and hold where the servo is (the value is ignored by the servo).
        playtime_ticks: Time to reach the goal, 0..254 ticks of 11.2 ms
            (:func:`~ohmni_tb.herkulex.units.playtime_ticks_from_s` converts seconds).
            S_JOG has one playtime for every servo; there this must be 0 or equal it.

    Raises:
        InvalidArgumentError: A field has the wrong type.
        OutOfRangeError: A field is out of range; nothing was built.
    """

    sid: int
    value: int
    mode: JogMode = JogMode.POSITION
    led: Led = Led.NONE
    stop: bool = False
    playtime_ticks: int = 0

    def __post_init__(self) -> None:
        check_sid(self.sid, allow_broadcast=False)
        if self.mode not in (JogMode.POSITION, JogMode.TURN):
            raise InvalidArgumentError(f"mode must be a JogMode, not {self.mode!r}")
        if isinstance(self.value, bool) or not isinstance(self.value, int):
            raise InvalidArgumentError(
                f"jog value must be an int, not {type(self.value).__name__} {self.value!r}"
            )
        if self.mode == JogMode.TURN:
            if not -MAX_PWM <= self.value <= MAX_PWM:
                raise OutOfRangeError("pwm", self.value, -MAX_PWM, MAX_PWM)
        elif not 0 <= self.value <= _MAX_POSITION:
            raise OutOfRangeError("position", self.value, 0, _MAX_POSITION, "count")
        led: object = self.led  # typed Led, but callers may pass anything at run time
        if isinstance(led, bool) or not isinstance(led, int) or not 0 <= led <= 0x07:
            raise InvalidArgumentError(f"led must be Led flags, not {led!r}")
        if not isinstance(self.stop, bool):
            raise InvalidArgumentError(f"stop must be a bool, not {self.stop!r}")
        check_playtime_ticks(self.playtime_ticks)

    @property
    def jog_word(self) -> int:
        """The 16-bit jog value as sent (turn mode: sign bit 0x4000 plus magnitude)."""
        return encode_jog_word(self.value, turn=self.mode == JogMode.TURN)

    @property
    def set_byte(self) -> int:
        """The SET byte: stop, mode and LED bits."""
        return JogSet(turn=self.mode == JogMode.TURN, stop=self.stop, led=int(self.led)).to_byte()

    @classmethod
    def from_wire(
        cls, jog_word: int, set_byte: int, sid: int, playtime_ticks: int
    ) -> JogTarget | None:
        """Decode one tag as a servo does; ``None`` for a tag marked "jog invalid".

        Raises:
            ProtocolError: Reserved bits are set or a field is out of range.
        """
        try:
            flags = JogSet.from_byte(set_byte)
            value = decode_jog_word(jog_word, turn=flags.turn)
        except ProtocolError as exc:
            raise ProtocolError(f"jog tag for sid {show(sid)}: {exc}") from exc
        if flags.invalid:
            return None
        try:
            return cls(
                sid=sid,
                value=value,
                mode=JogMode.TURN if flags.turn else JogMode.POSITION,
                led=Led(flags.led),
                stop=flags.stop,
                playtime_ticks=playtime_ticks,
            )
        except InvalidArgumentError as exc:
            raise ProtocolError(f"jog tag out of range: {exc}") from exc

    def to_wire(self) -> JogTag:
        """This target as a wire tag (:mod:`ohmni_tb.protocol.jog`)."""
        return JogTag(self.jog_word, self.set_byte, self.sid, self.playtime_ticks)


def i_jog(*targets: JogTarget) -> Packet:
    """Build an I_JOG: each servo with its own playtime.

    A single target goes to its servo's id (which may acknowledge under ACK policy 2);
    several go to broadcast with the real ids in the tags, so no servo replies.

    Raises:
        InvalidArgumentError: No targets, a target is not a JogTarget, or two name the
            same servo.
        OutOfRangeError: More than 43 targets.
    """
    sid = _jog_sid(targets, MAX_I_JOG_TARGETS)
    return Packet(sid, Command.I_JOG, jog_data(Command.I_JOG, [t.to_wire() for t in targets]))


def s_jog(playtime_ticks: int, *targets: JogTarget) -> Packet:
    """Build an S_JOG: every servo starts together and arrives after ``playtime_ticks``.

    Args:
        playtime_ticks: The shared playtime, 0..254 ticks of 11.2 ms.
        *targets: The servos; their own ``playtime_ticks`` must be 0 or equal the
            shared one (a different value would be silently ignored otherwise).

    Raises:
        InvalidArgumentError: No targets, duplicates, or a conflicting target playtime.
        OutOfRangeError: The playtime or the number of targets (max 53) is out of range.
    """
    check_playtime_ticks(playtime_ticks)
    sid = _jog_sid(targets, MAX_S_JOG_TARGETS)
    for t in targets:
        if t.playtime_ticks not in (0, playtime_ticks):
            raise InvalidArgumentError(
                f"target sid {t.sid} has playtime_ticks={t.playtime_ticks}, but S_JOG uses "
                f"one playtime for all ({playtime_ticks}); use i_jog for per-servo times"
            )
    tags = [t.to_wire() for t in targets]
    return Packet(sid, Command.S_JOG, jog_data(Command.S_JOG, tags, playtime_ticks=playtime_ticks))


def decode_jog(packet: Packet) -> tuple[JogTarget, ...]:
    """Decode the tags of an I_JOG or S_JOG request (the servo's side).

    S_JOG's shared playtime is copied into every target. Tags marked "jog invalid" are
    left out.

    Raises:
        ProtocolError: Not a jog, the data is not whole tags, or a tag is out of range.
    """
    out: list[JogTarget] = []
    for tag in jog_tags(packet):
        target = JogTarget.from_wire(tag.word, tag.set_byte, tag.sid, tag.playtime_ticks)
        if target is not None:
            out.append(target)
    return tuple(out)


def ram_read(
    sid: int, register: Register | str | int, *, through: Register | str | int | None = None
) -> Packet:
    """Build a RAM_READ of one register, or of every byte from it through ``through``.

    Args:
        sid: The servo (0..0xFD). Broadcast is refused: every servo would answer at once.
        register: The first register (an object from :data:`RAM`, its name or address).
        through: The last register to include, for a block read in one transaction.

    Raises:
        InvalidArgumentError: Unknown register, an EEP register, or ``through`` before
            ``register``.
        OutOfRangeError: ``sid`` is out of range, or broadcast.
    """
    return _read(Memory.RAM, sid, register, through)


def eep_read(
    sid: int, register: Register | str | int, *, through: Register | str | int | None = None
) -> Packet:
    """Build an EEP_READ; see :func:`ram_read`."""
    return _read(Memory.EEP, sid, register, through)


def ram_write(sid: int, register: Register | str | int, value: int) -> Packet:
    """Build a RAM_WRITE of one register (acts at once).

    Args:
        sid: The servo (0..0xFD), or 0xFE for every servo.
        register: A register object from :data:`RAM`, its name, or its address.
        value: The value, checked against the register's range.

    Raises:
        InvalidArgumentError: Unknown or read-only register, an EEP register, a value
            that is not an int or not one of the register's choices.
        OutOfRangeError: ``sid`` or ``value`` is out of range.
    """
    return ram_write_many(sid, {register: value})


def eep_write(sid: int, register: Register | str | int, value: int) -> Packet:
    """Build an EEP_WRITE of one register (acts after REBOOT); see :func:`ram_write`."""
    return eep_write_many(sid, {register: value})


def ram_write_many(sid: int, values: Mapping[Register | str | int, int]) -> Packet:
    """Build one RAM_WRITE of several adjacent registers (e.g. Kp and Kd together).

    Raises:
        InvalidArgumentError: The registers leave a gap, overlap, or one is read-only
            or unknown.
        OutOfRangeError: ``sid`` or a value is out of range.
    """
    return _write(Memory.RAM, sid, values)


def eep_write_many(sid: int, values: Mapping[Register | str | int, int]) -> Packet:
    """Build one EEP_WRITE of several adjacent registers; see :func:`ram_write_many`."""
    return _write(Memory.EEP, sid, values)


def clear_status(sid: int) -> Packet:
    """Build the RAM_WRITE that clears RAM 48/49 (``addr 48, len 2, 00 00``).

    This is how a latched fault (over-temperature, overload…) is acknowledged; turn the
    torque on again afterwards.
    """
    return ram_write_many(sid, {"status_error": 0, "status_detail": 0})


def model_read(sid: int) -> Packet:
    """Build the EEP_READ of addr 0, length 2 that :func:`parse_model` decodes."""
    return eep_read(sid, "model_no1", through="model_no2")


def parse_model(reply: Reply) -> Model:
    """The model named by the reply to :func:`model_read` (first byte = model no1).

    Raises:
        InvalidArgumentError: The reply does not hold EEP 0..1, or names an unknown model.
    """
    if reply.memory is not Memory.EEP or reply.addr != 0 or len(reply.data) != 2:
        raise InvalidArgumentError(f"not a reply to model_read(): {reply!r}")
    return model_from_bytes(reply.data)


def stat(sid: int) -> Packet:
    """Build a STAT. It is answered whatever the ACK policy.

    Broadcast is allowed but every servo answers at once and the replies collide; use
    it only with one servo on the line.

    Raises:
        OutOfRangeError: ``sid`` is out of range.
    """
    check_sid(sid, allow_broadcast=True)
    return Packet(sid, Command.STAT)


def reboot(sid: int) -> Packet:
    """Build a REBOOT: the servo copies EEP to RAM and starts with torque free.

    Raises:
        OutOfRangeError: ``sid`` is out of range.
    """
    check_sid(sid, allow_broadcast=True)
    return Packet(sid, Command.REBOOT)


def rollback(sid: int, keep_id: bool = True, keep_baud: bool = True) -> Packet:
    """Build a ROLLBACK to factory EEP values.

    Args:
        sid: The servo, or 0xFE for every servo.
        keep_id: Keep the servo's id (otherwise it becomes 0xFD).
        keep_baud: Keep the baud rate (otherwise it becomes 115,200).

    Raises:
        OutOfRangeError: ``sid`` is out of range.
    """
    check_sid(sid, allow_broadcast=True)
    return Packet(sid, Command.ROLLBACK, bytes((int(bool(keep_id)), int(bool(keep_baud)))))


@dataclass(frozen=True, slots=True)
class Reply:
    """A parsed HerkuleX reply.

    Read replies carry ``memory``, ``addr`` and ``data``. Replies made of the two status
    bytes only (STAT always; writes, jogs, ROLLBACK and REBOOT under ACK policy 2) have
    ``memory`` and ``addr`` ``None`` and empty ``data``.

    Attributes:
        sid: The servo that answered.
        cmd: The request the reply answers.
        status_error: The servo's RAM 48 when it replied.
        status_detail: The servo's RAM 49 when it replied.
        memory: RAM or EEP for a read reply, else ``None``.
        addr: The first address read, else ``None``.
        data: The register bytes read, else ``b""``.
    """

    sid: int
    cmd: Command
    status_error: StatusError
    status_detail: StatusDetail
    memory: Memory | None = None
    addr: int | None = None
    data: bytes = b""

    def value(self, register: Register | str) -> int:
        """Decode one register from a read reply's bytes.

        Raises:
            InvalidArgumentError: Not a read reply, or the register is not in the bytes.
        """
        if self.memory is None or self.addr is None:
            raise InvalidArgumentError(f"a {self.cmd.name} reply carries no register bytes")
        reg = resolve(register, self.memory)
        start = reg.addr - self.addr
        if start < 0 or reg.end > self.addr + len(self.data):
            raise InvalidArgumentError(
                f"{reg.name} ({self.memory.name} {reg.addr}..{reg.end - 1}) is not in this "
                f"reply ({self.addr}..{self.addr + len(self.data) - 1})"
            )
        return reg.decode(self.data[start : start + reg.size])


def parse_reply(packet: Packet) -> Reply:
    """Parse any HerkuleX reply.

    Raises:
        MalformedReplyError: Not a reply, an unknown command, or a layout that does not
            fit the command (a read reply's length byte disagrees with its bytes, a status
            reply without exactly two bytes).
    """
    if not packet.is_reply:
        raise MalformedReplyError(f"not a reply: {packet!r}")
    try:
        cmd = Command(packet.cmd & ~REPLY_FLAG)
    except ValueError:
        raise MalformedReplyError(f"reply to an unknown command: {packet!r}") from None
    if cmd in _READS:
        rr = ReadReply.parse(packet)
        return Reply(
            sid=rr.sid,
            cmd=cmd,
            status_error=rr.status_error,
            status_detail=rr.status_detail,
            memory=rr.memory,
            addr=rr.addr,
            data=rr.data,
        )
    sr = StatusReply.parse(packet)
    return Reply(sid=sr.sid, cmd=cmd, status_error=sr.status_error, status_detail=sr.status_detail)


# -- private ------------------------------------------------------------------------


def _jog_sid(targets: tuple[JogTarget, ...], max_targets: int) -> int:
    """The packet id for these tags: their one id, or broadcast for several."""
    if not targets:
        raise InvalidArgumentError("a jog needs at least one JogTarget")
    for t in targets:
        if not isinstance(t, JogTarget):
            raise InvalidArgumentError(f"jog targets must be JogTarget, not {type(t).__name__}")
    if len(targets) > max_targets:
        raise OutOfRangeError("len(targets)", len(targets), 1, max_targets)
    sids = [t.sid for t in targets]
    if len(set(sids)) != len(sids):
        raise InvalidArgumentError(f"two jog targets name the same servo: {sids}")
    # One servo: address it, so it may acknowledge under ACK policy 2. Several: broadcast,
    # since a packet to one id is ignored by every other servo.
    return sids[0] if len(sids) == 1 else BROADCAST_ID


def _read(
    memory: Memory,
    sid: int,
    register: Register | str | int,
    through: Register | str | int | None,
) -> Packet:
    first = resolve(register, memory)
    last = first if through is None else resolve(through, memory)
    if last.end <= first.addr:
        raise InvalidArgumentError(f"through={last.name} comes before {first.name}")
    return read_request(sid, first.addr, last.end - first.addr, memory)


def _write(memory: Memory, sid: int, values: Mapping[Register | str | int, int]) -> Packet:
    regs = sorted(((resolve(r, memory), v) for r, v in values.items()), key=lambda rv: rv[0].addr)
    if not regs:
        raise InvalidArgumentError("nothing to write")
    data = bytearray()
    next_addr = regs[0][0].addr
    for reg, value in regs:
        if reg.addr != next_addr:
            raise InvalidArgumentError(
                f"{reg.name} does not follow the register before it; one write covers one "
                f"gapless block"
            )
        data += reg.encode(value)
        next_addr = reg.end
    return write_request(sid, regs[0][0].addr, bytes(data), memory)
