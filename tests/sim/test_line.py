"""The simulated line: wire timing, collisions, USB latency, faults, and the host's end.

Every test runs on the virtual clock, so wire times are exact and nothing sleeps. Most
drive the host's end (:class:`SimTransport`) directly with frames, and check the bytes
and the times the host gets; a few go through the Bus end to end.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Callable, Coroutine
from typing import Any

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.errors import (
    BusTimeoutError,
    ConfigError,
    MalformedReplyError,
    OutOfRangeError,
    StateError,
    TransportClosedError,
    TransportError,
)
from ohmni_tb.herkulex import ram_read, ram_write
from ohmni_tb.protocol import (
    Command,
    Packet,
    PacketDecoder,
    ReadReply,
    encode_packet,
)
from ohmni_tb.protocol.drive import parse_count, read_count, wheel_command
from ohmni_tb.protocol.worm_neck import parse_feedback, read_feedback, set_target
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.servo import GARBAGE_TIMEOUT_S, SimServo
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import Transport, open_transport

_BYTE_S = 10 / 115_200
_TURNAROUND_S = 0.0005
#: A 4-byte read (a wheel count): 9-byte request, 15-byte reply.
_COUNT_REQUEST, _COUNT_REPLY = 9, 15


async def _open_sim(url: str = "sim://") -> SimTransport:
    transport = await open_transport(url)
    assert isinstance(transport, SimTransport)
    return transport


def _frame(*packets: Packet) -> bytes:
    return b"".join(encode_packet(p) for p in packets)


class _Host:
    """The host in push mode: records every chunk it gets with its time since the start."""

    def __init__(self, sim: SimTransport) -> None:
        self.sim = sim
        self.loop = asyncio.get_running_loop()
        self.t0 = self.loop.time()
        self.chunks: list[tuple[float, bytes]] = []
        self.lost: list[TransportError] = []
        sim.start_receiving(self._on_data, self.lost.append)

    def _on_data(self, chunk: bytes) -> None:
        self.chunks.append((self.loop.time() - self.t0, chunk))

    def write(self, *packets: Packet) -> None:
        self.sim.write_nowait(_frame(*packets))

    async def at(self, t_s: float) -> None:
        """Sleep until ``t_s`` seconds after the start."""
        await asyncio.sleep(self.t0 + t_s - self.loop.time())

    def replies(self) -> list[tuple[float, Packet]]:
        """The packets received, each with the time of the chunk that completed it."""
        decoder = PacketDecoder()
        return [(t, p) for t, chunk in self.chunks for p in decoder.feed(chunk)]


def _on_host(
    body: Callable[[_Host], Coroutine[Any, Any, None]], url: str = "sim://"
) -> SimTransport:
    """Run ``body`` with a recording host on a fresh ``url``; return the (closed) end."""

    async def main() -> SimTransport:
        async with await _open_sim(url) as sim:
            await body(_Host(sim))
            return sim

    return run_virtual(main())


async def _round_trip(transport: Transport, request: Packet) -> tuple[Packet, float]:
    """Write ``request`` by hand and wait for one whole reply (pull mode); return it and
    the time taken."""
    loop = asyncio.get_running_loop()
    decoder = PacketDecoder()
    start = loop.time()
    await transport.write(encode_packet(request))
    while True:
        packets = decoder.feed(await transport.read())
        if packets:
            assert len(packets) == 1
            return packets[0], loop.time() - start


def _pending(loop: asyncio.AbstractEventLoop) -> list[asyncio.Handle]:
    """Callbacks the loop still holds, timers and ready ones, not counting cancelled ones."""
    # The loop keeps no public list of what is scheduled; these two attributes are where
    # asyncio's base loop holds its timers and its ready queue.
    handles = [*loop._scheduled, *loop._ready]  # type: ignore[attr-defined]  # see above
    return [h for h in handles if not h.cancelled()]


# -- wire timing --------------------------------------------------------------------------


def test_a_two_byte_read_costs_its_wire_time_plus_turnaround() -> None:
    async def main() -> tuple[Packet, float, SimTransport]:
        async with await _open_sim() as sim:
            reply, elapsed = await _round_trip(sim, Packet(0, Command.RAM_READ, bytes((58, 2))))
            return reply, elapsed, sim

    reply, elapsed, sim = run_virtual(main())
    assert reply.cmd == Command.RAM_READ | 0x40
    # 9-byte request, 13-byte reply (7 header + addr, len, 2 bytes, 2 status bytes).
    assert elapsed == pytest.approx((9 + 13) * _BYTE_S + _TURNAROUND_S, abs=1e-9)
    stats = sim.line.stats
    assert (stats.bytes_to_devices, stats.bytes_to_host) == (9, 13)
    assert (stats.packets, stats.replies, stats.collisions) == (1, 1, 0)
    assert stats.busy_s == pytest.approx(22 * _BYTE_S, abs=1e-9)


def test_baudrate_and_turnaround_options_change_the_timing() -> None:
    async def main() -> float:
        async with await _open_sim("sim://?baudrate=9600&turnaround_us=2000") as sim:
            _, elapsed = await _round_trip(sim, Packet(0, Command.RAM_READ, bytes((58, 2))))
            return elapsed

    assert run_virtual(main()) == pytest.approx(22 * 10 / 9600 + 0.002, abs=1e-9)


def test_the_bus_sees_the_same_round_trip() -> None:
    async def main() -> float:
        async with Bus(await _open_sim()) as bus:
            loop = asyncio.get_running_loop()
            start = loop.time()
            await bus.read(1, 58, 2)
            return loop.time() - start

    assert run_virtual(main()) == pytest.approx(22 * _BYTE_S + _TURNAROUND_S, abs=1e-9)


def test_a_request_is_seen_when_its_last_byte_arrives_however_it_was_written() -> None:
    # Half a read now, the rest 2 ms later: the board answers the turnaround after the
    # second half's last byte, not before.
    frame = encode_packet(read_count(0))

    async def body(host: _Host) -> None:
        host.sim.write_nowait(frame[:4])
        await host.at(0.002)
        host.sim.write_nowait(frame[4:])
        await host.at(0.02)
        ((t, reply),) = host.replies()
        assert reply.sid == 0
        assert t == pytest.approx(0.002 + 5 * _BYTE_S + _TURNAROUND_S + 15 * _BYTE_S, abs=1e-9)

    _on_host(body)


def test_each_packet_of_one_write_is_seen_at_its_own_time_and_answered_in_turn() -> None:
    # The worm neck travels at 80000 units/s: each of three reads written together
    # reports where the neck was when that read's own last byte arrived.
    target = set_target(100_000)
    got: list[tuple[float, Packet]] = []

    async def main() -> None:
        async with await _open_sim("sim://?neck=worm") as sim:
            host = _Host(sim)
            host.write(target)  # 13 bytes: the neck starts at 13 byte times
            await host.at(0.010)
            host.write(read_feedback(), read_feedback(), read_feedback())
            await host.at(0.030)
            got.extend(host.replies())

    run_virtual(main())
    assert len(got) == 3
    moving_since = target.size * _BYTE_S
    positions = [parse_feedback(ReadReply.parse(p)).position for _, p in got]
    seen_at = [0.010 + 9 * (i + 1) * _BYTE_S for i in range(3)]
    assert positions == [round(80_000 * (t - moving_since)) for t in seen_at]
    assert positions[0] < positions[1] < positions[2]  # three moments, not one
    # The first reply waits for the line to be quiet (the rest of the write), then
    # each queues behind the one before: 16-byte replies, back to back.
    reply_s = 16 * _BYTE_S
    first_end = 0.010 + 27 * _BYTE_S + reply_s
    assert [t for t, _ in got] == pytest.approx(
        [first_end, first_end + reply_s, first_end + 2 * reply_s], abs=1e-9
    )


def test_a_broadcast_gets_no_reply_and_keeps_the_line_busy_only_for_its_bytes() -> None:
    async def main() -> SimTransport:
        async with await _open_sim() as sim:
            await sim.write(encode_packet(Packet(0xFE, Command.RAM_WRITE, bytes((52, 1, 0x60)))))
            await asyncio.sleep(0.1)
            return sim

    stats = run_virtual(main()).line.stats
    assert (stats.packets, stats.replies, stats.bytes_to_host) == (1, 0, 0)
    assert stats.busy_s == pytest.approx(10 * _BYTE_S, abs=1e-9)


def test_a_broadcast_wheel_command_reaches_both_drive_boards() -> None:
    async def body(host: _Host) -> None:
        host.write(wheel_command(400, 400))
        await host.at(0.3)
        host.write(wheel_command(0, 0))
        await host.at(1.3)  # coasted to a stop
        host.write(read_count(0), read_count(1))
        await host.at(1.31)
        left, right = (parse_count(ReadReply.parse(p)) for _, p in host.replies())
        assert left > 0 > right  # the right board counts mirrored
        assert abs(left + right) <= 1

    _on_host(body)


def test_a_servo_answers_to_its_new_id_after_a_write_of_it() -> None:
    async def body(host: _Host) -> None:
        host.write(ram_write(11, "id", 15))  # ACK policy 1: no reply
        await host.at(0.01)
        host.write(ram_read(15, "id"))
        await host.at(0.02)
        host.write(ram_read(11, "id"))
        await host.at(0.03)
        got = host.replies()
        assert [(p.sid, ReadReply.parse(p).data) for _, p in got] == [(15, b"\x0f")]

    _on_host(body)


# -- collisions between devices -----------------------------------------------------------


def _twin_servos() -> SimLine:
    """Two servos that both answer to id 11, their horns at different positions."""
    return SimLine([SimServo(11, pos_raw=100), SimServo(11, pos_raw=900)])


def test_two_devices_answering_one_read_collide_and_the_host_gets_garbage() -> None:
    line = _twin_servos()

    async def main() -> _Host:
        async with SimTransport(line) as sim:
            host = _Host(sim)
            host.write(Packet(11, Command.RAM_READ, bytes((60, 2))))  # the two replies differ
            await host.at(0.01)
            return host

    host = run_virtual(main())
    assert line.stats.collisions == 1
    ((t, wire),) = host.chunks
    assert len(wire) == 13
    assert t == pytest.approx(22 * _BYTE_S + _TURNAROUND_S, abs=1e-9)
    assert host.replies() == []  # the ANDed bytes fail the checksum


def test_identical_colliding_replies_still_read_as_one() -> None:
    # Both drivers send the same bits, so the wire carries a valid frame: the host cannot
    # tell, but the line counts the collision.
    line = _twin_servos()

    async def main() -> list[tuple[float, Packet]]:
        async with SimTransport(line) as sim:
            host = _Host(sim)
            host.write(Packet(11, Command.STAT))
            await host.at(0.01)
            return host.replies()

    ((_, reply),) = run_virtual(main())
    assert reply == Packet(11, Command.STAT | 0x40, b"\0\0")
    assert line.stats.collisions == 1


# -- the host talking over a reply --------------------------------------------------------

#: When the reply to a wheel-count read written at 0 is on the line.
_REPLY_START_S = _COUNT_REQUEST * _BYTE_S + _TURNAROUND_S
_REPLY_END_S = _REPLY_START_S + _COUNT_REPLY * _BYTE_S


def test_a_request_written_over_a_reply_collides_both_ways_and_is_counted() -> None:
    async def body(host: _Host) -> None:
        host.write(read_count(0))
        await host.at(_REPLY_START_S + 5 * _BYTE_S)  # a third of the way into the reply
        host.write(read_count(1))
        await host.at(0.02)
        assert host.replies() == []  # the reply did not survive
        assert sum(len(c) for _, c in host.chunks) == _COUNT_REPLY

    stats = _on_host(body).line.stats
    assert stats.host_collisions == 1
    assert stats.collisions == 0
    # Nor did the request: the board decoded only the first one and answered it alone.
    assert (stats.packets, stats.replies) == (1, 1)


def test_a_request_written_before_the_reply_starts_defers_the_reply() -> None:
    # In the turnaround the line is quiet: the board waits for the new request to pass,
    # then answers both in turn. Nothing collides.
    write_s = _COUNT_REQUEST * _BYTE_S + 0.0001
    got: list[list[tuple[float, Packet]]] = []

    async def body(host: _Host) -> None:
        host.write(read_count(0))
        await host.at(write_s)
        host.write(read_count(1))
        await host.at(0.02)
        got.append(host.replies())

    sim = _on_host(body)
    ((t0, first), (t1, second)) = got[0]
    assert (first.sid, second.sid) == (0, 1)
    request_end = write_s + _COUNT_REQUEST * _BYTE_S
    assert t0 == pytest.approx(request_end + _COUNT_REPLY * _BYTE_S, abs=1e-9)
    assert t1 == pytest.approx(t0 + _COUNT_REPLY * _BYTE_S, abs=1e-9)
    assert sim.line.stats.host_collisions == 0


def test_a_request_written_after_the_reply_is_clean() -> None:
    async def body(host: _Host) -> None:
        host.write(read_count(0))
        await host.at(_REPLY_END_S)
        host.write(read_count(1))
        await host.at(0.02)
        assert [p.sid for _, p in host.replies()] == [0, 1]

    assert _on_host(body).line.stats.host_collisions == 0


def test_without_realtime_the_host_queues_behind_the_line_and_never_collides() -> None:
    async def body(host: _Host) -> None:
        host.write(read_count(0))
        host.write(read_count(1))  # at once: in real time this would meet the reply
        await asyncio.sleep(0)
        assert [(t, p.sid) for t, p in host.replies()] == [(0.0, 0), (0.0, 1)]

    sim = _on_host(body, "sim://?realtime=0&turnaround_us=0")
    assert sim.line.stats.host_collisions == 0
    # The simulated time ran ahead by both transactions' wire time.
    assert sim.line.now_s() == pytest.approx(2 * 24 * _BYTE_S, abs=1e-9)


# -- USB latency ----------------------------------------------------------------------------


def test_usb_latency_releases_bytes_on_its_grid() -> None:
    # 1 ms timer: the reply's bytes that arrived by 2 ms go then, the rest at 3 ms.
    async def body(host: _Host) -> None:
        host.write(read_count(0))
        await host.at(0.01)

    async def main() -> list[tuple[float, bytes]]:
        async with await _open_sim("sim://?usb_latency_ms=1") as sim:
            host = _Host(sim)
            await body(host)
            return host.chunks

    chunks = run_virtual(main())
    by_2ms = int((0.002 - _REPLY_START_S) / _BYTE_S)
    assert by_2ms == 8
    assert [t for t, _ in chunks] == pytest.approx([0.002, 0.003], abs=1e-9)
    assert [len(c) for _, c in chunks] == [8, _COUNT_REPLY - 8]
    (reply,) = PacketDecoder().feed(b"".join(c for _, c in chunks))
    assert parse_count(ReadReply.parse(reply)) == 0


def test_usb_latency_sends_a_full_usb_packet_without_waiting() -> None:
    # A read of all 74 bytes of RAM: an 85-byte reply. The first 62 bytes go the moment
    # the 62nd arrives; the other 23 wait for the 16 ms tick.
    async def main() -> list[tuple[float, bytes]]:
        async with await _open_sim("sim://?usb_latency_ms=16") as sim:
            host = _Host(sim)
            host.write(Packet(3, Command.RAM_READ, bytes((0, 74))))
            await host.at(0.05)
            return host.chunks

    chunks = run_virtual(main())
    reply_start = 9 * _BYTE_S + _TURNAROUND_S
    assert [len(c) for _, c in chunks] == [62, 23]
    assert [t for t, _ in chunks] == pytest.approx([reply_start + 62 * _BYTE_S, 0.016], abs=1e-9)
    (reply,) = PacketDecoder().feed(b"".join(c for _, c in chunks))
    assert (reply.sid, len(reply.data)) == (3, 2 + 74 + 2)


def test_usb_latency_hands_two_short_replies_over_together() -> None:
    async def main() -> list[tuple[float, bytes]]:
        async with await _open_sim("sim://?usb_latency_ms=16") as sim:
            host = _Host(sim)
            host.write(read_count(0), read_count(1))
            await host.at(0.05)
            return host.chunks

    ((t, chunk),) = run_virtual(main())
    assert t == pytest.approx(0.016, abs=1e-9)
    assert [p.sid for p in PacketDecoder().feed(chunk)] == [0, 1]


def test_usb_latency_grid_counts_from_the_line_start() -> None:
    # A read written at 12.3 ms has its reply on the line from 13.58 to 14.88 ms: the
    # 4 ms grid of the line releases it at 16 ms, not 4 ms after anything the host did.
    async def main() -> list[tuple[float, bytes]]:
        async with await _open_sim("sim://?usb_latency_ms=4") as sim:
            host = _Host(sim)
            await host.at(0.0123)
            host.write(read_count(0))
            await host.at(0.05)
            return host.chunks

    ((t, chunk),) = run_virtual(main())
    assert t == pytest.approx(0.016, abs=1e-9)
    assert len(chunk) == _COUNT_REPLY


# -- half frames expire ----------------------------------------------------------------------


def _half_then_rest(rest_after_s: float) -> tuple[list[Packet], SimTransport]:
    """Half a STAT to the neck, its rest ``rest_after_s`` after the half's last byte
    arrived, then a STAT that reports the neck's status bits."""
    frame = encode_packet(Packet(3, Command.STAT))

    async def main() -> tuple[list[Packet], SimTransport]:
        async with await _open_sim() as sim:
            host = _Host(sim)
            sim.write_nowait(frame[:4])
            # The rest's first byte arrives one byte time after it is written.
            rest_s = 4 * _BYTE_S + rest_after_s - _BYTE_S
            await host.at(rest_s)
            sim.write_nowait(frame[4:])
            await host.at(rest_s + 0.01)
            host.write(Packet(3, Command.STAT))
            await host.at(rest_s + 0.02)
            return [p for _, p in host.replies()], sim

    return run_virtual(main())


def test_a_frame_completed_just_inside_the_garbage_timeout_is_answered() -> None:
    replies, sim = _half_then_rest(GARBAGE_TIMEOUT_S - 1e-6)
    assert [p.data for p in replies] == [b"\0\0", b"\0\0"]
    assert sim.line.stats.expired == 0


def test_a_frame_left_quiet_for_the_garbage_timeout_is_dropped_and_flagged() -> None:
    replies, sim = _half_then_rest(GARBAGE_TIMEOUT_S)
    # The half was given up; its rest is junk; the neck flags garbage (INVALID_PACKET,
    # GARBAGE_DETECTED) and answers only the later STAT.
    assert [p.data for p in replies] == [bytes((0x08, 0x20))]
    assert sim.line.stats.expired == 1


def test_a_half_frame_expires_on_time_with_no_more_bytes() -> None:
    # Nothing follows the half: a timer gives it up, exactly the timeout after its last
    # byte, and the board flags it then.
    frame = encode_packet(read_count(0))

    async def main() -> None:
        async with await _open_sim() as sim:
            host = _Host(sim)
            sim.write_nowait(frame[:5])
            expires_s = 5 * _BYTE_S + GARBAGE_TIMEOUT_S
            await host.at(expires_s - 1e-7)
            assert sim.line.stats.expired == 0
            await host.at(expires_s + 1e-7)
            assert sim.line.stats.expired == 1
            host.write(Packet(0, Command.STAT))
            await host.at(expires_s + 0.01)
            assert [p.data for _, p in host.replies()] == [bytes((0x08, 0x20))]

    run_virtual(main())


# -- a flood of junk ------------------------------------------------------------------------


def test_a_flood_of_junk_costs_little_cpu_and_the_next_request_is_answered_after_it() -> None:
    """Random bytes written far faster than the wire (a host that queued them): the
    request behind them is answered within a reply window of the junk's end on the wire,
    and the line's work on the junk stays a small fraction of that wire time."""
    size = 2_000_000  # 174 s of wire
    junk = random.Random(11).randbytes(size)
    request = Packet(20, Command.STAT)

    async def main() -> tuple[float, list[Packet], float]:
        async with await _open_sim() as sim:
            loop = asyncio.get_running_loop()
            start = loop.time()
            cpu0 = time.process_time()
            for i in range(0, size, 4096):  # as a pseudo-terminal hands it over
                sim.write_nowait(junk[i : i + 4096])
            sim.write_nowait(encode_packet(request))
            cpu = time.process_time() - cpu0
            decoder = PacketDecoder()
            replies: list[Packet] = []
            while not any(p.sid == 20 for p in replies):
                replies += decoder.feed(await sim.read())
            return loop.time() - start, replies, cpu

    elapsed, replies, cpu = run_virtual(main())
    assert replies[-1] == Packet(20, Command.STAT | 0x40, b"\0\0")
    wire_end = (size + 9) * _BYTE_S
    assert elapsed >= wire_end
    # A false header in the junk may hold the request until the garbage timeout.
    assert elapsed <= wire_end + GARBAGE_TIMEOUT_S + _TURNAROUND_S + 9 * _BYTE_S + 1e-6
    # Byte by byte this cost ~1.5 s a megabyte; junk outside a frame is skipped in bulk.
    assert cpu < 1.0, f"{cpu:.2f} s of CPU for {size} bytes of junk"


# -- faults ----------------------------------------------------------------------------------


def test_a_silent_device_does_not_answer_and_the_others_do() -> None:
    async def body(host: _Host) -> None:
        host.sim.line.faults.silent.add(1)
        host.write(read_count(1))
        await host.at(0.01)
        host.write(read_count(0))
        await host.at(0.02)
        host.sim.line.faults.silent.clear()
        host.write(read_count(1))
        await host.at(0.03)
        assert [p.sid for _, p in host.replies()] == [0, 1]

    _on_host(body)


def test_unplugged_cable_passes_nothing_then_works_when_plugged_back() -> None:
    async def body(host: _Host) -> None:
        faults = host.sim.line.faults
        faults.unplugged = True
        host.write(read_count(0))
        await host.at(0.01)
        host.write(read_count(1))
        # The cable is put back while that reply would be on its way: it is lost too.
        await host.at(0.01 + _COUNT_REQUEST * _BYTE_S)
        faults.unplugged = False
        await host.at(0.02)
        assert host.replies() == []
        host.write(read_count(0))
        await host.at(0.03)
        assert [p.sid for _, p in host.replies()] == [0]

    stats = _on_host(body).line.stats
    assert stats.dropped_bytes == 2 * _COUNT_REQUEST
    assert stats.packets == 1


def _noisy_chunks(url: str, count: int) -> tuple[list[tuple[float, bytes]], SimTransport]:
    async def main() -> tuple[list[tuple[float, bytes]], SimTransport]:
        async with await _open_sim(url) as sim:
            host = _Host(sim)
            for i in range(count):
                host.write(read_count(i % 2))
                await host.at((i + 1) * 0.005)
            return host.chunks, sim

    return run_virtual(main())


def test_a_seeded_faulty_run_repeats_exactly() -> None:
    url = "sim://?drop=0.02&corrupt=0.02&seed=11"
    first, first_sim = _noisy_chunks(url, 100)
    second, second_sim = _noisy_chunks(url, 100)
    assert first == second
    assert first_sim.line.stats == second_sim.line.stats
    stats = first_sim.line.stats
    assert stats.dropped_bytes > 0
    assert stats.corrupted_bytes > 0
    other, other_sim = _noisy_chunks("sim://?drop=0.02&corrupt=0.02&seed=12", 100)
    assert other != first
    assert other_sim.line.stats != stats


def test_a_corrupted_request_is_flagged_by_the_device_it_was_for() -> None:
    async def main() -> None:
        sim = await _open_sim()
        async with sim:
            frame = bytearray(encode_packet(read_count(0)))
            frame[-1] ^= 0x10  # breaks the checksum, not the header
            await sim.write(bytes(frame))
            await asyncio.sleep(0.01)
            reply, _ = await _round_trip(sim, Packet(0, Command.STAT))
            assert reply.data == bytes((0x08, 0x04))  # INVALID_PACKET, CHECKSUM_ERROR
            assert sim.line.stats.replies == 1  # the broken read got no answer

    run_virtual(main())


# -- the host's end: unplug, reconnect, close ------------------------------------------------


def test_unplugging_usb_loses_the_link_and_a_new_end_finds_the_robot_running() -> None:
    async def main() -> None:
        first = await _open_sim()
        line, robot = first.line, first.robot
        host = _Host(first)
        host.write(wheel_command(500, 500))
        await host.at(0.1)
        host.write(read_count(0))
        await host.at(0.11)
        ((_, reply),) = host.replies()
        before = parse_count(ReadReply.parse(reply))
        assert before > 0

        first.unplug_usb()
        assert first.closed
        with pytest.raises(TransportError, match="unplugged"):
            first.write_nowait(encode_packet(read_count(0)))
        assert host.lost == []  # noticed by the loop, not inside the call
        await asyncio.sleep(0)
        assert len(host.lost) == 1
        assert isinstance(host.lost[0], TransportError)
        await first.aclose()

        await host.at(0.6)  # unplugged for half a second: the wheels keep turning
        second = SimTransport(line, robot=robot)
        async with second:
            after, _ = await _round_trip(second, read_count(0))
            assert parse_count(ReadReply.parse(after)) > before + 10_000
            assert robot is not None
            assert robot.wheel_speeds_mps()[0] > 0.3
            assert line.now_s() == pytest.approx(asyncio.get_running_loop().time(), abs=0.01)

    run_virtual(main())


def test_a_pull_reader_sees_the_unplug_as_an_error() -> None:
    async def main() -> None:
        async with await _open_sim() as sim:
            reader = asyncio.create_task(sim.read())
            await asyncio.sleep(0.001)
            sim.unplug_usb()
            with pytest.raises(TransportError, match="unplugged"):
                await reader

    run_virtual(main())


def test_one_host_at_a_time() -> None:
    async def main() -> None:
        async with await _open_sim() as sim:
            with pytest.raises(StateError):
                SimTransport(sim.line, robot=sim.robot)
        # Closed: the line takes a new host, which answers.
        async with SimTransport(sim.line, robot=sim.robot) as again:
            reply, _ = await _round_trip(again, read_count(1))
            assert reply.sid == 1
        with pytest.raises(TransportClosedError):
            again.write_nowait(b"\xff")

    run_virtual(main())


@pytest.mark.parametrize("url", ["sim://", "sim://?realtime=0", "sim://?usb_latency_ms=8"], ids=str)
def test_aclose_leaves_nothing_scheduled(url: str) -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        sim = await _open_sim(url)
        host = _Host(sim)
        # A reply on its way and a half frame waiting for its garbage timeout.
        host.write(read_count(0))
        sim.write_nowait(encode_packet(read_count(1))[:4])
        assert _pending(loop)
        await sim.aclose()
        assert _pending(loop) == []
        assert asyncio.all_tasks() == {asyncio.current_task()}
        await asyncio.sleep(0.1)
        assert host.chunks == []

    run_virtual(main())


def test_unplug_then_aclose_leaves_nothing_scheduled() -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        sim = await _open_sim()
        host = _Host(sim)
        host.write(read_count(0))
        sim.unplug_usb()
        await sim.aclose()
        assert _pending(loop) == []
        await asyncio.sleep(0.1)
        assert (host.chunks, host.lost) == ([], [])

    run_virtual(main())


# -- sim:// options -----------------------------------------------------------------------


def test_url_options_reach_the_line() -> None:
    async def main() -> SimTransport:
        url = "sim://?silent=20,4&drop=0.01&seed=3&corrupt=0.5&usb_latency_ms=16"
        async with await _open_sim(url) as sim:
            return sim

    line = run_virtual(main()).line
    assert line.faults.silent == {20, 4}
    assert line.faults.drop_rate == 0.01
    assert line.faults.corrupt_rate == 0.5
    assert line.usb_latency_s == 0.016
    assert not line.faults.unplugged


def test_default_url_has_a_clean_line() -> None:
    async def main() -> SimTransport:
        async with await _open_sim() as sim:
            return sim

    sim = run_virtual(main())
    assert sim.line.faults.silent == set()
    assert (sim.line.faults.drop_rate, sim.line.faults.corrupt_rate) == (0.0, 0.0)
    assert sim.line.usb_latency_s == 0.0
    assert sim.baudrate == 115_200


@pytest.mark.parametrize(
    ("url", "named"),
    [
        ("sim://?neck=9999", "neck"),
        ("sim://?drop=2", "drop"),
        ("sim://?corrupt=-0.1", "corrupt"),
        ("sim://?drop=lots", "drop"),
        ("sim://?bogus=1", "bogus"),
        ("sim://?ext=11,11", "repeat"),
        ("sim://?count_offset=4294967296", "count_offset"),
        ("sim://?silent=core", "silent"),
        ("sim://?silent=300", "silent"),
        ("sim://?seed=-1", "seed"),
        ("sim://?baudrate=fast", "baudrate"),
        ("sim://?turnaround_us=1000000", "turnaround_us"),
        ("sim://?usb_latency_ms=33", "usb_latency_ms"),
        ("sim://?usb_latency_ms=-1", "usb_latency_ms"),
        ("sim://?usb_latency_ms=soon", "usb_latency_ms"),
        ("sim://?soc=150", "soc"),
        ("sim://?soc=full", "soc"),
        ("sim://?docked=maybe", "docked"),
        ("sim://?count_offset=big", "count_offset"),
        ("sim://?ext=20", "20"),
        ("sim://?ext=eleven", "ext"),
        ("sim://?drop=0.1&drop=0.2", "drop"),
        ("sim://robot", "robot"),
    ],
)
def test_bad_options_are_refused_by_name(url: str, named: str) -> None:
    async def main() -> None:
        transport = await open_transport(url)
        await transport.aclose()  # not reached when the URL is refused

    with pytest.raises(ConfigError, match=named):
        run_virtual(main())


def test_a_line_refuses_a_usb_latency_out_of_range() -> None:
    with pytest.raises(OutOfRangeError, match="usb_latency_s"):
        SimLine([], usb_latency_s=0.033)
    with pytest.raises(OutOfRangeError, match="usb_latency_s"):
        SimLine([], usb_latency_s=-0.001)


# -- through the Bus ------------------------------------------------------------------------


def test_dropped_and_corrupted_bytes_are_mostly_recovered_by_retries() -> None:
    async def main() -> tuple[int, Bus, SimTransport]:
        sim = await _open_sim("sim://?drop=0.005&corrupt=0.005&seed=3")
        ok = 0
        async with Bus(sim) as bus:
            for i in range(300):
                try:
                    await bus.read(i % 2, 59, 4)
                # The checksum cannot see a flipped bit 0 (both sums mask it), so now
                # and then a garbled reply decodes and fails its own length check.
                except (BusTimeoutError, MalformedReplyError):
                    continue
                ok += 1
        return ok, bus, sim

    ok, bus, sim = run_virtual(main())
    assert ok >= 290
    line = sim.line.stats
    assert line.dropped_bytes > 0
    assert line.corrupted_bytes > 0
    stats = bus.stats
    assert sum(d.retries for d in stats.devices.values()) > 0
    decoder = stats.decoder
    assert decoder.checksum_errors + decoder.bad_headers > 0
    assert decoder.bytes_discarded > 0


def test_on_a_lossy_line_every_read_returns_its_own_register_or_times_out() -> None:
    """End to end: drops and late replies never hand one request another's data."""
    # Distinct, known values: RAM 8 acceleration_ratio 25, 24..25 Kp 440, 26..27 Kd 8000,
    # 44 in-position margin 3, 0 id 3.
    expected = {
        8: (1, b"\x19"),
        24: (2, (440).to_bytes(2, "little")),
        26: (2, (8000).to_bytes(2, "little")),
        44: (1, b"\x03"),
        0: (1, b"\x03"),
    }

    async def main() -> tuple[int, int]:
        transport = await open_transport("sim://?drop=0.02&seed=5&ext=none")
        ok = timeouts = 0
        async with Bus(transport, timeout_s=0.005) as bus:
            for i in range(400):
                addr = list(expected)[i % len(expected)]
                length, value = expected[addr]
                try:
                    reply = await bus.read(3, addr, length)
                except BusTimeoutError:
                    timeouts += 1
                    continue
                assert (reply.addr, reply.data) == (addr, value)
                ok += 1
        return ok, timeouts

    ok, timeouts = run_virtual(main())
    assert ok + timeouts == 400
    assert ok > 350
