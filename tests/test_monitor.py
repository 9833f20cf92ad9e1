"""The bus monitor: captured bytes in, described packets and per-device statistics out."""

from __future__ import annotations

import asyncio

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.monitor import BusMonitor, MonitorEvent, describe, register_name
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Memory,
    Packet,
    encode_packet,
)
from ohmni_tb.protocol.core import TbcoreStatus, encode_status, read_status, set_light_ring
from ohmni_tb.protocol.drive import read_count, read_firmware_tag, wheel_command
from ohmni_tb.protocol.worm_neck import (
    WormFeedback,
    WormFlags,
    encode_feedback,
    read_feedback,
    set_target,
)
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.transport import Transport, open_transport
from ohmni_tb.transport.base import LostHandler, Receiver


def _reply(request: Packet, data: bytes, error: int = 0, detail: int = 0) -> Packet:
    """The read reply a device sends to ``request``."""
    addr = request.data[0]
    return Packet(
        request.sid,
        request.cmd | REPLY_FLAG,
        bytes((addr, len(data))) + data + bytes((error, detail)),
    )


STATUS = TbcoreStatus(
    cell_mv=(3300, 3301, 3302, 3303, 3304),
    charging_current_ma=-1500,
    docked=True,
    fet_status=3,
    status=(1, 0, 0, 0),
)

#: A session as it would be logged from the line: requests and the replies to them.
SESSION = [
    read_count(0),
    _reply(read_count(0), (-123_456).to_bytes(4, "little", signed=True)),
    read_status(),
    _reply(read_status(), encode_status(STATUS)),
    wheel_command(300, 300),
    set_light_ring(0, 255, 255),
    read_feedback(),
    _reply(read_feedback(), encode_feedback(WormFeedback(100_000, WormFlags.MOVING))),
    read_firmware_tag(20),
    _reply(read_firmware_tag(20), b"sim-core-1.0"),
    set_target(-5000),
]
CAPTURE = b"".join(encode_packet(p) for p in SESSION)

EXPECTED = [
    ("left", "RAM_READ count len 4"),
    ("left", "RAM_READ reply count = -123456"),
    ("core", "RAM_READ status (assumed) len 18"),
    (
        "core",
        "RAM_READ reply status (assumed) = cells 3300/3301/3302/3303/3304 mV, "
        "pack 16510 mV, -1500 mA, docked, 80 %",
    ),
    ("broadcast", "S_JOG wheels: left pwm +300, right pwm -300 (board frame)"),
    ("core", "RAM_WRITE light_ring = 00 ff ff"),
    ("worm-neck", "RAM_READ feedback (assumed) len 5"),
    ("worm-neck", "RAM_READ reply feedback (assumed) = position 100000 MOVING"),
    ("core", "EEP_READ firmware_tag len 0"),
    ("core", "EEP_READ reply firmware_tag = 'sim-core-1.0'"),
    ("worm-neck", "RAM_WRITE target (assumed) = 78 ec ff ff"),
]


def _texts(events: list[MonitorEvent]) -> list[tuple[str, str]]:
    return [(e.device, e.text) for e in events]


# -- describing packets -------------------------------------------------------------------


@pytest.mark.parametrize("chunk", [len(CAPTURE), len(CAPTURE) // 2 + 1, 1])
def test_a_capture_is_described_with_device_and_register_names(chunk: int) -> None:
    monitor = BusMonitor()
    events: list[MonitorEvent] = []
    for i in range(0, len(CAPTURE), chunk):
        events += monitor.feed(CAPTURE[i : i + chunk])
    assert _texts(events) == EXPECTED
    assert [e.packet for e in events] == SESSION
    assert all(e.t_s is None and e.latency_s is None for e in events)
    assert monitor.decoder_stats.packets == len(SESSION)
    assert monitor.decoder_stats.bytes_discarded == 0


def test_per_device_counts_of_a_capture() -> None:
    monitor = BusMonitor()
    monitor.feed(CAPTURE)
    left, core, neck = monitor.devices[0], monitor.devices[20], monitor.devices[4]
    assert (left.requests, left.replies, left.unanswered) == (1, 1, 0)
    assert (core.requests, core.replies, core.unanswered) == (3, 2, 0)
    assert (neck.requests, neck.replies) == (2, 1)
    assert monitor.devices[BROADCAST_ID].requests == 1
    assert 1 not in monitor.devices


def test_a_request_overtaken_by_a_later_reply_is_counted_unanswered() -> None:
    monitor = BusMonitor()
    monitor.feed(encode_packet(read_count(1)))
    monitor.feed(encode_packet(read_count(0)))
    monitor.feed(encode_packet(_reply(read_count(0), bytes(4))))
    monitor.feed(encode_packet(Packet(20, Command.STAT)))
    monitor.feed(encode_packet(read_status()))
    assert monitor.devices[1].unanswered == 1
    assert monitor.devices[0].unanswered == 0
    # The STAT and the read may still be answered (a host-side capture runs ahead).
    assert monitor.devices[20].unanswered == 0
    events = monitor.feed(encode_packet(_reply(read_status(), bytes(18))))
    assert monitor.devices[20].unanswered == 1  # the STAT, overtaken by the read's reply
    assert events[0].latency_s is None  # no times given


def test_pipelined_requests_pair_with_their_replies_in_order() -> None:
    monitor = BusMonitor()
    monitor.feed(encode_packet(read_count(0)), 0.000)
    monitor.feed(encode_packet(read_count(1)), 0.003)
    monitor.feed(encode_packet(read_status()), 0.006)
    monitor.feed(encode_packet(_reply(read_count(0), bytes(4))), 0.016)
    monitor.feed(encode_packet(_reply(read_count(1), bytes(4))), 0.016)
    monitor.feed(encode_packet(_reply(read_status(), bytes(18))), 0.016)
    monitor.finish()
    for sid, latency in ((0, 0.016), (1, 0.013), (20, 0.010)):
        traffic = monitor.devices[sid]
        assert (traffic.replies, traffic.unanswered) == (1, 0)
        assert traffic.latencies_s == [pytest.approx(latency)]


def test_a_request_left_unanswered_at_the_end_of_a_capture_is_counted() -> None:
    monitor = BusMonitor()
    monitor.feed(encode_packet(read_status()))
    assert monitor.devices[20].unanswered == 0  # its answer may still come
    monitor.finish()
    assert monitor.devices[20].unanswered == 1


def test_rate_is_measured_between_requests() -> None:
    monitor = BusMonitor()
    for i in range(5):
        monitor.feed(encode_packet(read_count(0)), t_s=0.1 * i)
        monitor.feed(encode_packet(_reply(read_count(0), bytes(4))), t_s=0.1 * i + 0.003)
    rate = monitor.devices[0].rate_hz()
    assert rate is not None
    assert rate == pytest.approx(10.0)


def test_writes_and_jogs_are_not_expected_to_answer() -> None:
    monitor = BusMonitor()
    for packet in (set_light_ring(1, 2, 3), wheel_command(10, 10), read_count(0)):
        monitor.feed(encode_packet(packet))
    assert all(t.unanswered == 0 for t in monitor.devices.values())


def test_replies_are_paired_with_requests_for_latency() -> None:
    monitor = BusMonitor()
    t = 10.0
    for i in range(3):
        assert monitor.feed(encode_packet(read_count(0)), t)[0].latency_s is None
        (event,) = monitor.feed(
            encode_packet(_reply(read_count(0), bytes(4))), t + 0.0025 + i / 1e3
        )
        assert event.latency_s == pytest.approx(0.0025 + i / 1e3)
        assert event.t_s == pytest.approx(t + 0.0025 + i / 1e3)
        t += 0.02
    traffic = monitor.devices[0]
    assert traffic.latencies_s == pytest.approx([0.0025, 0.0035, 0.0045])
    assert traffic.first_s == 10.0


def test_the_request_rate_of_a_stream() -> None:
    monitor = BusMonitor()
    assert monitor.feed(encode_packet(read_count(1)), 0.0)
    assert monitor.devices[1].rate_hz() is None  # one request: no rate yet
    for i in range(1, 100):
        t = i / 50
        monitor.feed(encode_packet(read_count(1)), t)
        monitor.feed(encode_packet(_reply(read_count(1), bytes(4))), t + 0.002)
    assert monitor.devices[1].rate_hz() == pytest.approx(50.0, rel=0.01)


def test_a_reply_to_something_else_has_no_latency() -> None:
    monitor = BusMonitor()
    monitor.feed(encode_packet(read_count(0)), 1.0)
    (event,) = monitor.feed(encode_packet(_reply(read_count(1), bytes(4))), 1.001)
    assert event.latency_s is None
    (event,) = monitor.feed(encode_packet(_reply(read_count(0), bytes(4))), 1.002)
    assert event.latency_s == pytest.approx(0.002)


def test_error_replies_are_flagged_and_counted() -> None:
    monitor = BusMonitor()
    request = Packet(0, Command.RAM_READ, bytes((0x99, 2)))
    monitor.feed(encode_packet(request))
    (event,) = monitor.feed(encode_packet(_reply(request, b"\0\0", error=0x08, detail=0x10)))
    assert event.text == "RAM_READ reply RAM[153] = 00 00 [error INVALID_PACKET]"
    assert monitor.devices[0].error_replies == 1


def test_junk_and_broken_frames_are_counted_by_the_decoder() -> None:
    broken = bytearray(encode_packet(read_count(0)))
    broken[-1] ^= 0x10
    good = encode_packet(read_status())
    monitor = BusMonitor()
    events = monitor.feed(b"\x00\x13junk" + bytes(broken) + good + b"\xff")
    assert [e.packet for e in events] == [read_status()]
    stats = monitor.decoder_stats
    assert stats.checksum_errors == 1
    assert stats.bytes_discarded == 6 + len(broken)
    assert stats.bytes_pending == 1  # a lone FF may start the next header


# -- describe() and register names --------------------------------------------------------


@pytest.mark.parametrize(
    ("packet", "text"),
    [
        (Packet(0, Command.STAT), "STAT"),
        (Packet(0, Command.STAT | REPLY_FLAG, b"\x08\x14"), "STAT reply error INVALID_PACKET"),
        (Packet(3, Command.RAM_READ, bytes((60, 2))), "RAM_READ absolute_position len 2"),
        (
            _reply(Packet(0, Command.RAM_READ, bytes((58, 2))), (16383).to_bytes(2, "little")),
            "RAM_READ reply motor_position = 16383",
        ),
        (
            _reply(
                Packet(1, Command.RAM_READ, bytes((62, 2))),
                (-20).to_bytes(2, "little", signed=True),
            ),
            "RAM_READ reply differential_position = -20",
        ),
        (Packet(0, 0x0A), "unknown command 0x0A"),
        (Packet(0, Command.RAM_READ | REPLY_FLAG, b"\x3b\x04\x00"), "malformed"),
        (Packet(BROADCAST_ID, Command.REBOOT), "REBOOT"),
    ],
)
def test_describe(packet: Packet, text: str) -> None:
    assert text in describe(packet)


@pytest.mark.parametrize(
    ("sid", "memory", "addr", "name"),
    [
        (0, Memory.RAM, 59, "count"),
        (1, Memory.RAM, 58, "motor_position"),
        (20, Memory.RAM, 0xC1, "light_ring"),
        (20, Memory.EEP, 0xF1, "firmware_tag"),
        (4, Memory.RAM, 0x70, "target (assumed)"),
        (3, Memory.RAM, 52, "torque_control"),
        (11, Memory.EEP, 0, "model_no1"),
        (20, Memory.RAM, 52, "RAM[52]"),  # a board is not a HerkuleX servo
    ],
)
def test_register_names(sid: int, memory: Memory, addr: int, name: str) -> None:
    assert register_name(sid, memory, addr) == name


# -- a live session on the simulator, tapped ----------------------------------------------


class _Tap(Transport):
    """Records every byte both ways with the loop time, like a sniffer on the line."""

    def __init__(self, inner: Transport) -> None:
        self.inner = inner
        self.baudrate = inner.baudrate
        self.log: list[tuple[float, bytes]] = []

    @property
    def closed(self) -> bool:
        return self.inner.closed

    def write_nowait(self, data: bytes) -> None:
        self.log.append((asyncio.get_running_loop().time(), data))
        self.inner.write_nowait(data)

    async def read(self) -> bytes:
        data = await self.inner.read()
        self.log.append((asyncio.get_running_loop().time(), data))
        return data

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        def tapped(data: bytes) -> None:
            self.log.append((asyncio.get_running_loop().time(), data))
            on_data(data)

        self.inner.start_receiving(tapped, on_lost)

    async def aclose(self) -> None:
        await self.inner.aclose()


def test_a_tapped_simulator_session_decodes_with_the_bus_latencies() -> None:
    async def main() -> tuple[_Tap, Bus]:
        tap = _Tap(await open_transport("sim://"))
        async with Bus(tap) as bus:
            for _ in range(5):
                await bus.read(0, 59, 4)
                await bus.read(20, 0xA0, 18)
                await bus.send(wheel_command(200, 200))
                await asyncio.sleep(0.02)
        return tap, bus

    tap, bus = run_virtual(main())
    monitor = BusMonitor()
    events: list[MonitorEvent] = []
    for t, chunk in tap.log:
        events += monitor.feed(chunk, t)
    assert len(events) == 5 * 5
    assert monitor.decoder_stats.bytes_discarded == 0
    core = monitor.devices[20]
    assert (core.requests, core.replies, core.unanswered) == (5, 5, 0)
    stats = bus.stats.devices
    for sid in (0, 20):
        latencies = sorted(monitor.devices[sid].latencies_s)
        assert latencies[len(latencies) // 2] == pytest.approx(stats[sid].latency_p50_s)
    assert "undocked" in next(e.text for e in events if e.packet.sid == 20 and e.packet.is_reply)
