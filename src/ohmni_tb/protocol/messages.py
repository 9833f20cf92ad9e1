"""Read/write requests, the replies they get, and the rules that pair them (sans-IO).

Every device on the bus answers reads the HerkuleX way::

    request  RAM_READ / EEP_READ        data = addr, length
    reply    cmd | 0x40                 data = addr, length, bytes..., status_error, status_detail
    request  RAM_WRITE / EEP_WRITE      data = addr, length, bytes...
    reply    (ACK policy 2 only)        data = status_error, status_detail
    request  STAT                       data = (none)
    reply    always                     data = status_error, status_detail

A read of length 0 (the firmware tag at EEP 0xF1) is answered with as many bytes as the
device has; the reply's length byte says how many.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.protocol.framing import (
    BROADCAST_ID,
    MAX_DATA_SIZE,
    MAX_SID,
    REPLY_FLAG,
    Command,
    Packet,
)

__all__ = [
    "AckPolicy",
    "Memory",
    "ReadReply",
    "StatusDetail",
    "StatusError",
    "StatusReply",
    "check_sid",
    "flag_names",
    "read_request",
    "reply_expected",
    "reply_matches",
    "write_request",
]

#: Read/write data starts with addr and length: the payload gets the rest.
_RW_OVERHEAD = 2
#: A read reply ends with the two status bytes.
_STATUS_SIZE = 2
#: The largest payload one read reply can carry.
MAX_READ_LENGTH = MAX_DATA_SIZE - _RW_OVERHEAD - _STATUS_SIZE


class Memory(enum.Enum):
    """Which register file a read or write addresses."""

    RAM = "ram"
    EEP = "eep"

    @property
    def read_cmd(self) -> Command:
        """The read command for this memory."""
        return Command.RAM_READ if self is Memory.RAM else Command.EEP_READ

    @property
    def write_cmd(self) -> Command:
        """The write command for this memory."""
        return Command.RAM_WRITE if self is Memory.RAM else Command.EEP_WRITE


class AckPolicy(enum.IntEnum):
    """When a device replies (HerkuleX EEP 7 / RAM 1)."""

    STAT_ONLY = 0
    READS = 1
    ALL = 2


class StatusError(enum.IntFlag):
    """The status error byte (HerkuleX RAM 48)."""

    NONE = 0
    INPUT_VOLTAGE = 0x01
    POSITION_LIMIT = 0x02
    TEMPERATURE = 0x04
    INVALID_PACKET = 0x08
    OVERLOAD = 0x10
    DRIVER_FAULT = 0x20
    EEP_DISTORTED = 0x40


class StatusDetail(enum.IntFlag):
    """The status detail byte (HerkuleX RAM 49)."""

    NONE = 0
    MOVING = 0x01
    INPOSITION = 0x02
    CHECKSUM_ERROR = 0x04
    UNKNOWN_COMMAND = 0x08
    EXCEED_REG_RANGE = 0x10
    GARBAGE_DETECTED = 0x20
    MOTOR_ON = 0x40


#: Every status byte's flags, built once: making an IntFlag from an int runs the enum
#: machinery, and the bus parses two status bytes in every read reply.
STATUS_ERRORS: tuple[StatusError, ...] = tuple(StatusError(b) for b in range(256))
STATUS_DETAILS: tuple[StatusDetail, ...] = tuple(StatusDetail(b) for b in range(256))


def flag_names(flags: enum.IntFlag) -> str:
    """Flags for people: ``"TEMPERATURE|OVERLOAD"``, ``"none"``, unknown bits in hex."""
    value = int(flags)
    names = [m.name for m in type(flags) if m.value and m.value & value == m.value and m.name]
    rest = value
    for m in type(flags):
        if m.value & value == m.value:
            rest &= ~m.value
    if rest:
        names.append(f"0x{rest:02X}")
    return "|".join(names) if names else "none"


def check_sid(sid: int, *, allow_broadcast: bool) -> int:
    """Return ``sid`` if it is a device id (0..0xFD), or broadcast when allowed.

    Raises:
        OutOfRangeError: Not an int in range (a bool is not an id).
    """
    high = MAX_SID if allow_broadcast else MAX_SID - 1
    if isinstance(sid, bool) or not isinstance(sid, int) or not 0 <= sid <= high:
        raise OutOfRangeError("sid", sid, 0, high)
    return sid


def _check_addr(addr: int) -> None:
    if isinstance(addr, bool) or not isinstance(addr, int) or not 0 <= addr <= 0xFF:
        raise OutOfRangeError("addr", addr, 0, 0xFF)


def read_request(sid: int, addr: int, length: int, memory: Memory = Memory.RAM) -> Packet:
    """Build a read of ``length`` bytes from ``addr``.

    A broadcast read is refused: every device would answer at once and the replies
    would collide.

    Raises:
        OutOfRangeError: sid, addr or length is out of range.
    """
    check_sid(sid, allow_broadcast=False)
    _check_addr(addr)
    if isinstance(length, bool) or not isinstance(length, int):
        raise InvalidArgumentError(f"length must be an int, not {type(length).__name__}")
    if not 0 <= length <= MAX_READ_LENGTH:
        raise OutOfRangeError("length", length, 0, MAX_READ_LENGTH, "bytes")
    return Packet(sid, memory.read_cmd, bytes((addr, length)))


def write_request(
    sid: int, addr: int, data: bytes | bytearray, memory: Memory = Memory.RAM
) -> Packet:
    """Build a write of ``data`` at ``addr``; broadcast (0xFE) is allowed.

    Raises:
        OutOfRangeError: sid, addr or the data length is out of range.
    """
    check_sid(sid, allow_broadcast=True)
    _check_addr(addr)
    if not isinstance(data, bytes | bytearray):
        raise InvalidArgumentError(f"data must be bytes, not {type(data).__name__}")
    if not 1 <= len(data) <= MAX_DATA_SIZE - _RW_OVERHEAD:
        raise OutOfRangeError("len(data)", len(data), 1, MAX_DATA_SIZE - _RW_OVERHEAD, "bytes")
    return Packet(sid, memory.write_cmd, bytes((addr, len(data))) + bytes(data))


@dataclass(frozen=True, slots=True)
class ReadReply:
    """A parsed reply to RAM_READ or EEP_READ.

    Attributes:
        sid: The device that answered.
        memory: RAM or EEP.
        addr: The first register address read.
        data: The register bytes.
        status_error: The device's error flags at the time of the reply.
        status_detail: The device's detail flags at the time of the reply.
    """

    sid: int
    memory: Memory
    addr: int
    data: bytes
    status_error: StatusError
    status_detail: StatusDetail

    @property
    def length(self) -> int:
        """How many register bytes the reply carries."""
        return len(self.data)

    @classmethod
    def parse(cls, packet: Packet) -> ReadReply:
        """Parse a read reply packet.

        Raises:
            MalformedReplyError: the packet is not a read reply, or its length byte does
                not match its payload.
        """
        if packet.cmd == Command.RAM_READ | REPLY_FLAG:
            memory = Memory.RAM
        elif packet.cmd == Command.EEP_READ | REPLY_FLAG:
            memory = Memory.EEP
        else:
            raise MalformedReplyError(f"not a read reply: {packet!r}")
        d = packet.data
        if len(d) < _RW_OVERHEAD + _STATUS_SIZE:
            raise MalformedReplyError(f"read reply too short ({len(d)} data bytes): {packet!r}")
        addr, length = d[0], d[1]
        if len(d) != length + _RW_OVERHEAD + _STATUS_SIZE:
            raise MalformedReplyError(
                f"read reply says {length} bytes but carries {len(d) - 4}: {packet!r}"
            )
        return cls(
            sid=packet.sid,
            memory=memory,
            addr=addr,
            data=d[2 : 2 + length],
            status_error=STATUS_ERRORS[d[-2]],
            status_detail=STATUS_DETAILS[d[-1]],
        )


@dataclass(frozen=True, slots=True)
class StatusReply:
    """A parsed two-status-byte reply (STAT, and writes/jogs under ACK policy 2)."""

    sid: int
    cmd: int
    status_error: StatusError
    status_detail: StatusDetail

    @classmethod
    def parse(cls, packet: Packet) -> StatusReply:
        """Parse a reply whose data is just the two status bytes.

        Raises:
            MalformedReplyError: the packet is not a reply or does not carry two bytes.
        """
        if not packet.is_reply or len(packet.data) != _STATUS_SIZE:
            raise MalformedReplyError(f"not a status reply: {packet!r}")
        return cls(
            sid=packet.sid,
            cmd=packet.cmd,
            status_error=STATUS_ERRORS[packet.data[0]],
            status_detail=STATUS_DETAILS[packet.data[1]],
        )


_READS = frozenset({Command.RAM_READ, Command.EEP_READ})


def reply_expected(cmd: int, sid: int, ack_policy: int = AckPolicy.READS) -> bool:
    """Whether a request gets a reply: the one place that decides it.

    * STAT always answers, even under policy 0 and even to broadcast (then every device
      answers at once, so never broadcast it on a shared bus).
    * Any other request to broadcast (0xFE) gets no reply.
    * Reads answer under policy 1 and 2; writes, jogs, rollback and reboot only under 2.

    Raises:
        InvalidArgumentError: An argument is not an int.
    """
    for name, value in (("cmd", cmd), ("sid", sid), ("ack_policy", ack_policy)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InvalidArgumentError(f"{name} must be an int, not {type(value).__name__}")
    return _reply_expected(cmd, sid, ack_policy)


def _reply_expected(cmd: int, sid: int, ack_policy: int) -> bool:
    """:func:`reply_expected` without the argument checks, for callers whose arguments
    come from a :class:`Packet` (the bus asks it for every request it sends)."""
    if cmd == Command.STAT:
        return True
    if sid == BROADCAST_ID:
        return False
    return ack_policy >= (AckPolicy.READS if cmd in _READS else AckPolicy.ALL)


def reply_matches(request: Packet, reply: Packet) -> bool:
    """Whether ``reply`` answers ``request``: same sid, the reply code, and for reads the
    same address, a length byte that fits the payload, and the length asked for (unless
    the request asked for length 0).

    The checksums ignore bit 0, so a line error can leave a reply whose length byte
    disagrees with its bytes; such a reply answers nothing, and the read is retried.
    """
    if reply.sid != request.sid or reply.cmd != request.cmd | REPLY_FLAG:
        return False
    if request.cmd in _READS:
        rd, qd = reply.data, request.data
        if len(rd) < _RW_OVERHEAD or len(qd) < _RW_OVERHEAD or rd[0] != qd[0]:
            return False
        if len(rd) != rd[1] + _RW_OVERHEAD + _STATUS_SIZE:
            return False
        return qd[1] == 0 or rd[1] == qd[1]
    return True
