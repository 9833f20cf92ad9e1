"""Bus framing: packets, their encoding, and a resynchronising stream decoder (sans-IO).

Every device on the Ohmni bus speaks HerkuleX-compatible framing::

     0    1    2     3    4    5    6    7 ...
    +----+----+-----+----+----+----+----+---------------+
    | FF | FF | size| sid| cmd| cs1| cs2| data ...      |
    +----+----+-----+----+----+----+----+---------------+
    size = whole packet length, header included (7..223)
    cs1  = (size ^ sid ^ cmd ^ data[0] ^ ... ^ data[n-1]) & 0xFE
    cs2  = ~(size ^ sid ^ cmd ^ data...) & 0xFE        so cs1 ^ cs2 == 0xFE

A reply carries the request's command code with bit 0x40 set. This module never touches a
port or a clock: bytes go into :meth:`PacketDecoder.feed`, packets come out, and
:func:`encode_packet` turns a packet into bytes.
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

__all__ = [
    "BROADCAST_ID",
    "HEADER",
    "HEADER_SIZE",
    "MAX_DATA_SIZE",
    "MAX_PACKET_SIZE",
    "MAX_SID",
    "MIN_PACKET_SIZE",
    "REPLY_FLAG",
    "Command",
    "DecoderStats",
    "Packet",
    "PacketDecoder",
    "RejectReason",
    "checksum",
    "encode_packet",
]

HEADER = b"\xff\xff"
#: FF FF size sid cmd cs1 cs2: the fixed part of every packet.
HEADER_SIZE = 7
#: A packet with no data is just its header.
MIN_PACKET_SIZE = HEADER_SIZE
#: The HerkuleX manual's limit (one page says 233; 223 agrees with every other limit).
MAX_PACKET_SIZE = 223
MAX_DATA_SIZE = MAX_PACKET_SIZE - HEADER_SIZE
#: 0xFE addresses every device; 0xFF can never be an id because it is the header byte.
BROADCAST_ID = 0xFE
MAX_SID = BROADCAST_ID
#: A reply's command code is the request's with this bit set.
REPLY_FLAG = 0x40


class Command(enum.IntEnum):
    """Request command codes. A reply carries ``cmd | REPLY_FLAG``."""

    EEP_WRITE = 0x01
    EEP_READ = 0x02
    RAM_WRITE = 0x03
    RAM_READ = 0x04
    I_JOG = 0x05
    S_JOG = 0x06
    STAT = 0x07
    ROLLBACK = 0x08
    REBOOT = 0x09

    @property
    def reply(self) -> int:
        """The command code of this request's reply."""
        return self.value | REPLY_FLAG


@dataclass(frozen=True, slots=True, eq=False)
class Packet:
    """One bus packet, request or reply.

    Two packets are equal when their sid, command and data are, whatever their class: a
    subclass that carries more (a reply with the times it was sent and received) still
    equals, and hashes like, the plain packet with the same content. Its extra fields take
    no part in equality, so that equality stays transitive; a frozen, slotted dataclass
    subclass gets this comparison and hash without declaring anything (it needs
    ``kw_only=True`` for extra fields without defaults, since ``data`` has one).

    Attributes:
        sid: The device id (0..0xFD) or 0xFE for broadcast.
        cmd: A request code (:class:`Command`) or a reply code (``cmd | 0x40``).
        data: The payload after the checksums.
    """

    sid: int
    cmd: int
    data: bytes = b""

    def __init_subclass__(cls, **kwargs: object) -> None:
        # A dataclass subclass would otherwise get a generated __eq__ that refuses other
        # classes and a __hash__ over its extra fields. The dataclass decorator keeps
        # methods the class already has, and this runs before it.
        super(Packet, cls).__init_subclass__(**kwargs)
        for name in ("__eq__", "__hash__"):
            if name not in cls.__dict__:
                setattr(cls, name, getattr(Packet, name))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Packet):
            return NotImplemented
        return (self.sid, self.cmd, self.data) == (other.sid, other.cmd, other.data)

    def __hash__(self) -> int:
        return hash((self.sid, self.cmd, self.data))

    @property
    def is_reply(self) -> bool:
        """Whether the command code carries the reply flag."""
        return bool(self.cmd & REPLY_FLAG)

    @property
    def size(self) -> int:
        """The packet's length on the wire, header included."""
        return HEADER_SIZE + len(self.data)

    def __repr__(self) -> str:
        try:
            name = Command(self.cmd & ~REPLY_FLAG).name
        except ValueError:
            name = f"0x{self.cmd:02X}"
        kind = " reply" if self.is_reply else ""
        return f"Packet(sid={self.sid}, cmd={name}{kind}, data={self.data.hex(' ')!r})"


# The decoder builds packets through the slot descriptors: the frozen dataclass __init__
# sets each field with object.__setattr__ by name, which takes twice as long.
_set_sid: Callable[[Packet, int], None] = Packet.__dict__["sid"].__set__
_set_cmd: Callable[[Packet, int], None] = Packet.__dict__["cmd"].__set__
_set_data: Callable[[Packet, bytes], None] = Packet.__dict__["data"].__set__


def checksum(size: int, sid: int, cmd: int, data: bytes | bytearray | memoryview) -> int:
    """Return the XOR of size, sid, cmd and every data byte (cs1 before masking)."""
    x = size ^ sid ^ cmd
    for b in data:
        x ^= b
    return x


def encode_packet(packet: Packet, *, max_size: int = MAX_PACKET_SIZE) -> bytes:
    """Encode a packet to its wire bytes.

    Args:
        packet: The packet to encode.
        max_size: The largest packet the receiver accepts (223 for HerkuleX; the Ohmni
            boards accept 64).

    Returns:
        The bytes to write, header and checksums included.

    Raises:
        OutOfRangeError: ``sid``, ``cmd`` or the packet size is out of range; the error
            names the field.
    """
    sid, cmd, data = packet.sid, packet.cmd, packet.data
    if not isinstance(sid, int) or not 0 <= sid <= MAX_SID:
        raise OutOfRangeError("sid", sid, 0, MAX_SID)
    if not isinstance(cmd, int) or not 0 <= cmd <= 0xFF:
        raise OutOfRangeError("cmd", cmd, 0, 0xFF)
    if not isinstance(data, bytes | bytearray):
        raise InvalidArgumentError(f"data must be bytes, not {type(data).__name__}")
    size = HEADER_SIZE + len(data)
    if size > max_size:
        raise OutOfRangeError("size", size, MIN_PACKET_SIZE, max_size, "bytes")
    x = checksum(size, sid, cmd, data)
    return bytes((0xFF, 0xFF, size, sid, cmd, x & 0xFE, ~x & 0xFE)) + data


@dataclass(frozen=True, slots=True)
class DecoderStats:
    """Counters of a :class:`PacketDecoder`; nothing received goes uncounted.

    ``bytes_in == bytes_consumed + bytes_discarded + bytes_pending`` always holds.

    Attributes:
        bytes_in: Bytes fed.
        packets: Packets decoded.
        bytes_consumed: Bytes that went into decoded packets.
        bytes_discarded: Bytes dropped as junk (outside any valid packet).
        bytes_pending: Bytes held for a packet not yet complete.
        checksum_errors: Frames whose header looked right but whose checksum did not match.
        bad_headers: ``FF FF`` followed by an impossible header (checksum pair, sid).
        bad_sizes: Headers whose size field was out of range (too small or oversize).
        unknown_commands: Headers carrying a command code not in the accepted set.
        expired: Incomplete frames given up because the line went quiet.
    """

    bytes_in: int
    packets: int
    bytes_consumed: int
    bytes_discarded: int
    bytes_pending: int
    checksum_errors: int
    bad_headers: int
    bad_sizes: int
    unknown_commands: int
    expired: int


class RejectReason(enum.Enum):
    """Why the decoder gave up a candidate frame."""

    BAD_SIZE = "size field out of range"
    BAD_HEADER = "impossible checksum pair or sid"
    UNKNOWN_COMMAND = "unknown command code"
    CHECKSUM = "checksum mismatch"
    EXPIRED = "frame cut short"


#: Called with why a frame was rejected and the bytes held for it (from ``FF FF`` on).
RejectHandler = Callable[[RejectReason, bytes], None]


#: ``FF FF size sid cmd cs1 cs2`` read in one call; the marker is 0xFFFF at a header.
_unpack_header = struct.Struct("<H5B").unpack_from
#: The only cs2 that goes with each cs1 (``cs1 ^ 0xFE``), or -1: an odd cs1 is never valid.
_CS2_OF = tuple(-1 if cs1 & 1 else cs1 ^ 0xFE for cs1 in range(256))


def _default_commands() -> frozenset[int]:
    codes = {int(c) for c in Command}
    return frozenset(codes | {c | REPLY_FLAG for c in codes})


class PacketDecoder:
    """Turn a byte stream into packets, resynchronising after junk and corruption.

    Requests and replies alike come out, in order. Recovery:

    * junk before a frame: skipped up to the next ``FF FF``;
    * a false header (``FF FF`` inside junk or data): rejected from its 7 header bytes
      when its size is out of range, ``cs1 ^ cs2 != 0xFE``, either checksum is odd, the
      sid is 0xFF, or the command is not in ``commands``; the scan resumes one byte after
      the rejected ``FF``, so junk never holds back the packets behind it;
    * a bad checksum over the whole frame: the scan also resumes one byte after the
      header start, so a packet hidden inside the rejected bytes is still found;
    * a frame cut short: held until its size arrives; :meth:`expire` gives it up when
      the caller knows the line went quiet.

    The buffer never holds more than one incomplete frame (< ``max_size`` bytes).
    Every dropped byte is counted in :attr:`stats`.

    Args:
        commands: Accepted command codes (requests and replies). Defaults to the nine
            HerkuleX commands and their replies; pass a wider set if a device uses more.
        max_size: The largest packet accepted (7..223).
        on_reject: Called for every candidate frame given up, with the reason and the
            bytes held for it; a simulated device uses it to flag a bad checksum the way
            the firmware does. Junk outside any ``FF FF`` is only counted.
    """

    def __init__(
        self,
        *,
        commands: Iterable[int] | None = None,
        max_size: int = MAX_PACKET_SIZE,
        on_reject: RejectHandler | None = None,
    ) -> None:
        if not MIN_PACKET_SIZE <= max_size <= MAX_PACKET_SIZE:
            raise OutOfRangeError("max_size", max_size, MIN_PACKET_SIZE, MAX_PACKET_SIZE)
        self._commands = frozenset(commands) if commands is not None else _default_commands()
        for code in self._commands:
            if not 0 <= code <= 0xFF:
                raise OutOfRangeError("command code", code, 0, 0xFF)
        self._max_size = max_size
        self._on_reject = on_reject
        # The bytes held are self._buf[self._pos:]. _pos is 0 except while on_reject runs
        # (or after it raised): the handler, and a caller catching its exception, then see
        # the decoder as it stands at the rejected frame, without a copy of the buffer.
        self._buf = b""
        self._pos = 0
        self._bytes_in = 0
        self._packets = 0
        self._consumed = 0
        self._discarded = 0
        self._checksum_errors = 0
        self._bad_headers = 0
        self._bad_sizes = 0
        self._unknown_commands = 0
        self._expired = 0

    @property
    def stats(self) -> DecoderStats:
        """A snapshot of the counters."""
        return DecoderStats(
            bytes_in=self._bytes_in,
            packets=self._packets,
            bytes_consumed=self._consumed,
            bytes_discarded=self._discarded,
            bytes_pending=len(self._buf) - self._pos,
            checksum_errors=self._checksum_errors,
            bad_headers=self._bad_headers,
            bad_sizes=self._bad_sizes,
            unknown_commands=self._unknown_commands,
            expired=self._expired,
        )

    @property
    def discarded(self) -> int:
        """Bytes dropped as junk so far (``stats.bytes_discarded``, without the snapshot)."""
        return self._discarded

    @property
    def pending(self) -> int:
        """Bytes held for an incomplete frame."""
        return len(self._buf) - self._pos

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Add received bytes and return every packet they complete, in order."""
        self._bytes_in += len(data)
        held = self._buf
        if self._pos:
            held = held[self._pos :]
        # bytes(data) is data itself when it already is bytes: no copy on the common path.
        return self._scan(held + data if held else bytes(data), 0)

    def expire(self) -> list[Packet]:
        """Give up the incomplete frame held, if any, and rescan the bytes after its start.

        Call it when the line has been quiet long enough that the rest of the frame is
        not coming (the frame was a false header, or its tail was lost). Packets hidden in
        the held bytes are returned.
        """
        out: list[Packet] = []
        # The rescan can stop at a second incomplete frame (another false header further
        # in); it cannot complete either, so give it up too and keep rescanning, or a
        # packet behind it would be lost.
        while True:
            held = self._buf[self._pos :] if self._pos else self._buf
            if not held:
                return out
            if held.startswith(HEADER):
                self._expired += 1
                if self._on_reject is not None:
                    self._on_reject(RejectReason.EXPIRED, held)
                self._discarded += 1
                out += self._scan(held, 1)
            else:
                # A lone trailing FF: the first half of a header that never came.
                self._discarded += len(held)
                self._buf = b""
                self._pos = 0

    def reset(self) -> None:
        """Drop any held bytes (counted as discarded). Counters are kept."""
        self._discarded += len(self._buf) - self._pos
        self._buf = b""
        self._pos = 0

    # -- private ---------------------------------------------------------------------

    def _scan(self, buf: bytes, pos: int) -> list[Packet]:
        """Decode ``buf`` from ``pos`` on and keep what is left as the bytes held.

        The buffer is never modified: ``pos`` walks it. The counters live in locals until
        the end, or until ``on_reject`` runs (it may read them); ``bytes_consumed`` is not
        even counted, since every byte passed over is either consumed or discarded.
        """
        out: list[Packet] = []
        append = out.append
        new, set_sid, set_cmd, set_data = object.__new__, _set_sid, _set_cmd, _set_data
        find = buf.find
        unpack_header = _unpack_header
        commands = self._commands
        max_size = self._max_size
        on_reject = self._on_reject
        end = len(buf)
        base = pos
        discarded = counted = 0
        while True:
            if end - pos >= HEADER_SIZE:
                mark, size, sid, cmd, cs1, cs2 = unpack_header(buf, pos)
            else:
                mark = 0
            if mark != 0xFFFF:
                start = find(HEADER, pos)
                if start < 0:
                    # Keep a trailing FF: it may be the first half of a header.
                    stop = end - 1 if pos < end and buf[-1] == 0xFF else end
                    discarded += stop - pos
                    pos = stop
                    break
                discarded += start - pos
                pos = start
                if end - pos < HEADER_SIZE:
                    break
                continue
            if not MIN_PACKET_SIZE <= size <= max_size:
                self._bad_sizes += 1
                reason, held = RejectReason.BAD_SIZE, HEADER_SIZE
            elif _CS2_OF[cs1] != cs2 or sid == 0xFF:
                self._bad_headers += 1
                reason, held = RejectReason.BAD_HEADER, HEADER_SIZE
            elif cmd not in commands:
                self._unknown_commands += 1
                reason, held = RejectReason.UNKNOWN_COMMAND, HEADER_SIZE
            else:
                stop = pos + size
                if stop > end:
                    break
                data = buf[pos + HEADER_SIZE : stop]
                x = size ^ sid ^ cmd
                for b in data:
                    x ^= b
                if x & 0xFE == cs1:
                    packet = new(Packet)
                    set_sid(packet, sid)
                    set_cmd(packet, cmd)
                    set_data(packet, data)
                    append(packet)
                    pos = stop
                    continue
                self._checksum_errors += 1
                reason, held = RejectReason.CHECKSUM, size
            if on_reject is not None:
                # Bring the decoder up to date first, as if each byte had been handled
                # on its own: the handler may read the stats, or raise out of feed().
                self._buf, self._pos = buf, pos
                self._discarded += discarded
                self._consumed += pos - base - discarded
                self._packets += len(out) - counted
                base, discarded, counted = pos, 0, len(out)
                on_reject(reason, buf[pos : pos + held])
            # Resume one byte on: a packet may start inside the rejected bytes.
            discarded += 1
            pos += 1
        self._buf = buf[pos:]
        self._pos = 0
        self._discarded += discarded
        self._consumed += pos - base - discarded
        self._packets += len(out) - counted
        return out
