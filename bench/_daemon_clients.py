"""The clients of ``bench/daemon.py``, in their own process so the daemon's CPU is its own.

Run by the benchmark, not by hand::

    python bench/_daemon_clients.py URL readers N [--stalled K]
    python bench/_daemon_clients.py URL churn [--every-s 0.2]
    python bench/_daemon_clients.py URL driver N
    python bench/_daemon_clients.py URL flood N [--rate 90]
    python bench/_daemon_clients.py URL holder

``readers``: N :class:`~ohmni_tb.client.RobotClient` connections on one event loop, each
subscribed to every stream of :data:`TOPICS` with one task per subscription reading it
continuously; ``--stalled`` adds K raw WebSocket connections that subscribe to the same
and never read (a small receive buffer, so the daemon sees them stall within a second).
``churn``: a new raw WebSocket connection every ``--every-s``, visiting for 0.5–3.5 s
(about ten at a time): most subscribe to a few topics (some capped at 5 Hz) and
unsubscribe politely, some leave with their subscriptions open, some cut the TCP
connection without a closing handshake.
``driver``: one connection takes the control lease and sends a new open-loop PWM
(``drive_pwm``, so the wheel packet carries exactly the value) every 50–150 ms, as a
teleop does, noting ``time.monotonic()`` just before each; N readers of every stream
beside it. Its ``done`` line carries the commands, ``[[t, [left, right]], …]``.
``flood``: N raw WebSocket connections without the lease, each calling ``stats``
``--rate`` times a second (90: under the daemon's per-client limit of 100) without
waiting for the replies, which another task per connection reads and counts; a
connection the daemon refuses is counted and not tried again. ``holder``: one
connection takes the control lease and drives at 0.3 m/s, the command again every 50 ms
(a teleop inside the watchdog time), until a ``silence`` line on stdin: then it sends
nothing more, its connection left open (as a driver whose process froze), and says
``{"event": "silent", "last_t": …}``, the ``time.monotonic()`` of its last command.

It talks to the benchmark in JSON lines: it prints ``{"event": "ready", …}`` once every
reader is subscribed, answers each ``mark`` line on stdin with its cumulative figures
(``{"event": "mark", …}``), and on ``quit`` (or stdin's end: the benchmark is gone)
closes every connection, prints ``{"event": "done", …}`` and exits. Errors go to stderr.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import random
import socket
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ohmni_tb.client import RobotClient
from ohmni_tb.robot import SampleStream

#: Every stream the Robot runs by default (not ``new_neck``: the simulated neck is a
#: HerkuleX servo; not ``pid_debug``: off unless configured).
TOPICS = (
    "wheel_encoder",
    "wheel_odom",
    "tbcore_status",
    "servo_neck",
    "servo_ext1",
    "servo_ext2",
    "robot_state",
)
#: The stalled connections' kernel receive buffer (Linux doubles it): small, so the
#: daemon's own buffers fill within a second instead of after megabytes of autotuning.
_STALLED_RECEIVE_BUFFER = 4096
#: How long a churn visit lasts, s (uniform): with a visit every 0.2 s, ten at a time.
_VISIT_S = (0.5, 3.5)
#: Churn visits by kind, and their weights.
_KINDS = ("polite", "leave", "abort")
_WEIGHTS = (6, 3, 1)


@dataclass
class Tally:
    """What the clients received and lost, cumulative."""

    received: Counter[str] = field(default_factory=Counter)
    subscriptions: list[SampleStream[Any]] = field(default_factory=list)
    #: The readers' connections: what the daemon dropped for each is in ``lost_samples``.
    clients: list[RobotClient] = field(default_factory=list)
    connected: int = 0
    visits: Counter[str] = field(default_factory=Counter)
    errors: Counter[str] = field(default_factory=Counter)
    stalled_peers: list[str] = field(default_factory=list)
    sent: list[tuple[float, tuple[int, int]]] = field(default_factory=list)
    #: flood: calls sent, replies read, connections refused by the daemon.
    calls: int = 0
    answered: int = 0
    refused: int = 0
    #: holder: when its last drive command went.
    last_t: float = 0.0

    def figures(self, event: str) -> dict[str, Any]:
        return {
            "event": event,
            "received": dict(self.received),
            "dropped": sum(s.dropped for s in self.subscriptions)
            + sum(c.lost_samples for c in self.clients),
            "connected": self.connected,
            "visits": dict(self.visits),
            "errors": dict(self.errors),
            "stalled_peers": self.stalled_peers,
            "commands": self.sent,
            "calls": self.calls,
            "answered": self.answered,
            "refused": self.refused,
            "cpu_s": time.process_time(),
        }

    def error(self, exc: BaseException) -> None:
        key = f"{type(exc).__name__}: {exc}"[:200]
        if not self.errors[key]:
            print(f"clients: {key}", file=sys.stderr)
        self.errors[key] += 1


def say(message: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(message) + "\n")
    sys.stdout.flush()


async def count(subscription: SampleStream[Any], received: Counter[str]) -> None:
    async for _ in subscription:
        received[subscription.name] += 1


async def reader(
    url: str, tally: Tally, subscribed: Callable[[], None], stop: asyncio.Event
) -> None:
    """One connection reading every topic until ``stop``."""
    async with RobotClient.connect(url) as client, contextlib.AsyncExitStack() as stack:
        subscriptions = [
            await stack.enter_async_context(client.subscribe(topic)) for topic in TOPICS
        ]
        tally.subscriptions.extend(subscriptions)
        tally.clients.append(client)
        tally.connected += 1
        subscribed()
        async with asyncio.TaskGroup() as group:
            tasks = [group.create_task(count(s, tally.received)) for s in subscriptions]
            await stop.wait()
            for task in tasks:
                task.cancel()
        tally.connected -= 1


async def stalled(
    url: str, tally: Tally, subscribed: Callable[[], None], stop: asyncio.Event
) -> None:
    """One connection that subscribes to every topic and never reads."""
    from websockets.asyncio.client import connect  # noqa: PLC0415

    host, _, port = url.removeprefix("ws://").rpartition(":")
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _STALLED_RECEIVE_BUFFER)
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, (host, int(port)))
    # max_queue=1: websockets stops reading the socket after one unread frame.
    ws = await connect(url, sock=sock, compression=None, max_queue=1)
    try:
        for n, topic in enumerate(TOPICS, 1):
            await ws.send(json.dumps({"op": "subscribe", "id": n, "topic": topic}))
        local = ws.local_address
        tally.stalled_peers.append(f"{local[0]}:{local[1]}")
        subscribed()
        await stop.wait()
    finally:
        ws.transport.abort()


async def visit(url: str, kind: str, stay_s: float, rng: random.Random, tally: Tally) -> None:
    """One churn visit: connect, subscribe to a few topics, read for ``stay_s``, leave."""
    topics = rng.sample(TOPICS, rng.randint(2, 4))
    tally.visits[kind] += 1
    try:
        if kind == "abort":
            await _visit_abort(url, topics, stay_s)
            return
        await _visit(url, topics, stay_s, rng, polite=kind == "polite", tally=tally)
    except Exception as exc:  # counted and shown: the churn goes on, the daemon is judged
        tally.error(exc)


async def _visit(
    url: str, topics: list[str], stay_s: float, rng: random.Random, *, polite: bool, tally: Tally
) -> None:
    """Subscribe to ``topics`` (some capped at 5 Hz), maybe ask ``stats``, read for
    ``stay_s``; then unsubscribe (``polite``) or leave them open, and close."""
    from websockets.asyncio.client import connect  # noqa: PLC0415

    async with connect(url, compression=None) as ws:
        tally.connected += 1
        try:
            await ws.recv()  # hello
            n = 0
            if rng.random() < 0.3:
                n += 1
                await ws.send(json.dumps({"op": "call", "id": n, "method": "stats"}))
            for topic in topics:
                n += 1
                max_hz = rng.choice((None, None, 5.0))
                await ws.send(
                    json.dumps({"op": "subscribe", "id": n, "topic": topic, "max_hz": max_hz})
                )
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(stay_s):
                    async for _ in ws:
                        pass
            if polite:
                for topic in topics:
                    n += 1
                    await ws.send(json.dumps({"op": "unsubscribe", "id": n, "topic": topic}))
        finally:
            tally.connected -= 1


async def _visit_abort(url: str, topics: list[str], stay_s: float) -> None:
    from websockets.asyncio.client import connect  # noqa: PLC0415

    ws = await connect(url, compression=None)
    try:
        for n, topic in enumerate(topics, 1):
            await ws.send(json.dumps({"op": "subscribe", "id": n, "topic": topic}))
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(stay_s):
                async for _ in ws:
                    pass
    finally:
        ws.transport.abort()  # no closing handshake: as a process that crashed


async def churn(url: str, every_s: float, tally: Tally, stop: asyncio.Event) -> None:
    rng = random.Random(12)
    loop = asyncio.get_running_loop()
    async with asyncio.TaskGroup() as group:
        due = loop.time()
        while not stop.is_set():
            kind = rng.choices(_KINDS, _WEIGHTS)[0]
            group.create_task(visit(url, kind, rng.uniform(*_VISIT_S), rng, tally))
            due += every_s
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout_at(due):
                    await stop.wait()


async def driver(url: str, tally: Tally, ready: asyncio.Event, stop: asyncio.Event) -> None:
    """The lease holder: a new PWM every 50–150 ms until ``stop`` (the same values and
    pauses as ``bench/robot.py``'s teleop, seeded alike)."""
    rng = random.Random(7)
    async with RobotClient.connect(url) as client, client.lease():
        ready.set()
        previous = (0, 0)
        while not stop.is_set():
            pwm = previous
            while pwm == previous:
                value = rng.randrange(-300, 301, 10)
                pwm = (value, value)
            tally.sent.append((time.monotonic(), pwm))
            client.drive_pwm(*pwm)
            previous = pwm
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(rng.uniform(0.05, 0.15)):
                    await stop.wait()
        client.drive_pwm(0, 0)
        await client.confirm()


async def flooder(
    url: str, rate_hz: float, tally: Tally, connected: Callable[[], None], stop: asyncio.Event
) -> None:
    """One connection calling ``stats`` ``rate_hz`` times a second, not waiting for the
    replies (read and counted by a task of its own), until ``stop``."""
    from websockets.asyncio.client import connect  # noqa: PLC0415
    from websockets.exceptions import InvalidHandshake  # noqa: PLC0415

    try:
        ws = await connect(url, compression=None, open_timeout=30)
        await ws.recv()  # hello
    except (OSError, InvalidHandshake, TimeoutError):
        tally.refused += 1
        connected()
        return
    connected()

    async def replies() -> None:
        async for _ in ws:
            tally.answered += 1

    loop = asyncio.get_running_loop()
    try:
        async with asyncio.TaskGroup() as group:
            reading = group.create_task(replies())
            due, n = loop.time(), 0
            while not stop.is_set():
                await ws.send(f'{{"op":"call","id":{n},"method":"stats"}}')
                tally.calls += 1
                n += 1
                # A fixed rate; after a send that waited (the daemon's backpressure), on
                # from now rather than a burst to catch up.
                due = max(due + 1.0 / rate_hz, loop.time())
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout_at(due):
                        await stop.wait()
            reading.cancel()
    except Exception as exc:  # counted and shown: the daemon is judged, not this client
        tally.error(exc)
    finally:
        ws.transport.abort()


async def holder(
    url: str, tally: Tally, ready: asyncio.Event, silence: asyncio.Event, silent: asyncio.Event
) -> None:
    """The lease holder: drives at 0.3 m/s every 50 ms until ``silence``; then sends
    nothing more, its connection open, until the process ends."""
    async with RobotClient.connect(url) as client:
        await client.acquire()
        ready.set()
        while not silence.is_set():
            tally.last_t = time.monotonic()
            client.drive(0.3, 0.0)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.05):
                    await silence.wait()
        silent.set()
        await asyncio.Event().wait()  # silent until cancelled


async def commands(
    tally: Tally,
    stop: asyncio.Event,
    silence: asyncio.Event | None = None,
    silent: asyncio.Event | None = None,
) -> None:
    """Answer the benchmark's ``mark`` (and ``silence``) lines; ``quit`` or the end of
    stdin stops."""
    loop = asyncio.get_running_loop()
    lines = asyncio.StreamReader()
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(lines), sys.stdin)
    while line := (await lines.readline()).decode().strip():
        if line == "mark":
            say(tally.figures("mark"))
        elif line == "silence" and silence is not None and silent is not None:
            silence.set()
            await silent.wait()
            say({"event": "silent", "last_t": tally.last_t})
        elif line == "quit":
            break
    stop.set()


async def run(args: argparse.Namespace) -> None:
    tally = Tally()
    stop = asyncio.Event()
    if args.mode == "holder":
        ready, silence, silent = asyncio.Event(), asyncio.Event(), asyncio.Event()
        async with asyncio.TaskGroup() as group:
            driving = group.create_task(holder(args.url, tally, ready, silence, silent))
            await ready.wait()
            say({"event": "ready"})
            await commands(tally, stop, silence, silent)
            driving.cancel()
        say(tally.figures("done"))
        return
    async with asyncio.TaskGroup() as group:
        if args.mode == "flood":
            connected = 0
            everyone = asyncio.Event()

            def one_more() -> None:
                nonlocal connected
                connected += 1
                if connected == args.clients:
                    everyone.set()

            for _ in range(args.clients):
                group.create_task(flooder(args.url, args.rate, tally, one_more, stop))
            if args.clients:
                await everyone.wait()
        elif args.mode in ("readers", "driver"):
            # A client that fails to connect fails the group, and this process with it.
            total = args.clients + args.stalled
            subscribed = 0
            everyone = asyncio.Event()

            def one_more() -> None:
                nonlocal subscribed
                subscribed += 1
                if subscribed == total:
                    everyone.set()

            for n in range(total):
                client = reader if n < args.clients else stalled
                group.create_task(client(args.url, tally, one_more, stop))
            if total:
                await everyone.wait()
            if args.mode == "driver":
                holding = asyncio.Event()
                group.create_task(driver(args.url, tally, holding, stop))
                await holding.wait()
        else:
            group.create_task(churn(args.url, args.every_s, tally, stop))
        say({"event": "ready"})
        group.create_task(commands(tally, stop))
    say(tally.figures("done"))


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("url")
    parser.add_argument("mode", choices=("readers", "churn", "driver", "flood", "holder"))
    parser.add_argument("clients", type=int, nargs="?", default=0)
    parser.add_argument("--stalled", type=int, default=0)
    parser.add_argument("--every-s", type=float, default=0.2)
    parser.add_argument("--rate", type=float, default=90.0, help="flood: calls/s a connection")
    args = parser.parse_args()
    try:
        asyncio.run(run(args))
    except KeyboardInterrupt:
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
