"""The async Bus against a scripted HerkuleX-style device on the in-memory pair.

Where a test needs a reply to be late or missing it uses short timeouts (10-50 ms);
where a reply must be on time it uses a long one, so a loaded machine cannot turn a
success into a timeout. Nothing asserts speed: only lower bounds on elapsed time.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Iterable
from dataclasses import dataclass

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.errors import (
    BusClosedError,
    BusTimeoutError,
    InvalidArgumentError,
    OutOfRangeError,
    TransportClosedError,
    TransportError,
)
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Memory,
    Packet,
    PacketDecoder,
    StatusDetail,
    StatusError,
    StatusReply,
    encode_packet,
    read_request,
    write_request,
)
from ohmni_tb.transport import Manipulator, MemoryTransport, corrupt_byte, drop_bytes

#: A reply timeout that only a hang reaches: for requests that must succeed.
ON_TIME_S = 1.0
#: Generous slack for comparing loop-clock readings (lower bounds only).
CLOCK_SLACK_S = 0.001

Responder = Callable[[Packet], list[Packet]]


class FakeServo:
    """HerkuleX-style devices on the device end of a memory pair.

    It decodes what the bus sends and answers the way the manual says: reads under ACK
    policy 1 and 2, STAT always, writes and the rest only under policy 2, broadcast
    never. Tests reshape it with the attributes below or replace :meth:`answer`.
    """

    def __init__(self, transport: MemoryTransport, sids: Iterable[int] = (3,)) -> None:
        self.transport = transport
        self.sids = set(sids)
        self.ack_policy = 1
        self.reply_delay_s = 0.0
        self.echo = False
        self.hang_up = False
        self.respond: Responder | None = None
        self.registers: dict[tuple[int, int], bytes] = {}
        self.received: list[Packet] = []
        self._arrived = asyncio.Event()

    async def wait_received(self, count: int) -> None:
        """Wait until ``count`` packets have arrived (a hang ends in a clear failure)."""
        async with asyncio.timeout(5.0):
            while len(self.received) < count:
                self._arrived.clear()
                await self._arrived.wait()

    def answer(self, request: Packet) -> list[Packet]:
        """The replies a device with id ``request.sid`` sends (none for broadcast)."""
        sid, cmd = request.sid, request.cmd
        if sid not in self.sids:
            return []
        if cmd in (Command.RAM_READ, Command.EEP_READ):
            if self.ack_policy < 1:
                return []
            addr, length = request.data[0], request.data[1]
            value = self.registers.get((sid, addr), bytes([addr]) * max(length, 1))
            if length:
                value = value[:length].ljust(length, b"\x00")
            return [Packet(sid, cmd | REPLY_FLAG, bytes([addr, len(value)]) + value + b"\0\0")]
        if cmd in (Command.RAM_WRITE, Command.EEP_WRITE):
            self.registers[sid, request.data[0]] = request.data[2:]
        if cmd == Command.STAT or self.ack_policy >= 2:
            return [Packet(sid, cmd | REPLY_FLAG, b"\x00\x00")]
        return []

    async def run(self) -> None:
        decoder = PacketDecoder()
        try:
            while True:
                data = await self.transport.read()
                for packet in decoder.feed(data):
                    await self._handle(packet)
        except TransportClosedError:
            return

    async def _handle(self, packet: Packet) -> None:
        self.received.append(packet)
        self._arrived.set()
        if self.echo:
            await self.transport.write(encode_packet(packet))
        if self.hang_up:
            await self.transport.aclose()
            raise TransportClosedError("hung up")
        replies = (self.respond or self.answer)(packet)
        if replies and self.reply_delay_s:
            await asyncio.sleep(self.reply_delay_s)
        for reply in replies:
            await self.transport.write(encode_packet(reply))


@dataclass
class Rig:
    host: MemoryTransport
    device: FakeServo


@pytest.fixture
async def rig(memory_pair: tuple[MemoryTransport, MemoryTransport]) -> AsyncIterator[Rig]:
    host, device_end = memory_pair
    device = FakeServo(device_end)
    task = asyncio.create_task(device.run(), name="fake-servo")
    yield Rig(host, device)
    task.cancel()
    await asyncio.wait({task})
    if not task.cancelled() and task.exception() is not None:
        raise AssertionError("the fake device failed") from task.exception()


def write_times(times: list[float]) -> Manipulator:
    """A clean line that notes the loop time of every write."""
    loop = asyncio.get_running_loop()

    def record(data: bytes) -> list[bytes | float]:
        times.append(loop.time())
        return [data]

    return record


# -- replies ------------------------------------------------------------------------------


async def test_read_returns_the_register_and_counts_latency(rig: Rig) -> None:
    rig.device.registers[3, 0x3A] = (1234).to_bytes(2, "little")
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        for _ in range(5):
            reply = await bus.read(3, 0x3A, 2)
            assert (reply.sid, reply.addr, reply.memory) == (3, 0x3A, Memory.RAM)
            assert int.from_bytes(reply.data, "little") == 1234
        stats = bus.stats
    assert rig.device.received == [read_request(3, 0x3A, 2)] * 5
    device = stats.devices[3]
    assert (device.requests, device.replies, device.timeouts, device.retries) == (5, 5, 0, 0)
    assert device.latency_p50_s is not None
    assert device.latency_p99_s is not None
    assert 0 <= device.latency_p50_s <= device.latency_p99_s
    assert stats.bytes_out == 5 * 9
    assert stats.decoder.packets == 5
    assert stats.unmatched == stats.echoes == 0


async def test_read_eeprom_and_a_length_zero_tag(rig: Rig) -> None:
    rig.device.sids.add(20)
    rig.device.registers[20, 0xF1] = b"stable"
    rig.device.registers[3, 0x1E] = bytes.fromhex("B8 01 40 1F")
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        tag = await bus.read(20, 0xF1, 0, Memory.EEP)
        gains = await bus.read(3, 0x1E, 4, Memory.EEP)
    assert (tag.data, tag.memory) == (b"stable", Memory.EEP)
    assert gains.data == bytes.fromhex("B8 01 40 1F")


async def test_stat_gets_a_status_reply(rig: Rig) -> None:
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        reply = await bus.request(Packet(3, Command.STAT))
    assert reply is not None
    assert StatusReply.parse(reply).status_error == 0


async def test_concurrent_requests_go_one_at_a_time(rig: Rig) -> None:
    rig.device.reply_delay_s = 0.005
    sent: list[float] = []
    replied: list[float] = []
    rig.host.set_manipulator(write_times(sent))
    rig.device.transport.set_manipulator(write_times(replied))
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        replies = await asyncio.gather(*(bus.read(3, addr, 1) for addr in (0x10, 0x20, 0x30)))
    assert [r.data for r in replies] == [b"\x10", b"\x20", b"\x30"]
    # Each request waits for the reply to the one before it.
    assert len(sent) == len(replied) == 3
    assert sent[0] <= replied[0] <= sent[1] <= replied[1] <= sent[2] <= replied[2]


# -- timeouts and stray replies -----------------------------------------------------------


async def test_timeout_names_sid_command_and_attempts(rig: Rig) -> None:
    rig.device.sids.clear()
    async with Bus(rig.host, timeout_s=0.01, retries=2) as bus:
        with pytest.raises(BusTimeoutError) as info:
            await bus.read(3, 0x35, 1)
        stats = bus.stats.devices[3]
    err = info.value
    assert isinstance(err, TimeoutError)
    assert (err.sid, err.cmd, err.attempts) == (3, Command.RAM_READ, 3)
    assert "sid 3" in str(err)
    assert "0x04" in str(err)
    assert "3 attempt" in str(err)
    assert rig.device.received == [read_request(3, 0x35, 1)] * 3
    assert (stats.requests, stats.timeouts, stats.retries, stats.replies) == (3, 3, 2, 0)


async def test_per_request_retries_and_timeout(rig: Rig) -> None:
    rig.device.sids.clear()
    async with Bus(rig.host, timeout_s=ON_TIME_S, retries=5) as bus:
        with pytest.raises(BusTimeoutError) as info:
            await bus.request(Packet(3, Command.STAT), timeout_s=0.01, retries=0)
    assert info.value.attempts == 1
    assert info.value.timeout_s == 0.01
    assert len(rig.device.received) == 1


async def test_late_reply_is_discarded_not_handed_to_the_next_request(rig: Rig) -> None:
    rig.device.registers[3, 0x10] = b"\xaa"
    rig.device.registers[3, 0x20] = b"\xbb"
    rig.device.reply_delay_s = 0.05
    async with Bus(rig.host, timeout_s=0.01, retries=0) as bus:
        with pytest.raises(BusTimeoutError):
            await bus.read(3, 0x10, 1)
        rig.device.reply_delay_s = 0.0
        # The late 0x10 reply arrives while this request waits; it must not be taken.
        reply = await bus.request(read_request(3, 0x20, 1), timeout_s=ON_TIME_S)
        stats = bus.stats
    assert reply is not None
    assert reply.data == bytes([0x20, 1, 0xBB, 0, 0])
    assert stats.unmatched == 1
    assert stats.devices[3].unmatched == 1


@pytest.mark.parametrize("then_the_right_one", [True, False], ids=["then-right", "only-wrong"])
async def test_reply_from_wrong_sid_or_address_is_not_accepted(
    rig: Rig, then_the_right_one: bool
) -> None:
    rig.device.sids.update({4})
    rig.device.registers[3, 0x35] = b"\x01"

    def respond(request: Packet) -> list[Packet]:
        code = request.cmd | REPLY_FLAG
        wrong = [
            Packet(4, code, bytes([0x35, 1, 0xEE, 0, 0])),
            Packet(3, code, bytes([0x36, 1, 0xEE, 0, 0])),
        ]
        return wrong + (rig.device.answer(request) if then_the_right_one else [])

    rig.device.respond = respond
    timeout_s = ON_TIME_S if then_the_right_one else 0.02
    async with Bus(rig.host, timeout_s=timeout_s, retries=0) as bus:
        if then_the_right_one:
            assert (await bus.read(3, 0x35, 1)).data == b"\x01"
        else:
            with pytest.raises(BusTimeoutError):
                await bus.read(3, 0x35, 1)
        stats = bus.stats
    assert stats.unmatched == 2
    assert (stats.devices[3].unmatched, stats.devices[4].unmatched) == (1, 1)


async def test_corrupted_reply_is_retried(rig: Rig) -> None:
    rig.device.registers[3, 0x35] = b"\x01"
    # Offset 9 of the device's stream is the first reply's data byte.
    rig.device.transport.set_manipulator(corrupt_byte(9, xor=0x10))
    async with Bus(rig.host, timeout_s=0.05, retries=2) as bus:
        reply = await bus.read(3, 0x35, 1)
        stats = bus.stats
    assert reply.data == b"\x01"
    assert stats.decoder.checksum_errors == 1
    assert stats.devices[3].timeouts >= 1
    assert stats.devices[3].retries >= 1
    assert len(rig.device.received) == 1 + stats.devices[3].retries


async def test_a_reply_whose_length_byte_disagrees_is_retried_not_raised(rig: Rig) -> None:
    rig.device.registers[3, 0x35] = b"\x01"
    sent = 0

    def respond(request: Packet) -> list[Packet]:
        # The first answer is what a bit-0 error in the size byte leaves: a frame that
        # passes both checksums but is one byte short of what its length byte says.
        nonlocal sent
        sent += 1
        if sent == 1:
            return [Packet(3, request.cmd | REPLY_FLAG, bytes([0x35, 1, 0x01, 0]))]
        return rig.device.answer(request)

    rig.device.respond = respond
    async with Bus(rig.host, timeout_s=0.05, retries=2) as bus:
        reply = await bus.read(3, 0x35, 1)
        stats = bus.stats
    assert reply.data == b"\x01"
    assert stats.devices[3].unmatched == 1
    assert stats.devices[3].retries == 1


async def test_dropped_reply_bytes_time_out_then_retry(rig: Rig) -> None:
    rig.device.registers[3, 0x35] = b"\x01"
    # Lose one data byte of the first reply: its frame never completes.
    rig.device.transport.set_manipulator(drop_bytes(1, skip=9))
    async with Bus(rig.host, timeout_s=0.05, retries=2) as bus:
        reply = await bus.read(3, 0x35, 1)
        stats = bus.stats
    assert reply.data == b"\x01"
    assert stats.devices[3].timeouts >= 1
    # The bus gave the cut frame up at the timeout instead of gluing it to the retry's.
    assert stats.decoder.expired == 1
    assert stats.decoder.checksum_errors == 0


async def test_cancelled_request_leaves_the_bus_usable(rig: Rig) -> None:
    served = 0

    def counter(request: Packet) -> list[Packet]:
        # Each read of this register answers how many reads it has served.
        nonlocal served
        served += 1
        return [Packet(3, request.cmd | REPLY_FLAG, bytes([0x40, 1, served, 0, 0]))]

    rig.device.respond = counter
    rig.device.reply_delay_s = 0.02
    async with Bus(rig.host, timeout_s=0.2, retries=0) as bus:
        first = asyncio.create_task(bus.read(3, 0x40, 1))
        await rig.device.wait_received(1)
        first.cancel()
        with pytest.raises(asyncio.CancelledError):
            await first
        # Same register: the cancelled read still holds its reply window, and its reply
        # (served=1) is counted as abandoned, never taken as this request's.
        reply = await bus.read(3, 0x40, 1)
        stats = bus.stats
    assert reply.data == b"\x02"
    assert stats.abandoned == 1
    assert stats.unmatched == 0
    assert len(rig.device.received) == 2


async def test_echo_of_our_own_request_is_counted(rig: Rig) -> None:
    rig.device.echo = True
    async with Bus(rig.host, timeout_s=ON_TIME_S, guard_s=0.005) as bus:
        assert (await bus.read(3, 0x35, 1)).data == b"\x35"
        assert await bus.write(3, 0x35, b"\x07") is None
        assert (await bus.read(3, 0x35, 1)).data == b"\x07"
        stats = bus.stats
    assert stats.echoes == 3
    assert stats.unmatched == 0


# -- what is sent, and when ---------------------------------------------------------------


async def test_write_under_default_policy_does_not_wait(rig: Rig) -> None:
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        assert bus.ack_policy(3) == 1
        assert await bus.write(3, 0x35, b"\x01") is None
        assert (await bus.read(3, 0x35, 1)).data == b"\x01"
        stats = bus.stats.devices[3]
    assert rig.device.received[0] == write_request(3, 0x35, b"\x01")
    assert (stats.requests, stats.replies, stats.timeouts) == (2, 1, 0)


async def test_ack_policy_2_makes_writes_wait_for_status(rig: Rig) -> None:
    rig.device.ack_policy = 2
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        bus.set_ack_policy(3, 2)
        status = await bus.write(3, 0x35, b"\x01")
        stats = bus.stats
    assert status == StatusReply(
        3, Command.RAM_WRITE | REPLY_FLAG, StatusError.NONE, StatusDetail.NONE
    )
    assert stats.devices[3].replies == 1
    assert stats.unmatched == 0


async def test_write_expecting_status_is_never_repeated(rig: Rig) -> None:
    # The bus believes policy 2 but the device runs policy 1: no status comes.
    async with Bus(rig.host, timeout_s=0.01, retries=3) as bus:
        bus.set_ack_policy(3, 2)
        with pytest.raises(BusTimeoutError) as info:
            await bus.write(3, 0x35, b"\x01")
    assert info.value.attempts == 1
    assert rig.device.received == [write_request(3, 0x35, b"\x01")]


async def test_ack_policy_is_checked(rig: Rig) -> None:
    async with Bus(rig.host) as bus:
        with pytest.raises(OutOfRangeError, match="ack policy"):
            bus.set_ack_policy(3, 3)


async def test_broadcast_never_waits(rig: Rig) -> None:
    async with Bus(rig.host, timeout_s=0.5, retries=0) as bus:
        bus.set_ack_policy(BROADCAST_ID, 2)
        assert await bus.write(BROADCAST_ID, 0x34, b"\x60") is None
        forced = Packet(BROADCAST_ID, Command.RAM_WRITE, b"\x35\x01\x01")
        assert await bus.request(forced, expect_reply=True) is None
        await bus.send(Packet(BROADCAST_ID, Command.REBOOT))
        # send() returns once the bytes are in the port; the device reads them after.
        await rig.device.wait_received(3)
        stats = bus.stats
    assert [p.cmd for p in rig.device.received] == [Command.RAM_WRITE] * 2 + [Command.REBOOT]
    assert stats.devices[BROADCAST_ID].timeouts == 0
    assert stats.devices[BROADCAST_ID].requests == 3


async def test_stat_to_broadcast_is_refused_before_sending(rig: Rig) -> None:
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        with pytest.raises(InvalidArgumentError, match="broadcast"):
            await bus.request(Packet(BROADCAST_ID, Command.STAT))
        # The bus stays usable.
        assert await bus.request(Packet(3, Command.STAT)) is not None
    assert rig.device.received == [Packet(3, Command.STAT)]


async def test_guard_between_requests_is_honoured(rig: Rig) -> None:
    guard_s = 0.02
    sent: list[float] = []
    replied: list[float] = []
    rig.host.set_manipulator(write_times(sent))
    rig.device.transport.set_manipulator(write_times(replied))
    async with Bus(rig.host, timeout_s=ON_TIME_S, guard_s=guard_s) as bus:
        await bus.write(3, 0x35, b"\x01")
        await bus.write(3, 0x35, b"\x02")
        await bus.read(3, 0x35, 1)
        await bus.read(3, 0x35, 1)
        await bus.write(3, 0x35, b"\x03")
    assert len(sent) == 5
    assert len(replied) == 2
    # After a write: the guard after the request. After a read: the guard after its reply
    # (this link has no baud rate, so nothing is pipelined).
    quiet_from = [sent[0], sent[1], replied[0], replied[1]]
    for start, next_request in zip(quiet_from, sent[1:], strict=True):
        assert next_request - start >= guard_s - CLOCK_SLACK_S


@pytest.mark.parametrize(
    "packet",
    [
        Packet(0xFF, Command.RAM_READ, b"\x35\x01"),
        Packet(3, 0x100),
        Packet(3, Command.RAM_WRITE, bytes(58)),
    ],
    ids=["sid-FF", "cmd-100", "over-64-bytes"],
)
async def test_bad_packet_raises_before_anything_is_written(rig: Rig, packet: Packet) -> None:
    async with Bus(rig.host, timeout_s=ON_TIME_S, max_packet_size=64) as bus:
        with pytest.raises(OutOfRangeError):
            await bus.request(packet)
        with pytest.raises(OutOfRangeError, match="sid"):
            await bus.read(BROADCAST_ID, 0x35, 1)
        with pytest.raises(OutOfRangeError, match="len"):
            await bus.write(3, 0x35, b"")
        await asyncio.sleep(0.01)
        assert bus.stats.bytes_out == 0
    assert rig.host.bytes_written == 0
    assert rig.device.received == []


async def test_a_read_whose_reply_cannot_fit_fails_up_front(rig: Rig) -> None:
    # A 100-byte read is answered with 111 bytes: past a 64-byte limit the reply would be
    # dropped by the receiver, so the read could only time out. It is refused unsent.
    async with Bus(rig.host, timeout_s=ON_TIME_S, max_packet_size=64) as bus:
        with pytest.raises(OutOfRangeError, match=r"length=100 .*allowed 0\.\.53") as info:
            await bus.read(3, 0, 100)
        assert info.value.name == "length"
        assert (info.value.low, info.value.high) == (0, 53)
        assert "max_packet_size=64" in str(info.value)
        with pytest.raises(OutOfRangeError, match="length=54"):
            await bus.request(read_request(3, 0, 54, Memory.EEP))
        # The largest read that fits still goes, and a length-0 read asks for what fits.
        assert len((await bus.read(3, 0, 53)).data) == 53
        assert bus.stats.bytes_out == len(encode_packet(read_request(3, 0, 53)))
    assert [p.data for p in rig.device.received] == [bytes((0, 53))]


# -- link failures and lifecycle ----------------------------------------------------------


async def test_peer_close_surfaces_as_transport_error(rig: Rig) -> None:
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        assert (await bus.read(3, 0x35, 1)).data == b"\x35"
        await rig.device.transport.aclose()
        with pytest.raises(TransportError):
            await bus.read(3, 0x35, 1)
        with pytest.raises(TransportError):
            await bus.read(3, 0x35, 1)


async def test_peer_close_fails_the_pending_request(rig: Rig) -> None:
    rig.device.hang_up = True
    # A timeout this long would fail the test with BusTimeoutError if the bus waited it out.
    async with Bus(rig.host, timeout_s=2.0, retries=0) as bus:
        with pytest.raises(TransportError):
            await bus.read(3, 0x35, 1)
        with pytest.raises(TransportError, match="link failed"):
            await bus.read(3, 0x35, 1)
    assert len(rig.device.received) == 1


async def test_bus_lifecycle(rig: Rig) -> None:
    bus = Bus(rig.host, timeout_s=ON_TIME_S)
    with pytest.raises(BusClosedError, match="not started"):
        await bus.read(3, 0x35, 1)
    async with bus:
        bus.start()  # idempotent
        assert bus.transport is rig.host
        assert (await bus.read(3, 0x35, 1)).data == b"\x35"
    assert bus.closed
    assert rig.host.closed
    await bus.aclose()
    with pytest.raises(BusClosedError):
        await bus.read(3, 0x35, 1)
    with pytest.raises(BusClosedError):
        bus.start()


async def test_closing_the_bus_fails_the_pending_request(rig: Rig) -> None:
    rig.device.sids.clear()
    bus = Bus(rig.host, timeout_s=2.0, retries=0)
    bus.start()
    pending = asyncio.create_task(bus.read(3, 0x35, 1))
    await rig.device.wait_received(1)
    await bus.aclose()
    with pytest.raises(BusClosedError):
        await pending


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"timeout_s": 0.0}, "timeout_s"),
        ({"timeout_s": 11.0}, "timeout_s"),
        ({"guard_s": -0.001}, "guard_s"),
        ({"turnaround_s": 2.0}, "turnaround_s"),
        ({"max_wait_s": -1.0}, "max_wait_s"),
        ({"stall_s": 0.0}, "stall_s"),
        ({"retries": 11}, "retries"),
        ({"retries": -1}, "retries"),
    ],
)
async def test_bus_settings_are_checked(
    memory_pair: tuple[MemoryTransport, MemoryTransport], kwargs: dict[str, float], name: str
) -> None:
    with pytest.raises(OutOfRangeError) as info:
        Bus(memory_pair[0], **kwargs)  # type: ignore[arg-type]  # checked at run time
    assert info.value.name == name


async def test_query_parses_a_codec_read_and_refuses_anything_else(rig: Rig) -> None:
    rig.device.registers[3, 0x3A] = (777).to_bytes(2, "little")
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        reply = await bus.query(read_request(3, 0x3A, 2))
        assert int.from_bytes(reply.data, "little") == 777
        with pytest.raises(InvalidArgumentError, match="read request"):
            await bus.query(write_request(3, 0x3A, b"\x01"))
    assert rig.device.received == [read_request(3, 0x3A, 2)]


async def test_a_wider_command_set_lets_a_vendor_reply_through() -> None:
    vendor_reply = Packet(3, 0x4A, b"\x00\x00")  # a reply code outside the nine commands

    async def device(end: MemoryTransport) -> None:
        # Whatever arrives, answer with the vendor reply (the device's own decoding is not
        # what this test is about).
        while True:
            await end.read()
            await end.write(encode_packet(vendor_reply))

    async def ask(commands: set[int] | None) -> tuple[Packet | None, int]:
        host, end = MemoryTransport.pair("vendor")
        task = asyncio.create_task(device(end))
        try:
            async with Bus(host, timeout_s=0.02, retries=0, commands=commands) as bus:
                try:
                    reply = await bus.request(Packet(3, 0x0A), expect_reply=True)
                except BusTimeoutError:
                    reply = None
                return reply, bus.stats.decoder.unknown_commands
        finally:
            task.cancel()
            await asyncio.wait({task})
            await end.aclose()

    assert await ask(None) == (None, 1)  # the default set refuses it, and counts it
    assert await ask({0x0A, 0x4A}) == (vendor_reply, 0)


async def test_a_bad_per_request_retry_count_is_refused_before_sending(rig: Rig) -> None:
    async with Bus(rig.host, timeout_s=ON_TIME_S) as bus:
        with pytest.raises(OutOfRangeError, match=r"retries=-1.*0\.\.10"):
            await bus.request(read_request(3, 0x35, 1), retries=-1)
        assert bus.stats.bytes_out == 0
    assert rig.device.received == []
