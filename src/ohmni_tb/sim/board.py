"""Shared firmware behaviour of the Ohmni's own boards (drive, core, worm neck).

The boards speak HerkuleX framing. Each board here has a table of registers, one entry
per *address* (RAM 58 and 59 overlap on the drive boards, so they are registers, not a
byte array), and answers the way the project's assumed profile says:

* RAM_READ / EEP_READ of a known register with its size (or less) → the bytes;
  length 0 → the whole register (how the firmware tag at EEP 0xF1 is read);
* a read of an unknown address → zero bytes with INVALID_PACKET / EXCEED_REG_RANGE set;
* RAM_WRITE to a writable register → stored, no reply (ACK policy 1);
* STAT → the two status bytes; anything to another id is ignored;
* a frame for the board that fails its checksum, or is cut short, is flagged
  (INVALID_PACKET with CHECKSUM_ERROR or GARBAGE_DETECTED) and not answered.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    AckPolicy,
    Command,
    Packet,
    RejectReason,
    StatusDetail,
    StatusError,
    reply_expected,
)
from ohmni_tb.sim.device import SimDevice

__all__ = ["BoardRegister", "SimBoard"]

#: Frames the boards flag, as a HerkuleX servo does: a bad checksum, and a frame cut
#: short (the line went quiet before its last byte).
_REJECT_DETAIL = {
    RejectReason.CHECKSUM: StatusDetail.CHECKSUM_ERROR,
    RejectReason.EXPIRED: StatusDetail.GARBAGE_DETECTED,
}


@dataclass(slots=True)
class BoardRegister:
    """One register of a simulated board.

    Attributes:
        size: Bytes.
        read: Returns the current bytes (called after the physics is advanced).
        write: Takes new bytes, or ``None`` for a read-only register.
    """

    size: int
    read: Callable[[], bytes]
    write: Callable[[bytes], None] | None = None


class SimBoard(SimDevice):
    """A register-mapped board with one bus id.

    Args:
        sid: The board's bus id.
        tag: The firmware tag answered at EEP 0xF1.
    """

    #: EEP address of the firmware tag (confirmed).
    TAG_ADDR = 0xF1

    def __init__(self, sid: int, tag: str) -> None:
        self.sid = sid
        self.tag = tag
        self.ram: dict[int, BoardRegister] = {}
        self.eep: dict[int, BoardRegister] = {
            self.TAG_ADDR: BoardRegister(len(tag), lambda: self.tag.encode("ascii"))
        }
        self.status_error = StatusError.NONE
        self.status_detail = StatusDetail.NONE
        self.ack_policy = AckPolicy.READS
        self.packets_seen = 0

    # -- SimDevice -------------------------------------------------------------------

    def handle(self, packet: Packet, now_s: float) -> Packet | None:
        if packet.is_reply:
            return None
        if packet.sid not in (self.sid, BROADCAST_ID):
            return self.handle_foreign(packet, now_s)
        self.packets_seen += 1
        cmd = packet.cmd
        if cmd in (Command.RAM_READ, Command.EEP_READ):
            if packet.sid == BROADCAST_ID:
                return None
            return self._read(packet)
        if cmd in (Command.RAM_WRITE, Command.EEP_WRITE):
            self._write(packet)
        elif cmd in (Command.S_JOG, Command.I_JOG):
            self.handle_jog(packet, now_s)
        elif cmd == Command.REBOOT:
            self.power_cycle(now_s)
        elif cmd not in (Command.STAT, Command.ROLLBACK):
            self._flag_invalid(StatusDetail.UNKNOWN_COMMAND)
        if reply_expected(cmd, packet.sid, self.ack_policy):
            return self._status_reply(cmd)
        return None

    def on_rejected(self, reason: RejectReason, frame: bytes, now_s: float) -> None:
        detail = _REJECT_DETAIL.get(reason)
        if detail is not None and len(frame) > 3 and frame[3] == self.sid:
            self._flag_invalid(detail)

    # -- for subclasses --------------------------------------------------------------

    def handle_foreign(self, packet: Packet, now_s: float) -> Packet | None:
        """A packet addressed to another id (a broadcast jog may still name this board)."""
        del packet, now_s
        return None

    def handle_jog(self, packet: Packet, now_s: float) -> None:
        """A jog addressed to this board's id or to broadcast. Default: ignored."""
        del packet, now_s

    # -- private ---------------------------------------------------------------------

    def _flag_invalid(self, detail: StatusDetail) -> None:
        self.status_error |= StatusError.INVALID_PACKET
        self.status_detail |= detail

    def _status_bytes(self) -> bytes:
        return bytes((int(self.status_error), int(self.status_detail)))

    def _status_reply(self, cmd: int) -> Packet:
        return Packet(self.sid, cmd | REPLY_FLAG, self._status_bytes())

    def _read(self, packet: Packet) -> Packet | None:
        if len(packet.data) != 2:
            self._flag_invalid(StatusDetail.GARBAGE_DETECTED)
            return None
        addr, length = packet.data
        table = self.ram if packet.cmd == Command.RAM_READ else self.eep
        reg = table.get(addr)
        if reg is None or length > reg.size:
            self._flag_invalid(StatusDetail.EXCEED_REG_RANGE)
            body = bytes(length)
        else:
            value = reg.read()
            body = value if length == 0 else value[:length]
        return Packet(
            self.sid,
            packet.cmd | REPLY_FLAG,
            bytes((addr, len(body))) + body + self._status_bytes(),
        )

    def _write(self, packet: Packet) -> None:
        d = packet.data
        if len(d) < 3 or d[1] != len(d) - 2:
            self._flag_invalid(StatusDetail.GARBAGE_DETECTED)
            return
        addr = d[0]
        if packet.cmd == Command.RAM_WRITE and addr in (48, 49) and not any(d[2:]):
            # Clearing the status bytes, as on a HerkuleX servo.
            self.status_error = StatusError.NONE
            self.status_detail = StatusDetail.NONE
            return
        table = self.ram if packet.cmd == Command.RAM_WRITE else self.eep
        reg = table.get(addr)
        if reg is None or reg.write is None or d[1] != reg.size:
            self._flag_invalid(StatusDetail.EXCEED_REG_RANGE)
            return
        reg.write(bytes(d[2:]))
