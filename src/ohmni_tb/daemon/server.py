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

Commands go through a control lease (:meth:`RobotServer` ``acquire``): any number of
readers; one lease per command source (``local``, ``remote``, ``autonomy``… of the
Robot's ``command_sources``), each held by one client at most, whose drive commands and
motion goals go as that source — the Robot takes the highest live source's, so a person
at the robot overrides a remote script for a while. Only a client on the robot's own
computer (loopback, a unix socket) may take ``local`` or ``safety``. ``stop`` and
``estop`` are anyone's. On loopback every local program may connect; any other address
needs a token (:mod:`ohmni_tb.daemon.auth`), and a browser's handshake (it carries
``Origin``) is refused unless its origin is allowed — or is the web console's own
(:mod:`ohmni_tb.daemon.web`: the page served at ``/`` of the same port, on by default).

No load of clients holds the control tick back. At most ``max_clients`` connections
(:data:`DEFAULT_MAX_CLIENTS`, fewer when the process may open too few files to keep some
in reserve) are served; the next handshake is refused with HTTP 503. The messages of every
client but the lease holder share one budget (:data:`READER_MESSAGES_PER_S`): a message
beyond it waits in its socket, costing nothing, until its turn. ``stats`` is computed at
most once per :data:`STATS_INTERVAL_S`, and every caller gets the same encoded reply.
Refusals are counted and logged at most once per :data:`REFUSAL_LOG_S`.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import math
import os
import socket
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb._checks import integer
from ohmni_tb._ratelimit import TokenBucket
from ohmni_tb._version import __version__
from ohmni_tb.control.sources import LOOPBACK_SOURCES, claimable_beyond_loopback
from ohmni_tb.daemon.auth import (
    MIN_TOKEN_CHARS,
    WEB_PROTOCOL,
    check_origin,
    check_token,
    presented_token,
)
from ohmni_tb.daemon.web import WebConsole, page_url
from ohmni_tb.errors import (
    ConfigError,
    InvalidArgumentError,
    MotionError,
    OhmniError,
    StateError,
)
from ohmni_tb.robot.wire import (
    MAX_QUEUE,
    METHOD_SPECS,
    PROTOCOL_VERSION,
    AcquireArgs,
    Call,
    ErrorCode,
    Hello,
    LeaseMessage,
    Limits,
    Motion,
    ReleaseArgs,
    RequestError,
    Result,
    ServoCommand,
    Subscribe,
    Unsubscribe,
    call_args,
    encode,
    goal_json,
    parse_client_message,
    pid_state_json,
    result_json,
    sample_json,
    stats_json,
)

if TYPE_CHECKING:
    from websockets.asyncio.server import Server, ServerConnection
    from websockets.http11 import Request, Response
    from websockets.typing import Subprotocol

    from ohmni_tb.robot import Robot, RobotStats, SampleStream

__all__ = [
    "BURST_MESSAGES",
    "DEFAULT_HOST",
    "DEFAULT_MAX_CLIENTS",
    "DEFAULT_PORT",
    "HARD_MAX_MESSAGE_BYTES",
    "MAX_MESSAGES_PER_S",
    "MAX_MESSAGE_BYTES",
    "READER_BURST",
    "READER_MESSAGES_PER_S",
    "REFUSAL_LOG_S",
    "SAMPLE_FLUSH_S",
    "STATS_INTERVAL_S",
    "ClientFigures",
    "RobotServer",
    "check_listen",
    "is_loopback",
]

_log = logging.getLogger("ohmni_tb.daemon")

#: Loopback: only this machine's programs (any other address needs a token).
DEFAULT_HOST: Final = "127.0.0.1"
#: The shortest token a server accepts.
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
#: Connections served at once by default (``RobotServer(max_clients=...)``): a robot has a
#: handful of programs and people watching it; 64 readers of every stream cost the
#: daemon about a fifth of a core.
DEFAULT_MAX_CLIENTS: Final = 64
#: Messages a second that all the clients without the control lease may have handled
#: together (each 4 KiB of a message counts as one more). What is beyond waits in its socket
#: until its turn, in the order it came: the event loop spends at most a few per cent of
#: a core on them, however many clients send however much, and the control tick and the
#: lease holder go first. A program polling ``stats`` at 4 Hz costs 4 of these.
READER_MESSAGES_PER_S: Final = 500.0
#: Messages of those clients handled at once above that rate (connecting scripts
#: subscribing to every stream).
READER_BURST: Final = 100
#: ``stats`` is computed at most this often: every caller in between gets the same reply.
STATS_INTERVAL_S: Final = 0.2
#: A kind of refusal (connections over the cap, a client's bad messages, ``accept()``
#: out of descriptors) is logged at most once this often; the rest are counted, and the
#: count is logged with the next line.
REFUSAL_LOG_S: Final = 10.0
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
#: The kernel's receive buffer per client (Linux doubles it): websockets parses every
#: frame of a read at once, so a read of a flooding client's backlog is a few hundred
#: small frames (a few milliseconds of the event loop), not thousands; and the flood
#: backs up to the client sooner. A 16 KiB message still arrives, in two reads.
_SOCKET_RECEIVE_BUFFER = 8 * 1024
#: websockets' own buffer before ``send`` waits for the socket to drain.
_WRITE_LIMIT = 32 * 1024
#: Unread client frames websockets holds (the reader handles each at once).
_MAX_READ_QUEUE = 16
#: How long closing waits for a client's closing handshake (a stalled one never answers).
_CLOSE_TIMEOUT_S = 1.0
#: File descriptors kept free for everything but the clients: the serial port reopened,
#: the Foxglove view and its clients' few, log files, the simulator's pty.
_FD_RESERVE = 32
#: TCP connections beyond ``max_clients`` that may be in their handshake (answered 503
#: once their request arrives); any more are closed as soon as accepted.
_HANDSHAKE_SLACK = 16
#: A message's bytes that count as one more message of the readers' budget: parsing a
#: 16 KiB frame costs about what four small messages do.
_BUDGET_BYTES = 4096
#: The largest ``max_clients``: one descriptor and a few hundred KiB of buffers each.
_MAX_CLIENTS_LIMIT = 10_000
#: WebSocket close codes.
_GOING_AWAY = 1001
_POLICY_VIOLATION = 1008


#: The servo handle's maintenance calls, which only a HerkuleX servo has.
_HERKULEX_ONLY: Final = frozenset(
    {"info", "write", "set_id", "set_zero_offset", "status", "clear_errors"}
)


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
        token: When given, every client must present it (``Authorization: Bearer …``, a
            browser's ``ohmni.token.…`` subprotocol, or ``?token=…``); see
            :func:`ohmni_tb.daemon.auth.load_or_create_token`.
        origins: Browser origins allowed to connect (``"http://localhost:8080"``); a
            handshake with any other ``Origin`` header is refused (403).
        max_clients: Connections served at once (1..10000); the next handshake is
            refused with HTTP 503. Lowered at :meth:`start`, with a warning, when the
            process may open too few files (``ulimit -n``) to keep some in reserve.
        serves: The port the Robot was opened on (``sim://``, ``/dev/ttyUSB0``), told to
            clients in ``hello``; by default ``sim://`` for the built-in simulator, else
            not told.
        web: Serve the web console at ``/`` of the same port (:attr:`web_url`;
            :mod:`ohmni_tb.daemon.web`), and let its own origin connect.

    Raises:
        ConfigError: ``host`` is not a loopback address and there is no ``token``, or the
            token is shorter than 16 characters.
        InvalidArgumentError: ``port`` or ``max_clients`` out of range.
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
        max_clients: int = DEFAULT_MAX_CLIENTS,
        serves: str | None = None,
        web: bool = True,
    ) -> None:
        check_listen(host, token)
        if not 0 <= port <= 65535:
            raise InvalidArgumentError(f"port {port} is out of range: allowed 0..65535")
        integer("max_clients", max_clients, 1, _MAX_CLIENTS_LIMIT)
        self._robot = robot
        self._host = host
        self._port = port
        self._read_only = read_only
        self._server: Server | None = None
        self._clients: set[_Client] = set()
        self._pumps: dict[str, _Pump] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        #: Each command source's lease and the client holding it.
        self._leases: dict[str, _Client] = {}
        self._flusher = _Flusher(SAMPLE_FLUSH_S)
        self._closed = False
        self._web = WebConsole(token) if web else None
        self._door = _Doorkeeper(max_clients, token, tuple(origins), self._web)
        self._simulated = robot.sim is not None
        self._serves = serves if serves is not None else "sim://" if self._simulated else None
        self._budget = _Budget(READER_MESSAGES_PER_S, READER_BURST)
        self._stats: tuple[float, RobotStats, str] | None = None

    @property
    def url(self) -> str:
        """``ws://host:port`` it listens on (the port chosen, when 0 was asked)."""
        return f"ws://{_host_in_url(self._host)}:{self._port}"

    @property
    def web_url(self) -> str | None:
        """``http://host:port/``: the web console's page (a wildcard address shown as one
        other machines reach), or ``None`` when it is not served."""
        return None if self._web is None else page_url(self._host, self._port)

    @property
    def clients(self) -> list[ClientFigures]:
        """Every connected client's figures."""
        return [client.figures() for client in self._clients]

    @property
    def lease_holder(self) -> str | None:
        """The peer (``host:port``) holding the control lease of the highest command source
        held, or ``None``: nobody holds one."""
        for source in self._source_names():
            holder = self._leases.get(source)
            if holder is not None:
                return holder.peer
        return None

    @property
    def leases(self) -> dict[str, str]:
        """Each command source's lease held, and its holder (``host:port``), highest first."""
        return {
            source: self._leases[source].peer
            for source in self._source_names()
            if source in self._leases
        }

    @property
    def max_clients(self) -> int:
        """Connections served at once (as asked, or lowered at :meth:`start` to keep file
        descriptors in reserve)."""
        return self._door.max_clients

    @property
    def refused_connections(self) -> int:
        """Connections refused so far because ``max_clients`` were connected, and
        ``accept()`` failures (the process out of file descriptors)."""
        return self._door.refused

    async def start(self) -> None:
        """Listen.

        Raises:
            TransportError: The address cannot be bound (in use, not this machine's).
            ConfigError: This process may open too few more files (``ulimit -n``) to
                serve one client and keep 48 in reserve.
        """
        from websockets.asyncio.server import serve  # noqa: PLC0415  # loaded when serving

        from ohmni_tb.errors import TransportError  # noqa: PLC0415

        self._door.fit_descriptors()
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
                process_request=self._process_request,
                create_connection=_capped_connection(self._door),
                select_subprotocol=_select_subprotocol,
            )
        except OSError as exc:
            raise TransportError(f"cannot listen on {self.url}: {exc.strerror or exc}") from exc
        for listening in self._server.sockets:
            # Inherited by every connection accepted from now on; set on a connection
            # already open it would shrink a window the peer was promised, and stall it.
            listening.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, _SOCKET_RECEIVE_BUFFER)
        self._port = self._server.sockets[0].getsockname()[1]  # the one chosen for 0
        logging.getLogger("asyncio").addFilter(self._door.accept_failures)
        _log.info("serving on %s (at most %d clients)", self.url, self._door.max_clients)

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        """The web console's page (a plain HTTP request), else the handshake's checks."""
        if self._web is not None:
            page = self._web.respond(connection, request)
            if page is not None:
                return page
        return self._door.admit(connection, request)

    async def aclose(self) -> None:
        """Close every client (1001, going away), stop listening. Idempotent."""
        if self._closed:
            return
        self._closed = True
        logging.getLogger("asyncio").removeFilter(self._door.accept_failures)
        if self._server is not None:
            self._server.close(close_connections=True)
            await self._server.wait_closed()
        self._flusher.close()
        self._door.close()
        for pump in list(self._pumps.values()):
            pump.subscription.close()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        _log.info("stopped serving on %s", self.url)

    def _attach(self, client: _Client) -> None:
        """A client inside this process joins (:class:`~ohmni_tb.daemon.local.LocalClient`):
        it gets what every client gets (``lease`` messages), and counts among them."""
        self._clients.add(client)
        _log.info("client %s attached (%d now)", client.peer, len(self._clients))

    def _detach(self, client: _Client) -> None:
        """A client inside this process leaves: as a WebSocket client's departure."""
        self._clients.discard(client)
        for source in list(client.leases):
            self._set_holder(source, None, f"released: {client.peer} left")
        _log.info("client %s detached", client.peer)

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
            for source in list(client.leases):
                self._set_holder(source, None, f"released: {client.peer} disconnected")
            client.refusals.close()
            _log.info(
                "client %s left (%s; sent %d, dropped %d, refused %d messages, "
                "%d not handled: they came after the connection closed)",
                client.peer,
                _close_text(ws),
                client.sent,
                client.dropped_total,
                client.refusals.total,
                client.unhandled,
            )

    async def _read_loop(self, client: _Client) -> None:
        from websockets.protocol import State  # noqa: PLC0415  # loaded when serving

        bucket = TokenBucket(MAX_MESSAGES_PER_S, BURST_MESSAGES)
        async for frame in client.ws:
            size = len(frame) if isinstance(frame, bytes) else len(frame.encode())
            if client.ws.state is not State.OPEN and not _may_stop(frame, size):
                # Gone (or the server closing): what it queued before can no longer be
                # answered, and must not spend the readers' budget. Counted, not handled;
                # a stop or an estop it sent last still is.
                client.unhandled += 1
                continue
            if not client.leases and not _may_stop(frame, size):
                # The readers' shared budget, before any work on the frame: beyond it the
                # frame waits here, and the next ones in the socket (backpressure). A
                # short call that may be a stop or an estop never waits for it.
                delay = self._budget.reserve(1 + min(size, MAX_MESSAGE_BYTES) // _BUDGET_BYTES)
                if delay > 0.0:
                    await asyncio.sleep(delay)
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
        client.refusals.note(
            _log, "client %s: refused (%s): %s", client.peer, exc.code, exc.message
        )
        client.reply(exc.reply())

    def _shared_stats(self) -> tuple[RobotStats, str]:
        """:meth:`Robot.stats` and its JSON, computed at most once per
        :data:`STATS_INTERVAL_S` (a few hundred microseconds each time)."""
        now = time.monotonic()
        if self._stats is None or now >= self._stats[0]:
            stats = self._robot.stats()
            text = json.dumps(stats_json(stats), separators=(",", ":"))
            self._stats = (now + STATS_INTERVAL_S, stats, text)
        return self._stats[1], self._stats[2]

    def _hello(self, client: _Client) -> Hello:
        robot = self._robot
        stats, _ = self._shared_stats()
        config = robot.config
        return Hello(
            protocol=PROTOCOL_VERSION,
            read_only=self._read_only,
            serves=self._serves,
            simulated=self._simulated,
            version=__version__,
            peer=client.peer,
            lease=self.lease_holder,
            leases=self.leases,
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
        if spec.lease and not client.leases:
            holder = self.lease_holder
            raise RequestError(
                "no_lease",
                f"{call.method} needs the control lease: "
                + (f"{holder} holds it" if holder else "nobody holds it; acquire it first"),
                call.id,
            )
        kwargs = args.call_kwargs()
        if spec.sourced:
            kwargs["source"] = self._source_of(client, call, spec.lease, kwargs.get("source"))
        if call.method == "stats":
            # One encoding for every caller within the interval: only the id differs.
            _, text = self._shared_stats()
            client.reply_frame(f'{{"op":"result","id":{json.dumps(call.id)},"data":{text}}}')
            return
        if spec.awaited and spec.call is not None:
            task = asyncio.get_running_loop().create_task(
                self._call_later(client, call, spec.call, args, kwargs),
                name=f"ohmni-daemon-call {call.method}",
            )
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
            return
        try:
            if spec.call is None:
                data = self._OWN[call.method](self, client, args)
            else:
                data = result_json(call.method, self._bound(spec.call, args)(**kwargs))
        except OhmniError as exc:
            raise _robot_refusal(call, exc) from exc
        except RequestError as exc:
            exc.id = call.id
            raise
        if call.method in _CHANGES_STATS:
            self._stats = None  # the next stats shows the change, as on the Robot
        client.reply(Result(id=call.id, data=data))

    async def _call_later(
        self, client: _Client, call: Call, name: str, args: Any, kwargs: dict[str, Any]
    ) -> None:
        try:
            try:
                data = result_json(call.method, await self._bound(name, args)(**kwargs))
            except MotionError as exc:
                # A goal that ended short of its goal: what it did, and why, are its result.
                data = goal_json(exc)
            except OhmniError as exc:
                raise _robot_refusal(call, exc) from exc
        except RequestError as exc:
            self._refuse(client, exc)
            return
        if call.method in _CHANGES_STATS:
            self._stats = None
        client.reply(Result(id=call.id, data=data))

    def _bound(self, name: str, args: Any) -> Callable[..., Any]:
        """The Robot's method ``name`` (:attr:`MethodSpec.call`), or the neck's or servo's
        for a servo command."""
        robot = self._robot
        owner: object = robot
        if isinstance(args, ServoCommand):
            if args.target != "neck":
                owner = robot.servo(int(args.target))
            elif name == "torque" and robot.neck_kind == "worm":
                raise StateError("the worm-gear neck has no torque modes: it holds without power")
            elif name in _HERKULEX_ONLY and robot.neck_kind == "worm":
                raise StateError(
                    "the worm-gear neck is not a HerkuleX servo: it has no registers, status "
                    "bytes, id or zero offset"
                )
            else:
                owner = robot.neck
        method: Callable[..., Any] = getattr(owner, name)
        return method

    # The server's own services: the lease and the settings.

    def _acquire(self, client: _Client, args: AcquireArgs) -> Any:
        source = args.source
        self._check_claim(client, source)
        holder = self._leases.get(source)
        if holder is None or holder is client:
            if holder is None:
                self._set_holder(source, client, f"acquired by {client.peer}")
            return {"holder": client.peer, "you": True, "stolen_from": None, "source": source}
        if not args.steal:
            raise RequestError(
                "lease_held",
                f"the control lease of command source {source} is held by {holder.peer} (for "
                f"{time.monotonic() - holder.leases.get(source, 0.0):.0f} s): acquire "
                "with steal to take it",
            )
        _log.warning(
            "client %s: stole the control lease of command source %s from %s",
            client.peer,
            source,
            holder.peer,
        )
        self._set_holder(source, client, f"stolen by {client.peer} from {holder.peer}")
        return {"holder": client.peer, "you": True, "stolen_from": holder.peer, "source": source}

    def _check_claim(self, client: _Client, source: str) -> None:
        """A client may take the lease of ``source``: one of the Robot's command sources,
        and (beyond loopback) not one of a person or safety layer at the robot.

        Raises:
            RequestError: ``bad_value`` (no such source) or ``source_forbidden``.
        """
        table = self._robot.config.source_table()
        names = [row.name for row in table]
        if source not in names:
            raise RequestError(
                "bad_value",
                f"source={source!r} is not a command source of this robot: allowed "
                f"{', '.join(names)}",
            )
        if not client.loopback and not claimable_beyond_loopback(table, source):
            mine = [name for name in names if claimable_beyond_loopback(table, name)]
            raise RequestError(
                "source_forbidden",
                f"command source {source!r} is for programs on the robot's own computer "
                f"({' and '.join(sorted(LOOPBACK_SOURCES))}, and any above remote): "
                f"{client.peer} is beyond loopback and may take {', '.join(mine)}",
            )

    def _release(self, client: _Client, args: ReleaseArgs) -> Any:
        if args.source is not None and args.source not in client.leases:
            raise RequestError(
                "no_lease",
                f"release of the {args.source} lease: this client does not hold it (it holds "
                f"{', '.join(client.leases) or 'none'})",
            )
        released = [args.source] if args.source is not None else list(client.leases)
        for source in released:
            self._set_holder(source, None, f"released by {client.peer}")
        return {"holder": None, "you": False, "released": released}

    def _set_holder(self, source: str, client: _Client | None, reason: str) -> None:
        """Hand the lease of ``source`` over. The robot stops whenever it changes hands while
        that source drives (or none does): whoever drives next starts from standstill,
        and a driver that left does not leave it moving; a source above it that drives
        goes on."""
        previous = self._leases.pop(source, None)
        if previous is not None:
            previous.leases.pop(source, None)
        if client is not None:
            self._leases[source] = client
            client.leases[source] = time.monotonic()
        if previous is not None:
            self._stop_for(source)
        _log.info("lease of command source %s: %s", source, reason)
        holder = None if client is None else client.peer
        for other in self._clients:
            other.reply(
                LeaseMessage(holder=holder, you=other is client, reason=reason, source=source)
            )

    def _stop_for(self, source: str) -> None:
        """Stop the robot as ``source``, unless another source drives it."""
        active = self._robot.state.active_source
        if active is None or active == source:
            self._robot.stop(source=source)

    def _source_of(self, client: _Client, call: Call, leased: bool, given: str | None) -> str:
        """The command source ``call`` goes as: ``given`` when the client holds its lease,
        else the highest lease it holds; a stop from a client without one goes as the
        lowest source (obeyed, and it takes over from no one above it).

        Raises:
            RequestError: ``no_lease``: a command that needs a lease names a source whose
                lease the client does not hold.
        """
        names = self._source_names()
        held = [name for name in names if name in client.leases]
        if given is not None and given in client.leases:
            return given
        if leased and given is not None:
            holder = self._leases.get(given)
            raise RequestError(
                "no_lease",
                f"{call.method} as command source {given!r} needs the {given} lease: "
                + (f"{holder.peer} holds it" if holder else "acquire it first")
                + f" (this client holds {', '.join(held) or 'none'})",
                call.id,
            )
        return held[0] if held else names[-1]

    def _source_names(self) -> list[str]:
        """The Robot's command sources, highest priority first."""
        return [row.name for row in self._robot.config.source_table()]

    _OWN: Final[dict[str, _OwnCall]] = {
        "config": lambda self, client, args: self._robot.config.model_dump(mode="json"),
        "lease": lambda self, client, args: {
            "holder": self.lease_holder,
            "you": bool(client.leases),
            "leases": self.leases,
            "yours": [name for name in self._source_names() if name in client.leases],
        },
        "acquire": _acquire,
        "release": _release,
        "port": lambda self, client, args: self._robot.port,
        "pid_state": lambda self, client, args: _pid_state(self._robot),
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
        hz = self._shared_stats()[0].streams[topic].requested_hz
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


#: The commands whose effect ``stats`` shows (a rate, a stream on or off, the link): the
#: shared figures are computed again after them.
def _pid_state(robot: Robot) -> dict[str, Any]:
    """The ``pid_state`` service: both wheels' gains, and which PIDs run."""
    enabled = robot.controllers_enabled()
    return pid_state_json(
        robot.get_pid(wheel="left"),
        robot.get_pid(wheel="right"),
        (enabled["left"], enabled["right"]),
    )


_CHANGES_STATS: Final = frozenset(
    {"set_rate", "enable_stream", "release_port", "reclaim_port", "connect", "disconnect"}
)
#: One of the server's own services: (server, client, args) → result data.
_OwnCall = Callable[["RobotServer", "_Client", Any], Any]


#: The longest frame that may be a stop call and so skips the readers' budget.
_STOP_FRAME_BYTES = 200


def _may_stop(frame: str | bytes, size: int) -> bool:
    """Whether a frame may be a ``stop`` or ``estop`` call: short, and naming one."""
    if size > _STOP_FRAME_BYTES:
        return False
    text = frame if isinstance(frame, str) else frame.decode(errors="replace")
    return '"stop"' in text or '"estop"' in text


def _robot_refusal(call: Call, exc: OhmniError) -> RequestError:
    """What the Robot raised, as the ``error`` for the client: a bad value, a state that
    does not allow it, or another failure (a device that did not answer …)."""
    if isinstance(exc, InvalidArgumentError):
        code: ErrorCode = "bad_value"
    elif isinstance(exc, StateError):
        code = "robot_state"
    else:
        code = "robot_error"
    return RequestError(code, f"{call.method}: {exc}", call.id, raised=exc)


def _limit(value: float) -> float | None:
    """A speed limit for JSON: ``None`` for none (infinity)."""
    return None if math.isinf(value) else value


#: The Robot-side queue of a pump: it only falls behind when the event loop itself does.
_PUMP_QUEUE = 256


class _Pump:
    """One topic: the Robot's subscription, fanned out to every client's queue."""

    def __init__(self, topic: str, subscription: SampleStream[Any]) -> None:
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
        # Before any sample: the first one goes, and the cap counts from it (a clock that
        # starts near 0, as a virtual one, would otherwise let the second follow too soon).
        self.next_due_s = -math.inf
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
        #: The command sources whose lease it holds, each with when it took it (monotonic).
        self.leases: dict[str, float] = {}
        #: On the robot's own computer (loopback, a unix socket): it may take every source.
        self.loopback = _is_local_peer(ws)
        #: Its messages refused, logged at most once per REFUSAL_LOG_S.
        self.refusals = _Throttled(REFUSAL_LOG_S)
        #: Its messages left unhandled: read after its connection closed.
        self.unhandled = 0

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
        self.reply_frame(encode(message))

    def reply_frame(self, frame: str) -> None:
        """A message already encoded."""
        if len(self._outbox) >= _MAX_OUTBOX:
            self.overflowed = True
            return
        self._outbox.append(frame)
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


class _Budget:
    """Work shared by many: ``rate_per_s`` units a second, ``burst`` at once; a caller
    beyond it is told how long to wait for its turn, in the order of asking (a virtual
    schedule: each reservation takes the next free units, so waiting costs no work)."""

    def __init__(
        self, rate_per_s: float, burst: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self._unit_s = 1.0 / rate_per_s
        self._tolerance_s = (burst - 1) * self._unit_s
        self._clock = clock
        self._free_at = -math.inf

    def reserve(self, units: int = 1) -> float:
        """Take ``units``; the seconds to wait before using them (0: now)."""
        now = self._clock()
        start = max(self._free_at, now)
        self._free_at = start + units * self._unit_s
        return max(0.0, self._free_at - self._unit_s - self._tolerance_s - now)


class _Throttled:
    """A kind of refusal, logged at most once per ``interval_s``: the first at once, the
    ones after it counted and told in one line when the interval ends."""

    def __init__(self, interval_s: float) -> None:
        self._interval_s = interval_s
        #: Every one noted.
        self.total = 0
        self._quiet_until = -math.inf
        self._held = 0
        self._last: tuple[logging.Logger, str, tuple[object, ...]] | None = None
        self._timer: asyncio.TimerHandle | None = None

    def note(self, logger: logging.Logger, message: str, *args: object) -> bool:
        """Count one; log it unless one was logged within the interval. Whether logged."""
        self.total += 1
        now = time.monotonic()
        if now >= self._quiet_until:
            self._quiet_until = now + self._interval_s
            logger.warning(message, *args)
            return True
        self._held += 1
        self._last = (logger, message, args)
        if self._timer is None:
            try:
                loop = asyncio.get_running_loop()
            except RuntimeError:  # no loop in this thread: told with the next line instead
                return False
            self._timer = loop.call_later(self._quiet_until - now, self._tell)
        return False

    def _tell(self) -> None:
        self._timer = None
        if self._last is None or not self._held:
            return
        logger, message, args = self._last
        logger.warning(
            f"%d more since (%d in all); the last: {message}", self._held, self.total, *args
        )
        self._held = 0
        self._last = None
        self._quiet_until = time.monotonic() + self._interval_s

    def close(self) -> None:
        """Tell what is held now (leaving)."""
        if self._timer is not None:
            self._timer.cancel()
        self._tell()


class _AcceptFailures(logging.Filter):
    """asyncio's own report of ``accept()`` failing for want of file descriptors (on the
    ``asyncio`` logger, with a traceback, up to 100 times per wake-up of a listening
    socket): replaced by one line of ours, at most once per interval, with the count."""

    _MESSAGE = "socket.accept() out of system resource"

    def __init__(self, interval_s: float) -> None:
        super().__init__()
        self._throttled = _Throttled(interval_s)

    @property
    def total(self) -> int:
        return self._throttled.total

    def filter(self, record: logging.LogRecord) -> bool:
        if not isinstance(record.msg, str) or not record.msg.startswith(self._MESSAGE):
            return True
        exc = record.exc_info[1] if record.exc_info else None
        self._throttled.note(
            _log,
            "accept() failed (%s): this process is out of file descriptors (ulimit -n); "
            "new clients wait in the kernel's queue",
            exc.strerror if isinstance(exc, OSError) else "out of system resources",
        )
        return False

    def close(self) -> None:
        self._throttled.close()


class _Doorkeeper:
    """Who may come in: room for one more client (``max_clients``, fitted to the files
    the process may open), a browser's origin, then the token — checked in the
    handshake, a refusal an HTTP error before any WebSocket exists."""

    def __init__(
        self,
        max_clients: int,
        token: str | None,
        origins: tuple[str, ...],
        web: WebConsole | None = None,
    ) -> None:
        self.max_clients = max_clients
        self._token = token
        self._origins = origins
        self._web = web
        #: Connections admitted (the handshake's checks passed) and not yet gone.
        self._admitted: set[ServerConnection] = set()
        #: TCP connections open: from accepted until closed.
        self._tcp_connections = 0
        self._over_cap = _Throttled(REFUSAL_LOG_S)
        #: ``accept()`` failures, counted and logged from asyncio's log (a filter).
        self.accept_failures = _AcceptFailures(REFUSAL_LOG_S)

    @property
    def refused(self) -> int:
        """Connections refused over the cap, and ``accept()`` failures."""
        return self._over_cap.total + self.accept_failures.total

    def fit_descriptors(self) -> None:
        """Lower ``max_clients`` so that every client, the handshakes beyond and a reserve
        fit the files this process may open: a full server then refuses with 503 instead
        of failing ``accept()`` with the whole process out of descriptors."""
        room = _descriptors_free()
        if room is None:
            return
        fits = room - _FD_RESERVE - _HANDSHAKE_SLACK
        if fits < 1:
            raise ConfigError(
                f"this process may open {room} more files, too few to serve a client and "
                f"keep {_FD_RESERVE + _HANDSHAKE_SLACK} in reserve: raise ulimit -n"
            )
        if fits < self.max_clients:
            _log.warning(
                "serving at most %d clients instead of %d: this process may open %d more "
                "files (ulimit -n), %d of them kept in reserve",
                fits,
                self.max_clients,
                room,
                _FD_RESERVE + _HANDSHAKE_SLACK,
            )
            self.max_clients = fits

    def tcp_opened(self) -> bool:
        """One more TCP connection accepted: whether it fits (clients, handshakes and the
        closing ones together, at most ``max_clients`` + :data:`_HANDSHAKE_SLACK`)."""
        self._tcp_connections += 1
        if self._tcp_connections <= self.max_clients + _HANDSHAKE_SLACK:
            return True
        self._over_cap.note(
            _log,
            "connections closed at once: %d clients and %d handshakes already "
            "(ohmni serve --max-clients)",
            self.max_clients,
            _HANDSHAKE_SLACK,
        )
        return False

    def tcp_closed(self) -> None:
        self._tcp_connections -= 1

    def admit(self, connection: ServerConnection, request: Request) -> Response | None:
        """The handshake's checks: room for one more client, a browser's origin, then the
        token. A refusal is an HTTP error before any WebSocket exists, logged with the peer
        (over the cap: at most once per :data:`REFUSAL_LOG_S`)."""
        peer = _peer(connection)
        if len(self._admitted) >= self.max_clients:
            self._over_cap.note(
                _log,
                f"connections refused (503): {self.max_clients} clients connected, the "
                "most this daemon serves (ohmni serve --max-clients); the last from %s",
                peer,
            )
            return connection.respond(
                503, f"this daemon serves at most {self.max_clients} clients: try again later\n"
            )
        origin = request.headers.get("Origin")
        if not check_origin(origin, self._origins) and not (
            self._web is not None and self._web.own_origin(request)
        ):
            _log.warning("client %s: refused: origin %r is not allowed", peer, origin)
            return connection.respond(
                403, f"origin {origin} is not allowed (ohmni serve --allow-origin)\n"
            )
        if self._token is not None:
            given = presented_token(
                request.path,
                request.headers.get("Authorization"),
                ",".join(request.headers.get_all("Sec-WebSocket-Protocol")),
            )
            if not check_token(given, self._token):
                _log.warning(
                    "client %s: refused: %s token", peer, "no" if given is None else "a wrong"
                )
                return connection.respond(
                    401,
                    "this daemon needs its token: Authorization: Bearer <token>, or ?token=\n",
                )
        # Counted from here until its TCP connection is gone, handshake failed or not.
        self._admitted.add(connection)
        connection.connection_lost_waiter.add_done_callback(
            lambda _: self._admitted.discard(connection)
        )
        return None

    def close(self) -> None:
        self._over_cap.close()
        self.accept_failures.close()


def _capped_connection(door: _Doorkeeper) -> Any:
    """websockets' connection class, closing a TCP connection as soon as it is accepted
    when ``max_clients`` and the handshakes beyond are all taken: it then holds no file
    descriptor while it would wait for its handshake."""
    from websockets.asyncio.server import ServerConnection  # noqa: PLC0415

    class CappedConnection(ServerConnection):
        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            super().connection_made(transport)
            if not door.tcp_opened():
                self.transport.abort()

        def connection_lost(self, exc: Exception | None) -> None:
            door.tcp_closed()
            super().connection_lost(exc)

    return CappedConnection


def _select_subprotocol(
    connection: ServerConnection, offered: Sequence[Subprotocol]
) -> Subprotocol | None:
    """``ohmni`` when offered (the web console offers it, with the token beside it), else
    none: programs offer none. The token's own subprotocol is never picked, so never
    sent back."""
    for name in offered:
        if name == WEB_PROTOCOL:
            return name
    return None


def _descriptors_free() -> int | None:
    """How many more files this process may open (``ulimit -n`` less those open), or
    ``None`` when there is no limit or it cannot be told."""
    try:
        import resource  # noqa: PLC0415  # POSIX only

        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft == resource.RLIM_INFINITY:
            return None
        open_now = len(os.listdir("/proc/self/fd"))  # the listing's own counted: one spare
    except (ImportError, OSError):
        return None
    return int(soft) - open_now


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
    if token is not None and len(token) < MIN_TOKEN_CHARS:
        raise ConfigError(
            f"a daemon token of {len(token)} characters is too easy to guess: at least "
            f"{MIN_TOKEN_CHARS} (load_or_create_token() makes one)"
        )
    if token is None and not is_loopback(host):
        raise ConfigError(
            f"refusing to listen on {host!r} without a token: beyond loopback (127.0.0.1, "
            "::1, localhost) every client must present one (ohmni serve makes it)"
        )


def _is_local_peer(connection: ServerConnection) -> bool:
    """Whether ``connection`` comes from this computer: a loopback address (an IPv4 one
    mapped into IPv6 included), or a unix socket (no address)."""
    address = connection.remote_address
    if not isinstance(address, tuple):
        return True
    try:
        ip = ipaddress.ip_address(str(address[0]).split("%")[0])
    except ValueError:
        return False
    mapped = getattr(ip, "ipv4_mapped", None)
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


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
