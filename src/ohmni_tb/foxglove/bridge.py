"""The Foxglove app's live view of a Robot: the SDK's WebSocket server on every stream.

::

    async with Robot.open("sim://") as robot, FoxgloveBridge(robot) as bridge:
        print(bridge.url)                             # ws://127.0.0.1:8765
        await asyncio.Event().wait()                  # until cancelled

The server is foxglove-sdk's own (``foxglove.start_server``): it runs in the SDK's
threads, speaks the Foxglove WebSocket protocol (subprotocol ``foxglove.sdk.v1``) and
advertises the channels of :data:`~ohmni_tb.foxglove.channels.CHANNELS`. The bridge
reads the Robot's streams in its own tasks, through bounded subscriptions, and encodes
a sample only for channels a client subscribed to: with nobody connected it costs the
wake-ups alone. The SDK keeps a bounded queue per client (``message_backlog``) and drops
that client's oldest messages when it reads too slowly; nothing waits for a client.

Every client may watch. With a ``teleop`` or a writable ``control``, a client drives, sets
parameters and calls services only after unlocking control for itself with the token
(:mod:`ohmni_tb.foxglove.access`): the protocol has no authentication of its own.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import math
import threading
import time
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Any, Final, TypeVar

import foxglove
from foxglove.websocket import (
    Capability,
    Client,
    ClientChannel,
    MessageSchema,
    Parameter,
    ParameterType,
    ServerListener,
    Service,
    ServiceRequest,
    ServiceSchema,
    StatusLevel,
    WebSocketServer,
)

from ohmni_tb._checks import integer
from ohmni_tb.errors import ConfigError, OhmniError, TransportError
from ohmni_tb.foxglove._pump import DEFAULT_QUEUE, ChannelStats, Pump
from ohmni_tb.foxglove.access import (
    LOCKED_MESSAGE,
    LOCKED_STATUS_ID,
    UNLOCK_SCHEMAS,
    UNLOCK_SERVICE,
    AccessStats,
    ControlGate,
)
from ohmni_tb.foxglove.control import SERVICE_SCHEMAS, RobotControl

if TYPE_CHECKING:
    from ohmni_tb.robot import Robot

__all__ = [
    "DEFAULT_BACKLOG",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "TELEOP_RAMPED",
    "TELEOP_TOPICS",
    "FoxgloveBridge",
    "Teleop",
    "parse_twist",
]

_log = logging.getLogger("ohmni_tb.foxglove")
_T = TypeVar("_T")

#: Topics the Foxglove Teleop panel publishes ``geometry_msgs/Twist`` on (JSON), each with
#: whether its Twists go through the acceleration limits (``Robot.drive``'s ``ramped``):
#: tb_control's ``/tb_cmd_vel`` is the pure velocity command and ``/cmd_vel_accel`` the
#: acceleration-limited one; the panel's default ``/cmd_vel`` is ramped, as a person's
#: button presses want.
TELEOP_RAMPED: Final[dict[str, bool]] = {
    "/tb_cmd_vel": False,
    "/cmd_vel_accel": True,
    "/cmd_vel": True,
}
#: Topics the Foxglove Teleop panel publishes ``geometry_msgs/Twist`` on (JSON).
TELEOP_TOPICS: Final = tuple(TELEOP_RAMPED)
#: What the bridge calls, on the event loop, with each Twist: (linear m/s, angular rad/s,
#: ramped: :data:`TELEOP_RAMPED` of its topic).
Teleop = Callable[[float, float, bool], None]


def parse_twist(data: bytes) -> tuple[float, float]:
    """``linear.x`` and ``angular.z`` of a ``geometry_msgs/Twist`` in JSON.

    Raises:
        ValueError: Not JSON, not a Twist, or a value that is not a finite number.
    """
    twist = json.loads(data)
    try:
        linear, angular = twist["linear"]["x"], twist["angular"]["z"]
    except (KeyError, TypeError) as exc:
        raise ValueError(f"not a geometry_msgs/Twist: {data[:80]!r}") from exc
    for name, value in (("linear.x", linear), ("angular.z", angular)):
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            raise ValueError(f"{name} must be a finite number, not {value!r}")
    return float(linear), float(angular)


class _Listener(ServerListener):
    """What Foxglove clients send: Twists on :data:`TELEOP_TOPICS` (with a teleop),
    parameter reads and writes (with a control), each change only from a client the gate
    unlocked. The SDK calls this from its own threads: a Twist is handed to the event
    loop; a parameter request waits for the loop's answer (at most
    :data:`_CALL_TIMEOUT_S`)."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        teleop: Teleop | None,
        control: RobotControl,
        gate: ControlGate | None,
    ) -> None:
        self._loop = loop
        self._teleop = teleop
        self._control = control
        self._gate = gate
        # The clients' Twist channels, each with whether its topic is ramped.
        self._channels: dict[tuple[int, int], bool] = {}
        self._values: tuple[float, dict[str, float]] | None = None
        self._values_lock = threading.Lock()
        self.server: WebSocketServer | None = None

    def on_client_advertise(self, client: Client, channel: ClientChannel) -> None:
        if self._teleop is not None and channel.topic in TELEOP_TOPICS:
            if channel.encoding != "json":
                self._status(f"{channel.topic}: only JSON Twists are taken, not {channel.encoding}")
                return
            self._channels[client.id, channel.id] = TELEOP_RAMPED[channel.topic]

    def on_client_unadvertise(self, client: Client, client_channel_id: int) -> None:
        self._channels.pop((client.id, client_channel_id), None)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        ramped = self._channels.get((client.id, client_channel_id))
        if self._teleop is None or ramped is None:
            return
        gate = self._gate
        if gate is not None and not gate.allows(client.id):
            if gate.ignore_twist(client.id):  # counted; told once
                self._status(LOCKED_MESSAGE, status_id=LOCKED_STATUS_ID)
            return
        try:
            linear, angular = parse_twist(data)
        except ValueError as exc:
            self._status(f"twist refused: {exc}")
            return
        self._loop.call_soon_threadsafe(self._teleop, linear, angular, ramped)

    def on_get_parameters(
        self, client: Client, param_names: list[str], request_id: str | None = None
    ) -> list[Parameter]:
        try:
            values = self._parameters(fresh=False)
        except Exception as exc:  # told to the client, never raised into the SDK
            self._status(f"parameters unavailable: {exc}")
            return []
        wanted = set(param_names) or set(values)
        return [
            Parameter(name, value=value, type=ParameterType.Float64)
            for name, value in values.items()
            if name in wanted
        ]

    def on_set_parameters(
        self, client: Client, parameters: list[Parameter], request_id: str | None = None
    ) -> list[Parameter]:
        values = {parameter.name: parameter.get_value() for parameter in parameters}
        gate = self._gate
        tried = False
        if gate is not None and self._control.writable and not gate.allows(client.id):
            self._status(str(gate.refuse_change("parameters not set")), StatusLevel.Error)
        else:
            try:
                tried = True
                _on_loop(self._loop, self._control.set_parameters(values))
            except Exception as exc:  # told to the client, never raised into the SDK
                self._status(f"parameters not set: {exc}", StatusLevel.Error)
        # The values now, set or not: the app shows what the robot runs with (read anew
        # only after a change was tried: a locked client asking in a loop costs nothing).
        names = {parameter.name for parameter in parameters}
        try:
            now = self._parameters(fresh=tried)
        except Exception as exc:  # told to the client, never raised into the SDK
            self._status(f"parameters unavailable: {exc}")
            return []
        return [
            Parameter(name, value=value, type=ParameterType.Float64)
            for name, value in now.items()
            if name in names
        ]

    def _parameters(self, *, fresh: bool) -> dict[str, float]:
        """The values, read on the event loop, or those read less than
        :data:`_PARAMETERS_FRESH_S` ago (unless ``fresh``): a client asking in a loop
        costs the robot, or the daemon's connection, a few reads a second."""
        with self._values_lock:
            kept = self._values
        if not fresh and kept is not None and time.monotonic() - kept[0] < _PARAMETERS_FRESH_S:
            return kept[1]
        values = _on_loop(self._loop, self._control.parameters())
        with self._values_lock:
            self._values = (time.monotonic(), values)
        return values

    def service(self, name: str) -> Service:
        """The SDK's service ``name``, answered by the control on the event loop."""
        request, response = SERVICE_SCHEMAS[name]

        def handle(call: ServiceRequest) -> bytes:
            try:
                if self._gate is not None and not self._gate.allows(call.client_id):
                    raise self._gate.refuse_change(name)
                return _on_loop(self._loop, self._control.call(name, call.payload))
            except OhmniError as exc:
                _log.warning("foxglove service %s refused: %s", name, exc)
                raise  # the SDK answers the client with the message
            except TimeoutError as exc:
                raise TimeoutError(f"{name}: the robot did not answer in time") from exc

        return _service(name, request, response, handle)

    def unlock_service(self, gate: ControlGate) -> Service:
        """:data:`~ohmni_tb.foxglove.access.UNLOCK_SERVICE`, answered in the SDK's thread
        (it needs nothing of the loop)."""

        def handle(call: ServiceRequest) -> bytes:
            try:
                answer = gate.unlock(call.client_id, call.payload)
            except OhmniError as exc:
                _log.warning("foxglove client %d: %s", call.client_id, exc)
                raise  # the SDK answers the client with the message
            _log.info("foxglove client %d unlocked control", call.client_id)
            return answer

        return _service(UNLOCK_SERVICE, *UNLOCK_SCHEMAS, handle)

    def _status(
        self,
        message: str,
        level: StatusLevel = StatusLevel.Warning,
        *,
        status_id: str | None = None,
    ) -> None:
        _log.warning("foxglove: %s", message)
        if self.server is not None:
            self.server.publish_status(message, level, status_id)


def _service(
    name: str,
    request: dict[str, Any],
    response: dict[str, Any],
    handle: Callable[[ServiceRequest], bytes],
) -> Service:
    """An SDK service with JSON request and response schemas."""

    def schema(part: str, body: dict[str, Any]) -> MessageSchema:
        return MessageSchema(
            encoding="json",
            schema=foxglove.Schema(
                name=f"{name}/{part}", encoding="jsonschema", data=json.dumps(body).encode()
            ),
        )

    return Service(
        name,
        schema=ServiceSchema(
            name, request=schema("Request", request), response=schema("Response", response)
        ),
        handler=handle,
    )


#: How long an SDK thread waits for the event loop to answer a parameter request or a
#: service call.
_CALL_TIMEOUT_S: Final = 5.0
#: Parameter values this recent answer a read: every read asks the Robot (through the
#: daemon, three messages), and any client, locked or not, may read.
_PARAMETERS_FRESH_S: Final = 0.2


def _on_loop(loop: asyncio.AbstractEventLoop, coro: Coroutine[Any, Any, _T]) -> _T:
    """Run ``coro`` on ``loop`` from another thread and wait for its result."""
    future = asyncio.run_coroutine_threadsafe(coro, loop)
    try:
        return future.result(_CALL_TIMEOUT_S)
    except concurrent.futures.TimeoutError:
        future.cancel()
        raise TimeoutError(f"no answer within {_CALL_TIMEOUT_S:g} s") from None


#: Loopback: the Foxglove protocol has no authentication, so the default is this machine.
DEFAULT_HOST: Final = "127.0.0.1"
#: The Foxglove app's default connection (ws://localhost:8765); ``ohmni serve`` uses 8766.
DEFAULT_PORT: Final = 8765
#: Messages the SDK queues per client before it drops that client's oldest: 2 s of every
#: stream (about 500 messages a second when a client subscribes to all of them).
DEFAULT_BACKLOG: Final = 1024


class _Served:
    """A Foxglove server's address (the bridge's and the replay's)."""

    _host: str
    _port: int

    @property
    def port(self) -> int:
        """The TCP port (the one chosen, when 0 was asked)."""
        return self._port

    @property
    def url(self) -> str:
        """``ws://host:port``: the Foxglove app's "Foxglove WebSocket" connection."""
        host = f"[{self._host}]" if ":" in self._host else self._host
        return f"ws://{host}:{self._port}"

    def _listen(self, **options: Any) -> WebSocketServer:
        """``foxglove.start_server`` on this address; the port it got is kept.

        Raises:
            TransportError: The address cannot be bound (in use, not this machine's).
        """
        try:
            server = foxglove.start_server(host=self._host, port=self._port, **options)
        except RuntimeError as exc:  # the SDK's FoxgloveError: "Failed to bind port: …"
            reason = str(exc).removeprefix("FoxgloveError: ").removeprefix("Failed to bind port: ")
            raise TransportError(f"cannot listen on {self.url}: {reason}") from exc
        self._port = server.port
        return server


class FoxgloveBridge(_Served):
    """Serves an open Robot's streams to the Foxglove app (an async context manager).

    Args:
        robot: An open :class:`~ohmni_tb.Robot`, or a daemon's
            :class:`~ohmni_tb.client.RobotClient` (its stamps are the daemon's clock, the
            same monotonic clock when it runs on this machine).
        host: Address to listen on. Beyond loopback anyone who reaches the port can watch:
            the protocol has no authentication.
        port: TCP port; 0 picks a free one (see :attr:`port`).
        name: The server's name, shown by the app.
        message_backlog: Messages queued per client before its oldest are dropped.
        queue: Samples each stream's subscription holds before its oldest are dropped.
        teleop: Take ``geometry_msgs/Twist`` (JSON) that unlocked Foxglove clients
            publish on :data:`TELEOP_TOPICS` (the Teleop panel) and call this with
            ``linear.x``, ``angular.z`` and whether the topic is ramped
            (:data:`TELEOP_RAMPED`) on the event loop; ``None`` (default):
            read-only, clients may not publish. It is the caller's to decide what a Twist
            may move and how often (``ohmni serve --foxglove-control`` coalesces them and
            goes through the daemon's control lease:
            :class:`~ohmni_tb.foxglove.teleop.FoxgloveTeleop`).
        control: The parameters and services (:mod:`ohmni_tb.foxglove.control`): a
            writable :class:`~ohmni_tb.foxglove.control.RobotControl` lets unlocked
            clients set parameters and call the services; ``None`` (default): the
            parameters can be read, not set, and no service is offered.
        token: Needed with a ``teleop`` or a writable ``control``: a client unlocks
            control for itself by calling ``/tb_control/unlock`` with it
            (:mod:`ohmni_tb.foxglove.access`); until then its Twists are ignored
            (counted, and told once) and its changes refused.

    Raises:
        OutOfRangeError: ``port`` not 0..65535, or ``message_backlog`` / ``queue`` not
            1..100000.
        ConfigError: Control offered without a token, or a token shorter than 16
            characters.
    """

    def __init__(
        self,
        robot: Robot,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        name: str = "ohmni_tb",
        message_backlog: int = DEFAULT_BACKLOG,
        queue: int = DEFAULT_QUEUE,
        teleop: Teleop | None = None,
        control: RobotControl | None = None,
        token: str | None = None,
    ) -> None:
        self._robot = robot
        self._control = control if control is not None else RobotControl(robot)
        self._gate: ControlGate | None = None
        if teleop is not None or self._control.writable:
            if token is None:
                raise ConfigError(
                    "a Foxglove server that takes control needs a token: "
                    "FoxgloveBridge(..., token=...); a client unlocks control with it "
                    f"({UNLOCK_SERVICE}), since the protocol has no authentication"
                )
            self._gate = ControlGate(token)
        self._host = host
        self._port = integer("port", port, 0, 65535)
        self._name = name
        self._backlog = integer("message_backlog", message_backlog, 1, 100_000)
        self._queue = integer("queue", queue, 1, 100_000)
        self._teleop = teleop
        self._context = foxglove.Context()
        self._pump: Pump | None = None
        self._server: WebSocketServer | None = None
        self._closed = False

    @property
    def host(self) -> str:
        """The address it listens on."""
        return self._host

    @property
    def app_url(self) -> str | None:
        """A link that opens this server in the Foxglove web app (``None`` once closed)."""
        return None if self._server is None else self._server.app_url()

    @property
    def channel_ids(self) -> dict[str, int]:
        """Each topic's channel id, as the server advertises it."""
        return {} if self._pump is None else self._pump.channel_ids

    def stats(self) -> dict[str, ChannelStats]:
        """Every channel's figures, by topic (messages go out only while a client listens)."""
        return {} if self._pump is None else self._pump.stats()

    def access_stats(self) -> AccessStats | None:
        """Clients unlocked, and what locked clients sent that was refused (``None``: the
        server takes no control)."""
        return None if self._gate is None else self._gate.stats()

    async def start(self) -> None:
        """Make the channels, listen, and start reading the streams.

        Raises:
            TransportError: The address cannot be bound (in use, not this machine's).
        """
        # The channels exist before the server, so a client sees them all at once.
        self._pump = Pump(self._robot, self._context, queue=self._queue)
        listener = _Listener(asyncio.get_running_loop(), self._teleop, self._control, self._gate)
        capabilities = [Capability.Parameters]
        if self._teleop is not None:
            capabilities.append(Capability.ClientPublish)
        services = [listener.service(name) for name in self._control.services]
        if self._gate is not None:
            services.insert(0, listener.unlock_service(self._gate))
        if services:
            capabilities.append(Capability.Services)
        try:
            self._server = self._listen(
                name=self._name,
                context=self._context,
                message_backlog_size=self._backlog,
                capabilities=capabilities,
                supported_encodings=["json"],
                server_listener=listener,
                services=services or None,
            )
        except TransportError:
            await self._pump.aclose()
            raise
        listener.server = self._server
        self._pump.start()

    async def aclose(self) -> None:
        """Stop reading the streams, close the clients, stop listening. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._pump is not None:
            await self._pump.aclose()
        if self._server is not None:
            # Off the loop: an SDK thread may be waiting for the loop to answer a call.
            server, self._server = self._server, None
            await asyncio.to_thread(server.stop)

    async def __aenter__(self) -> FoxgloveBridge:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
