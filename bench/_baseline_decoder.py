"""The previous :class:`~ohmni_tb.protocol.PacketDecoder`, kept to measure against.

``BaselineDecoder`` is a verbatim copy of the decoder as it was before the index-walking
rewrite (only the class name and its docstring's first line differ). ``bench/codec.py``
times both on the same stream, and ``tests/test_protocol_framing.py`` feeds both the same
random streams and requires identical packets, counters and rejects. Do not optimise it:
its whole value is being the reference the new decoder is compared with.
"""

from __future__ import annotations

from collections.abc import Iterable

from ohmni_tb.errors import OutOfRangeError
from ohmni_tb.protocol.framing import (
    HEADER,
    HEADER_SIZE,
    MAX_PACKET_SIZE,
    MIN_PACKET_SIZE,
    DecoderStats,
    Packet,
    RejectHandler,
    RejectReason,
    _default_commands,
    checksum,
)

__all__ = ["BaselineDecoder"]


class BaselineDecoder:
    """The previous implementation of PacketDecoder, kept verbatim to measure against.

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
        self._buf = bytearray()
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
            bytes_pending=len(self._buf),
            checksum_errors=self._checksum_errors,
            bad_headers=self._bad_headers,
            bad_sizes=self._bad_sizes,
            unknown_commands=self._unknown_commands,
            expired=self._expired,
        )

    @property
    def pending(self) -> int:
        """Bytes held for an incomplete frame."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Packet]:
        """Add received bytes and return every packet they complete, in order."""
        self._bytes_in += len(data)
        self._buf += data
        return self._scan()

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
        while self._buf:
            if self._buf.startswith(HEADER):
                self._expired += 1
                self._reject(RejectReason.EXPIRED, len(self._buf))
            else:
                # A lone trailing FF: the first half of a header that never came.
                self._drop(len(self._buf))
            out += self._scan()
        return out

    def reset(self) -> None:
        """Drop any held bytes (counted as discarded). Counters are kept."""
        self._discarded += len(self._buf)
        self._buf.clear()

    # -- private ---------------------------------------------------------------------

    def _drop(self, n: int) -> None:
        self._discarded += n
        del self._buf[:n]

    def _reject(self, reason: RejectReason, held: int) -> None:
        """Give up the candidate frame at the buffer start; rescan from its second byte."""
        if self._on_reject is not None:
            self._on_reject(reason, bytes(self._buf[:held]))
        self._drop(1)

    def _scan(self) -> list[Packet]:
        out: list[Packet] = []
        buf = self._buf
        commands = self._commands
        max_size = self._max_size
        while True:
            start = buf.find(HEADER)
            if start < 0:
                # Keep a trailing FF: it may be the first half of a header.
                keep = 1 if buf and buf[-1] == 0xFF else 0
                if len(buf) > keep:
                    self._drop(len(buf) - keep)
                return out
            if start:
                self._drop(start)
            if len(buf) < HEADER_SIZE:
                return out
            size, sid, cmd, cs1, cs2 = buf[2], buf[3], buf[4], buf[5], buf[6]
            if not MIN_PACKET_SIZE <= size <= max_size:
                self._bad_sizes += 1
                self._reject(RejectReason.BAD_SIZE, HEADER_SIZE)
                continue
            if cs1 ^ cs2 != 0xFE or cs1 & 1 or sid == 0xFF:
                self._bad_headers += 1
                self._reject(RejectReason.BAD_HEADER, HEADER_SIZE)
                continue
            if cmd not in commands:
                self._unknown_commands += 1
                self._reject(RejectReason.UNKNOWN_COMMAND, HEADER_SIZE)
                continue
            if len(buf) < size:
                return out
            data = bytes(buf[HEADER_SIZE:size])
            if checksum(size, sid, cmd, data) & 0xFE != cs1:
                self._checksum_errors += 1
                self._reject(RejectReason.CHECKSUM, size)
                continue
            del buf[:size]
            self._consumed += size
            self._packets += 1
            out.append(Packet(sid, cmd, data))
