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

Commands go through one control lease (:meth:`RobotServer` ``acquire``): any number of
readers, one driver; ``stop`` and ``estop`` are anyone's. On loopback every local program
may connect; any other address needs a token (:mod:`ohmni_tb.daemon.auth`), and a
browser's handshake (it carries ``Origin``) is refused unless its origin is allowed.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import math
import socket
import time
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb import __version__
from ohmni_tb.control.pid import PidGains
from ohmni_tb.daemon.auth import check_origin, check_token, presented_token
from ohmni_tb.daemon.protocol import (
    MAX_QUEUE,
    METHOD_SPECS,
    PROTOCOL_VERSION,
    AcquireArgs,
    Call,
    DriveArgs,
    DriveWheelsArgs,
    ErrorCode,
    Hello,
    LatestArgs,
    LeaseMessage,
    LightArgs,
    Limits,
    Motion,
    MoveArgs,
    PidArgs,
    ReleasePortArgs,
    RequestError,
    RestArgs,
    Result,
    Subscribe,
    TorqueArgs,
    Unsubscribe,
    call_args,
    encode,
    parse_client_message,
    sample_json,
    stats_json,
)
from ohmni_tb.errors import ConfigError, InvalidArgumentError, OhmniError, StateError
from ohmni_tb.robot.devices import ServoHandle

if TYPE_CHECKING:
    from websockets.asyncio.server import Server, ServerConnection
    from websockets.http11 import Request, Response

    from ohmni_tb.robot import Robot, Subscription

__all__ = [
    "BURST_MESSAGES",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "HARD_MAX_MESSAGE_BYTES",
    "MAX_MESSAGES_PER_S",
    "MAX_MESSAGE_BYTES",
    "SAMPLE_FLUSH_S",
    "ClientFigures",
    "RobotServer",
    "check_listen",
    "is_loopback",
]

_log = logging.getLogger("ohmni_tb.daemon")

#: Loopback: only this machine's programs (any other address needs a token).
DEFAULT_HOST: Final = "127.0.0.1"
#: The shortest token a server accepts.
_MIN_TOKEN_CHARS = 16
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
#: Samples wait this long at most before they go out, together, in one frame per client:
#: the fan-out then costs a send per client and flush instead of one per sample.
SAMPLE_FLUSH_S: Final = 0.02
#: Most samples in one frame (a few hundred bytes each).
_MAX_BATCH = 256
#: Writers woken in one pass of the event loop by a flush (each sends one frame).
_WAKE_AT_ONCE = 4
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
    """Serves a running Robot to WebSocket clients.

    Use ``async with RobotServer(robot) as server:`` or :meth:`start` / :meth:`aclose`.
    The Robot stays the caller's: the server does not close it.

    Args:
        robot: An open Robot.
        host: Address to listen on. Loopback by default; any other needs ``token``.
        port: TCP port; 0 picks a free one (see :attr:`url`).
        read_only: Refuse every command but ``stop`` and ``estop`` (and the lease).
        token: When given, every client must present it (``Authorization: Bearer …`` or
            ``?token=…``); see :func:`ohmni_tb.daemon.auth.load_or_create_token`.
        origins: Browser origins allowed to connect (``"http://localhost:8080"``); a
            handshake with any other ``Origin`` header is refused (403).

    Raises:
        ConfigError: ``host`` is not a loopback address and there is no ``token``, or the
            token is shorter than 16 characters.
    """

    def __init__(
        self,
        robot: Robot,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        read_only: bool = False,
        token: str | None = None,
        origins: Sequence[str] = (),
    ) -> None:
        check_listen(host, token)
        if not 0 <= port <= 65535:
            raise InvalidArgumentError(f"port {port} is out of range: allowed 0..65535")
        self._robot = robot
        self._host = host
        self._port = port
        self._read_only = read_only
        self._token = token
        self._origins = tuple(origins)
        self._server: Server | None = None
        self._clients: set[_Client] = set()
        self._pumps: dict[str, _Pump] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self._holder: _Client | None = None
        self._flusher = _Flusher(SAMPLE_FLUSH_S)
        self._closed = False

    @property
    def url(self) -> str:
        """``ws://host:port`` it listens on (the port chosen, when 0 was asked)."""
        return f"ws://{_host_in_url(self._host)}:{self._port}"

    @property
    def clients(self) -> list[ClientFigures]:
        """Every connected client's figures."""
        return [client.figures() for client in self._clients]

    @property
    def lease_holder(self) -> str | None:
        """The peer (``host:port``) holding the control lease, or ``None``."""
        return None if self._holder is None else self._holder.peer

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
                process_request=self._admit,
            )
        except OSError as exc:
            raise TransportError(f"cannot listen on {self.url}: {exc.strerror or exc}") from exc
        self._port = self._server.sockets[0].getsockname()[1]  # the one chosen for 0
        _log.info("serving on %s", self.url)

    def _admit(self, connection: ServerConnection, request: Request) -> Response | None:
        """The handshake's checks: a browser's origin, then the token. A refusal is an HTTP
        error before any WebSocket exists, logged with the peer."""
        peer = _peer(connection)
        origin = request.headers.get("Origin")
        if not check_origin(origin, self._origins):
            _log.warning("client %s: refused: origin %r is not allowed", peer, origin)
            return connection.respond(
                403, f"origin {origin} is not allowed (ohmni serve --allow-origin)\n"
            )
        if self._token is not None:
            given = presented_token(request.path, request.headers.get("Authorization"))
            if not check_token(given, self._token):
                _log.warning(
                    "client %s: refused: %s token", peer, "no" if given is None else "a wrong"
                )
                return connection.respond(
                    401,
                    "this daemon needs its token: Authorization: Bearer <token>, or ?token=\n",
                )
        return None

    async def aclose(self) -> None:
        """Close every client (1001, going away), stop listening. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._server is not None:
            self._server.close(close_connections=True)
            await self._server.wait_closed()
        self._flusher.close()
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

        client = _Client(ws, self._flusher)
        with contextlib.suppress(OSError, AttributeError):  # not a TCP socket (tests, unix)
            sock: socket.socket = ws.transport.get_extra_info("socket")
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, _SOCKET_SEND_BUFFER)
        self._clients.add(client)
        _log.info("client %s connected (%d now)", client.peer, len(self._clients))
        try:
            client.reply(self._hello(client))
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
            if self._holder is client:
                self._set_holder(None, f"released: {client.peer} disconnected")
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
                    self._call(client, message)
            except RequestError as exc:
                self._refuse(client, exc)
            if client.overflowed:
                client.close_after_flush(_POLICY_VIOLATION, "replies not read")
                return

    def _refuse(self, client: _Client, exc: RequestError) -> None:
        _log.warning("client %s: refused (%s): %s", client.peer, exc.code, exc.message)
        client.reply(exc.reply())

    def _hello(self, client: _Client) -> Hello:
        robot = self._robot
        stats = robot.stats()
        config = robot.config
        return Hello(
            protocol=PROTOCOL_VERSION,
            read_only=self._read_only,
            version=__version__,
            peer=client.peer,
            lease=self.lease_holder,
            topics={name: s.requested_hz for name, s in stats.streams.items()},
            motion=Motion(
                wheel_radius_m=config.wheel_radius_m,
                wheel_separation_m=config.wheel_separation_m,
                max_linear_mps=_limit(config.max_linear_mps),
                max_angular_radps=_limit(config.max_angular_radps),
                max_wheel_mps=_limit(config.max_wheel_mps),
                watchdog_s=config.watchdog_s,
            ),
            limits=Limits(
                max_message_bytes=MAX_MESSAGE_BYTES,
                max_messages_per_s=MAX_MESSAGES_PER_S,
                burst_messages=BURST_MESSAGES,
                max_queue=MAX_QUEUE,
            ),
        )

    # -- calls -------------------------------------------------------------------------------

    def _call(self, client: _Client, call: Call) -> None:
        """Serve one call: at once when the Robot answers at once, else in a task of its own,
        so a slow one (a rest move takes a second) does not hold up the client's next
        messages. The lease is checked here, on arrival, in the order of the messages."""
        spec = METHOD_SPECS[call.method]
        args = call_args(call)
        if self._read_only and (spec.lease or call.method == "acquire"):
            raise RequestError(
                "read_only",
                f"{call.method}: this daemon takes no commands (started read-only); "
                "stop and estop are still anyone's",
                call.id,
            )
        if spec.lease and self._holder is not client:
            holder = self.lease_holder
            raise RequestError(
                "no_lease",
                f"{call.method} needs the control lease: "
                + (f"{holder} holds it" if holder else "nobody holds it; acquire it first"),
                call.id,
            )
        serve = self._SYNC.get(call.method)
        if serve is not None:
            try:
                data = serve(self, client, args)
            except OhmniError as exc:
                raise _robot_refusal(call, exc) from exc
            except RequestError as exc:
                exc.id = call.id
                raise
            client.reply(Result(id=call.id, data=data))
            return
        task = asyncio.get_running_loop().create_task(
            self._call_later(client, call, args), name=f"ohmni-daemon-call {call.method}"
        )
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _call_later(self, client: _Client, call: Call, args: Any) -> None:
        serve = self._ASYNC[call.method]
        try:
            try:
                data = await serve(self, args)
            except OhmniError as exc:
                raise _robot_refusal(call, exc) from exc
        except RequestError as exc:
            self._refuse(client, exc)
            return
        client.reply(Result(id=call.id, data=data))

    # The services, each one line on the Robot.

    def _acquire(self, client: _Client, args: AcquireArgs) -> Any:
        holder = self._holder
        if holder is None or holder is client:
            if holder is None:
                self._set_holder(client, f"acquired by {client.peer}")
            return {"holder": client.peer, "you": True, "stolen_from": None}
        if not args.steal:
            raise RequestError(
                "lease_held",
                f"the control lease is held by {holder.peer} (for "
                f"{time.monotonic() - holder.lease_since:.0f} s): acquire with steal to take it",
            )
        _log.warning("client %s: stole the control lease from %s", client.peer, holder.peer)
        self._set_holder(client, f"stolen by {client.peer} from {holder.peer}")
        return {"holder": client.peer, "you": True, "stolen_from": holder.peer}

    def _release(self, client: _Client, args: object) -> Any:
        self._set_holder(None, f"released by {client.peer}")
        return {"holder": None, "you": False}

    def _set_holder(self, client: _Client | None, reason: str) -> None:
        """Hand the lease over. The robot stops whenever it changes hands: whoever drives
        next starts from standstill, and a driver that left does not leave it moving."""
        previous, self._holder = self._holder, client
        if client is not None:
            client.lease_since = time.monotonic()
        if previous is not None:
            self._robot.stop()
        _log.info("lease: %s", reason)
        for other in self._clients:
            other.reply(LeaseMessage(holder=self.lease_holder, you=other is client, reason=reason))

    def _latest(self, client: _Client, args: LatestArgs) -> Any:
        sample = self._robot.latest(args.topic)
        return None if sample is None else sample_json(sample)

    def _drive(self, client: _Client, args: DriveArgs) -> Any:
        limited = self._robot.drive(args.linear_mps, args.angular_radps)
        return {
            "requested": [limited.requested.linear_mps, limited.requested.angular_radps],
            "twist": [limited.twist.linear_mps, limited.twist.angular_radps],
            "scale": limited.scale,
        }

    def _drive_wheels(self, client: _Client, args: DriveWheelsArgs) -> Any:
        wheels = self._robot.drive_wheels(args.left_mps, args.right_mps)
        return {"left_mps": wheels.left_mps, "right_mps": wheels.right_mps}

    def _set_pid(self, client: _Client, args: PidArgs) -> Any:
        self._robot.set_pid(PidGains(**args.model_dump()))
        return None

    def _get_pid(self, client: _Client, args: object) -> Any:
        gains = self._robot.get_pid()
        return {name: getattr(gains, name) for name in ("kp", "ki", "kd", "kff", "ff_offset")}

    _SYNC: Final[dict[str, _SyncCall]] = {
        "stats": lambda self, client, args: stats_json(self._robot.stats()),
        "schedule": lambda self, client, args: [list(row) for row in self._robot.schedule()],
        "latest": _latest,
        "get_pid": _get_pid,
        "config": lambda self, client, args: self._robot.config.model_dump(mode="json"),
        "lease": lambda self, client, args: {
            "holder": self.lease_holder,
            "you": self._holder is client,
        },
        "acquire": _acquire,
        "release": _release,
        "stop": lambda self, client, args: self._robot.stop(),
        "drive": _drive,
        "drive_wheels": _drive_wheels,
        "drive_pwm": lambda self, client, args: self._robot.drive_pwm(args.left, args.right),
        "clear_estop": lambda self, client, args: self._robot.clear_estop(),
        "enable_controllers": lambda self, client, args: self._robot.enable_controllers(
            args.enabled
        ),
        "set_pid": _set_pid,
        "reset_odometry": lambda self, client, args: self._robot.reset_odometry(
            args.x_m, args.y_m, args.yaw_rad
        ),
        "enable_stream": lambda self, client, args: self._robot.enable_stream(
            args.topic, args.enabled
        ),
        "set_rate": lambda self, client, args: self._robot.set_rate(args.topic, args.hz),
    }

    async def _info(self, args: object) -> Any:
        return await self._robot.info()

    async def _estop(self, args: object) -> Any:
        await self._robot.estop()

    async def _light_ring(self, args: LightArgs) -> Any:
        await self._robot.light_ring(args.hue, args.saturation, args.value)

    def _handle_of(self, target: str | int) -> Any:
        return self._robot.neck if target == "neck" else self._robot.servo(int(target))

    async def _move(self, args: MoveArgs) -> Any:
        handle = self._handle_of(args.target)
        options = {
            name: value
            for name, value in (("rad", args.rad), ("playtime_s", args.playtime_s))
            if value is not None
        }
        await handle.move(args.raw, **options)

    async def _torque(self, args: TorqueArgs) -> Any:
        handle = self._handle_of(args.target)
        if not isinstance(handle, ServoHandle):
            raise StateError("the worm-gear neck has no torque modes: it holds without power")
        await handle.torque(args.mode)

    async def _rest(self, args: RestArgs) -> Any:
        await self._handle_of(args.target).rest(free=args.free)

    async def _release_port(self, args: ReleasePortArgs) -> Any:
        await self._robot.release_port(args.duration_s)

    async def _reclaim_port(self, args: object) -> Any:
        await self._robot.reclaim_port()

    _ASYNC: Final[dict[str, _AsyncCall]] = {
        "release_port": _release_port,
        "reclaim_port": _reclaim_port,
        "info": _info,
        "estop": _estop,
        "light_ring": _light_ring,
        "move": _move,
        "torque": _torque,
        "rest": _rest,
    }

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
        queue.configure(message.queue, message.max_hz, message.every)
        hz = self._robot.stats().streams[topic].requested_hz
        return {
            "topic": topic,
            "max_hz": message.max_hz,
            "every": message.every,
            "queue": message.queue,
            "hz": hz,
        }

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


#: A service served at once: (server, client, args) → result data.
_SyncCall = Callable[["RobotServer", "_Client", Any], Any]
#: A service that awaits the Robot: (server, args) → result data.
_AsyncCall = Callable[["RobotServer", Any], Awaitable[Any]]


def _robot_refusal(call: Call, exc: OhmniError) -> RequestError:
    """What the Robot raised, as the ``error`` for the client: a bad value, a state that
    does not allow it, or another failure (a device that did not answer …)."""
    if isinstance(exc, InvalidArgumentError):
        code: ErrorCode = "bad_value"
    elif isinstance(exc, StateError):
        code = "robot_state"
    else:
        code = "robot_error"
    return RequestError(code, f"{call.method}: {exc}", call.id)


def _limit(value: float) -> float | None:
    """A speed limit for JSON: ``None`` for none (infinity)."""
    return None if math.isinf(value) else value


#: The Robot-side queue of a pump: it only falls behind when the event loop itself does.
_PUMP_QUEUE = 256


class _Pump:
    """One topic: the Robot's subscription, fanned out to every client's queue."""

    def __init__(self, topic: str, subscription: Subscription[Any]) -> None:
        self.topic = topic
        self.subscription = subscription
        self.queues: set[_Queue] = set()

    async def run(self) -> None:
        async for sample in self.subscription:
            # Encoded once for every client; each writer only wraps it.
            data = json.dumps(sample_json(sample), separators=(",", ":"))
            # The rate cap goes by the samples' own stamps (the loop's clock), so a
            # late wake-up of this pump does not let two samples through close together.
            stamp = sample.stamp_s
            for queue in self.queues:
                queue.put(data, stamp)


class _Queue:
    """One client's queue of one topic: bounded, oldest dropped and counted; rate-capped."""

    def __init__(self, client: _Client, topic: str) -> None:
        self.client = client
        self.topic = topic
        self.items: deque[str] = deque()
        self.maxlen = 64
        self.interval_s = 0.0
        self.next_due_s = 0.0
        self.every = 1
        self._since_sent = 0
        #: Samples lost since the client's last one (told in that topic's next sample).
        self.dropped = 0
        self.dropped_total = 0
        self._prefix = f'{{"op":"sample","topic":{json.dumps(topic)},"dropped":'

    def configure(self, maxlen: int, max_hz: float | None, every: int | None) -> None:
        self.maxlen = maxlen
        self.interval_s = 0.0 if max_hz is None else 1.0 / max_hz
        self.every = every or 1
        self._since_sent = 0
        while len(self.items) > maxlen:
            self._drop()

    def put(self, data: str, now: float) -> None:
        if self.every > 1:
            # Every Nth sample of the stream: the first one, then each Nth after it.
            self._since_sent += 1
            if self._since_sent != 1:
                if self._since_sent >= self.every:
                    self._since_sent = 0
                return
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
        self.client.flusher.mark(self.client)

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

    def __init__(self, ws: ServerConnection, flusher: _Flusher) -> None:
        self.ws = ws
        self.flusher = flusher
        self.peer = _peer(ws)
        self.subscriptions: dict[str, _Queue] = {}
        self._outbox: deque[str] = deque()
        self._ready = asyncio.Event()
        self._finished = False
        self._close: tuple[int, str] | None = None
        self._turn = 0
        self.overflowed = False
        self.sent = 0
        #: When it took the control lease (monotonic), if it holds it.
        self.lease_since = 0.0

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

    def _samples(self) -> list[str]:
        """Waiting samples' frames, round robin between topics (one busy topic does not
        starve the others), at most :data:`_MAX_BATCH`."""
        frames: list[str] = []
        queues = [queue for queue in self.subscriptions.values() if queue.items]
        while queues and len(frames) < _MAX_BATCH:
            frames.extend(queue.pop() for queue in queues)
            queues = [queue for queue in queues if queue.items]
        return frames

    async def write_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        try:
            while True:
                await self._ready.wait()
                self._ready.clear()
                while self._outbox:
                    await self.ws.send(self._outbox.popleft())
                    self.sent += 1
                if self._finished:
                    if self._close is not None:
                        await self.ws.close(*self._close)
                    return
                frames = self._samples()
                if frames:
                    # One frame for what waited since the last flush: a system call and a
                    # WebSocket frame per client and flush, not per sample.
                    await self.ws.send(
                        frames[0]
                        if len(frames) == 1
                        else '{"op":"batch","samples":[' + ",".join(frames) + "]}"
                    )
                    self.sent += len(frames)
                    if any(queue.items for queue in self.subscriptions.values()):
                        self._ready.set()  # more than one batch waited: go on
        except ConnectionClosed:
            return


class _Flusher:
    """Wakes the writers of the clients that have samples waiting, every ``period_s`` at
    most: samples go out in one frame per client and flush instead of one per sample, so
    50 clients cost the Robot's event loop 50 sends a flush, not 50 per sample."""

    def __init__(self, period_s: float) -> None:
        self._period_s = period_s
        self._dirty: set[_Client] = set()
        self._timer: asyncio.TimerHandle | None = None

    def mark(self, client: _Client) -> None:
        self._dirty.add(client)
        if self._timer is None:
            self._timer = asyncio.get_running_loop().call_later(self._period_s, self._flush)

    def _flush(self) -> None:
        self._timer = None
        dirty, self._dirty = list(self._dirty), set()
        self._wake(dirty)

    def _wake(self, clients: list[_Client]) -> None:
        """A few writers a pass of the event loop: the Robot's timers are looked at between
        two passes, so a flush to many clients never holds the control tick back by more
        than a few sends."""
        for client in clients[:_WAKE_AT_ONCE]:
            client.wake()
        rest = clients[_WAKE_AT_ONCE:]
        if rest:
            asyncio.get_running_loop().call_soon(self._wake, rest)

    def close(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._dirty.clear()


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


def is_loopback(host: str) -> bool:
    """Whether ``host`` is ``localhost`` or a loopback address (only this machine)."""
    try:
        return host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_listen(host: str, token: str | None) -> None:
    """Refuse to listen beyond loopback without a token.

    Raises:
        ConfigError: ``host`` is not loopback and ``token`` is ``None``, or the token is
            shorter than 16 characters.
    """
    if token is not None and len(token) < _MIN_TOKEN_CHARS:
        raise ConfigError(
            f"a daemon token of {len(token)} characters is too easy to guess: at least "
            f"{_MIN_TOKEN_CHARS} (load_or_create_token() makes one)"
        )
    if token is None and not is_loopback(host):
        raise ConfigError(
            f"refusing to listen on {host!r} without a token: beyond loopback (127.0.0.1, "
            "::1, localhost) every client must present one (ohmni serve makes it)"
        )


def _peer(connection: ServerConnection) -> str:
    address = connection.remote_address
    return f"{address[0]}:{address[1]}" if isinstance(address, tuple) else str(address)


def _host_in_url(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _close_text(ws: ServerConnection) -> str:
    code = ws.close_code
    if code is None:
        return "no close code"
    return f"close {code}" + (f" {ws.close_reason}" if ws.close_reason else "")
