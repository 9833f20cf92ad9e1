"""Every robot an MQTT broker knows, and commands to them (``ohmni fleet`` in Python).

::

    async with Fleet("mqtt://broker:1883") as fleet:
        for robot in fleet.robots:
            print(robot.robot_id, robot.online, robot.battery_percent, robot.faults)
        await fleet.call("kitchen", "stop")

A robot is known by its retained ``ohmni/<robot_id>/state`` and ``availability``
(:mod:`ohmni_tb.mqtt.payloads`), published by ``ohmni serve --mqtt``: what :attr:`Fleet.
robots` holds as soon as the fleet is open, and keeps up to date while it stays open
(:meth:`Fleet.changes` for each change). :meth:`Fleet.call` sends a command with an MQTT 5
response topic and correlation data and returns the robot's reply. A lost broker is
reached again with a growing back-off; meanwhile the robots are as last seen. Needs the
mqtt extra (``pip install 'ohmni_tb[mqtt]'``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import secrets
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from pydantic import ValidationError

from ohmni_tb.errors import (
    ConfigError,
    InvalidArgumentError,
    LeaseError,
    OhmniError,
    StateError,
    TransportError,
)
from ohmni_tb.mqtt.broker import Backoff, Broker, require_client
from ohmni_tb.mqtt.payloads import (
    AVAILABILITY,
    ONLINE,
    RESPONSE,
    ROOT,
    STATE,
    ErrorReply,
    ResultReply,
    StatePayload,
    command_topic,
    robot_topic,
)
from ohmni_tb.robot.wire import raised_error

if TYPE_CHECKING:
    import aiomqtt

    from ohmni_tb.config import RobotConfig

__all__ = ["DEFAULT_CALL_TIMEOUT_S", "Fleet", "FleetRobot"]

_log = logging.getLogger("ohmni_tb.fleet")

#: How long :meth:`Fleet.call` waits for a reply by default, s (a motion goal answers
#: when it ends: give it its time).
DEFAULT_CALL_TIMEOUT_S: Final = 10.0
#: How long opening waits for the broker, s.
_OPEN_TIMEOUT_S: Final = 10.0
#: Messages the client holds unread; beyond, they are dropped (counted in ``dropped``).
_INCOMING_QUEUE: Final = 4096
#: The error codes a reply carries, as the exception :meth:`Fleet.call` raises.
_ERRORS: Final[dict[str, type[OhmniError]]] = {
    "bad_json": InvalidArgumentError,
    "bad_message": InvalidArgumentError,
    "unknown_method": InvalidArgumentError,
    "unknown_topic": InvalidArgumentError,
    "too_large": InvalidArgumentError,
    "bad_value": InvalidArgumentError,
    "no_lease": LeaseError,
    "lease_held": LeaseError,
}


@dataclass(frozen=True, slots=True)
class FleetRobot:
    """One robot as the broker knows it.

    Attributes:
        robot_id: Its name on the broker.
        online: Its availability: ``True`` online, ``False`` offline (it left, or the
            broker lost it: its Last Will), ``None`` not told.
        battery_percent: The coarse state of charge (20, 50, 80, 100), or ``None``.
        pack_v: The pack voltage, or ``None``.
        docked: On the dock, or ``None`` (not known).
        charging: Charging, or ``None``.
        faults: What is wrong, by its latest state.
        link: Its serial link (``connected``, ``lost`` …), or ``None``.
        lease: Which client drives it, or ``None``.
        last_seen: When it last published its state (Unix time, s), or ``None``.
        state: Its latest state, whole, or ``None``.
    """

    robot_id: str
    online: bool | None
    battery_percent: int | None
    pack_v: float | None
    docked: bool | None
    charging: bool | None
    faults: tuple[str, ...]
    link: str | None
    lease: str | None
    last_seen: float | None
    state: StatePayload | None

    @classmethod
    def of(cls, robot_id: str, online: bool | None, state: StatePayload | None) -> FleetRobot:
        """A robot from its availability and state."""
        battery = None if state is None else state.battery
        return cls(
            robot_id=robot_id,
            online=online,
            battery_percent=None if battery is None else battery.percent,
            pack_v=None if battery is None else battery.pack_v,
            docked=None if battery is None else battery.docked,
            charging=None if battery is None else battery.charging,
            faults=() if state is None else tuple(state.faults),
            link=None if state is None else state.link,
            lease=None if state is None else state.lease,
            last_seen=None if state is None else state.time,
            state=state,
        )

    def as_json(self) -> dict[str, Any]:
        """Its fields as JSON-ready data (``ohmni fleet --json``); the state whole."""
        return {
            "robot_id": self.robot_id,
            "online": self.online,
            "battery_percent": self.battery_percent,
            "pack_v": self.pack_v,
            "docked": self.docked,
            "charging": self.charging,
            "faults": list(self.faults),
            "link": self.link,
            "lease": self.lease,
            "last_seen": self.last_seen,
            "state": None if self.state is None else self.state.model_dump(mode="json"),
        }


class Fleet:
    """Every robot a broker knows (module docstring). Open it with ``async with``.

    Args:
        broker: The broker: a :class:`~ohmni_tb.mqtt.broker.Broker`, or its URL
            (``mqtt://HOST[:PORT]``, ``mqtts://HOST[:PORT]``; no credentials then).

    Raises:
        ConfigError: Not a broker URL, or the mqtt extra is not installed.
    """

    def __init__(self, broker: Broker | str) -> None:
        require_client()
        self._broker = Broker.from_url(broker) if isinstance(broker, str) else broker
        self._tag = secrets.token_hex(6)
        self._online: dict[str, bool] = {}
        self._states: dict[str, StatePayload] = {}
        self._changed = asyncio.Condition()
        self._version = 0
        self._client: aiomqtt.Client | None = None
        self._synced = asyncio.Event()
        self._first_failure = asyncio.Event()
        self._failed: BaseException | None = None
        self._task: asyncio.Task[None] | None = None
        self._waiting: dict[bytes, asyncio.Future[Any]] = {}
        self._listening: set[str] = set()
        #: Messages that were not a robot's state or availability as this version reads
        #: them, and messages the client had no room for: counted, not used.
        self.unreadable = 0
        self.dropped = 0

    @classmethod
    def from_config(cls, config: RobotConfig | None = None, url: str | None = None) -> Fleet:
        """The fleet on the broker of the settings (``mqtt_url`` or ``url``, with
        ``mqtt_username``, ``mqtt_password`` and the TLS files).

        Raises:
            ConfigError: No broker URL, or an invalid setting.
        """
        if config is None:
            from ohmni_tb.config import RobotConfig  # noqa: PLC0415

            config = RobotConfig.load()
        return cls(Broker.from_config(config, url))

    @property
    def url(self) -> str:
        """The broker's URL."""
        return self._broker.url

    @property
    def connected(self) -> bool:
        """Whether the fleet is connected to the broker now."""
        return self._client is not None

    @property
    def robots(self) -> list[FleetRobot]:
        """Every robot known, by id."""
        ids = sorted(set(self._online) | set(self._states))
        return [FleetRobot.of(i, self._online.get(i), self._states.get(i)) for i in ids]

    def robot(self, robot_id: str) -> FleetRobot | None:
        """The robot ``robot_id``, or ``None`` when the broker knows none so named."""
        if robot_id not in self._online and robot_id not in self._states:
            return None
        return FleetRobot.of(robot_id, self._online.get(robot_id), self._states.get(robot_id))

    async def open(self) -> None:
        """Connect, and read what the broker holds of every robot.

        Raises:
            TransportError: The broker cannot be reached or refused the connection.
        """
        self._task = asyncio.get_running_loop().create_task(
            self._run(), name=f"ohmni-fleet {self._broker.url}"
        )
        # The first attempt decides: connected and read, or refused (no use retrying a
        # wrong password or an address nothing listens on before the caller hears of it).
        synced = asyncio.ensure_future(self._synced.wait())
        refused = asyncio.ensure_future(self._first_failure.wait())
        try:
            await asyncio.wait(
                (synced, refused, self._task),
                timeout=_OPEN_TIMEOUT_S,
                return_when=asyncio.FIRST_COMPLETED,
            )
        finally:
            synced.cancel()
            refused.cancel()
        if not self._synced.is_set():
            failed = self._failed
            await self.aclose()
            raise TransportError(
                f"cannot reach the broker at {self._broker.url}: "
                f"{failed or f'no answer within {_OPEN_TIMEOUT_S:g} s'}"
            ) from failed

    async def aclose(self) -> None:
        """Disconnect. Idempotent."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(TransportError("the fleet was closed"))

    async def __aenter__(self) -> Fleet:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def changes(self) -> AsyncIterator[list[FleetRobot]]:
        """The robots now, then again after each change (changes that come close together
        are seen once, the newest)."""
        seen = -1

        def changed() -> bool:
            return self._version != seen

        while True:
            async with self._changed:
                await self._changed.wait_for(changed)
                seen = self._version
            yield self.robots

    async def call(
        self,
        robot_id: str,
        method: str,
        args: dict[str, Any] | None = None,
        *,
        timeout_s: float = DEFAULT_CALL_TIMEOUT_S,
    ) -> Any:
        """Command robot ``robot_id``: ``method`` (one of
        :data:`~ohmni_tb.mqtt.payloads.COMMANDS`) with ``args`` (the daemon's arguments of
        that method); the data of its result.

        Raises:
            OhmniError: The robot refused it: as the daemon's client would raise it
                (:class:`~ohmni_tb.errors.LeaseError` when another client drives it, the
                Robot's own :class:`~ohmni_tb.errors.InvalidArgumentError` …), a
                :class:`~ohmni_tb.errors.StateError` for the bridge's own refusals
                (driving off, not offered …).
            TimeoutError: No reply within ``timeout_s`` (the robot offline, or the broker's
                ACL does not let this client command it).
            TransportError: Not connected to the broker.
        """
        mqtt = require_client()
        client = self._client
        if client is None:
            raise TransportError(f"not connected to the broker at {self._broker.url}")
        reply_to = robot_topic(robot_id, RESPONSE, f"fleet-{self._tag}")
        if reply_to not in self._listening:
            await client.subscribe(reply_to, qos=1)
            self._listening.add(reply_to)
        correlation = secrets.token_bytes(8)
        from paho.mqtt.packettypes import PacketTypes  # noqa: PLC0415  # with the extra
        from paho.mqtt.properties import Properties  # noqa: PLC0415

        properties = Properties(PacketTypes.PUBLISH)  # type: ignore[no-untyped-call]  # paho
        properties.ResponseTopic = reply_to
        properties.CorrelationData = correlation
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._waiting[correlation] = future  # registered before the robot may answer
        try:
            await client.publish(
                command_topic(robot_id, method),
                json.dumps(args or {}),
                qos=1,
                properties=properties,
            )
            async with asyncio.timeout(timeout_s):
                return await future
        except mqtt.MqttError as exc:
            raise TransportError(f"{method} to {robot_id} not sent: {exc}") from exc
        except TimeoutError:
            raise TimeoutError(
                f"{robot_id} did not answer {method} within {timeout_s:g} s (offline, or "
                "the broker does not let this client command it)"
            ) from None
        finally:
            self._waiting.pop(correlation, None)

    # -- the connection --------------------------------------------------------------------

    async def _run(self) -> None:
        mqtt = require_client()
        backoff = Backoff()
        while True:
            client = self._broker.client(
                f"ohmni-fleet-{self._tag}",
                max_queued_incoming=_INCOMING_QUEUE,
                on_dropped=self._incoming_dropped,
            )
            try:
                async with client:
                    await self._session(client, backoff)
            except mqtt.MqttError as exc:
                self._failed = exc
                self._first_failure.set()
                if self._synced.is_set():
                    _log.warning("fleet: %s: %s (trying again)", self._broker.url, exc)
            except ConfigError as exc:  # a TLS file: no use trying again
                self._failed = exc
                self._first_failure.set()
                return
            finally:
                self._client = None
                self._listening.clear()
            await asyncio.sleep(backoff.next_s())

    async def _session(self, client: aiomqtt.Client, backoff: Backoff) -> None:
        messages = client.messages
        # Retained messages follow their subscription's acknowledgement, before the next
        # one's: once the last acknowledgement is in, every robot's are queued here.
        await client.subscribe(robot_topic("+", STATE), qos=1)
        await client.subscribe(robot_topic("+", AVAILABILITY), qos=1)
        await client.unsubscribe(f"{ROOT}/$sync/{self._tag}")
        while len(messages):
            self._take(await anext(messages))
        self._client = client
        backoff.reset()
        self._synced.set()
        await self._bump()
        async for message in messages:
            self._take(message)
            if not len(messages):
                await self._bump()

    def _incoming_dropped(self) -> None:
        self.dropped += 1

    async def _bump(self) -> None:
        async with self._changed:
            self._version += 1
            self._changed.notify_all()

    def _take(self, message: aiomqtt.Message) -> None:
        parts = str(message.topic).split("/")
        payload = message.payload if isinstance(message.payload, bytes) else b""
        if len(parts) >= 4 and parts[2] == RESPONSE:
            self._reply(message, payload)
            return
        if len(parts) != 3 or parts[0] != ROOT:
            self.unreadable += 1
            return
        robot_id, kind = parts[1], parts[2]
        if kind == AVAILABILITY:
            if not payload:  # the retained message cleared: the robot is forgotten
                self._online.pop(robot_id, None)
            else:
                self._online[robot_id] = payload.decode(errors="replace") == ONLINE
        elif kind == STATE:
            if not payload:
                self._states.pop(robot_id, None)
                return
            try:
                self._states[robot_id] = StatePayload.model_validate_json(payload)
            except ValidationError:
                self.unreadable += 1

    def _reply(self, message: aiomqtt.Message, payload: bytes) -> None:
        properties = message.properties
        correlation = getattr(properties, "CorrelationData", None) if properties else None
        future = self._waiting.get(correlation) if isinstance(correlation, bytes) else None
        if future is None or future.done():
            return
        try:
            data = json.loads(payload)
            if data.get("op") == "result":
                future.set_result(ResultReply.model_validate(data).data)
                return
            error = ErrorReply.model_validate(data)
        except (ValueError, AttributeError) as exc:
            future.set_exception(TransportError(f"an unreadable reply: {exc}"))
            return
        future.set_exception(_error(error))


def _error(reply: ErrorReply) -> OhmniError:
    """A robot's refusal as the exception a client of its daemon would raise."""
    if reply.code in ("bad_value", "robot_state", "robot_error"):
        said = reply.message.removeprefix(f"{reply.method}: ")
        own = raised_error(reply.raised, said)
        if own is not None:
            return own
    cls = _ERRORS.get(reply.code, StateError)
    text = f"{reply.method} refused ({reply.code}): {reply.message}"
    return LeaseError(text, holder=None) if cls is LeaseError else cls(text)
