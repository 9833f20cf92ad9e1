"""The bus protocol, sans-IO: framing, requests and replies, device codecs.

Nothing here imports asyncio or serial or reads a clock: bytes in, packets out.
"""

from __future__ import annotations

from ohmni_tb.protocol.connection import BusConnection, ReplyPacket
from ohmni_tb.protocol.framing import (
    BROADCAST_ID,
    MAX_PACKET_SIZE,
    MIN_PACKET_SIZE,
    REPLY_FLAG,
    Command,
    DecoderStats,
    Packet,
    PacketDecoder,
    RejectReason,
    checksum,
    encode_packet,
)
from ohmni_tb.protocol.messages import (
    AckPolicy,
    Memory,
    ReadReply,
    StatusDetail,
    StatusError,
    StatusReply,
    check_sid,
    flag_names,
    read_request,
    reply_expected,
    reply_matches,
    write_request,
)
from ohmni_tb.protocol.timing import transaction_cost_s, wire_time_s

__all__ = [
    "BROADCAST_ID",
    "MAX_PACKET_SIZE",
    "MIN_PACKET_SIZE",
    "REPLY_FLAG",
    "AckPolicy",
    "BusConnection",
    "Command",
    "DecoderStats",
    "Memory",
    "Packet",
    "PacketDecoder",
    "ReadReply",
    "RejectReason",
    "ReplyPacket",
    "StatusDetail",
    "StatusError",
    "StatusReply",
    "check_sid",
    "checksum",
    "encode_packet",
    "flag_names",
    "read_request",
    "reply_expected",
    "reply_matches",
    "transaction_cost_s",
    "wire_time_s",
    "write_request",
]
