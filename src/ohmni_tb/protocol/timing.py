"""What a transaction costs on the wire: the public cost model (sans-IO).

Every device shares one 8N1 line, so the bus's capacity is a budget of seconds. A
transaction occupies the line for::

    request bytes × 10 / baud          the request on the wire
  + turnaround_s                       the longest a device takes to start its answer
  + reply bytes × 10 / baud            the reply, if one is expected
  + guard_s                            quiet before the next request

The bus engine sends the next request when the previous transaction's time is up by this
model — not when the host has read the reply, which a USB adapter may deliver
milliseconds later — and the schedulers above it add these costs to know whether a
schedule fits::

    from ohmni_tb.protocol import read_request
    from ohmni_tb.protocol.timing import transaction_cost_s

    transaction_cost_s(read_request(0, 59, 4))    # 0.0033 s: 9 + 15 bytes, 1 ms, 0.2 ms

A read of length 0 (a firmware tag) is answered with as many bytes as the device has, so
the model budgets the largest packet the receiver accepts.
"""

from __future__ import annotations

import math

from ohmni_tb.errors import OutOfRangeError
from ohmni_tb.protocol.framing import (
    BROADCAST_ID,
    HEADER_SIZE,
    MAX_PACKET_SIZE,
    Command,
    Packet,
)
from ohmni_tb.protocol.messages import AckPolicy, reply_expected

__all__ = [
    "BITS_PER_BYTE",
    "DEFAULT_BAUDRATE",
    "DEFAULT_GUARD_S",
    "DEFAULT_TURNAROUND_S",
    "reply_size_range",
    "transaction_cost_s",
    "wire_time_s",
]

#: An 8N1 byte on the wire: start bit, 8 data bits, stop bit.
BITS_PER_BYTE = 10
#: The Ohmni bus runs at 115200 8N1 (confirmed).
DEFAULT_BAUDRATE = 115_200
#: The longest a device may take from a request's last byte to its reply's first. The
#: real figure is not public; the simulated devices answer in 0.5 ms, and this leaves the
#: same again as margin. A slower device gets its own (``Bus.set_turnaround``).
DEFAULT_TURNAROUND_S = 0.001
#: Quiet after a transaction before the next request: a few bit times for a device to
#: turn its line driver around.
DEFAULT_GUARD_S = 0.0002

#: A read reply: header, addr, len, the bytes, two status bytes.
_READ_REPLY_OVERHEAD = HEADER_SIZE + 4
#: STAT, and writes/jogs under ACK policy 2: header and two status bytes.
_STATUS_REPLY_SIZE = HEADER_SIZE + 2
_READS = frozenset({Command.RAM_READ, Command.EEP_READ})


def wire_time_s(nbytes: int, baudrate: int = DEFAULT_BAUDRATE) -> float:
    """Seconds ``nbytes`` bytes take on an 8N1 line at ``baudrate``."""
    return nbytes * BITS_PER_BYTE / baudrate


def reply_size_range(request: Packet, *, max_packet_size: int = MAX_PACKET_SIZE) -> tuple[int, int]:
    """The smallest and largest reply ``request`` can get, in bytes on the wire.

    A read of ``n`` bytes is answered with exactly ``n + 11``; a read of length 0 with
    anything up to ``max_packet_size``; every other reply is 9 bytes.
    """
    if request.cmd in _READS and len(request.data) >= 2:
        length = request.data[1]
        if length == 0:
            return _READ_REPLY_OVERHEAD, max_packet_size
        size = _READ_REPLY_OVERHEAD + length
        return size, size
    return _STATUS_REPLY_SIZE, _STATUS_REPLY_SIZE


def transaction_cost_s(
    packet: Packet,
    *,
    baudrate: int = DEFAULT_BAUDRATE,
    turnaround_s: float = DEFAULT_TURNAROUND_S,
    guard_s: float = DEFAULT_GUARD_S,
    ack_policy: int = AckPolicy.READS,
    expect_reply: bool | None = None,
    max_packet_size: int = MAX_PACKET_SIZE,
) -> float:
    """Seconds of line time one request and its reply take (see the module docstring).

    Args:
        packet: The request.
        baudrate: Line speed.
        turnaround_s: The longest the device takes to start its reply.
        guard_s: Quiet before the next request.
        ack_policy: The device's ACK policy, which decides whether a write is answered.
        expect_reply: Override that decision (``None``: :func:`reply_expected` decides;
            a broadcast is never answered).
        max_packet_size: The largest reply a length-0 read may get.

    Raises:
        OutOfRangeError: ``baudrate`` is not positive, or a time is negative or not finite.
    """
    if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
        raise OutOfRangeError("baudrate", baudrate, 1, 4_000_000, "baud")
    for name, value in (("turnaround_s", turnaround_s), ("guard_s", guard_s)):
        if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
            raise OutOfRangeError(name, value, 0, math.inf, "s")
    cost = wire_time_s(packet.size, baudrate) + guard_s
    if packet.sid == BROADCAST_ID:
        expect_reply = False
    elif expect_reply is None:
        expect_reply = reply_expected(packet.cmd, packet.sid, ack_policy)
    if expect_reply:
        _, largest = reply_size_range(packet, max_packet_size=max_packet_size)
        cost += turnaround_s + wire_time_s(largest, baudrate)
    return cost
