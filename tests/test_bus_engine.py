"""The bus engine under a fixed-rate load, in virtual time: slots, priorities, deadlines,
pipelining, the breaker, the stop path, reconnection — and never a stale reply.

The device here keeps the wire's timing (each byte 10 bits at the baud rate, a
turnaround, replies queued behind each other), counts a request that lands on the line
while a reply is on it (and, with ``garble``, breaks both, as a real collision does), and
stamps every read reply with the number of reads it has
served, so a reply handed to the wrong request shows.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import math
import random
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any, TypeVar

import pytest

from ohmni_tb.bus import Bus, BusStats, ReplyPacket, Slot
from ohmni_tb.errors import (
    BusClosedError,
    BusTimeoutError,
    DeadlineMissedError,
    DeviceUnavailableError,
    InvalidArgumentError,
    OutOfRangeError,
    StateError,
    TransportError,
)
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Packet,
    PacketDecoder,
    encode_packet,
    read_request,
    write_request,
)
from ohmni_tb.protocol.connection import BreakerState
from ohmni_tb.protocol.drive import read_count, wheel_command
from ohmni_tb.protocol.timing import DEFAULT_GUARD_S, DEFAULT_TURNAROUND_S, transaction_cost_s
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.transport import MemoryTransport, Transport, delay

T = TypeVar("T")
BAUD = 115_200


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


class TimedDevice:
    """Devices answering on the device end of a memory pair, with the wire's timing.

    Reads of ``n`` bytes answer the number of reads served so far: big-endian in ``n``
    bytes, and for 4-byte reads as two copies of a 2-byte stamp, so a value changed by the
    checksum's blind bit shows; STAT answers zeros; writes are not answered (policy 1).
    """

    def __init__(
        self,
        end: MemoryTransport,
        *,
        sids: set[int] | None = None,
        turnaround_s: float = 0.0005,
        baudrate: int = BAUD,
    ) -> None:
        self.end = end
        self.sids = {0, 1, 3, 11, 12, 20} if sids is None else sids
        self.silent: set[int] = set()
        self.turnaround_s = turnaround_s
        self.turnaround_of: dict[int, float] = {}
        self.byte_s = 10 / baudrate
        self.served = 0
        self.duplicate_next = False
        self.log: list[tuple[float, Packet]] = []
        self.collisions = 0
        self.garble = False
        self._line_free_at = 0.0
        self._replies: list[list[float]] = []  # [start, end, garbled]
        self._decoder = PacketDecoder()
        end.start_receiving(self._on_data, lambda exc: None)

    def _on_data(self, data: bytes) -> None:
        loop = asyncio.get_running_loop()
        now = loop.time()
        # The request's bytes are on the line from now: they must not meet a reply.
        start, end = now, now + len(data) * self.byte_s
        hit = False
        for reply in self._replies:
            if start < reply[1] - 1e-12 and reply[0] < end - 1e-12:
                self.collisions += 1
                hit = True
                reply[2] = 1.0
        self._replies = [r for r in self._replies if r[1] > start]
        if hit and self.garble:
            # Both sides garbled: the device's receiver throws the broken request away.
            self._decoder.feed(bytes(b & 0x0F for b in data))
            self._decoder.expire()
            return
        for packet in self._decoder.feed(data):
            self.log.append((now, packet))
            self._answer(packet, end, loop)

    def _answer(self, packet: Packet, at: float, loop: asyncio.AbstractEventLoop) -> None:
        if packet.sid not in self.sids or packet.sid in self.silent:
            return
        if packet.cmd in (Command.RAM_READ, Command.EEP_READ):
            self.served += 1
            length = packet.data[1] or 6
            value = self.served.to_bytes(length, "big")
            if length == 4:
                value = (self.served % 65536).to_bytes(2, "big") * 2
            reply = Packet(
                packet.sid,
                packet.cmd | REPLY_FLAG,
                bytes([packet.data[0], length]) + value + b"\0\0",
            )
        elif packet.cmd == Command.STAT:
            reply = Packet(packet.sid, packet.cmd | REPLY_FLAG, b"\0\0")
        else:
            return
        frame = encode_packet(reply)
        copies = 2 if self.duplicate_next else 1
        self.duplicate_next = False
        for _ in range(copies):
            turnaround = self.turnaround_of.get(packet.sid, self.turnaround_s)
            start = max(at + turnaround, self._line_free_at)
            end = start + len(frame) * self.byte_s
            self._line_free_at = end
            record = [start, end, 0.0]
            self._replies.append(record)
            loop.call_at(end, self._send, frame, record)

    def _send(self, frame: bytes, record: list[float]) -> None:
        if self.garble and record[2]:
            frame = frame[:5] + bytes(b & 0x0F for b in frame[5:])
        if not self.end.closed:
            self.end.write_nowait(frame)

    def sent(self, sid: int | None = None) -> list[Packet]:
        return [p for _, p in self.log if sid is None or p.sid == sid]


def pair(baudrate: int = BAUD) -> tuple[MemoryTransport, MemoryTransport]:
    return MemoryTransport.pair("engine", baudrate=baudrate)


def breaker(bus: Bus, sid: int) -> BreakerState:
    """The breaker state now (a call, so a type checker does not pin it across awaits)."""
    return bus.stats.devices[sid].breaker


def connected(bus: Bus) -> bool:
    return bus.connected


def value(reply: Packet | None) -> int:
    """The stamp in a read reply; -1 for a 4-byte stamp whose two copies disagree."""
    assert reply is not None
    data = reply.data[2:-2]
    if len(data) == 4:
        return int.from_bytes(data[:2], "big") if data[:2] == data[2:] else -1
    return int.from_bytes(data, "big")


# -- slots, priorities, deadlines ----------------------------------------------------------


def test_waiting_slots_go_by_priority_then_arrival() -> None:
    async def main() -> list[int]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            # The first slot takes the line; the rest queue behind it.
            tasks = [asyncio.ensure_future(bus.transact([read_count(0)]))]
            await asyncio.sleep(0)
            for sid, priority in ((1, 0), (3, 5), (20, 1), (11, 5)):
                tasks.append(
                    asyncio.ensure_future(
                        bus.transact([read_request(sid, 48, 2)], priority=priority)
                    )
                )
            await asyncio.gather(*tasks)
        await end.aclose()
        return [p.sid for p in device.sent()]

    assert virtual(main) == [0, 3, 11, 20, 1]


def test_a_low_priority_slot_is_not_starved() -> None:
    async def main() -> tuple[float, BusStats]:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host, max_wait_s=0.05) as bus:
            loop = asyncio.get_running_loop()
            stop = loop.time() + 0.3

            async def flood(sid: int) -> None:
                # Always a high-priority slot waiting: the line is never idle.
                while loop.time() < stop:
                    await bus.transact([read_request(sid, 48, 20)], priority=10)

            flooders = [asyncio.ensure_future(flood(sid)) for sid in (0, 1, 3)]
            await asyncio.sleep(0.01)
            t0 = loop.time()
            await bus.transact([read_request(20, 0xA0, 18)], priority=0)
            waited = loop.time() - t0
            await asyncio.gather(*flooders)
            stats = bus.stats
        await end.aclose()
        return waited, stats

    waited, stats = virtual(main)
    # Promoted after 50 ms; then at most the slot on the wire and its own transaction.
    slot_s = transaction_cost_s(read_request(0, 48, 20))
    assert 0.05 <= waited <= 0.05 + slot_s + transaction_cost_s(read_request(20, 0xA0, 18))
    assert stats.promoted >= 1


def test_a_slot_past_its_deadline_is_dropped_unsent() -> None:
    async def main() -> tuple[list[Packet], BusStats]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            with pytest.raises(DeadlineMissedError) as info:
                await bus.transact([read_count(0)], deadline=loop.time() - 0.001)
            assert info.value.late_s == pytest.approx(0.001)
            # A length-0 read budgets the largest reply (19 ms at 115200): a slot
            # behind it that must start within 5 ms cannot.
            tag = asyncio.ensure_future(bus.transact([read_request(20, 0xF1, 0)]))
            await asyncio.sleep(0)
            with pytest.raises(DeadlineMissedError):
                await bus.transact([read_count(1)], deadline=loop.time() + 0.0001)
            await tag
            stats = bus.stats
        await end.aclose()
        return device.sent(), stats

    sent, stats = virtual(main)
    assert sent == [read_request(20, 0xF1, 0)]
    assert stats.deadline_misses == 2


def test_a_slot_queued_ahead_starts_at_its_time_and_lets_others_use_the_line_before() -> None:
    async def main() -> tuple[float, list[tuple[float, Packet]], Slot, Slot, BusStats]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            # High priority, but not before t0 + 10 ms: the low one takes the free line.
            ahead = bus.submit([read_request(3, 48, 12)], priority=10, not_before=t0 + 0.010)
            other = bus.submit([read_count(0)], priority=0)
            await asyncio.gather(ahead.future, other.future)
            stats = bus.stats
        await end.aclose()
        return t0, device.log, ahead, other, stats

    t0, log, ahead, other, stats = virtual(main)
    assert [(round(at - t0, 6), p.sid) for at, p in log] == [(0.0, 0), (0.01, 3)]
    assert other.started_at == t0
    assert ahead.started_at == pytest.approx(t0 + 0.010)
    # Its waiting counts from its time, not from when it was queued.
    assert stats.queue_wait_p99_s == pytest.approx(0.0, abs=1e-9)


def test_a_slot_queued_ahead_whose_time_falls_on_a_busy_line_starts_as_the_line_frees() -> None:
    async def main() -> tuple[float, float, Slot]:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            long = bus.submit([read_request(3, 48, 12)])  # ~4 ms on the line
            ahead = bus.submit([read_count(0)], priority=10, not_before=t0 + 0.001)
            replies = await long.future
            freed = replies[0]
            assert freed is not None
            await ahead.future
        await end.aclose()
        return t0, freed.received_at, ahead

    t0, reply_at, ahead = virtual(main)
    assert ahead.started_at is not None
    # Not at its own time (the line was busy), but a guard after the reply came in.
    assert ahead.started_at > t0 + 0.001
    assert ahead.started_at == pytest.approx(reply_at + DEFAULT_GUARD_S)


def test_a_slot_queued_far_ahead_does_not_hold_back_the_slot_on_the_line() -> None:
    async def main() -> tuple[float, list[tuple[float, Packet]], list[ReplyPacket | None]]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            both = bus.submit([read_count(0), read_count(1)])
            later = bus.submit([read_request(3, 48, 2)], not_before=t0 + 0.050)
            replies = await both.future
            await later.future
        await end.aclose()
        return t0, device.log, replies

    t0, log, replies = virtual(main)
    first = replies[0]
    assert first is not None
    # The slot's second read goes a guard after the first reply, not at the other's time.
    assert [p.sid for _, p in log] == [0, 1, 3]
    assert log[1][0] == pytest.approx(first.received_at + DEFAULT_GUARD_S)
    assert log[2][0] == pytest.approx(t0 + 0.050)


@pytest.mark.parametrize("not_before", [math.nan, math.inf, "soon", True])
def test_not_before_must_be_a_loop_time(not_before: Any) -> None:
    async def main() -> tuple[str, list[Packet]]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            with pytest.raises(InvalidArgumentError) as info:
                bus.submit([read_count(0)], not_before=not_before)
            await asyncio.sleep(0.01)
        await end.aclose()
        return str(info.value), device.sent()

    message, sent = virtual(main)
    assert "not_before must be a loop.time() value" in message
    assert repr(not_before) in message
    assert sent == []


def test_retries_stop_at_the_deadline() -> None:
    async def main() -> tuple[list[Packet | None], int]:
        host, end = pair()
        device = TimedDevice(end)
        device.silent.add(3)
        async with Bus(host, retries=5) as bus:
            loop = asyncio.get_running_loop()
            replies = await bus.transact(
                [read_request(3, 48, 2), read_count(0)], deadline=loop.time() + 0.010
            )
        await end.aclose()
        return list(replies), len(device.sent(3))

    replies, attempts = virtual(main)
    assert replies[0] is None
    assert value(replies[1]) == 1
    assert attempts == 1


def test_an_atomic_slot_is_never_interleaved() -> None:
    async def main() -> list[int]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            tick = [read_count(0), read_count(1), wheel_command(100, 100)]
            servos = [read_request(3, 48, 12), read_request(11, 48, 12), read_request(12, 48, 12)]
            results = await asyncio.gather(
                *(bus.transact(tick, priority=10) for _ in range(3)),
                *(bus.transact(servos) for _ in range(3)),
            )
            for result in results:
                assert result[-1] is None or result[-1].is_reply
        await end.aclose()
        return [p.sid for p in device.sent()]

    sids = virtual(main)
    # Each slot's packets are contiguous on the wire.
    slots = [sids[i : i + 3] for i in range(0, len(sids), 3)]
    assert slots.count([0, 1, BROADCAST_ID]) == 3
    assert slots.count([3, 11, 12]) == 3


def test_a_slot_refuses_two_lookalike_reads() -> None:
    async def main() -> None:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host) as bus:
            with pytest.raises(InvalidArgumentError, match="look alike"):
                await bus.transact([read_count(0), read_count(0)])
            with pytest.raises(InvalidArgumentError, match="at least one"):
                await bus.transact([])
            with pytest.raises(InvalidArgumentError, match="broadcast"):
                await bus.query(Packet(BROADCAST_ID, Command.RAM_READ, b"\x3b\x04"))
            assert bus.stats.bytes_out == 0
        await end.aclose()

    virtual(main)


def test_a_tuple_resubmitted_is_checked_once_and_still_follows_the_ack_policy() -> None:
    """A stream's same tuple every cycle skips the encoding check after the first time;
    whether each packet waits for a reply is still asked every time."""

    async def main() -> None:
        host, end = pair()
        device = TimedDevice(end)
        write = write_request(3, 53, b"\x12")  # a RAM write: policy 1 answers reads only
        cycle = (read_count(0), write)
        async with Bus(host) as bus:
            first = await bus.transact(cycle)
            assert first[0] is not None
            assert first[1] is None  # no reply waited for
            bus.set_ack_policy(3, 2)  # now the write waits for a reply too
            slot = bus.submit(cycle, retries=0)
            await slot.future  # (this device does not answer writes: it times out)
            assert slot.expect == [True, True]
            sent = len(device.sent())
            # A tuple that does not encode is refused each time, never remembered.
            bad = (read_count(0), Packet(0xFF, Command.RAM_READ, b"\x00\x02"))
            for _ in range(2):
                with pytest.raises(OutOfRangeError):
                    bus.submit(bad)
            assert len(device.sent()) == sent
        await end.aclose()

    virtual(main)


# -- pipelining ---------------------------------------------------------------------------


def run_schedule(*, pipelined: bool, usb_latency_s: float) -> tuple[float, int, BusStats]:
    """30 reads of different registers submitted at once; replies reach the host late."""
    requests = [read_request(sid, addr, 4) for addr in range(10) for sid in (0, 1, 20)]

    async def main() -> tuple[float, int, BusStats]:
        host, end = pair()
        device = TimedDevice(end)
        if usb_latency_s:
            end.set_manipulator(delay(usb_latency_s))
        async with Bus(host, pipelined=pipelined) as bus:
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            replies = await asyncio.gather(*(bus.transact([r]) for r in requests))
            elapsed = loop.time() - t0
            stats = bus.stats
        await end.aclose()
        # Each reply answers its own request, and the device served them in order.
        assert [r[0].data[0] if r[0] else None for r in replies] == [r.data[0] for r in requests]
        assert [value(r[0]) for r in replies] == list(range(1, 31))
        return elapsed, device.collisions, stats

    return virtual(main)


def test_pipelined_slots_keep_the_wire_rate_when_replies_are_seen_late() -> None:
    cost = sum(transaction_cost_s(read_request(sid, 0, 4)) for sid in (0, 1, 20)) * 10
    fast, collisions, stats = run_schedule(pipelined=True, usb_latency_s=0.016)
    # On the wire's timing; the adapter's 16 ms shows once, at the end.
    assert fast <= cost + 0.016 + 0.001
    assert collisions == 0
    assert stats.unmatched == 0
    slow, collisions, _ = run_schedule(pipelined=False, usb_latency_s=0.016)
    # Request at a time pays the adapter's latency on every transaction.
    assert slow >= 30 * 0.016
    assert collisions == 0
    assert slow / fast > 4


def late_device_reads(caution_s: float) -> tuple[int, int, BusStats, int]:
    """Two streams of reads for 1 s; servo 3 answers 1 ms later than its budget allows."""

    async def main() -> tuple[int, int, BusStats, int]:
        host, end = pair()
        device = TimedDevice(end)
        device.garble = True
        device.turnaround_of[3] = DEFAULT_TURNAROUND_S + 0.001
        good = failed = 0
        async with Bus(host, caution_s=caution_s, breaker_timeouts=1000) as bus:
            loop = asyncio.get_running_loop()
            stop = loop.time() + 1.0

            async def stream(sid: int) -> None:
                nonlocal good, failed
                while loop.time() < stop:
                    before = device.served
                    try:
                        reply = await bus.read(sid, 48, 12)
                    except BusTimeoutError:
                        failed += 1
                        continue
                    assert int.from_bytes(reply.data, "big") > before  # never stale
                    good += 1

            await asyncio.gather(stream(3), stream(11), stream(12))
            stats = bus.stats
        await end.aclose()
        return good, failed, stats, device.collisions

    return virtual(main)


def test_a_device_later_than_its_budget_costs_a_collision_then_requests_go_one_at_a_time() -> None:
    # Without caution the pipelined request after one of servo 3's reads talks over its
    # late reply: both are lost, again and again, and some reads fail all three attempts.
    good, failed, stats, collisions = late_device_reads(caution_s=0.0)
    assert collisions > 20
    assert failed > 5
    assert stats.cautions == 0
    careless = good
    # With it, the first collision's junk makes the bus wait for each reply for
    # caution_s; a collision comes back only when pipelining resumes.
    good, failed, stats, collisions = late_device_reads(caution_s=0.25)
    assert collisions <= 5
    assert 1 <= stats.cautions <= 5
    assert failed == 0
    assert good > careless


# -- never a stale reply ------------------------------------------------------------------


def fresh_reads(
    setup: Callable[[TimedDevice, MemoryTransport, MemoryTransport], None],
    reads: int,
    **bus_settings: Any,
) -> tuple[int, int, BusStats, int]:
    """Sequential reads of one register: (fresh, timed out, stats, collisions).

    A read is fresh when the reply's stamp was served after the read was called; a stale
    reply (an earlier request's) fails the test at once. A stamp whose copies disagree
    (a bit the checksum cannot see was flipped: a limit of the protocol, measured in
    bench/faults.py) counts as neither.
    """

    async def main() -> tuple[int, int, BusStats, int]:
        host, end = pair()
        device = TimedDevice(end)
        setup(device, host, end)
        fresh = timeouts = blind = 0
        async with Bus(host, **bus_settings) as bus:
            for _ in range(reads):
                before = device.served
                try:
                    reply = await bus.request(read_count(0))
                except BusTimeoutError:
                    timeouts += 1
                    continue
                stamp = value(reply)
                if stamp < 0:
                    blind += 1
                    continue
                assert stamp > before, f"stale reply: stamp {stamp}, {before} served before"
                fresh += 1
            assert blind <= reads // 100
            stats = bus.stats
        await end.aclose()
        return fresh, timeouts, stats, device.collisions

    return virtual(main)


def test_a_device_slower_than_the_timeout_never_answers_the_next_read() -> None:
    def slow(device: TimedDevice, host: MemoryTransport, end: MemoryTransport) -> None:
        device.turnaround_s = 0.030

    fresh, timeouts, stats, _ = fresh_reads(slow, 50, breaker_timeouts=1000)
    assert fresh == 0
    assert timeouts == 50
    assert stats.devices[0].late > 0
    # Given its own turnaround budget, the same device is read fine.
    fresh, timeouts, stats, collisions = fresh_reads(slow, 50, turnaround_s=0.035)
    assert (fresh, timeouts, collisions) == (50, 0, 0)


def test_a_duplicate_reply_is_counted_and_never_taken() -> None:
    def duplicate(device: TimedDevice, host: MemoryTransport, end: MemoryTransport) -> None:
        device.duplicate_next = True

    fresh, timeouts, stats, _ = fresh_reads(duplicate, 100)
    assert fresh + timeouts == 100
    assert fresh >= 99
    assert stats.unmatched >= 1


@pytest.mark.parametrize("direction", ["replies", "requests", "both"])
def test_a_corrupting_line_never_returns_an_earlier_reply(direction: str) -> None:
    rng = random.Random(7)

    def corrupt(data: bytes) -> list[bytes | float]:
        out = bytearray(data)
        for i in range(len(out)):
            if rng.random() < 0.005:
                out[i] ^= 1 << rng.randrange(8)
        return [bytes(out)]

    def noisy(device: TimedDevice, host: MemoryTransport, end: MemoryTransport) -> None:
        if direction in ("replies", "both"):
            end.set_manipulator(corrupt)
        if direction in ("requests", "both"):
            host.set_manipulator(corrupt)

    fresh, timeouts, stats, _ = fresh_reads(noisy, 1000, breaker_timeouts=1000)
    assert fresh + timeouts >= 990
    assert fresh > 900
    assert stats.decoder.checksum_errors + stats.decoder.bad_headers + stats.unmatched > 0


# -- silent devices -----------------------------------------------------------------------


def test_a_silent_device_trips_its_breaker_and_is_probed_until_it_answers() -> None:
    async def main() -> None:
        host, end = pair()
        device = TimedDevice(end)
        device.silent.add(11)
        async with Bus(host, breaker_timeouts=3, breaker_quiet_s=0.05) as bus:
            loop = asyncio.get_running_loop()
            # One read's three attempts, and 0.1 s of silence: the breaker opens.
            with pytest.raises(BusTimeoutError) as timed_out:
                await bus.read(11, 48, 12)
            assert type(timed_out.value) is BusTimeoutError
            assert timed_out.value.attempts == 3
            sent_before = len(device.sent(11))
            t0 = loop.time()
            with pytest.raises(DeviceUnavailableError, match="sid 11") as info:
                await bus.read(11, 48, 12)
            assert loop.time() == t0  # refused at once, nothing sent
            assert len(device.sent(11)) == sent_before
            assert info.value.retry_in_s == pytest.approx(0.125, abs=0.01)
            assert breaker(bus, 11) is BreakerState.OPEN
            # The other devices go on as before.
            assert value(await bus.request(read_count(0))) >= 1
            # Still silent: the first probe fails, and the next waits twice as long.
            await asyncio.sleep(info.value.retry_in_s)
            with pytest.raises(BusTimeoutError):
                await bus.read(11, 48, 12)
            with pytest.raises(DeviceUnavailableError) as info:
                await bus.read(11, 48, 12)
            assert 0.15 < info.value.retry_in_s <= 0.25  # 0.25 s from the probe's start
            # It comes back; the next probe closes it.
            device.silent.discard(11)
            await asyncio.sleep(info.value.retry_in_s)
            assert (await bus.read(11, 48, 12)).length == 12
            assert breaker(bus, 11) is BreakerState.CLOSED
            # Two reads refused outright, and the failed probe's retry not sent.
            assert bus.stats.refused == 3
        await end.aclose()

    virtual(main)


def test_a_probe_asks_a_device_whose_breaker_is_open_and_closes_it() -> None:
    # A drive board missed its replies on a noisy line and its breaker opened; a stop's
    # confirmation must still read its count (transact(probe=True)), which a plain read
    # is refused, and its answer closes the breaker at once.
    async def main() -> None:
        host, end = pair()
        device = TimedDevice(end)
        device.silent.add(1)
        async with Bus(host, breaker_timeouts=3, breaker_quiet_s=0.05) as bus:
            with pytest.raises(BusTimeoutError):
                await bus.request(read_count(1))
            assert breaker(bus, 1) is BreakerState.OPEN
            device.silent.discard(1)
            assert await bus.transact([read_count(1)]) == [None]  # refused, not sent
            sent_before = len(device.sent(1))
            (reply,) = await bus.transact([read_count(1)], probe=True)
            assert reply is not None
            assert len(device.sent(1)) == sent_before + 1
            assert breaker(bus, 1) is BreakerState.CLOSED
            with pytest.raises(InvalidArgumentError, match="probe must be True or False, not 1"):
                await bus.transact([read_count(1)], probe=1)  # type: ignore[arg-type]  # the check under test
        await end.aclose()

    virtual(main)


def test_a_silent_device_costs_the_wheel_slot_nothing() -> None:
    """Wheel slots at 50 Hz keep their rate while two servos read at 30 Hz are silent."""

    async def main() -> tuple[int, int]:
        host, end = pair()
        device = TimedDevice(end)
        device.silent.update({11, 12})
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            ticks = 0

            async def wheels() -> None:
                nonlocal ticks
                for k in range(100):
                    due = t0 + k * 0.02
                    await asyncio.sleep(max(0.0, due - loop.time()))
                    replies = await bus.transact(
                        [read_count(0), read_count(1), wheel_command(0, 0)],
                        priority=10,
                        deadline=due + 0.005,
                    )
                    if replies[0] is not None and replies[1] is not None:
                        ticks += 1

            async def servo(sid: int) -> None:
                for k in range(60):
                    await asyncio.sleep(max(0.0, t0 + k / 30 - loop.time()))
                    with contextlib.suppress(BusTimeoutError, DeadlineMissedError):
                        await bus.read(sid, 48, 12)

            await asyncio.gather(wheels(), servo(3), servo(11), servo(12))
        await end.aclose()
        return ticks, device.collisions

    ticks, collisions = virtual(main)
    assert ticks == 100
    assert collisions == 0


# -- the stop path ------------------------------------------------------------------------


def test_send_now_jumps_the_queue() -> None:
    async def main() -> list[Packet]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            reads = [
                asyncio.ensure_future(bus.transact([read_request(sid, 48, 12)]))
                for sid in (0, 1, 3, 11, 12)
            ]
            await asyncio.sleep(0)
            await bus.send_now(wheel_command(0, 0))
            await asyncio.gather(*reads)
        await end.aclose()
        return device.sent()

    sent = virtual(main)
    # Only the read already on the wire went before the stop.
    assert [p.sid for p in sent] == [0, BROADCAST_ID, 1, 3, 11, 12]


def test_a_read_sent_now_in_the_middle_of_a_slot_is_not_sent_twice_by_it() -> None:
    # The stop path reads a wheel's count at once (send_now), between the packets of a
    # control slot that reads the same count; that device then stays silent. The slot's
    # own read would be told from the stop's by nothing: it is not sent, and is counted;
    # the slot completes (it used to hang, with an error in the loop's callback).
    async def main() -> tuple[object, BusStats, list[Packet], list[dict[str, Any]]]:
        loop = asyncio.get_running_loop()
        errors: list[dict[str, Any]] = []
        loop.set_exception_handler(lambda _loop, context: errors.append(context))
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            slot = asyncio.ensure_future(bus.transact([read_count(0), read_count(1)]))
            await asyncio.sleep(0)  # the slot's first read is on the line
            device.silent.add(1)
            await bus.send_now(read_count(1))
            result = await asyncio.wait_for(slot, 1.0)
            stats = bus.stats
        await end.aclose()
        return result, stats, device.sent(), errors

    result, stats, sent, errors = virtual(main)
    assert errors == []
    assert isinstance(result, list)
    assert result[0] is not None
    assert result[1] is None
    assert stats.twins == 1
    assert [p.sid for p in sent] == [0, 1]


def test_the_final_stop_goes_out_while_the_bus_closes_even_when_cancelled() -> None:
    async def main() -> tuple[list[Packet], list[BaseException]]:
        host, end = pair()
        device = TimedDevice(end)
        bus = Bus(host)
        bus.start()
        reads = [
            asyncio.ensure_future(bus.transact([read_request(sid, 48, 12)]))
            for sid in (0, 1, 3, 11)
        ]
        await asyncio.sleep(0)
        closing = asyncio.ensure_future(bus.aclose(final=[wheel_command(0, 0)]))
        await asyncio.sleep(0)
        closing.cancel()  # the closer is cancelled before the line is free
        with pytest.raises(asyncio.CancelledError):
            await closing
        results = await asyncio.gather(*reads, return_exceptions=True)
        await asyncio.sleep(0.001)
        await end.aclose()
        assert bus.closed
        assert host.closed
        return device.sent(), [r for r in results if isinstance(r, BaseException)]

    sent, errors = virtual(main)
    assert sent == [read_request(0, 48, 12), wheel_command(0, 0)]
    assert len(errors) == 4
    assert all(isinstance(e, BusClosedError) for e in errors)


def test_a_cancelled_read_at_9600_baud_keeps_its_whole_reply_window() -> None:
    """A 20 ms device at 9600 baud: the next request must wait for the late reply's end."""

    async def main() -> tuple[int, BusStats, list[tuple[float, Packet]]]:
        host, end = pair(9600)
        device = TimedDevice(end, baudrate=9600)
        device.turnaround_of[3] = 0.020
        async with Bus(host) as bus:
            bus.set_turnaround(3, 0.025)
            slow = asyncio.ensure_future(bus.read(3, 48, 12))
            await asyncio.sleep(0.001)
            slow.cancel()
            with pytest.raises(asyncio.CancelledError):
                await slow
            reply = await bus.request(read_count(0))
            await asyncio.sleep(0.1)
            stats = bus.stats
        await end.aclose()
        assert value(reply) == 2
        return device.collisions, stats, device.log

    collisions, stats, log = virtual(main)
    assert collisions == 0
    assert stats.abandoned == 1
    (t_slow, _), (t_next, _) = log
    reply_end = t_slow + 9 * 10 / 9600 + 0.020 + 23 * 10 / 9600
    assert t_next >= reply_end


# -- the link -----------------------------------------------------------------------------


def test_a_lost_link_is_reported_and_reconnect_reopens_it() -> None:
    async def main() -> BusStats:
        ends: list[MemoryTransport] = []
        devices: list[TimedDevice] = []
        failures = [2]

        async def reopen() -> Transport:
            if failures[0]:
                failures[0] -= 1
                raise TransportError("no such port (still plugging in)")
            host, end = pair()
            ends.append(end)
            devices.append(TimedDevice(end))
            devices[-1].served = devices[0].served
            return host

        first = await reopen_first(reopen, ends, devices)
        bus = Bus(first, reopen=reopen)
        async with bus:
            assert value(await bus.request(read_count(0))) == 1
            pending = asyncio.ensure_future(bus.read(3, 48, 2))
            await asyncio.sleep(0)
            await ends[0].aclose()  # the cable is pulled
            lost = await bus.wait_lost()
            assert "closed" in str(lost)
            with pytest.raises(TransportError, match="lost"):
                await pending
            assert not connected(bus)
            with pytest.raises(TransportError, match="reconnect"):
                await bus.request(read_count(0))
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            await bus.reconnect(backoff_s=0.1)
            assert loop.time() - t0 == pytest.approx(0.3)  # two failures: 0.1 s, 0.2 s
            assert connected(bus)
            assert value(await bus.request(read_count(0))) == 2
            stats = bus.stats
        for end in ends:
            await end.aclose()
        return stats

    stats = virtual(main)
    assert (stats.link_losses, stats.reconnects) == (1, 1)
    assert stats.devices[0].replies == 2


async def reopen_first(
    reopen: Callable[[], Awaitable[Transport]],
    ends: list[MemoryTransport],
    devices: list[TimedDevice],
) -> Transport:
    host, end = pair()
    ends.append(end)
    devices.append(TimedDevice(end))
    return host


def test_reconnect_needs_a_way_to_reopen() -> None:
    async def main() -> None:
        host, end = pair()
        async with Bus(host) as bus:
            with pytest.raises(StateError, match="reopen"):
                await bus.reconnect()
        await end.aclose()

    virtual(main)


def test_a_port_that_stops_taking_bytes_fails_the_link_instead_of_hanging() -> None:
    async def main() -> None:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host, stall_s=0.2) as bus:
            host.set_stalled(True)
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            with pytest.raises(TransportError, match="not sent"):
                await bus.request(read_count(0))
            with pytest.raises(TransportError):
                await bus.request(read_count(1))
            assert loop.time() - t0 == pytest.approx(0.2, abs=0.01)
        await end.aclose()

    virtual(main)


def test_a_length_zero_read_at_1200_baud_is_answered_not_unmatched() -> None:
    async def main() -> BusStats:
        host, end = pair(1200)
        TimedDevice(end, baudrate=1200)
        async with Bus(host) as bus:
            for _ in range(3):
                reply = await bus.read(20, 0xF1, 0)
                assert reply.length == 6
            stats = bus.stats
        await end.aclose()
        return stats

    stats = virtual(main)
    assert stats.unmatched == 0
    assert stats.devices[20].timeouts == 0


# -- submit: slots without a task ----------------------------------------------------------


def test_submit_returns_a_slot_whose_future_and_start_time_tell_what_happened() -> None:
    async def main() -> tuple[list[int], float, float | None, float | None, list[Packet]]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            done: list[list[ReplyPacket | None]] = []
            t0 = loop.time()
            first = bus.submit([read_count(0), read_count(1)], priority=1)
            second = bus.submit([read_request(3, 48, 2)], priority=1)
            first.future.add_done_callback(lambda f: done.append(f.result()))
            assert first.started_at == t0  # the line was free: it went at once
            assert second.started_at is None  # it waits behind the first
            replies = await second.future
            await asyncio.sleep(0)
        await end.aclose()
        values = [value(r) for r in done[0]] + [value(r) for r in replies]
        return values, t0, first.started_at, second.started_at, device.sent()

    values, t0, started_first, started_second, sent = virtual(main)
    assert values == [1, 2, 3]  # each reply is its own request's, in order
    assert started_first == t0
    assert started_second is not None
    assert started_second > t0 + transaction_cost_s(read_count(0))  # after both reads
    assert [p.sid for p in sent] == [0, 1, 3]


def test_cancelling_a_submitted_future_withdraws_the_slot_unsent() -> None:
    async def main() -> tuple[list[Packet], int]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            bus.submit([read_count(0)])
            waiting = bus.submit([read_request(3, 48, 2)])
            waiting.future.cancel()
            after = await bus.transact([read_count(1)])
            await asyncio.sleep(0.05)
        await end.aclose()
        return device.sent(), value(after[0])

    sent, answer = virtual(main)
    assert [p.sid for p in sent] == [0, 1]
    assert answer == 2  # the second read served: the withdrawn one never went


def test_a_submitted_slot_past_its_deadline_fails_its_future() -> None:
    async def main() -> BaseException | None:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            first = bus.submit([read_count(0)])
            late = bus.submit([read_count(1)], deadline=loop.time() + 0.0001)
            with contextlib.suppress(DeadlineMissedError):
                await late.future
            exc = late.future.exception()
            await first.future
        await end.aclose()
        return exc

    exc = virtual(main)
    assert isinstance(exc, DeadlineMissedError)


def test_on_done_is_called_once_as_the_slot_completes_and_cancel_withdraws() -> None:
    async def main() -> tuple[list[tuple[bool, int]], list[Packet], int]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            seen: list[tuple[bool, int]] = []

            def done(slot: Slot) -> None:
                # Called from inside the bus: the future is already done.
                seen.append((slot.future.done(), value(slot.future.result()[0])))

            bus.submit([read_count(0)], on_done=done)
            waiting = bus.submit([read_request(3, 48, 2)], on_done=done)
            bus.cancel(waiting)
            after = await bus.transact([read_count(1)])
            await asyncio.sleep(0.05)
        await end.aclose()
        return seen, device.sent(), value(after[0])

    seen, sent, answer = virtual(main)
    assert seen == [(True, 1)]  # once, for the slot that ran; never for the withdrawn one
    assert [p.sid for p in sent] == [0, 1]
    assert answer == 2


def test_a_dropped_slots_on_done_may_submit_and_cancel_while_the_bus_drops_it() -> None:
    """A scheduler reacts to a missed deadline from inside the bus: it queues the next
    cycle and withdraws another slot. Both changes hold; nothing is lost or revived."""

    async def main() -> tuple[list[Packet], list[int], bool]:
        host, end = pair()
        device = TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            queued: list[Slot] = []
            first = bus.submit([read_count(0)])  # holds the line for ~3 ms
            doomed = bus.submit([read_request(11, 48, 2)])

            def missed(slot: Slot) -> None:
                assert isinstance(slot.future.exception(), DeadlineMissedError)
                bus.cancel(doomed)
                queued.append(bus.submit([read_request(3, 48, 2)], priority=1))

            bus.submit([read_count(1)], deadline=loop.time() + 0.001, on_done=missed)
            await first.future
            [reply] = await queued[0].future
            await asyncio.sleep(0.05)
        await end.aclose()
        return device.sent(), [value(reply)], doomed.future.cancelled()

    sent, values, withdrawn = virtual(main)
    assert [p.sid for p in sent] == [0, 3]  # the late read never went, nor the withdrawn one
    assert values == [2]
    assert withdrawn


def test_on_done_hears_of_a_slot_dropped_while_it_is_submitted() -> None:
    async def main() -> list[BaseException | None]:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            heard: list[BaseException | None] = []
            first = bus.submit([read_count(0)])  # holds the line for ~3 ms
            # Hopeless from the start: dropped inside submit(), before it returns.
            bus.submit(
                [read_count(1)],
                deadline=loop.time() + 0.0001,
                on_done=lambda slot: heard.append(slot.future.exception()),
            )
            await first.future
        await end.aclose()
        return heard

    [heard] = virtual(main)
    assert isinstance(heard, DeadlineMissedError)


def test_a_completed_slot_goes_again_as_a_new_cycle_without_a_new_slot() -> None:
    async def main() -> tuple[list[int], list[int], list[bool], float | None, float]:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host) as bus:
            loop = asyncio.get_running_loop()
            cycle = (read_count(0), read_count(1))
            got: list[list[int]] = []

            def done(slot: Slot) -> None:
                got.append([value(r) for r in slot.results])

            slot = bus.submit(cycle, priority=3, on_done=done, tag="first")
            with pytest.raises(StateError, match="completed"):
                bus.resubmit(slot)  # still on the line
            await asyncio.sleep(0.02)
            first_results = slot.results
            due = loop.time() + 0.01
            again = bus.resubmit(slot, not_before=due, on_done=done, tag="second")
            assert again is slot
            assert (slot.finished, slot.started_at, slot.tag) == (False, None, "second")
            await asyncio.sleep(0.02)
            replies = await slot.future  # a fresh future, for the second cycle
            flags = [first_results is not slot.results, slot.finished, slot.priority == 3]
        await end.aclose()
        return got[0], [value(r) for r in replies], flags, slot.started_at, due

    first, second, flags, started, due = virtual(main)
    assert (first, second) == ([1, 2], [3, 4])
    assert flags == [True, True, True]
    assert started is not None
    assert started >= due  # it waited for its not_before


def test_a_slot_withdrawn_or_failed_can_go_again_and_another_bus_cannot_take_it() -> None:
    async def main() -> tuple[list[int], BaseException | None]:
        host, end = pair()
        TimedDevice(end)
        async with Bus(host) as bus, Bus(pair()[0]) as other:
            loop = asyncio.get_running_loop()
            bus.submit([read_count(0)])  # holds the line
            late = bus.submit([read_count(1)], deadline=loop.time() + 0.0001)
            error = late.error
            with pytest.raises(StateError):
                other.resubmit(late)
            bus.resubmit(late)
            replies = await late.future
        await end.aclose()
        return [value(r) for r in replies], error

    values, error = virtual(main)
    assert isinstance(error, DeadlineMissedError)
    assert values == [2]


def test_finished_slots_leave_no_reference_cycle_for_the_collector() -> None:
    # ~150 slots a second under the Robot: left to the cycle collector, they promoted
    # garbage into the generation whose collection paused the loop for a control period.
    async def main() -> list[str]:
        host, end = pair()
        TimedDevice(end, sids={0, 1})  # sid 3 stays silent: its slot ends without replies
        async with Bus(host, retries=0) as bus:
            await bus.transact([read_count(0), read_count(1)])  # answered
            await bus.transact([wheel_command(0, 0)])  # no reply expected
            with pytest.raises(BusTimeoutError):
                await bus.read(3, 48, 2)  # timed out
            withdrawn = bus.submit([read_count(0)], priority=1)
            withdrawn.future.cancel()  # cancelled before it went out
            await asyncio.sleep(0.1)
            gc.collect()
            gc.set_debug(gc.DEBUG_SAVEALL)
            try:
                for _ in range(20):
                    await bus.transact([read_count(0), read_count(1)])
                    await bus.transact([wheel_command(0, 0)])
                    with pytest.raises(BusTimeoutError):
                        await bus.read(3, 48, 2)
                    withdrawn = bus.submit([read_count(0)], priority=1)
                    withdrawn.future.cancel()
                    await asyncio.sleep(0)
                del withdrawn
                gc.collect()
                kinds = sorted(
                    {
                        type(o).__name__
                        for o in gc.garbage
                        if type(o).__module__.startswith("ohmni_tb")
                    }
                )
            finally:
                gc.set_debug(0)
                gc.garbage.clear()
        await end.aclose()
        return kinds

    assert virtual(main) == []
