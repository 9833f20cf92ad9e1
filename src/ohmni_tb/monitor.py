"""Decode bus traffic for people: device and register names, values, rates, latencies.

:class:`BusMonitor` is sans-IO: feed it bytes (with the time they arrived, when known)
and it returns one :class:`MonitorEvent` per packet, described in words, and keeps
per-device counts. ``ohmni bus monitor`` runs it on a live port or a capture file; it is
the tool for capturing a real robot's unknown bytes and checking them against the
project's assumed tables. The boards' registers are named and decoded as a
:class:`~ohmni_tb.protocol.profile.BusProfile` says (the assumed one unless given); a wheel
command is decoded in either jog form, so a capture shows which one the vendor sends.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError
from ohmni_tb.herkulex import EEP as HERKULEX_EEP
from ohmni_tb.herkulex import RAM as HERKULEX_RAM
from ohmni_tb.protocol import (
    REPLY_FLAG,
    Command,
    DecoderStats,
    Memory,
    Packet,
    PacketDecoder,
    ReadReply,
    StatusReply,
    flag_names,
)
from ohmni_tb.protocol.connection import ReplyMatcher
from ohmni_tb.protocol.core import parse_status
from ohmni_tb.protocol.devices import DeviceId, device_name
from ohmni_tb.protocol.drive import WheelJogForm, decode_wheel_command
from ohmni_tb.protocol.profile import DEFAULT_PROFILE, BusProfile
from ohmni_tb.protocol.worm_neck import parse_feedback

__all__ = ["BusMonitor", "DeviceTraffic", "MonitorEvent", "describe"]

_LATENCY_WINDOW = 1024
#: Requests kept waiting for their replies; a capture of requests alone stays bounded.
_PENDING_LIMIT = 16


@functools.cache
def _board_registers(profile: BusProfile) -> dict[tuple[int, Memory, int], str]:
    """The boards' register names where ``profile`` puts them."""
    drive, core, worm = profile.drive, profile.core, profile.worm
    return {
        **{
            (sid, Memory.RAM, addr): name
            for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE)
            for addr, name in (
                (drive.count_addr, "count"),
                (drive.motor_position_addr, "motor_position"),
                (60, "absolute_position"),
                (62, "differential_position"),
                (drive.torque_addr, "torque (assumed)"),
                (0x6B, "unknown_6B"),
            )
        },
        (DeviceId.CORE, Memory.RAM, core.status_addr): "status (assumed)",
        (DeviceId.CORE, Memory.RAM, core.light_ring_addr): "light_ring",
        (DeviceId.WORM_NECK, Memory.RAM, worm.target_addr): "target (assumed)",
        (DeviceId.WORM_NECK, Memory.RAM, worm.feedback_addr): "feedback (assumed)",
    }


_TAG_ADDR = 0xF1
_BOARD_IDS = frozenset(
    {DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE, DeviceId.WORM_NECK}
)


def register_name(
    sid: int, memory: Memory, addr: int, profile: BusProfile = DEFAULT_PROFILE
) -> str:
    """A name for a register of device ``sid``: the boards' (where ``profile`` puts them),
    else HerkuleX's."""
    name = _board_registers(profile).get((sid, memory, addr))
    if name is not None:
        return name
    if addr == _TAG_ADDR and memory is Memory.EEP:
        return "firmware_tag"
    if sid not in _BOARD_IDS:
        table = HERKULEX_RAM if memory is Memory.RAM else HERKULEX_EEP
        try:
            return table.by_addr(addr).name
        except InvalidArgumentError:
            pass
    return f"{memory.name}[{addr}]"


def _value_text(reply: ReadReply, profile: BusProfile) -> str:
    sid, addr, data = reply.sid, reply.addr, reply.data
    drive, core, worm = profile.drive, profile.core, profile.worm
    try:
        if reply.memory is Memory.EEP and addr == _TAG_ADDR:
            return repr(data.decode("ascii", errors="replace"))
        if sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
            if addr == drive.count_addr and len(data) == 4:
                return str(int.from_bytes(data, "little", signed=True))
            if addr in (drive.motor_position_addr, 60) and len(data) == 2:
                return str(int.from_bytes(data, "little"))
            if addr == 62 and len(data) == 2:
                return str(int.from_bytes(data, "little", signed=True))
        if sid == DeviceId.CORE and addr == core.status_addr:
            s = parse_status(reply, core)
            cells = "/".join(str(mv) for mv in s.cell_mv)
            return (
                f"cells {cells} mV, pack {s.pack_mv} mV, {s.charging_current_ma} mA, "
                f"{'docked' if s.docked else 'undocked'}, {s.percent} %"
            )
        if sid == DeviceId.WORM_NECK and addr == worm.feedback_addr:
            f = parse_feedback(reply, worm)
            return f"position {f.position} {flag_names(f.flags)}"
        if sid not in _BOARD_IDS and reply.memory is Memory.RAM:
            reg = HERKULEX_RAM.by_addr(addr)
            if reg.size == len(data):
                return str(reg.decode(data))
    except (MalformedReplyError, InvalidArgumentError, ValueError):
        pass
    return data.hex(" ")


def describe(packet: Packet, profile: BusProfile = DEFAULT_PROFILE) -> str:
    """One line of words for a packet, request or reply, the boards' registers read as
    ``profile`` says."""
    base = packet.cmd & ~REPLY_FLAG
    try:
        cmd_name = Command(base).name
    except ValueError:
        return f"unknown command 0x{packet.cmd:02X} data {packet.data.hex(' ')}"
    sid = packet.sid
    if not packet.is_reply:
        if base in (Command.RAM_READ, Command.EEP_READ) and len(packet.data) == 2:
            memory = Memory.RAM if base == Command.RAM_READ else Memory.EEP
            name = register_name(sid, memory, packet.data[0], profile)
            return f"{cmd_name} {name} len {packet.data[1]}"
        if base in (Command.RAM_WRITE, Command.EEP_WRITE) and len(packet.data) >= 2:
            memory = Memory.RAM if base == Command.RAM_WRITE else Memory.EEP
            name = register_name(sid, memory, packet.data[0], profile)
            return f"{cmd_name} {name} = {packet.data[2:].hex(' ')}"
        if base in (Command.S_JOG, Command.I_JOG):
            try:
                # Either form: a capture shows which one the vendor's software sends.
                form = dataclasses.replace(profile.drive, wheel_form=WheelJogForm(base))
                wheels = decode_wheel_command(packet, form)
            except MalformedReplyError:
                wheels = {}
            if wheels:
                parts = ", ".join(f"{device_name(s)} pwm {v:+d}" for s, v in wheels.items())
                return f"{cmd_name} wheels: {parts} (board frame)"
        return f"{cmd_name} {packet.data.hex(' ')}".rstrip()
    try:
        if base in (Command.RAM_READ, Command.EEP_READ):
            reply = ReadReply.parse(packet)
            text = f"{cmd_name} reply {register_name(sid, reply.memory, reply.addr, profile)} = "
            text += _value_text(reply, profile)
            if reply.status_error:
                text += f" [error {flag_names(reply.status_error)}]"
            return text
        status = StatusReply.parse(packet)
        error, detail = flag_names(status.status_error), flag_names(status.status_detail)
        return f"{cmd_name} reply error {error} detail {detail}"
    except MalformedReplyError as exc:
        return f"{cmd_name} reply, malformed: {exc}"


@dataclass(frozen=True, slots=True)
class MonitorEvent:
    """One decoded packet.

    Attributes:
        t_s: When it arrived, if known.
        packet: The packet.
        device: The device's short name.
        text: The packet in words.
        latency_s: For a reply, the time since the request it answers, if known.
    """

    t_s: float | None
    packet: Packet
    device: str
    text: str
    latency_s: float | None


@dataclass(slots=True)
class DeviceTraffic:
    """What one device id saw on the bus."""

    sid: int
    requests: int = 0
    replies: int = 0
    unanswered: int = 0
    error_replies: int = 0
    first_s: float | None = None  # time of the first request seen
    last_s: float | None = None  # time of the last request seen
    latencies_s: list[float] = field(default_factory=list)

    def rate_hz(self) -> float | None:
        """Requests a second between the first and the last request, if times are known."""
        if self.first_s is None or self.last_s is None or self.last_s <= self.first_s:
            return None
        return (self.requests - 1) / (self.last_s - self.first_s) if self.requests > 1 else None


class BusMonitor:
    """Decode a byte stream into described packets and per-device statistics.

    Args:
        profile: Where the boards' registers are, and how they decode (default the
            assumed profile; ``ohmni bus monitor`` passes the configured one).
    """

    def __init__(self, profile: BusProfile = DEFAULT_PROFILE) -> None:
        self.profile = profile
        self._decoder = PacketDecoder()
        # The bus engine's own pairing rule: a reply answers the oldest request it fits,
        # so a capture taken at the host, where requests run ahead of their replies,
        # pairs as well as one taken on the wire.
        self._pending: ReplyMatcher[tuple[Packet, float | None]] = ReplyMatcher(
            limit=_PENDING_LIMIT
        )
        self.devices: dict[int, DeviceTraffic] = {}

    @property
    def decoder_stats(self) -> DecoderStats:
        """Junk, checksum errors and the rest of the decoder's counters."""
        return self._decoder.stats

    def feed(self, data: bytes, t_s: float | None = None) -> list[MonitorEvent]:
        """Decode ``data`` (arrived at ``t_s``) into events."""
        return [self._event(p, t_s) for p in self._decoder.feed(data)]

    def finish(self) -> None:
        """The capture ended: a request still waiting for its answer counts as unanswered."""
        self._unanswered(self._pending.clear())

    def _traffic(self, sid: int) -> DeviceTraffic:
        traffic = self.devices.get(sid)
        if traffic is None:
            traffic = self.devices[sid] = DeviceTraffic(sid)
        return traffic

    def _unanswered(self, requests: list[tuple[Packet, float | None]]) -> None:
        for request, _ in requests:
            self._traffic(request.sid).unanswered += 1

    def _event(self, packet: Packet, t_s: float | None) -> MonitorEvent:
        latency: float | None = None
        traffic = self._traffic(packet.sid)
        if packet.is_reply:
            traffic.replies += 1
            answered, overtaken = self._pending.match(packet)
            self._unanswered(overtaken)
            if answered is not None:
                sent_s = answered[1]
                if t_s is not None and sent_s is not None:
                    latency = t_s - sent_s
                    if len(traffic.latencies_s) < _LATENCY_WINDOW:
                        traffic.latencies_s.append(latency)
            if len(packet.data) >= 2 and packet.data[-2]:
                traffic.error_replies += 1
        else:
            traffic.requests += 1
            if t_s is not None:
                if traffic.first_s is None:
                    traffic.first_s = t_s
                traffic.last_s = t_s
            if packet.cmd in _ANSWERED:
                self._unanswered(self._pending.add(packet, (packet, t_s)))
        text = describe(packet, self.profile)
        return MonitorEvent(t_s, packet, device_name(packet.sid), text, latency)


_ANSWERED = frozenset({Command.RAM_READ, Command.EEP_READ, Command.STAT})
