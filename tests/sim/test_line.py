"""The simulated line: wire timing, collisions, faults, and the sim:// URL options.

Every test runs on the virtual clock, so wire times are exact and nothing sleeps.
"""

from __future__ import annotations

import asyncio

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.errors import BusTimeoutError, ConfigError, MalformedReplyError
from ohmni_tb.protocol import Command, Packet, PacketDecoder, encode_packet
from ohmni_tb.protocol.drive import parse_count, read_count
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.line import SimLine, SimTransport
from ohmni_tb.sim.servo import SimServo
from ohmni_tb.transport import Transport, open_transport

_BYTE_S = 10 / 115_200
_TURNAROUND_S = 0.0005


async def _open_sim(url: str = "sim://") -> SimTransport:
    transport = await open_transport(url)
    assert isinstance(transport, SimTransport)
    return transport


async def _round_trip(transport: Transport, request: Packet) -> tuple[Packet, float]:
    """Write ``request`` by hand and wait for one whole reply; return it and the time taken."""
    loop = asyncio.get_running_loop()
    decoder = PacketDecoder()
    start = loop.time()
    await transport.write(encode_packet(request))
    while True:
        packets = decoder.feed(await transport.read())
        if packets:
            assert len(packets) == 1
            return packets[0], loop.time() - start


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


def test_requests_written_together_are_answered_one_after_the_other() -> None:
    async def main() -> tuple[list[tuple[Packet, float]], SimTransport]:
        async with await _open_sim() as sim:
            loop = asyncio.get_running_loop()
            decoder = PacketDecoder()
            start = loop.time()
            # Two reads in one write: the line carries 18 request bytes before either reply.
            await sim.write(encode_packet(read_count(0)) + encode_packet(read_count(1)))
            got: list[tuple[Packet, float]] = []
            while len(got) < 2:
                packets = decoder.feed(await sim.read())
                got += [(packet, loop.time() - start) for packet in packets]
            return got, sim

    got, sim = run_virtual(main())
    assert [p.sid for p, _ in got] == [0, 1]
    first_end = 18 * _BYTE_S + _TURNAROUND_S + 15 * _BYTE_S
    assert got[0][1] == pytest.approx(first_end, abs=1e-9)
    # The second reply queues behind the first: the line is never driven twice at once.
    assert got[1][1] == pytest.approx(first_end + 15 * _BYTE_S, abs=1e-9)
    assert sim.line.stats.collisions == 0


def test_a_broadcast_gets_no_reply_and_keeps_the_line_busy_only_for_its_bytes() -> None:
    async def main() -> SimTransport:
        async with await _open_sim() as sim:
            await sim.write(encode_packet(Packet(0xFE, Command.RAM_WRITE, bytes((52, 1, 0x60)))))
            await asyncio.sleep(0.1)
            return sim

    stats = run_virtual(main()).line.stats
    assert (stats.packets, stats.replies, stats.bytes_to_host) == (1, 0, 0)
    assert stats.busy_s == pytest.approx(10 * _BYTE_S, abs=1e-9)


# -- collisions ---------------------------------------------------------------------------


def _twin_servos() -> SimLine:
    """Two servos that both answer to id 11, their horns at different positions."""
    return SimLine([SimServo(11, pos_raw=100), SimServo(11, pos_raw=900)])


def test_two_devices_answering_one_read_collide_and_the_bus_times_out() -> None:
    line = _twin_servos()

    async def main() -> Bus:
        async with Bus(SimTransport(line)) as bus:
            with pytest.raises(BusTimeoutError) as info:
                await bus.read(11, 60, 2)  # absolute position: the two replies differ
            assert info.value.sid == 11
            return bus

    bus = run_virtual(main())
    assert line.stats.collisions == 3  # the first attempt and both retries
    decoder = bus.stats.decoder
    assert decoder.packets == 0
    assert decoder.bytes_discarded == decoder.bytes_in > 0
    assert decoder.bad_headers + decoder.checksum_errors > 0


def test_identical_colliding_replies_still_read_as_one() -> None:
    # Both drivers send the same bits, so the wire carries a valid frame: the host cannot
    # tell, but the line counts the collision.
    line = _twin_servos()

    async def main() -> Packet | None:
        async with Bus(SimTransport(line)) as bus:
            return await bus.request(Packet(11, Command.STAT))

    assert run_virtual(main()) == Packet(11, Command.STAT | 0x40, b"\0\0")
    assert line.stats.collisions == 1


# -- faults as the bus sees them ----------------------------------------------------------


def test_a_silent_device_times_out_by_its_id_and_the_others_still_answer() -> None:
    async def main() -> None:
        async with Bus(await _open_sim("sim://?silent=20")) as bus:
            with pytest.raises(BusTimeoutError, match="sid 20") as info:
                await bus.read(20, 0xA0, 18)
            assert info.value.sid == 20
            assert info.value.attempts == 3
            assert (await bus.read(0, 59, 4)).sid == 0
            assert bus.stats.devices[20].timeouts == 3

    run_virtual(main())


def test_silence_can_be_set_and_lifted_at_any_time() -> None:
    async def main() -> None:
        sim = await _open_sim()
        async with Bus(sim) as bus:
            sim.line.faults.silent.add(1)
            with pytest.raises(BusTimeoutError):
                await bus.read(1, 59, 4)
            sim.line.faults.silent.clear()
            assert (await bus.read(1, 59, 4)).sid == 1

    run_virtual(main())


def test_unplugged_cable_times_out_then_works_when_plugged_back() -> None:
    async def main() -> SimTransport:
        sim = await _open_sim()
        async with Bus(sim) as bus:
            sim.line.faults.unplugged = True
            for sid in (0, 20):
                with pytest.raises(BusTimeoutError):
                    await bus.read(sid, 0xF1, 0)
            sim.line.faults.unplugged = False
            assert parse_count(await bus.read(0, 59, 4)) == 0
            return sim

    stats = run_virtual(main()).line.stats
    assert stats.dropped_bytes == 6 * 9  # six attempts, nine bytes each, none arrived
    assert stats.packets == 1


def _noisy_reads(url: str, count: int) -> tuple[int, Bus, SimTransport]:
    async def main() -> tuple[int, Bus, SimTransport]:
        sim = await _open_sim(url)
        ok = 0
        async with Bus(sim) as bus:
            for i in range(count):
                try:
                    await bus.read(i % 2, 59, 4)
                # The checksum cannot see a flipped bit 0 (both sums mask it), so now
                # and then a garbled reply decodes and fails its own length check.
                except (BusTimeoutError, MalformedReplyError):
                    continue
                ok += 1
        return ok, bus, sim

    return run_virtual(main())


def test_dropped_and_corrupted_bytes_are_mostly_recovered_by_retries() -> None:
    ok, bus, sim = _noisy_reads("sim://?drop=0.005&corrupt=0.005&seed=3", 300)
    assert ok >= 290
    line = sim.line.stats
    assert line.dropped_bytes > 0
    assert line.corrupted_bytes > 0
    stats = bus.stats
    assert sum(d.retries for d in stats.devices.values()) > 0
    decoder = stats.decoder
    assert decoder.checksum_errors + decoder.bad_headers > 0
    assert decoder.bytes_discarded > 0


def test_a_seeded_faulty_run_repeats_exactly() -> None:
    url = "sim://?drop=0.02&corrupt=0.02&seed=11"
    first = _noisy_reads(url, 60)
    second = _noisy_reads(url, 60)
    assert first[0] == second[0]
    assert first[1].stats == second[1].stats
    assert first[2].line.stats == second[2].line.stats
    other = _noisy_reads("sim://?drop=0.02&corrupt=0.02&seed=12", 60)
    assert other[2].line.stats != first[2].line.stats


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


# -- sim:// options -----------------------------------------------------------------------


def test_url_options_reach_the_line() -> None:
    async def main() -> SimTransport:
        async with await _open_sim("sim://?silent=20,4&drop=0.01&seed=3&corrupt=0.5") as sim:
            return sim

    line = run_virtual(main()).line
    assert line.faults.silent == {20, 4}
    assert line.faults.drop_rate == 0.01
    assert line.faults.corrupt_rate == 0.5
    assert not line.faults.unplugged


def test_default_url_has_a_clean_line() -> None:
    async def main() -> SimTransport:
        async with await _open_sim() as sim:
            return sim

    sim = run_virtual(main())
    assert sim.line.faults.silent == set()
    assert (sim.line.faults.drop_rate, sim.line.faults.corrupt_rate) == (0.0, 0.0)
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


def test_realtime_off_answers_at_once_and_keeps_simulated_time() -> None:
    """realtime=0: replies come without waiting; the simulated time still counts the wire."""

    async def main(url: str) -> tuple[float, float]:
        transport = await open_transport(url)
        assert isinstance(transport, SimTransport)
        async with Bus(transport, gap_s=0.0) as bus:
            for _ in range(10):
                await bus.read(3, 58, 2)
            latency = bus.stats.devices[3].latency_p50_s
            assert latency is not None
            return latency, transport.line.now_s()

    wire_s = (9 + 13) * 10 / 115_200
    latency_rt, sim_rt = run_virtual(main("sim://?turnaround_us=0"))
    latency_fast, sim_fast = run_virtual(main("sim://?turnaround_us=0&realtime=0"))
    assert latency_rt == pytest.approx(wire_s)
    assert latency_fast == 0.0
    # Both simulated clocks counted the same ten reads on the wire.
    assert sim_fast == pytest.approx(10 * wire_s)
    assert sim_rt == pytest.approx(10 * wire_s)


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
            stats = bus.stats
        assert stats.devices[3].retries > 0  # the faults did bite
        return ok, timeouts

    ok, timeouts = run_virtual(main())
    assert ok + timeouts == 400
    assert ok > 350
