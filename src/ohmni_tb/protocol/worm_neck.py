"""Worm-gear neck (sid 4): target position and feedback.

Confirmed: the command range −127000 (up) … 0 (neutral) … 120000 (down), and that a
target beyond it stalls the motor until the robot is power-cycled — so targets outside the
range are refused here, before a byte is built. **Assumed**: the addresses and layouts in
:data:`WORM_PROFILE`.
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.framing import Packet
from ohmni_tb.protocol.messages import ReadReply, read_request, write_request

__all__ = [
    "WORM_MAX",
    "WORM_MIN",
    "WORM_PROFILE",
    "WormFeedback",
    "WormFlags",
    "WormProfile",
    "check_worm_target",
    "encode_feedback",
    "parse_feedback",
    "read_feedback",
    "set_target",
]

#: Fully up. Beyond it the motor stalls until a power cycle.
WORM_MIN = -127_000
#: Fully down.
WORM_MAX = 120_000

_FEEDBACK = struct.Struct("<iB")


class WormFlags(enum.IntFlag):
    """Feedback flag bits (**assumed**)."""

    NONE = 0
    MOVING = 0x01
    STALLED = 0x02


@dataclass(frozen=True, slots=True)
class WormProfile:
    """Where things live on the worm neck (settings ``worm_target_addr``,
    ``worm_feedback_addr``; ``ohmni probe`` judges the feedback).

    Attributes:
        target_addr: RAM address of the int32 LE target (**assumed**).
        feedback_addr: RAM address of position int32 LE + flags u8 (**assumed**).

    Raises:
        OutOfRangeError: An address is not 0..255.
    """

    target_addr: int = 0x70
    feedback_addr: int = 0x74

    def __post_init__(self) -> None:
        for name, addr in (
            ("target_addr", self.target_addr),
            ("feedback_addr", self.feedback_addr),
        ):
            if isinstance(addr, bool) or not isinstance(addr, int):
                raise InvalidArgumentError(f"worm neck {name} must be an int, not {addr!r}")
            if not 0 <= addr <= 0xFF:
                raise OutOfRangeError(f"worm neck {name}", addr, 0, 0xFF)


WORM_PROFILE = WormProfile()


@dataclass(frozen=True, slots=True)
class WormFeedback:
    """What the worm neck reports.

    Attributes:
        position: Raw position, −127000 (up) … 120000 (down).
        flags: Moving / stalled.
    """

    position: int
    flags: WormFlags

    @property
    def moving(self) -> bool:
        """The neck is travelling to its target."""
        return bool(self.flags & WormFlags.MOVING)

    @property
    def stalled(self) -> bool:
        """The motor stalled; only a power cycle clears it."""
        return bool(self.flags & WormFlags.STALLED)


def check_worm_target(position: int) -> int:
    """Return ``position`` if it is a valid worm-neck target.

    Raises:
        OutOfRangeError: Outside −127000…120000 (the hardware would stall).
        InvalidArgumentError: Not an integer.
    """
    if not isinstance(position, int) or isinstance(position, bool):
        raise InvalidArgumentError(f"worm neck position must be an int, not {position!r}")
    if not WORM_MIN <= position <= WORM_MAX:
        raise OutOfRangeError("worm neck position", position, WORM_MIN, WORM_MAX, "raw")
    return position


def set_target(position: int, profile: WormProfile = WORM_PROFILE) -> Packet:
    """Move the worm neck to ``position`` (range-checked first)."""
    check_worm_target(position)
    return write_request(
        DeviceId.WORM_NECK, profile.target_addr, position.to_bytes(4, "little", signed=True)
    )


def read_feedback(profile: WormProfile = WORM_PROFILE) -> Packet:
    """Read the worm neck's position and flags."""
    return read_request(DeviceId.WORM_NECK, profile.feedback_addr, _FEEDBACK.size)


def parse_feedback(reply: ReadReply, profile: WormProfile = WORM_PROFILE) -> WormFeedback:
    """Decode a :func:`read_feedback` reply.

    Raises:
        MalformedReplyError: Wrong address or size.
    """
    if reply.addr != profile.feedback_addr or reply.length != _FEEDBACK.size:
        raise MalformedReplyError(
            f"expected {_FEEDBACK.size} feedback bytes at RAM 0x{profile.feedback_addr:02X}, "
            f"got {reply.length} at 0x{reply.addr:02X}"
        )
    position, flags = _FEEDBACK.unpack(reply.data)
    return WormFeedback(position=position, flags=WormFlags(flags & 0x03))


def encode_feedback(feedback: WormFeedback) -> bytes:
    """The feedback bytes (the simulated worm neck answers with these).

    Raises:
        InvalidArgumentError: The position or the flags are not an int.
        OutOfRangeError: The position does not fit int32, or the flags a byte.
    """
    position, flags = feedback.position, feedback.flags
    for name, value in (("worm neck position", position), ("flags", flags)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InvalidArgumentError(f"{name} must be an int, not {value!r}")
    if not -(1 << 31) <= position < 1 << 31:
        raise OutOfRangeError("worm neck position", position, -(1 << 31), (1 << 31) - 1, "raw")
    if not 0 <= flags <= 0xFF:
        raise OutOfRangeError("flags", flags, 0, 0xFF)
    return _FEEDBACK.pack(position, int(flags))
