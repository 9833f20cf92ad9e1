"""Drive boards (sid 0 left, 1 right): wheel counts, motor position, the wheel command.

Every address and layout is in :data:`DRIVE_PROFILE`; the ones marked ``assumed`` are the
project's guess until a capture from a real robot says otherwise (docs/hardware.md says
how to capture one). Confirmed: RAM 59 is the accumulated wheel count (int32 LE), RAM 58
the 14-bit motor position, EEP 0xF1 the firmware tag, and the right wheel counts and is
commanded mirrored (forward = left +, right −).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from ohmni_tb._checks import show
from ohmni_tb.errors import (
    InvalidArgumentError,
    MalformedReplyError,
    OutOfRangeError,
    ProtocolError,
)
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.framing import BROADCAST_ID, Command, Packet
from ohmni_tb.protocol.jog import (
    JogSet,
    JogTag,
    decode_jog_word,
    encode_jog_word,
    jog_data,
    jog_tags,
)
from ohmni_tb.protocol.messages import Memory, ReadReply, read_request, write_request

__all__ = [
    "DRIVE_PROFILE",
    "MOTOR_POSITION_MODULUS",
    "PWM_LIMIT",
    "DriveProfile",
    "DriveTorque",
    "WheelJogForm",
    "decode_wheel_command",
    "parse_count",
    "parse_motor_position",
    "read_count",
    "read_firmware_tag",
    "read_motor_position",
    "set_board_id",
    "set_torque",
    "wheel_command",
]

# The two device facts below are defined here and nowhere else: control.defaults and the
# simulator import them, so a measurement changes one line.

#: Largest PWM magnitude the drive boards take (tb_msgs: −1000..1000).
PWM_LIMIT = 1000
#: The motor position register is 14 bits and wraps once per motor turn, so this is also
#: the encoder's ticks per motor turn.
MOTOR_POSITION_MODULUS = 1 << 14
#: SET byte of a wheel tag: continuous rotation, no stop, LEDs off (HerkuleX layout).
_WHEEL_SET = JogSet(turn=True).to_byte()
_DRIVE_SIDS = (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE)


class DriveTorque(enum.IntEnum):
    """Torque states (HerkuleX values; **assumed** for the drive boards)."""

    FREE = 0x00
    BRAKE = 0x40
    ON = 0x60


_TORQUES = frozenset(DriveTorque)


class WheelJogForm(enum.IntEnum):
    """The packet the wheel command is assumed to be (**assumed**; a capture decides).

    Either way it goes to broadcast, in continuous-rotation mode, with one tag per board
    naming the board's id (see :mod:`ohmni_tb.protocol.jog`). The value is the command
    code.
    """

    #: One S_JOG: a shared playtime byte (0), then a 4-byte tag per board.
    S_JOG = int(Command.S_JOG)
    #: One I_JOG: a 5-byte tag per board, each with its own playtime (0).
    I_JOG = int(Command.I_JOG)


@dataclass(frozen=True, slots=True)
class DriveProfile:
    """Where things live on a drive board (settings ``wheel_form``, ``right_mirrored``,
    ``drive_torque_addr``; ``ohmni probe`` finds the wheel form).

    Attributes:
        count_addr: RAM address of the accumulated wheel count (confirmed).
        count_size: Its size in bytes, int32 LE (confirmed).
        motor_position_addr: RAM address of the 14-bit motor position (confirmed).
        motor_position_size: Its size in bytes (confirmed).
        tag_addr: EEP address of the firmware tag, read with length 0 (confirmed).
        torque_addr: RAM address of the torque control (**assumed**: HerkuleX RAM 52).
        wheel_form: Which packet carries the wheel command (**assumed**: one S_JOG).
            :func:`wheel_command` builds it and :func:`decode_wheel_command` (the
            simulator, the bus monitor) reads it, so changing it changes both sides.
        right_mirrored: The right wheel counts and is commanded mirrored (confirmed):
            :func:`wheel_command` negates the right PWM, and the simulated right motor is
            mounted mirrored.
        id_eep_addr: EEP address of the board's bus id, one byte, read at power-up
            (**assumed**: HerkuleX EEP 6; tb_control's ``reset_servo_id`` changes a motor
            board's id, its bytes are not public).
        id_ram_addr: RAM address of the id the board answers to now (**assumed**:
            HerkuleX RAM 0).

    Raises:
        InvalidArgumentError: ``wheel_form`` is not a :class:`WheelJogForm`, or
            ``right_mirrored`` is not a bool.
        OutOfRangeError: An address is not 0..255.
    """

    count_addr: int = 59
    count_size: int = 4
    motor_position_addr: int = 58
    motor_position_size: int = 2
    tag_addr: int = 0xF1
    torque_addr: int = 52
    wheel_form: WheelJogForm = WheelJogForm.S_JOG
    right_mirrored: bool = True
    id_eep_addr: int = 6
    id_ram_addr: int = 0

    def __post_init__(self) -> None:
        for name in (
            "count_addr",
            "motor_position_addr",
            "tag_addr",
            "torque_addr",
            "id_eep_addr",
            "id_ram_addr",
        ):
            addr = getattr(self, name)
            if isinstance(addr, bool) or not isinstance(addr, int):
                raise InvalidArgumentError(f"drive board {name} must be an int, not {addr!r}")
            if not 0 <= addr <= 0xFF:
                raise OutOfRangeError(f"drive board {name}", addr, 0, 0xFF)
        form: object = self.wheel_form  # typed, but a table edited by hand may hold anything
        if not isinstance(form, WheelJogForm):
            raise InvalidArgumentError(
                f"wheel_form must be one of {[f.name for f in WheelJogForm]}, not {form!r}"
            )
        if not isinstance(self.right_mirrored, bool):
            raise InvalidArgumentError(
                f"right_mirrored must be a bool, not {self.right_mirrored!r}"
            )


#: The profile in use. ``assumed``: torque_addr, wheel_form; the rest is confirmed.
DRIVE_PROFILE = DriveProfile()


def _check_drive_sid(sid: int, *, allow_broadcast: bool = False) -> None:
    # A bool or a float equal to 0 or 1 is not a board id: only true ints pass.
    allowed = (*_DRIVE_SIDS, BROADCAST_ID) if allow_broadcast else _DRIVE_SIDS
    if isinstance(sid, bool) or not isinstance(sid, int) or sid not in allowed:
        raise OutOfRangeError(
            "drive sid", sid, 0, 1, "(or 0xFE, broadcast)" if allow_broadcast else ""
        )


def read_count(sid: int, profile: DriveProfile = DRIVE_PROFILE) -> Packet:
    """Read the accumulated wheel count of drive board ``sid``."""
    _check_drive_sid(sid)
    return read_request(sid, profile.count_addr, profile.count_size)


def parse_count(reply: ReadReply, profile: DriveProfile = DRIVE_PROFILE) -> int:
    """The raw int32 count of a :func:`read_count` reply (not mirrored here).

    Raises:
        MalformedReplyError: The reply is for another register or size.
    """
    _expect(reply, profile.count_addr, profile.count_size)
    return int.from_bytes(reply.data, "little", signed=True)


def read_motor_position(sid: int, profile: DriveProfile = DRIVE_PROFILE) -> Packet:
    """Read the 14-bit motor position of drive board ``sid``."""
    _check_drive_sid(sid)
    return read_request(sid, profile.motor_position_addr, profile.motor_position_size)


def parse_motor_position(reply: ReadReply, profile: DriveProfile = DRIVE_PROFILE) -> int:
    """The motor position 0..16383 of a :func:`read_motor_position` reply.

    Raises:
        MalformedReplyError: The reply is for another register, or out of 14 bits.
    """
    _expect(reply, profile.motor_position_addr, profile.motor_position_size)
    value = int.from_bytes(reply.data, "little")
    if value >= MOTOR_POSITION_MODULUS:
        raise MalformedReplyError(f"motor position {value} does not fit 14 bits")
    return value


def read_firmware_tag(sid: int, tag_addr: int = DRIVE_PROFILE.tag_addr) -> Packet:
    """Read a board's firmware tag (EEP 0xF1 with length 0; the reply sets the length)."""
    return read_request(sid, tag_addr, 0, Memory.EEP)


def set_torque(sid: int, torque: DriveTorque, profile: DriveProfile = DRIVE_PROFILE) -> Packet:
    """Set a drive board's torque state (**assumed** register). Broadcast allowed.

    Raises:
        OutOfRangeError: ``sid`` is not 0, 1 or broadcast.
        InvalidArgumentError: ``torque`` is not one of :class:`DriveTorque`.
    """
    _check_drive_sid(sid, allow_broadcast=True)
    given: object = torque  # typed DriveTorque, but callers may pass any value
    if isinstance(given, bool) or not isinstance(given, int) or given not in _TORQUES:
        allowed = ", ".join(f"{t.name} (0x{t.value:02X})" for t in DriveTorque)
        raise InvalidArgumentError(f"torque={show(torque)} is not one of {allowed}")
    return write_request(sid, profile.torque_addr, bytes((DriveTorque(torque),)))


def wheel_command(left_pwm: int, right_pwm: int, profile: DriveProfile = DRIVE_PROFILE) -> Packet:
    """One packet that sets both wheels' PWM (**assumed** layout, from ``profile``).

    The boards are assumed to take a HerkuleX jog in continuous-rotation mode, sent to
    broadcast with both board ids in its tags, the PWM as magnitude plus the 0x4000
    sign bit; ``profile.wheel_form`` says whether it is an S_JOG or an I_JOG.
    ``left_pwm`` and ``right_pwm`` are *forward-positive*; with ``profile.right_mirrored``
    (the robot's case) the right wheel is mirrored here, so ``wheel_command(250, 250)``
    drives forward as the vendor's ``manual_move +250 -250`` does.

    Raises:
        OutOfRangeError: A PWM is outside −1000..1000; nothing is built.
        InvalidArgumentError: A PWM is not an integer.
    """
    for name, value in (("left_pwm", left_pwm), ("right_pwm", right_pwm)):
        if isinstance(value, float) and not math.isfinite(value):
            raise OutOfRangeError(name, value, -PWM_LIMIT, PWM_LIMIT)
        if not isinstance(value, int) or isinstance(value, bool):
            raise InvalidArgumentError(f"{name} must be an int, not {value!r}")
        if not -PWM_LIMIT <= value <= PWM_LIMIT:
            raise OutOfRangeError(name, value, -PWM_LIMIT, PWM_LIMIT)
    right_raw = -right_pwm if profile.right_mirrored else right_pwm
    tags = [
        JogTag(encode_jog_word(pwm, turn=True), _WHEEL_SET, sid)
        for sid, pwm in zip(_DRIVE_SIDS, (left_pwm, right_raw), strict=True)
    ]
    # Playtime 0: a jog in continuous rotation ignores it.
    cmd = Command(profile.wheel_form)
    return Packet(BROADCAST_ID, cmd, jog_data(cmd, tags))


def set_board_id(
    sid: int, new_sid: int, profile: DriveProfile = DRIVE_PROFILE
) -> tuple[Packet, Packet]:
    """The writes that give board ``sid`` the id ``new_sid``: EEP (kept over a power
    cycle), then RAM (it answers to the new id at once). **Assumed** layout
    (:attr:`DriveProfile.id_eep_addr`).

    Raises:
        OutOfRangeError: An id is not 0..253.
    """
    for name, value in (("sid", sid), ("new_sid", new_sid)):
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < BROADCAST_ID:
            raise OutOfRangeError(name, value, 0, BROADCAST_ID - 1)
    data = bytes((new_sid,))
    return (
        write_request(sid, profile.id_eep_addr, data, Memory.EEP),
        write_request(sid, profile.id_ram_addr, data),
    )


def decode_wheel_command(packet: Packet, profile: DriveProfile = DRIVE_PROFILE) -> dict[int, int]:
    """The raw (board-side, not un-mirrored) PWM per drive sid in a wheel command.

    Read as ``profile`` says the boards take it: the simulator's drive boards and the bus
    monitor call this, so they follow the same table as :func:`wheel_command`. Tags for
    other ids, tags in position mode and tags marked "jog invalid" are ignored.

    Raises:
        MalformedReplyError: The packet is not the profile's jog, is not whole tags, or a
            drive board's tag sets reserved bits.
    """
    form = profile.wheel_form
    if packet.cmd != form:
        raise MalformedReplyError(f"not a wheel command ({form.name} assumed): {packet!r}")
    out: dict[int, int] = {}
    try:
        for tag in jog_tags(packet):
            if tag.sid not in _DRIVE_SIDS:
                continue
            flags = JogSet.from_byte(tag.set_byte)
            if flags.turn and not flags.invalid:
                out[tag.sid] = decode_jog_word(tag.word, turn=True)
    except ProtocolError as exc:
        raise MalformedReplyError(f"bad wheel command: {exc}") from exc
    return out


def _expect(reply: ReadReply, addr: int, size: int) -> None:
    if reply.addr != addr or reply.length != size:
        raise MalformedReplyError(
            f"expected {size} bytes at RAM {addr}, got {reply.length} at {reply.addr}"
        )
