"""Transports: one conformance suite for every kind, the in-memory faults, open_transport.

The serial transport runs on a real pseudo-terminal: the test opens the slave side with
``SerialTransport`` and plays the device on the master side through the event loop.
"""

from __future__ import annotations

import asyncio
import os
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from urllib.parse import SplitResult

import pytest

from ohmni_tb.errors import ConfigError, TransportClosedError, TransportError
from ohmni_tb.transport import (
    DEFAULT_BAUDRATE,
    MemoryTransport,
    SerialTransport,
    Transport,
    corrupt_byte,
    delay,
    drop_bytes,
    open_transport,
    register_transport,
    registered_schemes,
    split,
)

#: Long enough never to fire on a loaded machine; only a hang reaches it.
HANG_S = 5.0
EVERY_BYTE = bytes(range(256))


async def read_exactly(transport: Transport, n: int) -> bytes:
    """Read until ``n`` bytes have arrived (reads may return any part of them)."""
    buf = bytearray()
    async with asyncio.timeout(HANG_S):
        while len(buf) < n:
            buf += await transport.read()
    assert len(buf) == n, "more bytes arrived than were sent"
    return bytes(buf)


@contextmanager
def open_pty() -> Iterator[tuple[int, str]]:
    """A pseudo-terminal: the master fd (non-blocking) and the slave's path."""
    master, slave = os.openpty()
    try:
        os.set_blocking(master, False)
        # The slave fd stays open so the master never sees a hang-up mid-test.
        yield master, os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


class PtyDevice:
    """The far end of a pseudo-terminal, read through the event loop."""

    def __init__(self, master: int) -> None:
        self._master = master
        self._loop = asyncio.get_running_loop()
        self._buf = bytearray()
        self._ready = asyncio.Event()
        self._loop.add_reader(master, self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = os.read(self._master, 65536)
        except BlockingIOError:
            return
        self._buf += data
        self._ready.set()

    async def send(self, data: bytes) -> None:
        view = memoryview(data)
        async with asyncio.timeout(HANG_S):
            while view:
                try:
                    view = view[os.write(self._master, view) :]
                except BlockingIOError:
                    await asyncio.sleep(0.001)

    async def receive(self, n: int) -> bytes:
        async with asyncio.timeout(HANG_S):
            while len(self._buf) < n:
                self._ready.clear()
                await self._ready.wait()
        assert len(self._buf) == n, "more bytes arrived than were sent"
        data = bytes(self._buf)
        self._buf.clear()
        return data

    def close(self) -> None:
        self._loop.remove_reader(self._master)


@dataclass
class Link:
    """A transport under test and its far end."""

    transport: Transport
    #: The far end sends bytes to the transport.
    send: Callable[[bytes], Awaitable[None]]
    #: The far end receives exactly n bytes from the transport.
    receive: Callable[[int], Awaitable[bytes]]


@pytest.fixture(params=["memory-pair", "loopback", "serial-pty"])
async def link(request: pytest.FixtureRequest) -> AsyncIterator[Link]:
    kind: str = request.param
    if kind == "memory-pair":
        host, device = MemoryTransport.pair()
        yield Link(host, device.write, lambda n: read_exactly(device, n))
        await host.aclose()
        await device.aclose()
    elif kind == "loopback":
        loop = MemoryTransport.loopback()
        yield Link(loop, loop.write, lambda n: read_exactly(loop, n))
        await loop.aclose()
    else:
        with open_pty() as (master, path):
            transport = await SerialTransport.open(path)
            far_end = PtyDevice(master)
            try:
                yield Link(transport, far_end.send, far_end.receive)
            finally:
                await transport.aclose()
                far_end.close()


# -- conformance: every transport ---------------------------------------------------------


async def test_bytes_cross_both_ways_unchanged(link: Link) -> None:
    # Every byte value, control characters included: the line must be raw.
    await link.transport.write(EVERY_BYTE)
    assert await link.receive(len(EVERY_BYTE)) == EVERY_BYTE
    await link.send(EVERY_BYTE[::-1])
    assert await read_exactly(link.transport, 256) == EVERY_BYTE[::-1]


async def test_many_writes_arrive_in_order(link: Link) -> None:
    chunks = [bytes([i]) * (1 + i % 7) for i in range(200)]
    for chunk in chunks:
        await link.transport.write(chunk)
    assert await link.receive(sum(map(len, chunks))) == b"".join(chunks)


async def test_aclose_is_idempotent_then_io_raises(link: Link) -> None:
    transport = link.transport
    closed = [transport.closed]
    await transport.aclose()
    await transport.aclose()
    closed.append(transport.closed)
    assert closed == [False, True]
    with pytest.raises(TransportClosedError):
        await transport.read()
    with pytest.raises(TransportClosedError):
        await transport.write(b"\x00")


async def test_aclose_wakes_a_pending_read(link: Link) -> None:
    reader = asyncio.create_task(link.transport.read())
    await asyncio.sleep(0.01)
    assert not reader.done()
    await link.transport.aclose()
    with pytest.raises(TransportClosedError):
        await asyncio.wait_for(reader, HANG_S)


async def test_async_context_manager_closes(link: Link) -> None:
    async with link.transport as transport:
        assert transport is link.transport
        await transport.write(b"\xff\xff")
        assert await link.receive(2) == b"\xff\xff"
    assert link.transport.closed
    with pytest.raises(TransportClosedError):
        await link.transport.read()


# -- the in-memory pair -------------------------------------------------------------------


async def test_memory_peer_close_ends_the_stream(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    await device.write(b"last words")
    assert await read_exactly(host, 10) == b"last words"
    pending = asyncio.create_task(host.read())
    await asyncio.sleep(0)
    await device.aclose()
    with pytest.raises(TransportClosedError, match="other end"):
        await pending
    assert host.closed  # a lost link counts as closed (Transport.closed)
    with pytest.raises(TransportClosedError):
        await host.write(b"\x00")


async def test_memory_bytes_written_before_close_are_still_read(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    await device.write(b"abc")
    await device.aclose()
    assert await host.read() == b"abc"
    with pytest.raises(TransportClosedError):
        await host.read()


async def test_memory_split_delivers_pieces(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    host.set_manipulator(split(2))
    await host.write(b"abcde")
    async with asyncio.timeout(HANG_S):
        assert [await device.read() for _ in range(3)] == [b"ab", b"cd", b"e"]
        host.set_manipulator(None)
        await host.write(b"fgh")
        assert await device.read() == b"fgh"
    assert (host.bytes_written, device.bytes_read) == (8, 8)
    with pytest.raises(ValueError, match="at least 1"):
        split(0)


async def test_memory_split_one_byte_per_read(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    host.set_manipulator(split(1))
    await host.write(EVERY_BYTE)
    async with asyncio.timeout(HANG_S):
        reads = [await device.read() for _ in range(256)]
    assert reads == [bytes([b]) for b in EVERY_BYTE]


async def test_memory_delay_keeps_order(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    loop = asyncio.get_running_loop()
    host.set_manipulator(delay(0.03))
    start = loop.time()
    await host.write(b"first")
    host.set_manipulator(None)
    await host.write(b"second")
    assert await asyncio.wait_for(device.read(), HANG_S) == b"first"
    # Lower bounds only: a loaded machine can be late, never early.
    assert loop.time() - start >= 0.029
    assert await asyncio.wait_for(device.read(), HANG_S) == b"second"


async def test_memory_delayed_bytes_die_with_the_writer(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    host.set_manipulator(delay(0.01))
    await host.write(b"never")
    await host.aclose()
    await asyncio.sleep(0.03)
    with pytest.raises(TransportClosedError):
        await device.read()


async def test_memory_drop_bytes_counts_across_writes(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    host.set_manipulator(drop_bytes(3, skip=2))
    for chunk in (b"abc", b"de", b"fgh"):
        await host.write(chunk)
    assert await read_exactly(device, 5) == b"abfgh"


async def test_memory_drop_a_whole_write(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    host.set_manipulator(drop_bytes(4))
    await host.write(b"gone")
    await host.write(b"kept")
    assert await device.read() == b"kept"


async def test_memory_corrupt_byte_once_at_a_stream_offset(
    memory_pair: tuple[MemoryTransport, MemoryTransport],
) -> None:
    host, device = memory_pair
    host.set_manipulator(corrupt_byte(4, xor=0xFF))
    for chunk in (b"abc", b"defg", b"abcdefg"):
        await host.write(chunk)
    expected = b"abcd" + bytes([ord("e") ^ 0xFF]) + b"fgabcdefg"
    assert await read_exactly(device, len(expected)) == expected


async def test_loopback_reads_its_own_writes() -> None:
    async with MemoryTransport.loopback() as loop:
        await loop.write(b"\x01\x02")
        assert await loop.read() == b"\x01\x02"


# -- open_transport -----------------------------------------------------------------------


@pytest.fixture
def pty() -> Iterator[tuple[int, str]]:
    with open_pty() as pair:
        yield pair


async def test_open_a_device_path(pty: tuple[int, str]) -> None:
    master, path = pty
    async with await open_transport(path) as transport:
        assert isinstance(transport, SerialTransport)
        assert transport.port == path
        assert transport.baudrate == DEFAULT_BAUDRATE == 115_200
        device = PtyDevice(master)
        try:
            await transport.write(b"\xff\xff\x07")
            assert await device.receive(3) == b"\xff\xff\x07"
            await device.send(b"\x0d\x0a\x03")
            assert await read_exactly(transport, 3) == b"\x0d\x0a\x03"
        finally:
            device.close()


async def test_serial_keeps_what_a_full_port_does_not_take_and_sends_it_in_order(
    pty: tuple[int, str],
) -> None:
    """A peer that does not read fills the pty: the rest waits in the backlog (nothing
    lost, nothing blocks), and goes out in order once the peer reads."""
    master, path = pty
    payload = bytes(range(256)) * 64  # 16 KiB a write
    async with await open_transport(path) as transport:
        assert isinstance(transport, SerialTransport)
        for _ in range(16):  # 256 KiB: more than a pty buffers
            transport.write_nowait(payload)
        assert transport.backlog > 0
        device = PtyDevice(master)
        try:
            received = await asyncio.wait_for(device.receive(16 * len(payload)), 10)
            assert received == payload * 16
            async with asyncio.timeout(5):
                await transport.drain()
            assert transport.backlog == 0
        finally:
            device.close()


@pytest.mark.parametrize("prefix", ["serial://", "serial:/"], ids=["three-slashes", "two-slashes"])
async def test_open_a_serial_url_with_options(pty: tuple[int, str], prefix: str) -> None:
    _, path = pty
    url = f"{prefix}{path}?baudrate=57600&low_latency=off&exclusive=0"
    async with await open_transport(url) as transport:
        assert isinstance(transport, SerialTransport)
        assert transport.baudrate == 57_600
        assert transport.port == path


async def test_serial_is_exclusive_by_default(pty: tuple[int, str]) -> None:
    _, path = pty
    first = await open_transport(path)
    try:
        with pytest.raises(TransportError, match=path) as info:
            await SerialTransport.open(path)
        assert not isinstance(info.value, ConfigError)
    finally:
        await first.aclose()
    # The lock goes with the port.
    again = await open_transport(path)
    await again.aclose()


async def test_serial_unplugged_surfaces_as_transport_error() -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    transport = await SerialTransport.open(path)
    try:
        reader = asyncio.create_task(transport.read())
        await asyncio.sleep(0.01)
        os.close(master)
        with pytest.raises(TransportError):
            await asyncio.wait_for(reader, HANG_S)
        with pytest.raises(TransportError):
            await transport.write(b"\x00")
    finally:
        await transport.aclose()


@pytest.mark.parametrize("url", ["/dev/ohmni-no-such-port", "serial:///dev/ohmni-no-such-port"])
async def test_missing_serial_device_names_the_path(url: str) -> None:
    with pytest.raises(TransportError, match="/dev/ohmni-no-such-port") as info:
        await open_transport(url)
    assert not isinstance(info.value, ConfigError)
    assert isinstance(info.value.__cause__, OSError)


async def test_open_memory_loopback() -> None:
    async with await open_transport("memory://") as transport:
        await transport.write(b"echo")
        assert await transport.read() == b"echo"


async def test_open_memory_by_name_pairs_two_opens() -> None:
    name = f"pair-{uuid.uuid4().hex}"
    a = await open_transport(f"memory://{name}")
    b = await open_transport(f"memory://{name}")
    async with a, b:
        assert a is not b
        await a.write(b"ping")
        assert await b.read() == b"ping"
        await b.write(b"pong")
        assert await a.read() == b"pong"


@pytest.mark.parametrize(
    ("url", "named"),
    [
        ("bogus://x", "'bogus'"),
        ("ttyUSB0", "ttyUSB0"),
        ("memory://?speed=1", "speed"),
        ("serial:///dev/ohmni-no-such-port?baudrate=fast", "baudrate"),
        ("serial:///dev/ohmni-no-such-port?baudrate=10", "baudrate"),
        ("serial:///dev/ohmni-no-such-port?exclusive=maybe", "exclusive"),
        ("serial:///dev/ohmni-no-such-port?low_latency=2", "low_latency"),
        ("serial:///dev/ohmni-no-such-port?parity=E", "parity"),
        ("serial:///dev/ohmni-no-such-port?baudrate=1&baudrate=2", "baudrate"),
        ("serial://", "device path"),
    ],
)
async def test_bad_urls_raise_config_error_naming_the_problem(url: str, named: str) -> None:
    # Checked before any port is touched: the path does not exist, yet no TransportError.
    with pytest.raises(ConfigError, match=named) as info:
        await open_transport(url)
    assert isinstance(info.value, ValueError)


async def test_schemes_can_be_registered() -> None:
    seen: list[tuple[str, dict[str, str]]] = []

    async def factory(url: SplitResult, options: dict[str, str]) -> Transport:
        seen.append((url.netloc, dict(options)))
        return MemoryTransport.loopback()

    scheme = f"t{uuid.uuid4().hex[:8]}"
    register_transport(scheme, factory)
    assert scheme in registered_schemes()
    assert {"memory", "serial", "sim"} <= set(registered_schemes())
    transport = await open_transport(f"{scheme.upper()}://here?x=1")
    await transport.aclose()
    assert seen == [("here", {"x": "1"})]
    with pytest.raises(ConfigError, match="already registered"):
        register_transport(scheme, factory)
    register_transport(scheme, factory, replace=True)


@pytest.mark.hardware
async def test_real_port_opens(ohmni_port: str) -> None:
    async with await open_transport(ohmni_port) as transport:
        assert isinstance(transport, SerialTransport)
        assert transport.baudrate == DEFAULT_BAUDRATE


async def test_serial_reports_a_hung_up_pty_by_name_and_keeps_a_quiet_one() -> None:
    master, slave = os.openpty()
    path = os.ttyname(slave)
    os.close(slave)
    transport = await SerialTransport.open(path)
    lost: list[TransportError] = []
    got: list[bytes] = []
    gone = asyncio.Event()

    def on_lost(exc: TransportError) -> None:
        lost.append(exc)
        gone.set()

    transport.start_receiving(got.append, on_lost)
    try:
        os.write(master, b"\x01\x02")
        await asyncio.sleep(0.05)
        # Quiet but alive: no bytes, and the link stays up.
        await asyncio.sleep(0.05)
        assert got == [b"\x01\x02"]
        assert not lost
        # The far end goes away, as a simulator that exits or an adapter pulled out.
        os.close(master)
        master = -1
        async with asyncio.timeout(HANG_S):
            await gone.wait()
        assert len(lost) == 1
        assert "hung up" in str(lost[0])
        assert transport.closed
    finally:
        if master >= 0:
            os.close(master)
        await transport.aclose()
