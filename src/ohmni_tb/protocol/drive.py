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

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.framing import BROADCAST_ID, Command, Packet
from ohmni_tb.protocol.messages import Memory, ReadReply, read_request, write_request

__all__ = [
    "DRIVE_PROFILE",
    "MOTOR_POSITION_MODULUS",
    "PWM_LIMIT",
    "DriveProfile",
    "DriveTorque",
    "decode_wheel_command",
    "parse_count",
    "parse_motor_position",
    "read_count",
    "read_firmware_tag",
    "read_motor_position",
    "set_torque",
    "wheel_command",
]

#: Largest PWM magnitude the drive boards take (tb_msgs: −1000..1000).
PWM_LIMIT = 1000
#: The motor position register is 14 bits and wraps.
MOTOR_POSITION_MODULUS = 1 << 14
#: JOG value bit that marks a negative PWM in continuous-rotation mode (HerkuleX layout).
_JOG_SIGN = 0x4000
#: SET byte bit that selects continuous rotation (HerkuleX layout).
_SET_TURN_MODE = 0x02


class DriveTorque(enum.IntEnum):
    """Torque states (HerkuleX values; **assumed** for the drive boards)."""

    FREE = 0x00
    BRAKE = 0x40
    ON = 0x60


@dataclass(frozen=True, slots=True)
class DriveProfile:
    """Where things live on a drive board. Change this table after a capture.

    Attributes:
        count_addr: RAM address of the accumulated wheel count (confirmed).
        count_size: Its size in bytes, int32 LE (confirmed).
        motor_position_addr: RAM address of the 14-bit motor position (confirmed).
        motor_position_size: Its size in bytes (confirmed).
        tag_addr: EEP address of the firmware tag, read with length 0 (confirmed).
        torque_addr: RAM address of the torque control (**assumed**: HerkuleX RAM 52).
        wheel_jog: Whether the wheel command is one S_JOG in continuous-rotation mode to
            both boards (**assumed**).
        right_mirrored: The right wheel counts and is commanded mirrored (confirmed).
    """

    count_addr: int = 59
    count_size: int = 4
    motor_position_addr: int = 58
    motor_position_size: int = 2
    tag_addr: int = 0xF1
    torque_addr: int = 52
    wheel_jog: bool = True
    right_mirrored: bool = True


#: The profile in use. ``assumed``: torque_addr, wheel_jog; the rest is confirmed.
DRIVE_PROFILE = DriveProfile()


def _check_drive_sid(sid: int) -> None:
    if sid not in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
        raise OutOfRangeError("drive sid", sid, 0, 1)


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
    """Set a drive board's torque state (**assumed** register). Broadcast allowed."""
    if sid not in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, BROADCAST_ID):
        raise OutOfRangeError("drive sid", sid, 0, 1)
    return write_request(sid, profile.torque_addr, bytes((DriveTorque(torque),)))


def wheel_command(left_pwm: int, right_pwm: int, *, mirror_right: bool = True) -> Packet:
    """One packet that sets both wheels' PWM (**assumed** layout).

    The boards are assumed to take a HerkuleX S_JOG in continuous-rotation mode, sent to
    broadcast with both board ids in its tags, the PWM as magnitude plus the 0x4000
    sign bit. ``left_pwm`` and ``right_pwm`` are *forward-positive*; the right wheel is
    mirrored here, so ``wheel_command(250, 250)`` drives forward as the vendor's
    ``manual_move +250 -250`` does.

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
    right_raw = -right_pwm if mirror_right else right_pwm
    data = bytearray((0,))  # playtime: ignored in continuous rotation
    for sid, pwm in ((DeviceId.LEFT_DRIVE, left_pwm), (DeviceId.RIGHT_DRIVE, right_raw)):
        jog = abs(pwm) | (_JOG_SIGN if pwm < 0 else 0)
        data += bytes((jog & 0xFF, jog >> 8, _SET_TURN_MODE, sid))
    return Packet(BROADCAST_ID, Command.S_JOG, bytes(data))


def decode_wheel_command(packet: Packet) -> dict[int, int]:
    """The raw (board-side, not un-mirrored) PWM per drive sid in a wheel S_JOG.

    Used by the simulator and the bus monitor. Tags for other ids are ignored.

    Raises:
        MalformedReplyError: The packet is not an S_JOG of whole 4-byte tags.
    """
    if packet.cmd != Command.S_JOG or (len(packet.data) - 1) % 4:
        raise MalformedReplyError(f"not an S_JOG: {packet!r}")
    out: dict[int, int] = {}
    d = packet.data
    for i in range(1, len(d), 4):
        jog = d[i] | d[i + 1] << 8
        set_byte, sid = d[i + 2], d[i + 3]
        if sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE) and set_byte & _SET_TURN_MODE:
            magnitude = jog & (_JOG_SIGN - 1)
            out[sid] = -magnitude if jog & _JOG_SIGN else magnitude
    return out


def _expect(reply: ReadReply, addr: int, size: int) -> None:
    if reply.addr != addr or reply.length != size:
        raise MalformedReplyError(
            f"expected {size} bytes at RAM {addr}, got {reply.length} at {reply.addr}"
        )
