"""The daemon's server: one running :class:`~ohmni_tb.Robot` shared by many WebSocket clients.

::

    async with Robot.open("sim://") as robot, RobotServer(robot) as server:
        print(server.url)                              # ws://127.0.0.1:8766
        await asyncio.Event().wait()                   # until cancelled

Fan-out never waits for a client. Per topic that anyone subscribed to, one pump reads
the Robot's own subscription, encodes each sample once and appends it to every
subscribed client's bounded queue (no await in that path). One writer task per client
sends from its queues; a client that reads slowly or not at all fills only its own
queues, whose **oldest** samples are dropped and counted (the next sample it gets says
how many in ``dropped``). Neither the Robot's control tick nor other clients wait for it.

Read-only in this version, and loopback only: binding another address is refused until
the token of the next step exists.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import socket
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb import __version__
from ohmni_tb.daemon.protocol import (
    MAX_QUEUE,
    PROTOCOL_VERSION,
    Call,
    Hello,
    Limits,
    RequestError,
    Result,
    Subscribe,
    Unsubscribe,
    encode,
    parse_client_message,
    sample_json,
    stats_json,
)
from ohmni_tb.errors import ConfigError, InvalidArgumentError, OhmniError

if TYPE_CHECKING:
    from websockets.asyncio.server import Server, ServerConnection

    from ohmni_tb.robot import Robot, Subscription

__all__ = [
    "BURST_MESSAGES",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "HARD_MAX_MESSAGE_BYTES",
    "MAX_MESSAGES_PER_S",
    "MAX_MESSAGE_BYTES",
    "ClientFigures",
    "RobotServer",
    "check_loopback",
]

_log = logging.getLogger("ohmni_tb.daemon")

#: Loopback only until clients need a token (issue 12's next step).
DEFAULT_HOST: Final = "127.0.0.1"
#: Foxglove's bridge takes 8765; the daemon the next one, so both can run.
DEFAULT_PORT: Final = 8766
#: A client message is a few hundred bytes; anything longer is refused with an error.
MAX_MESSAGE_BYTES: Final = 16 * 1024
#: Frames longer than this are not even read: the connection is closed (1009).
HARD_MAX_MESSAGE_BYTES: Final = 1024 * 1024
#: Sustained messages a second a client may send; a person's tool needs a handful.
MAX_MESSAGES_PER_S: Final = 100.0
#: Messages allowed at once above that rate (a script subscribing to everything).
BURST_MESSAGES: Final = 200
#: Replies and errors waiting for a client that does not read them; beyond, it is closed.
_MAX_OUTBOX = 256
#: The kernel's send buffer per client (Linux doubles it): small, so that a stalled
#: client shows up in its queues (dropped, counted) within a second or two instead of
#: megabytes later; 50 clients of every stream need far less than this per second.
_SOCKET_SEND_BUFFER = 32 * 1024
#: websockets' own buffer before ``send`` waits for the socket to drain.
_WRITE_LIMIT = 32 * 1024
#: Unread client frames websockets holds (the reader handles each at once).
_MAX_READ_QUEUE = 16
#: How long closing waits for a client's closing handshake (a stalled one never answers).
_CLOSE_TIMEOUT_S = 1.0
#: WebSocket close codes.
_GOING_AWAY = 1001
_POLICY_VIOLATION = 1008


@dataclass(frozen=True, slots=True)
class ClientFigures:
    """One connected client's figures (:attr:`RobotServer.clients`).

    Attributes:
        peer: ``host:port`` of the client.
        topics: Its subscriptions.
        sent: Messages sent to it.
        dropped: Samples it lost by not keeping up, all topics.
        queued: Samples waiting in its queues.
    """

    peer: str
    topics: tuple[str, ...]
    sent: int
    dropped: int
    queued: int


class RobotServer:
    """Serves a running Robot to WebSocket clients (read-only; loopback only).

    Use ``async with RobotServer(robot) as server:`` or :meth:`start` / :meth:`aclose`.
    The Robot stays the caller's: the server does not close it.

    Args:
        robot: An open Robot.
        host: Address to listen on: a loopback address (or ``localhost``).
        port: TCP port; 0 picks a free one (see :attr:`url`).

    Raises:
        ConfigError: ``host`` is not a loopback address (no token authentication yet).
    """

    def __init__(self, robot: Robot, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT) -> None:
        check_loopback(host)
        if not 0 <= port <= 65535:
            raise InvalidArgumentError(f"port {port} is out of range: allowed 0..65535")
        self._robot = robot
        self._host = host
        self._port = port
        self._server: Server | None = None
        self._clients: set[_Client] = set()
        self._pumps: dict[str, _Pump] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = False

    @property
    def url(self) -> str:
        """``ws://host:port`` it listens on (the port chosen, when 0 was asked)."""
        return f"ws://{_host_in_url(self._host)}:{self._port}"

    @property
    def clients(self) -> list[ClientFigures]:
        """Every connected client's figures."""
        return [client.figures() for client in self._clients]

    async def start(self) -> None:
        """Listen.

        Raises:
            TransportError: The address cannot be bound (in use, not this machine's).
        """
        from websockets.asyncio.server import serve  # noqa: PLC0415  # loaded when serving

        from ohmni_tb.errors import TransportError  # noqa: PLC0415

        try:
            self._server = await serve(
                self._handle,
                self._host,
                self._port,
                max_size=HARD_MAX_MESSAGE_BYTES,
                max_queue=_MAX_READ_QUEUE,
                write_limit=_WRITE_LIMIT,
                close_timeout=_CLOSE_TIMEOUT_S,
                compression=None,  # loopback: deflate would cost CPU per client for nothing
            )
        except OSError as exc:
            raise TransportError(f"cannot listen on {self.url}: {exc.strerror or exc}") from exc
        self._port = self._server.sockets[0].getsockname()[1]  # the one chosen for 0
        _log.info("serving on %s", self.url)

    async def aclose(self) -> None:
        """Close every client (1001, going away), stop listening. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._server is not None:
            self._server.close(close_connections=True)
            await self._server.wait_closed()
        for pump in list(self._pumps.values()):
            pump.subscription.close()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        _log.info("stopped serving on %s", self.url)

    async def __aenter__(self) -> RobotServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    # -- one client ------------------------------------------------------------------------

    async def _handle(self, ws: ServerConnection) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        client = _Client(ws)
        with contextlib.suppress(OSError, AttributeError):  # not a TCP socket (tests, unix)
            sock: socket.socket = ws.transport.get_extra_info("socket")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCKET_SEND_BUFFER)
        self._clients.add(client)
        _log.info("client %s connected (%d now)", client.peer, len(self._clients))
        try:
            client.reply(self._hello())
            async with asyncio.TaskGroup() as group:
                group.create_task(client.write_loop(), name=f"ohmni-daemon-writer {client.peer}")
                try:
                    await self._read_loop(client)
                except ConnectionClosed:
                    pass
                finally:
                    client.finish()
        finally:
            for topic in list(client.subscriptions):
                self._unsubscribe(client, topic)
            self._clients.discard(client)
            _log.info(
                "client %s left (%s; sent %d, dropped %d)",
                client.peer,
                _close_text(ws),
                client.sent,
                client.dropped_total,
            )

    async def _read_loop(self, client: _Client) -> None:
        bucket = _TokenBucket(MAX_MESSAGES_PER_S, BURST_MESSAGES)
        async for frame in client.ws:
            if not bucket.take():
                self._refuse(
                    client,
                    RequestError(
                        "rate_limited",
                        f"more than {MAX_MESSAGES_PER_S:g} messages/s (burst "
                        f"{BURST_MESSAGES}): closing the connection",
                    ),
                )
                client.close_after_flush(_POLICY_VIOLATION, "message rate limit")
                return
            size = len(frame) if isinstance(frame, bytes) else len(frame.encode())
            if size > MAX_MESSAGE_BYTES:
                self._refuse(
                    client,
                    RequestError(
                        "too_large",
                        f"message of {size} bytes refused: the limit is {MAX_MESSAGE_BYTES} bytes",
                    ),
                )
                continue
            try:
                message = parse_client_message(frame)
                if isinstance(message, Subscribe):
                    client.reply(Result(id=message.id, data=self._subscribe(client, message)))
                elif isinstance(message, Unsubscribe):
                    if message.topic not in client.subscriptions:
                        raise RequestError(
                            "not_subscribed",
                            f"not subscribed to {message.topic!r}: subscribed to "
                            f"{', '.join(client.subscriptions) or 'nothing'}",
                            message.id,
                        )
                    self._unsubscribe(client, message.topic)
                    client.reply(Result(id=message.id, data={"topic": message.topic}))
                else:
                    client.reply(Result(id=message.id, data=await self._call(message)))
            except RequestError as exc:
                self._refuse(client, exc)
            if client.overflowed:
                client.close_after_flush(_POLICY_VIOLATION, "replies not read")
                return

    def _refuse(self, client: _Client, exc: RequestError) -> None:
        _log.warning("client %s: refused (%s): %s", client.peer, exc.code, exc.message)
        client.reply(exc.reply())

    def _hello(self) -> Hello:
        stats = self._robot.stats()
        return Hello(
            protocol=PROTOCOL_VERSION,
            read_only=True,
            version=__version__,
            topics={name: s.requested_hz for name, s in stats.streams.items()},
            limits=Limits(
                max_message_bytes=MAX_MESSAGE_BYTES,
                max_messages_per_s=MAX_MESSAGES_PER_S,
                burst_messages=BURST_MESSAGES,
                max_queue=MAX_QUEUE,
            ),
        )

    async def _call(self, call: Call) -> Any:
        robot = self._robot
        try:
            if call.method == "stats":
                return stats_json(robot.stats())
            if call.method == "schedule":
                return [list(row) for row in robot.schedule()]
            if call.method == "info":
                return await robot.info()
            topic = getattr(call.args, "topic", "")
            sample = robot.latest(topic)
            return None if sample is None else sample_json(sample)
        except OhmniError as exc:
            raise RequestError("robot_error", str(exc), call.id) from exc

    def _subscribe(self, client: _Client, message: Subscribe) -> dict[str, Any]:
        topic = message.topic
        pump = self._pumps.get(topic)
        if pump is None:
            pump = _Pump(topic, self._robot.subscribe(topic, maxlen=_PUMP_QUEUE))
            self._pumps[topic] = pump
            task = asyncio.get_running_loop().create_task(
                pump.run(), name=f"ohmni-daemon-pump {topic}"
            )
            self._tasks.add(task)
            task.add_done_callback(self._pump_done)
        queue = client.subscriptions.get(topic)
        if queue is None:
            queue = _Queue(client, topic)
            client.subscriptions[topic] = queue
            pump.queues.add(queue)
        queue.configure(message.queue, message.max_hz)
        hz = self._robot.stats().streams[topic].requested_hz
        return {"topic": topic, "max_hz": message.max_hz, "queue": message.queue, "hz": hz}

    def _unsubscribe(self, client: _Client, topic: str) -> None:
        queue = client.subscriptions.pop(topic)
        pump = self._pumps.get(topic)
        if pump is None:
            return
        pump.queues.discard(queue)
        if not pump.queues:
            # Nobody wants it: the Robot's subscription goes, and the pump ends with it.
            del self._pumps[topic]
            pump.subscription.close()

    def _pump_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            _log.error("a daemon pump failed", exc_info=task.exception())


#: The Robot-side queue of a pump: it only falls behind when the event loop itself does.
_PUMP_QUEUE = 256


class _Pump:
    """One topic: the Robot's subscription, fanned out to every client's queue."""

    def __init__(self, topic: str, subscription: Subscription[Any]) -> None:
        self.topic = topic
        self.subscription = subscription
        self.queues: set[_Queue] = set()

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        async for sample in self.subscription:
            # Encoded once for every client; each writer only wraps it.
            data = json.dumps(sample_json(sample), separators=(",", ":"))
            now = loop.time()
            for queue in self.queues:
                queue.put(data, now)


class _Queue:
    """One client's queue of one topic: bounded, oldest dropped and counted; rate-capped."""

    def __init__(self, client: _Client, topic: str) -> None:
        self.client = client
        self.topic = topic
        self.items: deque[str] = deque()
        self.maxlen = 64
        self.interval_s = 0.0
        self.next_due_s = 0.0
        #: Samples lost since the client's last one (told in that topic's next sample).
        self.dropped = 0
        self.dropped_total = 0
        self._prefix = f'{{"op":"sample","topic":{json.dumps(topic)},"dropped":'

    def configure(self, maxlen: int, max_hz: float | None) -> None:
        self.maxlen = maxlen
        self.interval_s = 0.0 if max_hz is None else 1.0 / max_hz
        while len(self.items) > maxlen:
            self._drop()

    def put(self, data: str, now: float) -> None:
        if self.interval_s:
            # Absolute due times: the average rate is the cap even when samples arrive
            # with jitter; after a pause it restarts instead of bursting to catch up.
            if now < self.next_due_s:
                return
            self.next_due_s += self.interval_s
            if self.next_due_s <= now:  # the first sample, or after a pause
                self.next_due_s = now + self.interval_s
        if len(self.items) >= self.maxlen:
            self._drop()
        self.items.append(data)
        self.client.wake()

    def pop(self) -> str:
        frame = f'{self._prefix}{self.dropped},"data":{self.items.popleft()}}}'
        self.dropped = 0
        return frame

    def _drop(self) -> None:
        self.items.popleft()
        self.dropped += 1
        self.dropped_total += 1


class _Client:
    """One connection: its queues, its replies, and the task that writes them."""

    def __init__(self, ws: ServerConnection) -> None:
        self.ws = ws
        address = ws.remote_address
        self.peer = f"{address[0]}:{address[1]}" if isinstance(address, tuple) else str(address)
        self.subscriptions: dict[str, _Queue] = {}
        self._outbox: deque[str] = deque()
        self._ready = asyncio.Event()
        self._finished = False
        self._close: tuple[int, str] | None = None
        self._turn = 0
        self.overflowed = False
        self.sent = 0

    @property
    def dropped_total(self) -> int:
        return sum(queue.dropped_total for queue in self.subscriptions.values())

    def figures(self) -> ClientFigures:
        queues = self.subscriptions.values()
        return ClientFigures(
            peer=self.peer,
            topics=tuple(self.subscriptions),
            sent=self.sent,
            dropped=self.dropped_total,
            queued=sum(len(queue.items) for queue in queues),
        )

    def wake(self) -> None:
        self._ready.set()

    def reply(self, message: Any) -> None:
        if len(self._outbox) >= _MAX_OUTBOX:
            self.overflowed = True
            return
        self._outbox.append(encode(message))
        self._ready.set()

    def finish(self) -> None:
        """The reader has ended: the writer stops (after the replies, when closing)."""
        self._finished = True
        self._ready.set()

    def close_after_flush(self, code: int, reason: str) -> None:
        self._close = (code, reason)
        self.finish()

    def _next(self) -> str | None:
        if self._outbox:
            return self._outbox.popleft()
        if self._finished:
            return None
        queues = [queue for queue in self.subscriptions.values() if queue.items]
        if not queues:
            return None
        self._turn += 1  # round robin: one busy topic does not starve the others
        return queues[self._turn % len(queues)].pop()

    async def write_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        try:
            while True:
                await self._ready.wait()
                self._ready.clear()
                while (frame := self._next()) is not None:
                    await self.ws.send(frame)
                    self.sent += 1
                if self._finished:
                    if self._close is not None:
                        await self.ws.close(*self._close)
                    return
        except ConnectionClosed:
            return


class _TokenBucket:
    """``rate_per_s`` sustained, ``burst`` at once."""

    def __init__(
        self, rate_per_s: float, burst: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._rate = rate_per_s
        self._burst = float(burst)
        self._tokens = float(burst)
        self._clock = clock
        self._last = clock()

    def take(self) -> bool:
        now = self._clock()
        self._tokens = min(self._burst, self._tokens + (now - self._last) * self._rate)
        self._last = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


def check_loopback(host: str) -> None:
    """Refuse to listen anywhere but loopback (no token authentication yet).

    Raises:
        ConfigError: ``host`` is not ``localhost`` nor a loopback address.
    """
    try:
        loopback = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = False
    if not loopback:
        raise ConfigError(
            f"refusing to listen on {host!r}: only loopback (127.0.0.1, ::1, localhost) "
            "until clients need a token; every local program can connect there"
        )


def _host_in_url(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _close_text(ws: ServerConnection) -> str:
    code = ws.close_code
    if code is None:
        return "no close code"
    return f"close {code}" + (f" {ws.close_reason}" if ws.close_reason else "")
