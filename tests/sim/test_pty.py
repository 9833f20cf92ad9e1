"""``ohmni sim --pty``: the simulated robot on a pseudo-terminal, driven by any serial client.

The raw-client test speaks to it with plain pyserial and bytes built by hand here, so it
checks the simulator against the reference page, not against this project's own codecs.
These tests run the simulator as a subprocess in real time: their timeouts are seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import select
import signal
import struct
import subprocess
import sys
import time
import tty
from collections.abc import Callable, Iterator

import pytest
import serial

from ohmni_tb.bus import Bus
from ohmni_tb.cli.sim import MAX_CONSOLE_LINE
from ohmni_tb.protocol import Packet, ReadReply
from ohmni_tb.protocol.core import parse_status, read_status
from ohmni_tb.protocol.drive import parse_count, read_count, wheel_command
from ohmni_tb.sim.line import HOST_BUFFER_BYTES, SimLine
from ohmni_tb.sim.pty import open_pty_pair
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.sim.servo import GARBAGE_TIMEOUT_S
from ohmni_tb.transport import SerialTransport, open_transport


def _can_open_pty() -> bool:
    if not hasattr(os, "openpty"):
        return False
    try:
        master, slave = os.openpty()
    except OSError:
        return False
    os.close(master)
    os.close(slave)
    return True


pytestmark = pytest.mark.skipif(not _can_open_pty(), reason="needs pseudo-terminals")

_START_TIMEOUT_S = 30.0
_IO_TIMEOUT_S = 5.0


class SimProcess:
    """One ``ohmni sim --pty`` subprocess and the device path it printed."""

    def __init__(self, *args: str, stdin: int = subprocess.PIPE) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ohmni_tb", "sim", "--pty", *args],
            stdin=stdin,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        self.path = self._first_line()

    def _first_line(self) -> str:
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + _START_TIMEOUT_S
        line = b""
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            ready, _, _ = select.select([fd], [], [], max(0.0, left))
            if not ready:
                raise AssertionError(f"no device path from ohmni sim in {_START_TIMEOUT_S} s")
            chunk = os.read(fd, 1)
            if not chunk:
                raise AssertionError(f"ohmni sim ended early: {self.finish()[1]!r}")
            line += chunk
        return line.decode().strip()

    def command(self, text: str) -> None:
        """Type an operator command on the simulator's stdin."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(text.encode() + b"\n")
        self.proc.stdin.flush()

    def finish(self) -> tuple[int, str]:
        """Wait for the exit; return the exit code and everything written on stderr."""
        _, err = self.proc.communicate(timeout=_START_TIMEOUT_S)
        return self.proc.returncode, err.decode(errors="replace")

    def kill(self) -> None:
        if self.proc.returncode is None:
            self.proc.kill()
            self.proc.communicate(timeout=_START_TIMEOUT_S)
        for stream in (self.proc.stdin, self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def start_sim() -> Iterator[Callable[..., SimProcess]]:
    """Start ``ohmni sim --pty`` subprocesses; any still running are killed afterwards."""
    started: list[SimProcess] = []

    def start(*args: str, stdin: int = subprocess.PIPE) -> SimProcess:
        sim = SimProcess(*args, stdin=stdin)
        started.append(sim)
        return sim

    yield start
    for sim in started:
        sim.kill()


# -- a raw client: pyserial and hand-made bytes only --------------------------------------


def frame(sid: int, cmd: int, data: bytes = b"") -> bytes:
    """FF FF size sid cmd cs1 cs2 data, with the checksums of the reference page."""
    size = 7 + len(data)
    x = size ^ sid ^ cmd
    for b in data:
        x ^= b
    return bytes((0xFF, 0xFF, size, sid, cmd, x & 0xFE, ~x & 0xFE)) + data


def read_frame(port: serial.Serial) -> tuple[int, int, bytes]:
    """Read one frame; check its checksums; return sid, cmd and data."""
    header = port.read(7)
    assert len(header) == 7, f"timed out with {header.hex(' ')!r}"
    assert header[:2] == b"\xff\xff"
    size, sid, cmd, cs1, cs2 = header[2:7]
    data = port.read(size - 7)
    assert len(data) == size - 7
    x = size ^ sid ^ cmd
    for b in data:
        x ^= b
    assert (cs1, cs2) == (x & 0xFE, ~x & 0xFE)
    return sid, cmd, data


def raw_read(port: serial.Serial, sid: int, addr: int, length: int, *, eep: bool = False) -> bytes:
    """RAM_READ (0x04) or EEP_READ (0x02); return the register bytes of the reply."""
    cmd = 0x02 if eep else 0x04
    port.write(frame(sid, cmd, bytes((addr, length))))
    r_sid, r_cmd, data = read_frame(port)
    assert (r_sid, r_cmd) == (sid, cmd | 0x40)
    assert data[0] == addr
    n = data[1]
    assert len(data) == 2 + n + 2
    assert data[-2:] == b"\0\0", "status error/detail bits set"
    return data[2 : 2 + n]


def raw_count(port: serial.Serial, sid: int) -> int:
    return int.from_bytes(raw_read(port, sid, 59, 4), "little", signed=True)


def standstill(port: serial.Serial) -> tuple[int, int]:
    """The wheel counts once two readings 0.1 s apart agree (a coasting wheel stops in
    about 0.3 s of the simulator's time; a loaded machine may hand it the stop late)."""
    last = (raw_count(port, 0), raw_count(port, 1))
    deadline = time.monotonic() + _IO_TIMEOUT_S
    while True:
        time.sleep(0.1)
        now = (raw_count(port, 0), raw_count(port, 1))
        if now == last:
            return now
        assert time.monotonic() < deadline, f"the wheels still turn: {last} then {now}"
        last = now


def raw_wheels(port: serial.Serial, left_pwm: int, right_pwm: int) -> None:
    """One broadcast S_JOG (0x06): playtime, then JOG lo, JOG hi, SET 0x02 (turn), id."""
    data = bytearray((0x00,))
    for sid, pwm in ((0, left_pwm), (1, right_pwm)):
        jog = abs(pwm) | (0x4000 if pwm < 0 else 0)
        data += bytes((jog & 0xFF, jog >> 8, 0x02, sid))
    port.write(frame(0xFE, 0x06, bytes(data)))


def test_a_raw_serial_client_reads_and_drives_the_simulator(
    start_sim: Callable[..., SimProcess],
) -> None:
    sim = start_sim()
    assert sim.path.startswith("/dev/")
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 0) == 0
        assert raw_count(port, 1) == 0

        block = raw_read(port, 20, 0xA0, 18)
        cells = struct.unpack("<5H", block[:10])
        assert all(3000 <= mv <= 3600 for mv in cells)
        (current_ma,) = struct.unpack("<h", block[10:12])
        assert current_ma < 0  # undocked: the pack discharges
        assert block[12] == 0  # not docked

        for sid in (0, 1, 20):
            tag = raw_read(port, sid, 0xF1, 0, eep=True)
            assert tag
            assert tag.isascii()
            assert tag.decode().isprintable()

        # Forward: left +PWM, right -PWM (mirrored), resent like a control loop would.
        counts_while_driving = []
        for _ in range(5):
            raw_wheels(port, 400, -400)
            time.sleep(0.1)
            counts_while_driving.append(raw_count(port, 0))
        raw_wheels(port, 0, 0)
        assert counts_while_driving[-1] > counts_while_driving[0]  # moving while driven

        left, right = standstill(port)  # it coasts to a stop
        assert left > 0
        assert right < 0
        assert abs(left + right) <= 1  # mirrored: the same motion, floor rounding only
        time.sleep(0.2)
        assert (raw_count(port, 0), raw_count(port, 1)) == (left, right)  # and stays

        port.write(frame(20, 0x07))  # STAT
        assert read_frame(port) == (20, 0x47, b"\0\0")

    sim.proc.send_signal(signal.SIGINT)
    code, err = sim.finish()
    assert code == 0
    assert "simulator stopped" in err
    assert "Traceback" not in err


def test_the_session_survives_the_client_reopening_the_port(
    start_sim: Callable[..., SimProcess],
) -> None:
    sim = start_sim()
    for _ in range(2):
        with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
            assert raw_count(port, 1) == 0
    sim.proc.send_signal(signal.SIGTERM)
    code, err = sim.finish()
    assert code == 0
    assert "simulator stopped" in err


def test_operator_commands_on_stdin(start_sim: Callable[..., SimProcess]) -> None:
    sim = start_sim()
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_read(port, 20, 0xA0, 18)[12] == 0
        sim.command("dock")
        deadline = time.monotonic() + _IO_TIMEOUT_S
        while raw_read(port, 20, 0xA0, 18)[12] != 1:
            assert time.monotonic() < deadline, "the dock command did not take"
            time.sleep(0.05)
        (current_ma,) = struct.unpack("<h", raw_read(port, 20, 0xA0, 18)[10:12])
        assert current_ma > 0  # charging

        sim.command("silent 0")
        deadline = time.monotonic() + _IO_TIMEOUT_S
        port.timeout = 0.3
        while True:
            port.reset_input_buffer()
            port.write(frame(0, 0x07))
            if not port.read(9):
                break
            assert time.monotonic() < deadline, "the silent command did not take"
    sim.command("quit")
    code, err = sim.finish()
    assert code == 0
    assert "ok" in err.splitlines()
    assert "simulator stopped" in err


def test_stall_and_slip_on_the_console_and_in_the_url(
    start_sim: Callable[..., SimProcess],
) -> None:
    sim = start_sim("--url", "sim://?slip=1")

    def left_turns() -> bool:
        """Whether the left wheel turns at PWM 400 (the command resent for 0.2 s)."""
        before = raw_count(port, 0)
        for _ in range(4):
            raw_wheels(port, 400, -400)
            time.sleep(0.05)
        raw_wheels(port, 0, 0)
        return raw_count(port, 0) != before

    def until(left: bool) -> None:
        deadline = time.monotonic() + _IO_TIMEOUT_S
        while left_turns() != left:
            assert time.monotonic() < deadline, (
                f"the left wheel never {'turned' if left else 'stood'}"
            )

    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        until(left=True)
        sim.command("stall 0")  # blocked: it does not turn whatever its PWM
        until(left=False)
        sim.command("status")
        sim.command("stall 9")
        sim.command("stall 0 maybe")
        sim.command("slip 1 off")
        sim.command("stall 0 off")
        until(left=True)
    sim.command("quit")
    code, err = sim.finish()
    assert code == 0
    lines = err.splitlines()
    assert any("stall SID [off] | slip SID [off]" in line for line in lines)  # the help
    assert any("faults stall 0, slip 1" in line for line in lines)  # the URL's and the console's
    assert (
        "stall: no drive board answers to id 9: the drive boards answer to 0 (left) and 1 (right)"
        in lines
    )
    assert "stall: say `stall SID` or `stall SID off`, not '0 maybe'" in lines
    assert "Traceback" not in err


def test_without_a_console_it_serves_and_stops_cleanly(
    start_sim: Callable[..., SimProcess],
) -> None:
    # Started from a service or a script: stdin is /dev/null.
    sim = start_sim(stdin=subprocess.DEVNULL)
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 0) == 0
    sim.proc.send_signal(signal.SIGINT)
    code, err = sim.finish()
    assert code == 0
    assert "simulator stopped" in err
    assert "Traceback" not in err
    assert "Exception" not in err


def test_it_keeps_serving_when_the_launcher_closes_its_console(
    start_sim: Callable[..., SimProcess],
) -> None:
    # A launcher that reads the path and closes the pipes: the simulator's next console
    # line fails, and that must not end the session its client is using.
    sim = start_sim()
    assert sim.proc.stderr is not None
    sim.proc.stderr.close()
    time.sleep(0.3)
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_read(port, 20, 0xF1, 0, eep=True).startswith(b"sim-core")
    assert sim.proc.poll() is None
    sim.proc.send_signal(signal.SIGINT)
    assert sim.proc.wait(timeout=_START_TIMEOUT_S) == 0


def test_url_options_reach_the_served_robot(start_sim: Callable[..., SimProcess]) -> None:
    sim = start_sim("--url", "sim://?neck=worm&count_offset=1000&silent=12")
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 0) == 1000
        assert raw_read(port, 4, 0xF1, 0, eep=True)  # the worm neck answers
    sim.proc.send_signal(signal.SIGINT)
    assert sim.finish()[0] == 0


# -- hardening: floods, a console nobody reads, signals, stdin ----------------------------

_BYTE_S = 10 / 115_200


async def test_junk_written_faster_than_the_wire_is_taken_at_wire_speed() -> None:
    """A host writing 20 kB at once is held back as a real adapter holds it (its write
    waits), the simulator does not swallow it all, and the request behind the junk is
    answered within a reply window of the junk's end on the wire."""
    robot = SimRobot()
    line = SimLine(robot.devices)
    robot.attach_clock(line.now_s)
    transport = open_pty_pair(baudrate=line.baudrate)
    server = asyncio.create_task(line.serve(transport))
    client = os.open(transport.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        tty.setraw(client)
        loop = asyncio.get_running_loop()
        data = random.Random(4).randbytes(20_000) + frame(20, 0x07)
        start = loop.time()
        written = 0
        most_ahead = 0.0
        got = b""
        deadline = start + 20.0
        while len(got) < 9:
            assert loop.time() < deadline, f"no reply; got {got.hex(' ')!r}"
            if written < len(data):
                with contextlib.suppress(BlockingIOError):
                    written += os.write(client, data[written:])
            with contextlib.suppress(BlockingIOError):
                got += os.read(client, 64)
            taken = line.stats.bytes_to_devices
            most_ahead = max(most_ahead, taken - (loop.time() - start) / _BYTE_S)
            await asyncio.sleep(0.005)
        elapsed = loop.time() - start
    finally:
        os.close(client)
        server.cancel()
        await asyncio.wait({server})
        await transport.aclose()
    assert got == frame(20, 0x47, b"\0\0")
    # Never more than the adapter's buffer and one read ahead of the wire.
    assert most_ahead <= HOST_BUFFER_BYTES + 4096 + 512, most_ahead
    assert line.stats.host_waits > 0
    wire_end = len(data) * _BYTE_S
    assert elapsed >= wire_end - 0.05
    assert elapsed <= wire_end + GARBAGE_TIMEOUT_S + 3.0  # generous: a loaded machine


def test_a_console_nobody_reads_never_stalls_the_robot_or_its_stop(
    start_sim: Callable[..., SimProcess],
) -> None:
    # stderr is a pipe the test never reads: ~200 kB of status replies overflow it.
    sim = start_sim()
    for _ in range(500):
        sim.command("status")
    time.sleep(0.5)
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        for _ in range(3):
            assert raw_count(port, 0) == 0
    sim.command("status")  # and still more while the pipe is full
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 1) == 0
    sim.proc.send_signal(signal.SIGTERM)
    assert sim.proc.wait(timeout=_IO_TIMEOUT_S) == 0


def test_sighup_stops_it_cleanly(start_sim: Callable[..., SimProcess]) -> None:
    sim = start_sim()
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 0) == 0
    sim.proc.send_signal(signal.SIGHUP)
    code, err = sim.finish()
    assert code == 0
    assert "simulator stopped" in err
    assert "Traceback" not in err


def test_end_of_its_console_stops_it(start_sim: Callable[..., SimProcess]) -> None:
    sim = start_sim()
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 0) == 0
    assert sim.proc.stdin is not None
    sim.proc.stdin.close()  # Ctrl-D, or a launcher that went away
    assert sim.proc.wait(timeout=_START_TIMEOUT_S) == 0
    assert sim.proc.stderr is not None
    err = sim.proc.stderr.read().decode(errors="replace")
    assert "simulator stopped" in err
    assert "Traceback" not in err


def test_with_stdin_closed_at_start_it_serves_until_a_signal() -> None:
    # A launcher that closes stdin before exec: no console, nothing to reach EOF on.
    proc = subprocess.Popen(
        ["/bin/sh", "-c", 'exec "$0" -m ohmni_tb sim --pty <&-', sys.executable],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        ready, _, _ = select.select([proc.stdout], [], [], _START_TIMEOUT_S)
        assert ready, "no device path"
        path = proc.stdout.readline().decode().strip()
        time.sleep(0.3)
        assert proc.poll() is None
        with serial.Serial(path, 115200, timeout=_IO_TIMEOUT_S) as port:
            assert raw_count(port, 0) == 0
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=_START_TIMEOUT_S)
        assert proc.returncode == 0
        assert "simulator stopped" in err.decode()
    finally:
        if proc.returncode is None:
            proc.kill()
            proc.communicate(timeout=_START_TIMEOUT_S)


def test_an_overlong_console_line_is_refused_with_one_line(
    start_sim: Callable[..., SimProcess],
) -> None:
    sim = start_sim()
    sim.command("x" * 70_000)
    sim.command("status")
    with serial.Serial(sim.path, 115200, timeout=_IO_TIMEOUT_S) as port:
        assert raw_count(port, 0) == 0
    sim.command("quit")
    code, err = sim.finish()
    assert code == 0
    assert "Traceback" not in err
    refused = [ln for ln in err.splitlines() if "longer than" in ln]
    assert len(refused) == 1, err[-2000:]
    assert str(MAX_CONSOLE_LINE) in refused[0]
    assert "xxxx" not in err  # the rest of the long line is not taken for a command
    (status,) = [ln for ln in err.splitlines() if ln.startswith("pose ")]  # the next one is
    # In words, not reprs: the line's counters and the faults injected.
    assert "B to the devices" in status
    assert status.endswith("faults none")
    assert "LineStats(" not in status
    assert "simulator stopped" in err


# -- this project's own SerialTransport and Bus on the pty --------------------------------


@pytest.fixture
def running_sim(start_sim: Callable[..., SimProcess]) -> SimProcess:
    """A simulator already serving (started outside the test's event loop)."""
    return start_sim()


async def test_serial_transport_and_bus_on_the_pty(running_sim: SimProcess) -> None:
    sim = running_sim
    transport = await open_transport(sim.path)
    assert isinstance(transport, SerialTransport)
    # A reply window a loaded machine keeps: the simulator is another process.
    async with Bus(transport, timeout_s=_IO_TIMEOUT_S) as bus:
        status = parse_status(ReadReply.parse(await _request(bus, read_status())))
        assert not status.docked
        assert 15_000 <= status.pack_mv <= 18_000

        await bus.send(wheel_command(-300, -300))  # backwards
        for _ in range(5):
            await asyncio.sleep(0.1)
            await bus.send(wheel_command(-300, -300))
        await bus.send(wheel_command(0, 0))
        # Coasting to a stop: until two readings 0.1 s apart agree.
        counts: tuple[int, int] | None = None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + _IO_TIMEOUT_S
        while True:
            await asyncio.sleep(0.1)
            left = parse_count(ReadReply.parse(await _request(bus, read_count(0))))
            right = parse_count(ReadReply.parse(await _request(bus, read_count(1))))
            if counts == (left, right):
                break
            assert loop.time() < deadline, f"the wheels still turn: {counts}, {left, right}"
            counts = (left, right)
        assert left < 0 < right
        assert abs(left + right) <= 1
        stats = bus.stats
        assert stats.decoder.bytes_discarded == 0
        assert all(d.timeouts == 0 for d in stats.devices.values())
    assert transport.closed
    sim.proc.send_signal(signal.SIGINT)
    assert sim.finish()[0] == 0


async def _request(bus: Bus, packet: Packet) -> Packet:
    reply = await bus.request(packet)
    assert reply is not None
    return reply
