"""The daemon under its clients: control tick, stream rates, fan-out, CPU share, memory.

Run: ``python bench/daemon.py [--seconds S] [--quick] [--soak-seconds S]`` (``--seconds``
per row, 30 by default; ``--soak-seconds``, 600 by default; ``--quick``: 5 s rows and a
20 s soak; ``--only rows``, ``--only flood`` or ``--only soak`` runs one part;
``--flooders N``, 200 by default; ``--only web``: the web console's pages).

The daemon is this process: ``Robot.open(...)`` with every stream on and
``RobotServer(robot)`` on a free loopback port, which is what ``ohmni serve`` runs, on the
pty of ``ohmni sim --pty`` in its own process (a fresh one per row). When no pty can be
had it falls back to ``sim://`` in this process and says so: the simulator's CPU is then
in the figure. The clients run in a third process (``bench/_daemon_clients.py``): N
``RobotClient`` connections on one event loop, each subscribed to every stream
(wheel_encoder, wheel_odom, tbcore_status, servo_neck, servo_ext1, servo_ext2,
robot_state) with one task per subscription reading it continuously. So the CPU figure
is the daemon's alone.

Rows: 0, 1 and 50 readers, and 50 readers beside one stalled connection (subscribed to
every stream, never reading). Per row, over the window (``--seconds``):

* the control tick (``wheel_encoder``): achieved rate against 50 Hz, within ±1 % or not,
  and its skipped cycles;
* control-tick jitter p50/p99 (a cycle's first byte on the wire after its due time) from
  the Robot's own sliding figures, which cover its last 512 cycles (10.2 s): read every
  10 s through the window, the p50 shown is the median of the readings and the p99 the
  worst; and the p99's difference from the 0-client row (target: within 1 ms);
* the other streams' achieved rates (samples published over the window);
* samples the clients received per second, beside what the Robot published for them
  (clients × the streams' achieved rates), and how many they lost (told by the daemon in
  ``dropped``, or lost in a client's own queue);
* CPU share of one core of the daemon (``time.process_time`` over wall time), and of the
  clients' process for reference;
* under each row: the simulator's CPU and the rest of the host's (``/proc/stat``: on a
  shared machine, what else ran), the garbage collector's passes and longest pause, and,
  when a stream fell short of its rate, its skipped and missed cycles with the bus's
  timeouts and deadline drops.

Then command → wire through the daemon, alone and beside 50 readers: a teleop-like
driver in the clients' process holds the control lease and sends a new open-loop PWM
(``drive_pwm``) every 50–150 ms; a tap under the Robot's port (``bench/robot.py``'s
``WheelTap``) notes when the first wheel packet carrying each value is written (p50/p99
against one 20 ms control period). And the ratio of the daemon's CPU with 50 readers to
its CPU with none.

The flood (``--only flood``): readers without the lease flooding the daemon beside a
driver that then goes silent. A holder in a process of its own takes the control lease and
drives at 0.3 m/s (the command again every 50 ms); ``--flooders`` connections in the
clients' process each call ``stats`` 90 times a second without waiting for the replies
(each under the per-client limit of 100/s). Rows: the driver alone; the driver beside the
flood with ``max_clients`` raised so that every flooder is served (what the readers'
shared budget must hold); and beside the flood at the default cap of 64 (the rest refused
with 503). Per row: the control tick's rate and skipped cycles over the window, the
daemon's CPU, the calls sent and answered a second, the connections refused; then the
driver goes silent (it sends nothing more, its connection open, as a frozen process) and
the time from its last command until the Robot's own ``wheel_encoder`` samples show both
wheels standing still (below 0.01 m/s, and staying so for 0.5 s): the watchdog's
``watchdog_s`` and the braking ramp, whatever the readers do.

The memory soak (``--soak-seconds``) runs first, in this still fresh process: the daemon
serves while the clients' process opens a connection every 0.2 s that subscribes to two
to four streams, reads for 0.5–3.5 s and leaves (about ten at a time); most unsubscribe
and close politely, some close with their subscriptions open, some cut the TCP
connection. Every 5 s (1 s in a short soak), after a ``gc.collect()``, the daemon's RSS
(``VmRSS``) and tracemalloc's traced size are sampled; printed are start, peak and end,
the slope over the second half (KiB/min, flat below 32; not judged when the half starts
in the bus's first 110 s, while its bounded windows still fill), the lines that grew
most over that half, and whether every client and every Robot subscription is gone once
the churn stops. tracemalloc runs only during the soak (it slows every allocation).

The web console (``--only web``): the daemon alone, then with ``--pages`` (5) pages of
its web console open in one headless Chromium (``bench/_web_pages.py``: the distribution's
Chromium driven by Playwright, a browser context each, a laptop's window, every plot
drawing), each subscribed as the page is (wheel counts and odometry at 20 Hz, the
battery at 2, the neck at 5, the state and diagnostics as they come). Per row: the
control tick's rate (target: within ±1 % of 50 Hz with the pages open) and skipped
cycles, the jitter, the daemon's CPU; and each page's own count of its plots' updates a
second.

``--sim in-process`` runs ``sim://`` in the daemon's process instead of the pty. On two
shared cores, the clients' bursts delay the pty's kernel work (its data goes through a
kernel worker thread) by milliseconds now and then; a request then reaches the simulator
late, its reply goes out late, and the next pipelined request collides with it (the bus
counts the garbled bytes and turns cautious for a while, ``cautions``). A USB adapter's
driver submits the write in the system call, so the robot's line does not have that
jitter; in-process, the simulated line keeps time with the daemon's own loop and the
rows show what the fan-out does to the control tick. Its CPU figure includes the
simulator (~7 % of a core). ``--clients-nice 19`` runs the clients' process at the
lowest priority: on two cores it competes with the daemon for them, and this shows how
much of the control tick's jitter is that contention rather than the daemon's own work.
``--clients-cpu N`` puts the clients' process (and the browser ``--only web`` starts) on
CPU N alone and the daemon on the others: the clients stand in for other devices (a
phone's browser), whose work never shares the robot's cores.
``--daemon-rt N`` runs the daemon as ``ohmni serve --rt-priority N`` does (its event loop
under SCHED_FIFO at N), the deployment docs/hardware.md describes; the clients stay
time-shared, and the pty's simulator runs at N too: it stands in for the robot's boards,
whose processors the clients cannot delay.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import json
import math
import os
import signal
import statistics
import sys
import tempfile
import time
import tracemalloc
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import ohmni_tb
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.eventloop import set_realtime
from ohmni_tb.robot import Robot
from ohmni_tb.robot.streams import StreamStats
from ohmni_tb.transport import Transport, open_transport

sys.path.insert(0, str(Path(__file__).parent))
from _daemon_clients import TOPICS
from _pty import simulator_on_pty, time_shared
from robot import WheelTap, latencies
from schedule import machine

#: One control period: a command must reach the wire within it (the Robot's own target).
CONTROL_PERIOD_MS = 20.0

T = TypeVar("T")

CLIENTS_SCRIPT = Path(__file__).with_name("_daemon_clients.py")
PAGES_SCRIPT = Path(__file__).with_name("_web_pages.py")
CONTROL = "wheel_encoder"
CONTROL_HZ = 50.0
#: The control tick's rate must be within this share of 50 Hz.
RATE_TOLERANCE = 0.01
#: The p99 of the control tick's jitter may grow this much with clients, ms.
JITTER_TARGET_MS = 1.0
#: The Robot's jitter figures cover its last 512 cycles (10.24 s at 50 Hz): read this
#: often, the readings cover the window end to end without overlapping much.
JITTER_READ_S = 10.0
#: Discovery done, every stream running, before anything is measured.
ROBOT_SETTLE_S = 1.0
#: Every client's first samples through and its buffers warm, before the window.
CLIENTS_SETTLE_S = 2.0
#: Connecting and subscribing 50 clients takes about a second; this is for a loaded host.
READY_TIMEOUT_S = 60.0
#: The bus's bounded windows fill for this long (1,024 reply latencies a device: 102 s for
#: the core board's at 10 Hz): a slope measured before is their warm-up, not a leak.
WARM_S = 110.0
#: Below this slope over the soak's second half, memory is called flat, KiB/min: a leak
#: of 100 bytes per visit at five visits a second would show as ~29 KiB/min.
FLAT_KIB_PER_MIN = 32.0
OTHER_STREAMS = tuple(topic for topic in TOPICS if topic != CONTROL)
SHORT = {
    "wheel_encoder": "wheel",
    "wheel_odom": "odom",
    "servo_neck": "neck",
    "servo_ext1": "ext1",
    "servo_ext2": "ext2",
    "tbcore_status": "core",
    "robot_state": "state",
}


# -- the daemon ------------------------------------------------------------------------------


@dataclass
class Daemon:
    """What ``ohmni serve`` runs, opened by :func:`serving`."""

    robot: Robot
    server: RobotServer
    transport: Transport


#: ``--sim in-process``: sim:// in the daemon's process instead of ``ohmni sim --pty``.
SIM_IN_PROCESS = False
#: ``--clients-nice N``: the clients' process runs at this niceness (0: as the daemon).
CLIENTS_NICE = 0
#: ``--daemon-rt N``: the daemon's SCHED_FIFO priority (0: time-shared).
DAEMON_RT = 0
#: ``--clients-cpu N``: the clients' process (and a browser it starts) on CPU N alone, the
#: daemon on the others (None: wherever the kernel puts them).
CLIENTS_CPU: int | None = None


@contextmanager
def simulator() -> Iterator[tuple[str, bool]]:
    """The port to open: ``ohmni sim --pty``'s (True), else ``sim://`` in this process."""
    if SIM_IN_PROCESS:
        yield "sim://", False
        return
    with contextlib.ExitStack() as stack:
        try:
            path = stack.enter_context(simulator_on_pty(DAEMON_RT))
        except OSError:
            path = ""
        if path and Path(path).exists():
            yield path, True
        else:
            yield "sim://", False


@asynccontextmanager
async def serving(
    port: str, wrap: Callable[[Transport], Transport] | None = None, **options: Any
) -> AsyncIterator[Daemon]:
    """The Robot on ``port`` with every stream on, served on a free loopback port; settled.

    ``wrap`` puts a tap between the Robot and its port, as ``bench/robot.py``'s
    ``WheelTap`` (what the command → wire row below will need). ``options`` go to
    ``RobotServer`` (``max_clients``).
    """
    transport = await open_transport(port)
    if wrap is not None:
        transport = wrap(transport)
    async with Robot.open(transport) as robot, RobotServer(robot, port=0, **options) as server:
        await asyncio.sleep(ROBOT_SETTLE_S)
        gc.freeze()  # as ohmni serve does once serving: out of the collector's full passes
        yield Daemon(robot, server, transport)


# -- command → wire latency through the daemon ------------------------------------------------


@dataclass
class LatencyRow:
    name: str
    latencies_ms: list[float]
    commands: int


async def command_latency_row(name: str, port: str, seconds: float, readers: int) -> LatencyRow:
    """A teleop-like driver in the clients' process (lease held, a new ``drive_pwm`` every
    50–150 ms), ``readers`` readers of every stream beside it: from the driver's call to
    the first wheel packet carrying the value written to the port (``bench/robot.py``'s
    ``WheelTap`` under the Robot). Both processes stamp with ``time.monotonic``, which is
    the event loop's clock: one clock on Linux."""
    taps: list[WheelTap] = []

    def tap(transport: Transport) -> Transport:
        taps.append(WheelTap(transport))
        return taps[-1]

    async with (
        serving(port, wrap=tap) as daemon,
        ClientProcess.start(daemon.server.url, "driver", str(readers)) as process,
    ):
        await asyncio.sleep(seconds)
        done = await process.finish()
    commands = [(float(t), (int(pwm[0]), int(pwm[1]))) for t, pwm in done["commands"]]
    return LatencyRow(name, latencies(commands, taps[0].wheel_writes()), len(commands))


def show_latency(row: LatencyRow) -> None:
    ordered = sorted(row.latencies_ms)
    if not ordered:
        print(f"{row.name:<20} | no command reached the wire")
        return
    p50 = ordered[len(ordered) // 2]
    p99 = ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))]
    verdict = "within" if p99 <= CONTROL_PERIOD_MS else "NOT within"
    print(
        f"{row.name:<20} | command → wheel packet on the wire p50 {p50:5.1f} ms, p99 "
        f"{p99:5.1f} ms, max {ordered[-1]:5.1f} ms ({len(ordered)} of {row.commands} "
        f"commands seen; p99 {verdict} one {CONTROL_PERIOD_MS:g} ms control period)"
    )


# -- the clients' process ----------------------------------------------------------------------


class ClientProcess:
    """``bench/_daemon_clients.py`` in its own process; ended on leaving, whatever happens."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self._process = process

    @classmethod
    @asynccontextmanager
    async def start(
        cls, url: str, *args: str, script: Path = CLIENTS_SCRIPT
    ) -> AsyncIterator[ClientProcess]:
        """Start it (``script``: the clients', or the web pages') and wait until every
        client is subscribed."""
        # --clients-nice: the clients yield the cores to the daemon (and the simulator),
        # to tell the daemon's own cost from the two processes' contention.
        nice = ["nice", "-n", str(CLIENTS_NICE)] if CLIENTS_NICE else []
        # --clients-cpu: the clients (a browser's processes inherit it) on a core of their
        # own, as a phone's browser is on a device of its own.
        pin = ["taskset", "-c", str(CLIENTS_CPU)] if CLIENTS_CPU is not None else []
        process = await asyncio.create_subprocess_exec(
            *pin,
            *nice,
            sys.executable,
            str(script),
            url,
            *args,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            # Time-shared whatever the daemon runs in: only the daemon is measured there.
            preexec_fn=time_shared,
        )
        clients = cls(process)
        try:
            await clients._expect("ready", READY_TIMEOUT_S)
            yield clients
        finally:
            await clients._end()

    async def mark(self) -> dict[str, Any]:
        """Its cumulative figures now."""
        await self._send("mark")
        return await self._expect("mark", 10.0)

    async def silence(self) -> float:
        """The holder stops sending; when its last command went (``time.monotonic``)."""
        await self._send("silence")
        silent = await self._expect("silent", 10.0)
        return float(silent["last_t"])

    async def finish(self) -> dict[str, Any]:
        """Close every client; their last figures."""
        await self._send("quit")
        figures = await self._expect("done", 30.0)
        await self._process.wait()
        return figures

    async def _send(self, line: str) -> None:
        assert self._process.stdin is not None
        self._process.stdin.write(line.encode() + b"\n")
        await self._process.stdin.drain()

    async def _expect(self, event: str, timeout_s: float) -> dict[str, Any]:
        assert self._process.stdout is not None
        try:
            async with asyncio.timeout(timeout_s):
                line = await self._process.stdout.readline()
        except TimeoutError:
            raise RuntimeError(
                f"the clients' process did not say {event!r} in {timeout_s:g} s"
            ) from None
        if not line:
            code = await self._process.wait()
            raise RuntimeError(
                f"the clients' process ended (exit {code}) before saying {event!r}; "
                "its error is above"
            )
        message: dict[str, Any] = json.loads(line)
        if message.get("event") != event:
            raise RuntimeError(f"the clients' process said {line!r}, not {event!r}")
        return message

    async def _end(self) -> None:
        process = self._process
        if process.returncode is not None:
            return
        process.terminate()
        try:
            async with asyncio.timeout(5.0):
                await process.wait()
        except TimeoutError:
            process.kill()
            await process.wait()


# -- the rows ------------------------------------------------------------------------------------


@dataclass
class Row:
    name: str
    clients: int
    seconds: float = math.nan
    rates: dict[str, float] = field(default_factory=dict)
    skipped: int = 0
    jitter_p50_ms: float = math.nan
    jitter_p99_ms: float = math.nan
    received_per_s: float = math.nan
    published_per_s: float = math.nan
    dropped: int = 0
    cpu: float = math.nan
    clients_cpu: float = math.nan
    simulator_cpu: float = math.nan
    #: The whole host's busy time over the window, in cores (all processes, anyone's).
    host_cpu: float = math.nan
    notes: list[str] = field(default_factory=list)

    @property
    def control_ok(self) -> bool:
        return abs(self.rates[CONTROL] - CONTROL_HZ) <= RATE_TOLERANCE * CONTROL_HZ


async def clients_row(name: str, port: str, seconds: float, clients: int, stalled: int = 0) -> Row:
    """The daemon with ``clients`` readers of every stream (and ``stalled`` non-readers)."""
    row = Row(name, clients)
    async with serving(port) as daemon, contextlib.AsyncExitStack() as stack:
        process: ClientProcess | None = None
        if clients or stalled:
            process = await stack.enter_async_context(
                ClientProcess.start(
                    daemon.server.url, "readers", str(clients), "--stalled", str(stalled)
                )
            )
            await asyncio.sleep(CLIENTS_SETTLE_S)
        first = await process.mark() if process else None
        await measure(row, daemon, seconds)
        last = await process.mark() if process else None
        if first is not None and last is not None:
            received = sum(last["received"].values()) - sum(first["received"].values())
            row.received_per_s = received / row.seconds
            row.dropped = last["dropped"] - first["dropped"]
            row.clients_cpu = (last["cpu_s"] - first["cpu_s"]) / row.seconds
            if last["errors"]:
                row.notes.append(f"client errors: {last['errors']}")
        for peer in last["stalled_peers"] if last else []:
            figures = [c for c in daemon.server.clients if c.peer == peer]
            if figures:
                c = figures[0]
                row.notes.append(
                    f"stalled client at the daemon: sent {c.sent}, dropped {c.dropped}, "
                    f"queued {c.queued} (since it connected)"
                )
            else:
                row.notes.append("stalled client: the daemon had closed it")
        if process:
            await process.finish()
    return row


async def measure(row: Row, daemon: Daemon, seconds: float) -> None:
    """Fill ``row`` from the Robot's figures and this process's CPU over ``seconds``."""
    robot = daemon.robot
    loop = asyncio.get_running_loop()
    start = robot.stats()
    readings: list[StreamStats] = []
    host0, sim0 = host_busy_s(), simulator_cpu_s()
    with CollectorWatch() as collector:
        cpu0 = time.process_time()
        wall0 = time.perf_counter()
        end_at = loop.time() + seconds
        while (left := end_at - loop.time()) > 0.05:
            await asyncio.sleep(min(JITTER_READ_S, left))
            readings.append(robot.stats().streams[CONTROL])
        cpu = time.process_time() - cpu0
        wall = time.perf_counter() - wall0
    host, sim = host_busy_s() - host0, simulator_cpu_s() - sim0
    end = robot.stats()
    row.seconds = wall
    row.cpu = cpu / wall
    row.simulator_cpu = sim / wall
    row.host_cpu = host / wall
    for topic in TOPICS:
        row.rates[topic] = (end.streams[topic].samples - start.streams[topic].samples) / wall
    row.skipped = end.streams[CONTROL].skipped - start.streams[CONTROL].skipped
    p50s = [r.jitter_p50_ms for r in readings if r.jitter_p50_ms is not None]
    p99s = [r.jitter_p99_ms for r in readings if r.jitter_p99_ms is not None]
    row.jitter_p50_ms = statistics.median(p50s) if p50s else math.nan
    row.jitter_p99_ms = max(p99s) if p99s else math.nan
    row.published_per_s = row.clients * sum(row.rates.values())
    pauses = [pause for _, pause in collector.pauses]
    full = sum(1 for generation, _ in collector.pauses if generation == 2)
    row.notes.append(
        f"garbage collector: {len(pauses)} collections ({full} full), longest "
        f"{max(pauses, default=0.0) * 1e3:.1f} ms, {sum(pauses) / wall:.2%} of the time"
    )
    # Only streams with enough samples in the window for 1 % to mean something.
    short = [
        t
        for t in TOPICS
        if end.streams[t].requested_hz * wall >= 100
        and row.rates[t] < (1 - RATE_TOLERANCE) * end.streams[t].requested_hz
    ]
    if short:
        skipped = {SHORT[t]: end.streams[t].skipped - start.streams[t].skipped for t in short}
        missed = {SHORT[t]: end.streams[t].missed - start.streams[t].missed for t in short}
        row.notes.append(
            f"short of rate: skipped {skipped}, missed {missed}; bus timeouts "
            f"{end.bus.timeouts - start.bus.timeouts}, slots dropped for their deadline "
            f"{end.bus.deadline_misses - start.bus.deadline_misses}"
        )


class CollectorWatch:
    """Each cyclic garbage collection while inside: its generation and how long it took."""

    def __init__(self) -> None:
        self.pauses: list[tuple[int, float]] = []
        self._started = 0.0

    def __enter__(self) -> CollectorWatch:
        gc.callbacks.append(self._note)
        return self

    def __exit__(self, *exc: object) -> None:
        gc.callbacks.remove(self._note)

    def _note(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._started = time.perf_counter()
        else:
            self.pauses.append((info["generation"], time.perf_counter() - self._started))


def show_header() -> None:
    others = " ".join(f"{SHORT[t]:>6}" for t in OTHER_STREAMS)
    header = (
        f"{'row':<18} | {'wheel':>6} {'±1%':>3} {'skip':>4} | {others} | "
        f"{'jit50':>5} {'jit99':>5} {'Δ99':>5} | {'recv/s':>7} {'of':>7} {'dropped':>7} | "
        f"{'CPU':>5} {'cliCPU':>6}"
    )
    print(header)
    print("-" * len(header))


def show(row: Row, base: Row | None) -> None:
    rates = " ".join(f"{row.rates[t]:6.2f}" for t in OTHER_STREAMS)
    delta = row.jitter_p99_ms - base.jitter_p99_ms if base else math.nan
    received = "      -" if math.isnan(row.received_per_s) else f"{row.received_per_s:7,.0f}"
    clients_cpu = "     -" if math.isnan(row.clients_cpu) else f"{row.clients_cpu:6.1%}"
    print(
        f"{row.name:<18} | {row.rates[CONTROL]:6.2f} {'yes' if row.control_ok else 'NO':>3} "
        f"{row.skipped:4d} | {rates} | {row.jitter_p50_ms:5.1f} {row.jitter_p99_ms:5.1f} "
        f"{'    -' if math.isnan(delta) else f'{delta:+5.1f}'} | {received} "
        f"{row.published_per_s:7,.0f} {row.dropped:7,d} | {row.cpu:5.1%} {clients_cpu}"
    )
    ours = (row.cpu, row.simulator_cpu, row.clients_cpu)
    others = row.host_cpu - sum(share for share in ours if not math.isnan(share))
    simulator = "in the daemon's" if math.isnan(row.simulator_cpu) else f"{row.simulator_cpu:.1%}"
    print(
        f"{'':<18}   CPU of one core: simulator {simulator}, everything else on the host "
        f"{others:.0%} (of {os.cpu_count()} cores)"
    )
    for note in row.notes:
        print(f"{'':<18}   {note}")


# -- readers flooding beside a driver that goes silent ---------------------------------------------

#: Each flooder's ``stats`` calls a second: under the daemon's per-client limit of 100.
FLOOD_RATE_HZ = 90.0
#: Below this, a wheel stands still (m/s); for this long after, it must stay so (s).
STILL_MPS = 0.01
STILL_FOR_S = 0.5
#: How long after the driver's last command the wheels are watched for standing still.
STOP_WATCH_S = 10.0


@dataclass
class FloodRow:
    name: str
    row: Row
    max_clients: int
    calls_per_s: float = math.nan
    answered_per_s: float = math.nan
    refused: int = 0
    #: From the driver's last command to the wheels standing still (NaN: not within
    #: STOP_WATCH_S); the control tick's rate meanwhile.
    stop_s: float = math.nan
    silent_control_hz: float = math.nan


async def flood_row(
    name: str, port: str, seconds: float, flooders: int, max_clients: int
) -> FloodRow:
    """The driver alone or beside ``flooders`` readers calling ``stats`` at 90/s each."""
    async with (
        serving(port, max_clients=max_clients) as daemon,
        ClientProcess.start(daemon.server.url, "holder") as holder,
        contextlib.AsyncExitStack() as stack,
    ):
        result = FloodRow(name, Row(name, flooders), daemon.server.max_clients)
        flood: ClientProcess | None = None
        if flooders:
            flood = await stack.enter_async_context(
                ClientProcess.start(
                    daemon.server.url, "flood", str(flooders), "--rate", str(FLOOD_RATE_HZ)
                )
            )
        await asyncio.sleep(CLIENTS_SETTLE_S)
        first = await flood.mark() if flood else None
        sent = sum(client.sent for client in daemon.server.clients)
        await measure(result.row, daemon, seconds)
        sent = sum(client.sent for client in daemon.server.clients) - sent
        last = await flood.mark() if flood else None
        if first is not None and last is not None:
            wall = result.row.seconds
            result.calls_per_s = (last["calls"] - first["calls"]) / wall
            # By the daemon's own figures (its messages to the clients, the holder's few
            # replies included): what it served, whether or not the flooders keep reading.
            result.answered_per_s = sent / wall
            result.row.clients_cpu = (last["cpu_s"] - first["cpu_s"]) / wall
            if last["errors"]:
                result.row.notes.append(f"flood errors: {last['errors']}")
        result.refused = daemon.server.refused_connections
        encoder = daemon.robot.subscribe(CONTROL, maxlen=4096)
        try:
            last_t = await holder.silence()
            result.stop_s, result.silent_control_hz = await standstill(encoder, last_t)
        finally:
            encoder.close()
        if flood is not None:
            await flood.finish()
        await holder.finish()
    return result


async def standstill(encoder: Any, last_t: float) -> tuple[float, float]:
    """From ``last_t`` until both wheels stand still by the Robot's own samples (s; NaN
    when they did not within STOP_WATCH_S), and the samples' rate meanwhile (Hz)."""
    loop = asyncio.get_running_loop()
    still_since: float | None = None
    samples = 0
    first_stamp = last_stamp = math.nan
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout_at(last_t + STOP_WATCH_S):
            async for sample in encoder:
                if sample.stamp_s <= last_t:
                    continue
                samples += 1
                last_stamp = sample.stamp_s
                if math.isnan(first_stamp):
                    first_stamp = sample.stamp_s
                if max(abs(sample.left_mps), abs(sample.right_mps)) >= STILL_MPS:
                    still_since = None
                elif still_since is None:
                    still_since = sample.stamp_s
                if still_since is not None and sample.stamp_s - still_since >= STILL_FOR_S:
                    break
    rate = (samples - 1) / (last_stamp - first_stamp) if samples >= 2 else 0.0
    if still_since is None or loop.time() - still_since < STILL_FOR_S - 0.05:
        return math.nan, rate
    return still_since - last_t, rate


def show_flood(rows: list[FloodRow], watchdog_s: float) -> None:
    header = (
        f"{'row':<30} | {'wheel':>6} {'±1%':>3} {'skip':>5} | {'CPU':>5} {'cliCPU':>6} | "
        f"{'calls/s':>7} {'answ/s':>7} {'refused':>7} | stop after silence"
    )
    print(header)
    print("-" * len(header))
    for result in rows:
        row = result.row
        calls = "      -" if math.isnan(result.calls_per_s) else f"{result.calls_per_s:7,.0f}"
        answered = (
            "      -" if math.isnan(result.answered_per_s) else f"{result.answered_per_s:7,.0f}"
        )
        clients_cpu = "     -" if math.isnan(row.clients_cpu) else f"{row.clients_cpu:6.1%}"
        stop = (
            f"NOT within {STOP_WATCH_S:g} s"
            if math.isnan(result.stop_s)
            else f"{result.stop_s:.2f} s"
        )
        print(
            f"{result.name:<30} | {row.rates[CONTROL]:6.2f} "
            f"{'yes' if row.control_ok else 'NO':>3} {row.skipped:5d} | {row.cpu:5.1%} "
            f"{clients_cpu} | {calls} {answered} {result.refused:7d} | {stop} (control tick "
            f"{result.silent_control_hz:.1f} Hz meanwhile)"
        )
        for note in row.notes:
            print(f"{'':<30}   {note}")
    print(
        f"stop after silence: from the driver's last command (0.3 m/s) until both wheels stand "
        f"still by the Robot's wheel_encoder samples (< {STILL_MPS:g} m/s for "
        f"{STILL_FOR_S:g} s): the watchdog ({watchdog_s:g} s) and the braking ramp"
    )
    print(
        "units: Hz | cycles | share of one core (the daemon; the flooders' process) | stats "
        "calls sent a second by all flooders together, and messages the daemon sent to its "
        "clients a second | connections refused (503)"
    )


def run_flood(seconds: float, flooders: int) -> None:
    from ohmni_tb.daemon.server import DEFAULT_MAX_CLIENTS  # noqa: PLC0415

    specs = [
        ("driver alone", 0, DEFAULT_MAX_CLIENTS),
        # Every flooder served (and the holder): what the readers' shared budget must hold.
        (f"driver + {flooders} flooding (all served)", flooders, flooders + 16),
    ]
    if flooders > DEFAULT_MAX_CLIENTS:
        specs.append(
            (
                f"driver + {flooders} flooding (cap {DEFAULT_MAX_CLIENTS})",
                flooders,
                DEFAULT_MAX_CLIENTS,
            )
        )
    rows: list[FloodRow] = []
    in_process = False
    for name, count, cap in specs:
        with simulator() as (port, on_pty):
            in_process |= not on_pty
            rows.append(run(flood_row(name, port, seconds, count, cap)))
    print(
        f"{seconds:g} s a row; each flooder calls stats {FLOOD_RATE_HZ:g} times a second "
        "without waiting for the replies"
    )
    show_flood(rows, ohmni_tb.RobotConfig().watchdog_s)
    if in_process:
        print("NOTE: sim:// ran in the daemon's process; its CPU is in the figure")


# -- the memory soak -----------------------------------------------------------------------------


@dataclass
class Soak:
    seconds: float
    #: (seconds since the churn began, RSS KiB, traced KiB, clients connected)
    points: list[tuple[float, float, float, int]] = field(default_factory=list)
    #: When the mid-soak snapshot was taken; the slope is fitted from there on.
    half_at_s: float = 0.0
    tracemalloc_own_kib: float = math.nan
    visits: dict[str, int] = field(default_factory=dict)
    errors: dict[str, int] = field(default_factory=dict)
    clients_after: int = -1
    clients_gone_s: float = math.nan
    subscribers_before: dict[str, int] = field(default_factory=dict)
    subscribers_after: dict[str, int] = field(default_factory=dict)
    after_rss_kib: float = math.nan
    after_traced_kib: float = math.nan
    control_hz: float = math.nan
    jitter_p99_ms: float = math.nan
    growth: list[str] = field(default_factory=list)


async def soak(port: str, seconds: float) -> Soak:
    """The daemon while clients come and go for ``seconds``; its memory sampled."""
    result = Soak(seconds)
    every_s = 5.0 if seconds >= 60 else 1.0
    tracemalloc.start()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            half_file = Path(tmp) / "half.snapshot"
            async with serving(port) as daemon:
                await _churn(result, daemon, seconds, every_s, half_file)
    finally:
        tracemalloc.stop()
    return result


async def _churn(
    result: Soak, daemon: Daemon, seconds: float, every_s: float, half_file: Path
) -> None:
    robot, server = daemon.robot, daemon.server
    loop = asyncio.get_running_loop()
    result.subscribers_before = {t: robot.stats().streams[t].subscribers for t in TOPICS}
    start = robot.stats()
    async with ClientProcess.start(server.url, "churn") as process:
        t0 = loop.time()
        k = 0
        while True:
            elapsed = loop.time() - t0
            # Live memory: every bus slot is a reference cycle, so without a collection
            # here the samples ride the collector's saw-tooth (~600 KiB, ~45 s period).
            gc.collect()
            result.points.append((elapsed, rss_kib(), traced_kib(), len(server.clients)))
            if not result.half_at_s and elapsed >= seconds / 2:
                # On disk: kept in memory, the snapshot would be traced and counted.
                _snapshot().dump(str(half_file))
                result.half_at_s = elapsed
            k += 1
            if k * every_s > seconds + 1e-6:
                break
            await asyncio.sleep(t0 + k * every_s - loop.time())
        end = robot.stats()
        wall = loop.time() - t0
        if result.half_at_s:
            # After the last sample: a snapshot's lists step the RSS up (the allocator keeps
            # their pages), so only the "after" RSS and the mid-soak step carry them.
            result.growth = _growth(tracemalloc.Snapshot.load(str(half_file)), _snapshot())
        figures = await process.finish()
    result.visits = figures["visits"]
    result.errors = figures["errors"]
    samples = end.streams[CONTROL].samples - start.streams[CONTROL].samples
    result.control_hz = samples / wall
    result.jitter_p99_ms = end.streams[CONTROL].jitter_p99_ms or math.nan
    gone_at = loop.time()
    # The server has no event for it: its figures are polled, as a user would.
    while server.clients and loop.time() - gone_at < 10.0:  # noqa: ASYNC110
        await asyncio.sleep(0.05)
    result.clients_after = len(server.clients)
    result.clients_gone_s = loop.time() - gone_at
    await asyncio.sleep(0.5)  # the pumps' tasks end after their subscription closes
    result.subscribers_after = {t: robot.stats().streams[t].subscribers for t in TOPICS}
    gc.collect()  # closed connections' reference cycles: garbage, not a leak
    result.after_rss_kib = rss_kib()
    result.after_traced_kib = traced_kib()
    result.tracemalloc_own_kib = tracemalloc.get_tracemalloc_memory() / 1024


def host_busy_s() -> float:
    """CPU time the whole host has spent busy, all cores, s (``/proc/stat``; NaN without)."""
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]
    except OSError:
        return math.nan
    ticks = [int(f) for f in fields]
    idle = ticks[3] + ticks[4]  # idle, iowait
    guest = sum(ticks[8:10])  # guest time is counted in user time already
    return (sum(ticks) - idle - guest) / os.sysconf("SC_CLK_TCK")


def simulator_cpu_s() -> float:
    """CPU time of this process's ``ohmni sim`` children, s (NaN without ``/proc``)."""
    total = math.nan
    for pid in _children():
        try:
            if b"ohmni_tb\0sim" not in Path(f"/proc/{pid}/cmdline").read_bytes():
                continue
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        # utime and stime: the stat file's 14th and 15th fields, after "pid (comm)".
        total = (0.0 if math.isnan(total) else total) + (int(fields[11]) + int(fields[12])) / (
            os.sysconf("SC_CLK_TCK")
        )
    return total


def _children() -> list[int]:
    pids: list[int] = []
    with contextlib.suppress(OSError):
        for task in Path("/proc/self/task").iterdir():
            pids += [int(pid) for pid in (task / "children").read_text().split()]
    return pids


def rss_kib() -> float:
    """This process's resident set, KiB (NaN where ``/proc`` is not)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return float(line.split()[1])
    except OSError:
        pass
    return math.nan


def traced_kib() -> float:
    return tracemalloc.get_traced_memory()[0] / 1024


def slope_kib_per_min(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of (seconds, KiB) points, in KiB a minute."""
    if len(points) < 2:
        return math.nan
    return statistics.linear_regression([t for t, _ in points], [v for _, v in points])[0] * 60


def _snapshot() -> tracemalloc.Snapshot:
    return tracemalloc.take_snapshot().filter_traces(
        (
            tracemalloc.Filter(inclusive=False, filename_pattern=tracemalloc.__file__),
            tracemalloc.Filter(inclusive=False, filename_pattern="<frozen importlib._bootstrap>"),
            tracemalloc.Filter(inclusive=False, filename_pattern="<unknown>"),
        )
    )


def _growth(before: tracemalloc.Snapshot, after: tracemalloc.Snapshot) -> list[str]:
    """The three source lines whose live memory grew most from ``before`` to ``after``."""
    lines = []
    for stat in after.compare_to(before, "lineno")[:3]:
        if stat.size_diff <= 0:
            break
        frame = stat.traceback[0]
        where = "/".join(Path(frame.filename).parts[-3:])
        lines.append(
            f"{where}:{frame.lineno} {stat.size_diff / 1024:+.1f} KiB "
            f"({stat.count_diff:+d} blocks; {stat.size / 1024:.1f} KiB live)"
        )
    return lines


def show_soak(result: Soak) -> None:
    visits = sum(result.visits.values())
    print(
        f"memory soak: {result.seconds:g} s, a connection every 0.2 s for 0.5-3.5 s each "
        f"({visits} visits: {result.visits.get('polite', 0)} polite, "
        f"{result.visits.get('leave', 0)} left subscribed, {result.visits.get('abort', 0)} "
        f"cut the TCP connection); connected at once: "
        f"{statistics.median(p[3] for p in result.points):.0f} median, "
        f"{max(p[3] for p in result.points)} max"
    )
    # From the first sample after the mid-soak snapshot (which steps the RSS up once).
    second_half = [p for p in result.points if p[0] > result.half_at_s > 0]
    print(f"{'':<12} {'start':>9} {'peak':>9} {'end':>9} {'after':>9}   second-half slope")
    for label, index, after in (
        ("RSS", 1, result.after_rss_kib),
        ("tracemalloc", 2, result.after_traced_kib),
    ):
        values = [p[index] for p in result.points]
        slope = slope_kib_per_min([(p[0], p[index]) for p in second_half])
        span_s = second_half[-1][0] - second_half[0][0] if second_half else math.nan
        per_visit = slope / 60 * 1024 / (visits / result.seconds) if visits else math.nan
        if result.half_at_s < WARM_S:
            verdict = f"too short to judge: the half starts in the first {WARM_S:g} s"
        else:
            verdict = "flat" if slope < FLAT_KIB_PER_MIN else "GROWING"
        print(
            f"{label:<12} {values[0]:9,.0f} {max(values):9,.0f} {values[-1]:9,.0f} "
            f"{after:9,.0f}   {slope:+8.1f} KiB/min over {span_s:.0f} s "
            f"({verdict}; {per_visit:+.0f} B a visit)"
        )
    if result.growth:
        print("grew most over the second half (tracemalloc, by line):")
        for line in result.growth:
            print(f"  {line}")
    leftover = {t: n for t, n in result.subscribers_after.items() if n}
    print(
        f"after the churn: server.clients {result.clients_after} "
        f"(in {result.clients_gone_s:.2f} s); the Robot's subscriptions "
        f"{'none left' if not leftover else f'LEFT: {leftover}'} "
        f"(before the clients: {sum(result.subscribers_before.values())}); "
        f"client errors: {result.errors or 'none'}"
    )
    print(
        f"control tick during the soak (tracemalloc on): {result.control_hz:.2f} Hz, "
        f"jitter p99 {result.jitter_p99_ms:.1f} ms (the last 512 cycles)"
    )
    print(
        "units: KiB of live memory (a gc.collect() before each sample); start, peak, end "
        "of the samples during the churn; after: once every client left. The RSS includes "
        f"tracemalloc's own {result.tracemalloc_own_kib:,.0f} KiB and steps up once at the "
        "mid-soak snapshot"
    )


# -- main ----------------------------------------------------------------------------------------


class TerminatedError(Exception):
    """SIGTERM arrived; everything this process started has been stopped."""


def run(main: Coroutine[Any, Any, T]) -> T:
    """``ohmni_tb.run`` (the loop ``ohmni serve`` runs on), with SIGTERM cancelling ``main``
    as Ctrl-C does, so its cleanup runs.

    A signal handler that raised instead would raise wherever the loop happens to be, even
    inside a transport's callback that swallows it.
    """

    async def guarded() -> T:
        task = asyncio.current_task()
        assert task is not None
        terminated = False

        def terminate() -> None:
            nonlocal terminated
            terminated = True
            task.cancel()

        asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, terminate)
        try:
            return await main
        except asyncio.CancelledError:
            if terminated:
                raise TerminatedError from None
            raise

    try:
        return ohmni_tb.run(guarded())
    finally:
        # Between the loops (starting the simulator, printing) SIGTERM stops at once; the
        # loop's handler is gone with the loop.
        signal.signal(signal.SIGTERM, _raise_terminated)


def _raise_terminated(signum: int, frame: object) -> None:
    raise TerminatedError


async def web_row(name: str, port: str, seconds: float, pages: int) -> Row:
    """The daemon with ``pages`` pages of its web console open (``bench/_web_pages.py``)."""
    row = Row(name, 0)
    async with serving(port) as daemon, contextlib.AsyncExitStack() as stack:
        process: ClientProcess | None = None
        if pages:
            page_url = daemon.server.web_url
            assert page_url is not None
            process = await stack.enter_async_context(
                ClientProcess.start(page_url, str(pages), script=PAGES_SCRIPT)
            )
            await asyncio.sleep(CLIENTS_SETTLE_S)
        await measure(row, daemon, seconds)
        if process is not None:
            connected = len(daemon.server.clients)
            done = await process.finish()
            row.notes.append(
                f"{connected} pages connected; their plots' updates a second each: "
                f"{done['updates_hz']}"
            )
    return row


def run_web(seconds: float, pages: int) -> None:
    show_header()
    rows: list[Row] = []
    for name, count in (("0 pages", 0), (f"{pages} pages", pages)):
        with simulator() as (port, on_pty):
            row = run(web_row(name, port, seconds, count))
        if not on_pty:
            row.notes.append("sim:// ran in the daemon's process; its CPU is in the figure")
        show(row, rows[0] if rows else None)
        rows.append(row)
    base, opened = rows
    hz = opened.rates[CONTROL]
    print(
        f"control tick with {pages} pages open: {hz:.2f} Hz, {hz / CONTROL_HZ - 1:+.2%} of "
        f"{CONTROL_HZ:g} Hz ({'within' if opened.control_ok else 'NOT within'} ±1 %); "
        f"daemon CPU {opened.cpu:.1%} of one core, {base.cpu:.1%} without them"
    )


def run_rows(seconds: float) -> None:
    show_header()
    specs = [
        ("0 clients", 0, 0),
        ("1 client", 1, 0),
        ("50 clients", 50, 0),
        ("50 + 1 stalled", 50, 1),
    ]
    rows: list[Row] = []
    in_process = False
    for name, clients, stalled in specs:
        with simulator() as (port, on_pty):
            in_process |= not on_pty
            row = run(clients_row(name, port, seconds, clients, stalled))
        show(row, rows[0] if rows else None)
        rows.append(row)
    for name, readers in (("driver alone", 0), ("driver + 50 readers", 50)):
        with simulator() as (port, on_pty):
            in_process |= not on_pty
            show_latency(run(command_latency_row(name, port, seconds, readers)))
    base, fifty = rows[0], rows[2]
    print(
        f"daemon CPU, 50 clients / 0 clients: {fifty.cpu / base.cpu:.1f}x "
        f"({fifty.cpu:.1%} / {base.cpu:.1%} of one core)"
    )
    growth = ", ".join(
        f"{row.name} {row.jitter_p99_ms - base.jitter_p99_ms:+.1f} ms"
        + ("" if row.jitter_p99_ms - base.jitter_p99_ms <= JITTER_TARGET_MS else " (NOT met)")
        for row in rows[1:]
    )
    target = f"target within +{JITTER_TARGET_MS:g} ms"
    print(f"control-tick jitter p99 against 0 clients ({target}): {growth}")
    print(
        "jitter: the Robot's sliding p50/p99 (last 512 control cycles, 10.2 s), read every "
        f"{JITTER_READ_S:g} s of the window: median p50, worst p99"
        + (" (a window this short also covers the settling before it)" if seconds < 10 else "")
    )
    if in_process:
        print("NOTE: sim:// ran in the daemon's process; its CPU is in the figure")
    print(
        "units: Hz (samples over the window) | ms | samples/s received by every client "
        "together, of what the Robot published for them; samples lost | share of one core"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="per row (default 30)")
    parser.add_argument("--soak-seconds", type=float, default=600.0, help="default 600")
    parser.add_argument("--quick", action="store_true", help="5 s rows, a 20 s soak")
    parser.add_argument("--only", choices=("rows", "flood", "soak", "web"), help="run one part")
    parser.add_argument(
        "--pages", type=int, default=5, help="web: the web console's pages open (5)"
    )
    parser.add_argument(
        "--flooders", type=int, default=200, help="flood: connections calling stats (200)"
    )
    parser.add_argument(
        "--sim", choices=("pty", "in-process"), default="pty", help="where the simulator runs"
    )
    parser.add_argument(
        "--clients-nice",
        type=int,
        default=0,
        choices=range(20),
        metavar="N",
        help="run the clients' process at niceness N (0..19; default 0)",
    )
    parser.add_argument(
        "--clients-cpu",
        type=int,
        default=None,
        metavar="N",
        help="run the clients' process (and the web pages' browser) on CPU N alone and the "
        "daemon on the other CPUs (default: the kernel places both)",
    )
    parser.add_argument(
        "--daemon-rt",
        type=int,
        default=0,
        choices=range(100),
        metavar="N",
        help="run the daemon under SCHED_FIFO at N, as ohmni serve --rt-priority N (default 0: "
        "time-shared)",
    )
    args = parser.parse_args()
    global SIM_IN_PROCESS, CLIENTS_NICE, DAEMON_RT, CLIENTS_CPU  # noqa: PLW0603  # settings for the whole run
    SIM_IN_PROCESS = args.sim == "in-process"
    CLIENTS_NICE = args.clients_nice
    DAEMON_RT = args.daemon_rt
    if args.clients_cpu is not None:
        cpus = os.sched_getaffinity(0)
        if args.clients_cpu not in cpus or len(cpus) < 2:
            parser.error(
                f"--clients-cpu {args.clients_cpu}: allowed one of {sorted(cpus)}, "
                "with another left for the daemon"
            )
        CLIENTS_CPU = args.clients_cpu
        os.sched_setaffinity(0, cpus - {CLIENTS_CPU})
    if DAEMON_RT:
        set_realtime(DAEMON_RT)  # this thread runs every row's event loop
    seconds = 5.0 if args.quick else args.seconds
    soak_seconds = 20.0 if args.quick else args.soak_seconds
    # SIGTERM as Ctrl-C: the finally blocks stop the clients' process and the simulator.
    signal.signal(signal.SIGTERM, _raise_terminated)
    print(machine())
    print(
        f"daemon: SCHED_FIFO at {DAEMON_RT}" if DAEMON_RT else "daemon: time-shared",
        f"| clients: nice {CLIENTS_NICE}, time-shared"
        + (
            ""
            if CLIENTS_CPU is None
            else f", on CPU {CLIENTS_CPU} alone (the daemon on the others)"
        ),
        "| simulator: "
        + (
            "in the daemon's process"
            if SIM_IN_PROCESS
            else f"pty, SCHED_FIFO at {DAEMON_RT}"
            if DAEMON_RT
            else "pty, time-shared"
        ),
    )
    try:
        if args.only == "flood":
            run_flood(seconds, args.flooders)
            return 0
        if args.only == "web":
            run_web(seconds, args.pages)
            return 0
        if args.only != "rows" and soak_seconds > 0:
            with simulator() as (port, on_pty):
                if not on_pty:
                    print("NOTE: no pty here: sim:// runs in the daemon's process")
                result = run(soak(port, soak_seconds))
            show_soak(result)
            print()
        if args.only != "soak":
            print(
                f"{seconds:g} s a row, real time; every client reads every stream: wheel 50, "
                "odom 50, servos 3 x 30, core 10, state 1 Hz"
            )
            run_rows(seconds)
        if args.only is None:
            print()
            run_flood(seconds, args.flooders)
    except (KeyboardInterrupt, TerminatedError):
        print("interrupted: the clients' process and the simulator were stopped", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
