"""The daemon on an MQTT broker: the robot's state and streams out, commands in.

::

    async with Robot.open("sim://") as robot, RobotServer(robot, port=0) as server:
        async with MqttBridge(robot, server, robot_id="kitchen"):   # robot.config.mqtt_url
            await asyncio.Event().wait()

The bridge is a client of the daemon like any other (:class:`~ohmni_tb.daemon.local.
LocalClient`): a command goes through the daemon's dispatch, its checks and its control
lease — taken for a command that needs it and released when the last such command ends
(the wheels stop, as whenever the lease changes hands), refused when another client
holds it. Driving (``drive_distance``, ``rotate``) is refused unless ``mqtt_drive``;
stopping is always allowed.

Losing the broker never holds the robot back: the bridge's work is a few small tasks
on the daemon's event loop (the streams sampled at their ``mqtt_rates``, the state once a
second), its queues are bounded (the oldest dropped and counted, in the state's
``bridge`` figures), and it reconnects with a growing back-off
(:class:`~ohmni_tb.mqtt.broker.Backoff`). A command that holds the lease when the broker
goes away ends: the lease is released and the wheels stop (as when a WebSocket driver
leaves), since nobody could stop it over MQTT any more.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import time
from collections import deque
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb._ratelimit import TokenBucket
from ohmni_tb._version import __version__
from ohmni_tb.daemon.local import LocalClient
from ohmni_tb.daemon.server import MAX_MESSAGE_BYTES
from ohmni_tb.errors import ConfigError, OhmniError
from ohmni_tb.mqtt.broker import Backoff, Broker, require_client
from ohmni_tb.mqtt.payloads import (
    AVAILABILITY,
    COMMAND,
    COMMANDS,
    HA_LIGHT,
    OFFLINE,
    ONLINE,
    RESPONSE,
    STATE,
    STATE_PERIOD_S,
    STREAM,
    BatteryState,
    BridgeFigures,
    ErrorReply,
    NeckState,
    ResultReply,
    StatePayload,
    discovery_messages,
    ha_light_args,
    response_topic_allowed,
    robot_topic,
    state_key,
)
from ohmni_tb.robot.samples import STREAM_NAMES
from ohmni_tb.robot.wire import RequestError, sample_json

if TYPE_CHECKING:
    import aiomqtt

    from ohmni_tb.daemon.server import RobotServer
    from ohmni_tb.robot import Robot

__all__ = ["COMMANDS_AT_ONCE", "COMMANDS_PER_S", "MqttBridge", "default_robot_id"]

_log = logging.getLogger("ohmni_tb.mqtt")

#: Stream samples waiting for the broker; beyond, the oldest is dropped and counted.
_SAMPLE_QUEUE: Final = 256
#: Replies waiting for the broker; beyond, the oldest is dropped and counted.
_REPLY_QUEUE: Final = 64
#: Command messages the client holds unread; beyond, they are dropped and counted.
_INCOMING_QUEUE: Final = 64
#: Commands running at once (a motion goal runs for seconds); beyond, refused (busy).
COMMANDS_AT_ONCE: Final = 8
#: Commands a second the bridge takes (a burst of as many at once); beyond, refused.
#: Stopping is never refused.
COMMANDS_PER_S: Final = 20.0
#: How often the state is looked at for a change, s.
_STATE_LOOK_S: Final = 1.0
#: How long leaving waits to say ``offline`` and disconnect, s.
_LEAVE_S: Final = 2.0
#: A connection held this long resets the back-off (one that drops at once does not).
_HELD_S: Final = 5.0
#: The commands stopping needs: never refused as busy.
_STOPS: Final = frozenset({"stop", "estop"})


def default_robot_id() -> str:
    """This computer's host name (its first label), as a ``robot_id``: characters other
    than letters, digits, ``-`` and ``_`` become ``-``; ``ohmni`` when there is none."""
    name = socket.gethostname().split(".")[0]
    cleaned = "".join(c if c.isascii() and (c.isalnum() or c in "-_") else "-" for c in name)
    return cleaned[:64] or "ohmni"


class MqttBridge:
    """Publishes a served robot on an MQTT broker and takes commands from it (module
    docstring). An async context manager: :meth:`start` and :meth:`aclose`.

    Args:
        robot: The daemon's open Robot.
        server: The daemon's server (started): commands go through its dispatch.
        broker: The broker; default: from the Robot's settings (``mqtt_url`` …).
        robot_id: The robot's name on the broker; default: ``robot_id``, else the host
            name (:func:`default_robot_id`).

    Raises:
        ConfigError: No broker, a ``mqtt_rates`` stream that does not exist, or the mqtt
            extra is not installed.
    """

    def __init__(
        self,
        robot: Robot,
        server: RobotServer,
        *,
        broker: Broker | None = None,
        robot_id: str | None = None,
    ) -> None:
        require_client()
        config = robot.config
        self._robot = robot
        self._server = server
        self._broker = broker or Broker.from_config(config)
        self.robot_id = robot_id or config.robot_id or default_robot_id()
        self._rates = config.mqtt_streams()
        unknown = sorted(set(self._rates) - set(STREAM_NAMES))
        if unknown:
            raise ConfigError(
                f"mqtt_rates={config.mqtt_rates!r} names no stream {', '.join(unknown)}: the "
                f"streams are {', '.join(STREAM_NAMES)}"
            )
        self._drive = config.mqtt_drive
        self._discovery = config.mqtt_discovery
        self._prefix = config.mqtt_discovery_prefix
        self._availability = robot_topic(self.robot_id, AVAILABILITY)
        self._state_topic = robot_topic(self.robot_id, STATE)
        self._response = robot_topic(self.robot_id, RESPONSE)
        self._local: LocalClient | None = None
        self._main: asyncio.Task[None] | None = None
        self._stop = asyncio.Event()
        self._connected = asyncio.Event()
        # What waits for the broker: the state (the newest wins), replies, samples.
        self._state_pending: bytes | None = None
        self._replies: deque[tuple[str, bytes, bytes | None]] = deque()
        self._samples: deque[tuple[str, bytes]] = deque()
        self._ready = asyncio.Event()
        self._state_due = asyncio.Event()
        self._last_state_key: tuple[Any, ...] | None = None
        self._last_state_at = -float("inf")
        self._firmware: dict[str, str] | None = None
        self._light = (0, 0, 255)
        self._running: set[asyncio.Task[None]] = set()
        self._lease_users = 0
        self._bucket = TokenBucket(COMMANDS_PER_S, int(COMMANDS_PER_S))
        #: Counts for the state's ``bridge`` figures.
        self.connects = 0
        self.published = 0
        self.dropped = 0
        self.commands = 0
        self.refused = 0

    @property
    def connected(self) -> bool:
        """Whether the bridge is connected to the broker now."""
        return self._connected.is_set()

    def figures(self) -> BridgeFigures:
        """What the bridge did so far (also in the state's ``bridge``)."""
        return BridgeFigures(
            connects=self.connects,
            published=self.published,
            dropped=self.dropped,
            commands=self.commands,
            refused=self.refused,
        )

    async def wait_connected(self) -> None:
        """Until the bridge is connected to the broker (and said ``online``)."""
        await self._connected.wait()

    async def start(self) -> None:
        """Join the daemon as a client and start connecting (in the background)."""
        self._local = LocalClient(self._server, f"mqtt:{self.robot_id}")
        self._local.on_lease = lambda _message: self._state_due.set()
        self._main = asyncio.get_running_loop().create_task(
            self._run(), name=f"ohmni-mqtt {self.robot_id}"
        )
        _log.info("MQTT: robot %s on %s", self.robot_id, self._broker.url)

    async def aclose(self) -> None:
        """Say ``offline``, disconnect, leave the daemon (releasing the lease if held).
        Idempotent."""
        self._stop.set()
        main, self._main = self._main, None
        if main is not None:
            try:
                async with asyncio.timeout(_LEAVE_S + 1.0):
                    await asyncio.shield(main)
            except TimeoutError:
                main.cancel()
                # Never longer than that again: a broker connection stuck in its own
                # goodbye must not keep the daemon from closing (and stopping the wheels).
                await asyncio.wait({main}, timeout=_LEAVE_S)
                if not main.done():
                    _log.warning("MQTT: the broker connection did not close; left behind")
        if self._local is not None:
            self._local.close()

    async def __aenter__(self) -> MqttBridge:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    # -- the tasks -----------------------------------------------------------------------------

    async def _run(self) -> None:
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._watch_state(), name="ohmni-mqtt state events")
                group.create_task(self._state_loop(), name="ohmni-mqtt state")
                for name, hz in self._rates.items():
                    group.create_task(self._sampler(name, hz), name=f"ohmni-mqtt {name}")
                await self._connection_loop()
                raise _LeavingError  # the others end with the group
        except* _LeavingError:
            pass

    async def _connection_loop(self) -> None:
        mqtt = require_client()
        backoff = Backoff()
        failures = 0
        while not self._stop.is_set():
            client = self._broker.client(
                f"ohmni-{self.robot_id}",
                will=(self._availability, OFFLINE),
                max_queued_incoming=_INCOMING_QUEUE,
                on_dropped=self._incoming_dropped,
            )
            since = time.monotonic()
            try:
                await self._connected_session(client)
            except mqtt.MqttError as exc:
                failures += 1
                if time.monotonic() - since > _HELD_S:
                    backoff.reset()
                level = logging.WARNING if failures == 1 else logging.DEBUG
                _log.log(level, "MQTT: %s: %s (trying again)", self._broker.url, exc)
            finally:
                self._connected.clear()
                await self._end_commands()
            if self._stop.is_set():
                return
            try:
                async with asyncio.timeout(backoff.next_s()):
                    await self._stop.wait()
            except TimeoutError:
                pass
        return

    async def _connected_session(self, client: aiomqtt.Client) -> None:
        async with client:
            self.connects += 1
            _log.info("MQTT: connected to %s as %s", self._broker.url, self.robot_id)
            await client.publish(self._availability, ONLINE, qos=1, retain=True)
            self._state_pending = self._state_bytes(force=True)
            if self._discovery:
                for topic, config in self._discovery_messages():
                    await client.publish(topic, json.dumps(config), qos=1, retain=True)
            await client.subscribe(robot_topic(self.robot_id, COMMAND, "+"), qos=1)
            await client.subscribe(robot_topic(self.robot_id, HA_LIGHT), qos=1)
            self._connected.set()
            self._ready.set()  # what waited meanwhile goes out
            tasks = [
                asyncio.create_task(self._publisher(client), name="ohmni-mqtt publisher"),
                asyncio.create_task(self._receiver(client), name="ohmni-mqtt receiver"),
                asyncio.create_task(self._stop.wait(), name="ohmni-mqtt stop"),
            ]
            try:
                done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            finally:
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
            if not self._stop.is_set():
                for task in done:
                    task.result()  # the MqttError that ended it: connect again
                return
            # Leaving: what waits goes out, then offline (else the Will would say it).
            with contextlib.suppress(Exception):  # the broker may be gone meanwhile
                async with asyncio.timeout(_LEAVE_S):
                    await self._flush(client)
                    await client.publish(self._availability, OFFLINE, qos=1, retain=True)

    async def _publisher(self, client: aiomqtt.Client) -> None:
        while True:
            await self._ready.wait()
            self._ready.clear()
            await self._flush(client)

    async def _flush(self, client: aiomqtt.Client) -> None:
        """Send what waits: the state first, then replies, then samples."""
        properties = _correlation_properties
        while True:
            if self._state_pending is not None:
                payload, self._state_pending = self._state_pending, None
                await client.publish(self._state_topic, payload, qos=1, retain=True)
            elif self._replies:
                topic, payload, correlation = self._replies.popleft()
                await client.publish(topic, payload, qos=1, properties=properties(correlation))
            elif self._samples:
                topic, payload = self._samples.popleft()
                await client.publish(topic, payload, qos=0)
            else:
                return
            self.published += 1

    async def _receiver(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            self._take(message)

    async def _watch_state(self) -> None:
        """Each robot_state event (a fault, an estop, the link) looks at the state at once."""
        async with self._robot.subscribe("robot_state", maxlen=4) as events:
            async for sample in events:
                if sample.event is not None:
                    self._state_due.set()

    async def _state_loop(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(_STATE_LOOK_S):
                    await self._state_due.wait()
            self._state_due.clear()
            if self._firmware is None:
                await self._read_firmware()
            payload = self._state_bytes()
            if payload is not None:
                self._state_pending = payload
                self._ready.set()

    async def _sampler(self, name: str, hz: float) -> None:
        """``name``'s newest sample, at most ``hz`` a second (absolute due times: no drift),
        each sample once."""
        loop = asyncio.get_running_loop()
        topic = robot_topic(self.robot_id, STREAM, name)
        period_s = 1.0 / hz
        due = loop.time()
        last: float | None = None
        while True:
            due += period_s
            now = loop.time()
            if due <= now:  # late (a busy loop): the next one on time, not a burst
                due = now + period_s
            await asyncio.sleep(due - now)
            sample = self._robot.latest(name)
            if sample is None or sample.stamp_s == last:
                continue
            last = sample.stamp_s
            if len(self._samples) >= _SAMPLE_QUEUE:
                self._samples.popleft()
                self.dropped += 1
            data = json.dumps(sample_json(sample), separators=(",", ":"))
            self._samples.append((topic, data.encode()))
            self._ready.set()

    # -- the state -------------------------------------------------------------------------

    async def _read_firmware(self) -> None:
        try:
            info = await self._robot.info()
        except OhmniError as exc:  # the port released, a board silent: later
            _log.debug("MQTT: firmware tags not read yet: %s", exc)
            return
        self._firmware = {str(k): str(v) for k, v in info.get("firmware", {}).items()}

    def _state(self) -> StatePayload:
        robot = self._robot
        core = robot.latest("tbcore_status")
        kind = robot.neck_kind
        neck = (
            robot.latest("servo_neck")
            if kind == "herkulex"
            else robot.latest("new_neck")
            if kind == "worm"
            else None
        )
        state = robot.state
        return StatePayload(
            robot_id=self.robot_id,
            time=time.time(),
            version=__version__,
            simulated=robot.sim is not None,
            link=str(state.link.value),
            estopped=state.estopped,
            faults=list(state.faults),
            battery=None
            if core is None
            else BatteryState(
                percent=core.percent,
                pack_v=round(core.pack_v, 3),
                cell_v=[round(v, 3) for v in core.cell_v],
                current_a=round(core.current_a, 3),
                docked=core.docked,
                charging=core.charging,
            ),
            neck=NeckState(kind=kind, position_raw=None if neck is None else neck.position_raw),
            lease=self._server.lease_holder,
            firmware=self._firmware or {},
            drive=self._drive,
            uptime_s=round(robot.stats().uptime_s, 1),
            bridge=self.figures(),
        )

    def _state_bytes(self, *, force: bool = False) -> bytes | None:
        """The state's JSON when it changed, is due (:data:`STATE_PERIOD_S`) or ``force``."""
        state = self._state()
        key = state_key(state)
        now = time.monotonic()
        if (
            not force
            and key == self._last_state_key
            and now - self._last_state_at < (STATE_PERIOD_S)
        ):
            return None
        self._last_state_key = key
        self._last_state_at = now
        return state.model_dump_json().encode()

    def _discovery_messages(self) -> list[tuple[str, dict[str, Any]]]:
        config = self._robot.config
        kind = self._robot.neck_kind
        neck_range = (
            (config.neck_min_raw, config.neck_max_raw)
            if kind == "herkulex"
            else (config.worm_min_raw, config.worm_max_raw)
            if kind == "worm"
            else None
        )
        return discovery_messages(
            self.robot_id,
            prefix=self._prefix,
            version=__version__,
            neck_kind=kind,
            neck_range_raw=neck_range,
        )

    # -- commands ------------------------------------------------------------------------------

    def _take(self, message: aiomqtt.Message) -> None:
        """One message on a command topic: checked here, run in a task of its own."""
        topic = str(message.topic)
        method = topic.rsplit("/", 1)[-1] if f"/{COMMAND}/" in topic else "light_ring"
        properties = message.properties
        reply_to = getattr(properties, "ResponseTopic", None) if properties else None
        correlation = getattr(properties, "CorrelationData", None) if properties else None
        answer = _Answer(self, method, reply_to, correlation)
        if message.retain:
            # A retained command would run again at every connect of the robot.
            answer.refuse("retained", f"{method}: a retained command is never run")
            return
        raw = message.payload
        body = raw if isinstance(raw, bytes | bytearray) else str(raw or "").encode()
        if len(body) > MAX_MESSAGE_BYTES:
            answer.refuse(
                "too_large", f"{method}: {len(body)} bytes: the limit is {MAX_MESSAGE_BYTES}"
            )
            return
        try:
            args = json.loads(body) if body.strip() else {}
        except (ValueError, UnicodeDecodeError, RecursionError) as exc:
            answer.refuse("bad_json", f"{method}: the body is not JSON: {exc}")
            return
        if not isinstance(args, dict):
            answer.refuse("bad_json", f"{method}: the body is a JSON object of the arguments")
            return
        if f"/{COMMAND}/" not in topic:
            try:
                hsv = ha_light_args(args, self._light)
            except ValueError as exc:
                answer.refuse("bad_message", f"light: {exc}")
                return
            args = {"hue": hsv[0], "saturation": hsv[1], "value": hsv[2]}
        kind = COMMANDS.get(method)
        if kind is None:
            answer.refuse(
                "not_offered",
                f"{method} is not taken over MQTT: the commands are {', '.join(COMMANDS)}",
            )
            return
        if method not in _STOPS:
            if len(self._running) >= COMMANDS_AT_ONCE:
                answer.refuse("busy", f"{method}: {COMMANDS_AT_ONCE} commands run already")
                return
            if not self._bucket.take():
                answer.refuse("busy", f"{method}: more than {COMMANDS_PER_S:g} commands a second")
                return
        task = asyncio.get_running_loop().create_task(
            self._command(answer, kind, args), name=f"ohmni-mqtt command {method}"
        )
        self._running.add(task)
        task.add_done_callback(self._running.discard)

    async def _command(self, answer: _Answer, kind: str, args: dict[str, Any]) -> None:
        method = answer.method
        local = self._local
        assert local is not None
        if kind == "drive" and not self._drive:
            answer.refuse(
                "driving_off",
                f"{method}: driving over MQTT is off on {self.robot_id} (mqtt_drive = true "
                "turns it on); stop and estop are always taken",
            )
            return
        needs_lease = kind in ("lease", "drive")
        if needs_lease and not (self._broker.authenticated or self._broker.local):
            answer.refuse(
                "unauthenticated",
                f"{method}: the broker {self._broker.url} was reached without credentials: "
                "over it the robot only stops and answers reads (set mqtt_username)",
            )
            return
        if method == "move" and args.get("target") != "neck":
            answer.refuse(
                "not_offered",
                f'move over MQTT moves the neck only: "target": "neck", not '
                f"{json.dumps(args.get('target'))}",
            )
            return
        try:
            if needs_lease:
                self._lease_users += 1
                try:
                    if not local.holds_lease:
                        await local.call("acquire")
                    data = await local.call(method, args)
                finally:
                    self._lease_users -= 1
                    if not self._lease_users and local.holds_lease:
                        await local.call("release")  # the wheels stop: as any client's
            else:
                data = await local.call(method, args)
        except RequestError as exc:
            answer.refuse(exc.code, exc.message, exc.raised)
            return
        if method == "light_ring":
            self._light = (args["hue"], args["saturation"], args["value"])
        answer.result(data)

    async def _end_commands(self) -> None:
        """The broker is gone: nobody can stop a command over it any more. Running
        commands end (their replies wait for the broker), and the lease is released,
        which stops the wheels."""
        running = list(self._running)
        for task in running:
            task.cancel()
        await asyncio.gather(*running, return_exceptions=True)
        local = self._local
        if local is not None and local.holds_lease:
            with contextlib.suppress(RequestError):
                await local.call("release")
        self._lease_users = 0

    def _incoming_dropped(self) -> None:
        """A command message the client had no room for (a flood): dropped, counted."""
        self.dropped += 1

    def _queue_reply(self, topic: str, payload: bytes, correlation: bytes | None) -> None:
        if len(self._replies) >= _REPLY_QUEUE:
            self._replies.popleft()
            self.dropped += 1
        self._replies.append((topic, payload, correlation))
        self._ready.set()


class _Answer:
    """Where one command's reply goes: its response topic when it is the robot's own
    (:func:`~ohmni_tb.mqtt.payloads.response_topic_allowed`), else the default one, with
    its correlation data."""

    def __init__(
        self, bridge: MqttBridge, method: str, reply_to: str | None, correlation: bytes | None
    ) -> None:
        self.bridge = bridge
        self.method = method
        allowed = reply_to is not None and response_topic_allowed(bridge.robot_id, reply_to)
        self.topic = reply_to if allowed and reply_to is not None else bridge._response
        self.correlation = correlation

    def result(self, data: Any) -> None:
        self.bridge.commands += 1
        reply = ResultReply(method=self.method, data=data)
        self.bridge._queue_reply(self.topic, reply.model_dump_json().encode(), self.correlation)

    def refuse(self, code: str, message: str, raised: dict[str, Any] | None = None) -> None:
        self.bridge.refused += 1
        _log.info("MQTT: %s refused (%s): %s", self.method, code, message)
        reply = ErrorReply(method=self.method, code=code, message=message, raised=raised)
        self.bridge._queue_reply(self.topic, reply.model_dump_json().encode(), self.correlation)


class _LeavingError(Exception):
    """The connection loop ended (the bridge is closing): the other tasks end too."""


def _correlation_properties(correlation: bytes | None) -> Any:
    """MQTT 5 publish properties carrying ``correlation``, or ``None`` without it."""
    if correlation is None:
        return None
    from paho.mqtt.packettypes import PacketTypes  # noqa: PLC0415  # with the extra
    from paho.mqtt.properties import Properties  # noqa: PLC0415

    properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]  # paho
    properties.CorrelationData = correlation
    return properties
