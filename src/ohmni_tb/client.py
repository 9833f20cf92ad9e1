"""The Robot's API over the daemon (``ohmni serve``): streams, services and, with the
control lease, the commands.

::

    from ohmni_tb.client import RobotClient

    async with RobotClient.connect("ws://127.0.0.1:8766") as robot:
        odom = await robot.latest("wheel_odom")        # the same WheelOdomSample
        async with robot.lease():                      # one driver at a time
            robot.drive(0.3, 0.0)                      # not awaited, as on the Robot
            await robot.neck.move(raw=400, playtime_s=1.0)
            await robot.confirm()                      # every command so far accepted
        print(await robot.stats())

Samples are the Robot's own frozen dataclasses, rebuilt from the daemon's JSON, so code
written against :class:`~ohmni_tb.Robot` reads them unchanged. The commands that are
plain calls on the Robot (``drive``, ``drive_wheels``, ``drive_pwm``, ``stop``,
``set_pid``, ``reset_odometry``, ``enable_stream`` …) are plain calls here too: checked
here first (a bad value, no lease: raised at once, nothing sent), then sent in order
without waiting. A command the daemon still refuses is logged, and raised by the next
command or by :meth:`RobotClient.confirm`. What differs from the embedded Robot:
``latest``, ``stats`` and ``get_pid`` are awaited (they may ask the daemon), there is one
subscription per topic and connection, and commands need the lease.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import os
from collections import deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any, Final, Generic, Literal, TypeVar, overload

from pydantic import ValidationError

from ohmni_tb._checks import number, ws_address
from ohmni_tb.control.kinematics import (
    DiffDrive,
    LimitedTwist,
    Twist,
    VelocityLimits,
    WheelSpeeds,
    limit_twist,
    saturate_wheel_speeds,
)
from ohmni_tb.control.pid import PidGains
from ohmni_tb.daemon.auth import TOKEN_ENV
from ohmni_tb.daemon.protocol import (
    METHOD_SPECS,
    BatchMessage,
    Call,
    ErrorMessage,
    Hello,
    LatestArgs,
    LeaseMessage,
    Result,
    SampleMessage,
    Subscribe,
    Unsubscribe,
    encode,
    parse_server_message,
    sample_from_json,
    stats_from_json,
)
from ohmni_tb.errors import (
    ConfigError,
    InvalidArgumentError,
    LeaseError,
    OhmniError,
    OutOfRangeError,
    ProtocolError,
    RobotClosedError,
    StateError,
    TransportClosedError,
    TransportError,
)
from ohmni_tb.protocol.drive import PWM_LIMIT
from ohmni_tb.robot.samples import (
    STREAM_NAMES,
    PidDebugSample,
    RobotStateSample,
    ServoSample,
    TbcoreStatusSample,
    WheelEncoderSample,
    WheelOdomSample,
    WormNeckSample,
)
from ohmni_tb.robot.streams import DEFAULT_QUEUE_SIZE

if TYPE_CHECKING:
    from pydantic import BaseModel
    from websockets.asyncio.client import ClientConnection

    from ohmni_tb.config import RobotConfig
    from ohmni_tb.robot.stats import RobotStats

__all__ = [
    "DEFAULT_TIMEOUT_S",
    "DEFAULT_URL",
    "MAX_UNSENT",
    "ClientSubscription",
    "RemoteServo",
    "RobotClient",
]

#: Where ``ohmni serve`` listens by default.
DEFAULT_URL: Final = "ws://127.0.0.1:8766"
#: How long connecting, and each call, may take.
DEFAULT_TIMEOUT_S: Final = 5.0
#: The server's messages are samples and small results; a stats reply is a few KiB.
_MAX_FRAME_BYTES = 1024 * 1024
#: Messages waiting to be sent to a daemon that does not take them; one more is an error.
MAX_UNSENT: Final = 256
#: Connecting again: the first wait, then doubling up to the last.
_FIRST_RETRY_S = 0.05
_MAX_RETRY_S = 2.0

_log = logging.getLogger("ohmni_tb.client")
#: The protocol's field names as this API's.
_OPTION = {"queue": "maxlen"}

T = TypeVar("T")

#: The daemon's error codes as ours: a bad request is the caller's ValueError.
_ERRORS: dict[str, type[OhmniError]] = {
    "bad_json": InvalidArgumentError,
    "bad_message": InvalidArgumentError,
    "unknown_op": InvalidArgumentError,
    "unknown_method": InvalidArgumentError,
    "unknown_topic": InvalidArgumentError,
    "too_large": InvalidArgumentError,
    "bad_value": InvalidArgumentError,
    "not_subscribed": StateError,
    "read_only": StateError,
    "robot_state": StateError,
    "no_lease": LeaseError,
    "lease_held": LeaseError,
    "rate_limited": ProtocolError,
}


class RobotClient:
    """A connection to the daemon: the Robot's streams and read-only services.

    Open it with ``async with RobotClient.connect(url) as robot:``.
    """

    def __init__(
        self,
        ws: ClientConnection,
        url: str,
        hello: Hello,
        timeout_s: float,
        *,
        headers: dict[str, str] | None = None,
        reconnect: bool = False,
    ) -> None:
        self._ws = ws
        self._headers = headers
        self._reconnect = reconnect
        #: Times the connection was made again after the daemon went away.
        self.reconnects = 0
        self._url = url
        self._hello = hello
        self._timeout_s = timeout_s
        self._ids = itertools.count(1)
        self._pending: dict[int | str, asyncio.Future[Any]] = {}
        self._latest: dict[str, Any] = {}
        self._subscriptions: dict[str, ClientSubscription[Any]] = {}
        self._reader: asyncio.Task[None] | None = None
        self._writer: asyncio.Task[None] | None = None
        self._closing = False
        self._lost: TransportClosedError | None = None
        # Every message goes out through one queue, in the order of the calls.
        self._unsent: deque[str] = deque()
        self._unsent_ready = asyncio.Event()
        # Commands sent without waiting: their answers, and the first refusal not raised.
        self._commands: set[asyncio.Future[Any]] = set()
        self._refusal: OhmniError | None = None
        self._holder: str | None = hello.lease
        motion = hello.motion
        self._drive = DiffDrive(motion.wheel_radius_m, motion.wheel_separation_m)
        self._limits = VelocityLimits(
            _unlimited(motion.max_linear_mps),
            _unlimited(motion.max_angular_radps),
            _unlimited(motion.max_wheel_mps),
        )

    @classmethod
    @asynccontextmanager
    async def connect(
        cls,
        url: str = DEFAULT_URL,
        *,
        token: str | None = None,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        reconnect: bool = False,
    ) -> AsyncIterator[RobotClient]:
        """Connect to the daemon at ``url``; leaving the block closes the connection.

        Args:
            url: ``ws://host:port`` of ``ohmni serve``.
            token: The daemon's token, needed when it listens beyond loopback (the
                content of its token file); default ``$OHMNI_DAEMON_TOKEN``, else none.
            timeout_s: How long connecting, and each call, may take.
            reconnect: When the daemon goes away (restarted, its machine rebooted),
                connect again and again (backing off to one try every 2 s) instead of
                ending: subscriptions stay open and are renewed, calls in between raise
                :class:`~ohmni_tb.errors.TransportClosedError`. The control lease is
                **not** taken again: a driver must ``acquire`` anew (:attr:`reconnects`
                tells it happened).

        Raises:
            ConfigError: ``url`` is not a ``ws://`` or ``wss://`` URL with a host (and a
                port in 0..65535).
            TransportError: Nothing answers at ``url``, it is not the daemon, or it
                refused the connection (no token or a wrong one: the message says).
        """
        _check_url(url)
        token = token if token is not None else os.environ.get(TOKEN_ENV) or None
        headers = {"Authorization": f"Bearer {token}"} if token else None
        ws, hello = await _open(url, headers, timeout_s)
        try:
            client = cls(ws, url, hello, timeout_s, headers=headers, reconnect=reconnect)
        except BaseException:
            await ws.close()
            raise
        client._start()
        try:
            yield client
        finally:
            await client._aclose()

    @property
    def url(self) -> str:
        """The daemon's address."""
        return self._url

    @property
    def hello(self) -> Hello:
        """What the daemon said on connecting: protocol, version, topics and rates, limits."""
        return self._hello

    @property
    def topics(self) -> dict[str, float]:
        """Every stream and its rate in Hz (0: on events)."""
        return dict(self._hello.topics)

    @property
    def peer(self) -> str:
        """This connection as the daemon names it (``host:port``)."""
        return self._hello.peer

    @property
    def lease_holder(self) -> str | None:
        """Who holds the control lease (a peer), as last told by the daemon; ``None``: nobody."""
        return self._holder

    @property
    def has_lease(self) -> bool:
        """Whether this connection holds the control lease."""
        return self._holder is not None and self._holder == self._hello.peer

    @overload
    async def latest(self, name: Literal["wheel_encoder"]) -> WheelEncoderSample | None: ...
    @overload
    async def latest(self, name: Literal["wheel_odom"]) -> WheelOdomSample | None: ...
    @overload
    async def latest(self, name: Literal["tbcore_status"]) -> TbcoreStatusSample | None: ...
    @overload
    async def latest(
        self, name: Literal["servo_neck", "servo_ext1", "servo_ext2"]
    ) -> ServoSample | None: ...
    @overload
    async def latest(self, name: Literal["new_neck"]) -> WormNeckSample | None: ...
    @overload
    async def latest(self, name: Literal["robot_state"]) -> RobotStateSample | None: ...
    @overload
    async def latest(self, name: Literal["pid_debug"]) -> PidDebugSample | None: ...
    @overload
    async def latest(self, name: str) -> Any: ...
    async def latest(self, name: str) -> Any:
        """The newest sample of stream ``name``, or ``None`` before the first.

        On a topic this connection subscribes to, the newest sample received (no round
        trip); otherwise the daemon is asked.

        Raises:
            InvalidArgumentError: No such stream.
            TransportError: The daemon did not answer in time, or went away.
        """
        _check_topic(name)
        if name in self._subscriptions and name in self._latest:
            return self._latest[name]
        data = await self._call("latest", LatestArgs(topic=name).model_dump())
        return None if data is None else sample_from_json(name, data)

    def subscribe(
        self,
        name: str,
        *,
        max_hz: float | None = None,
        every: int | None = None,
        maxlen: int = DEFAULT_QUEUE_SIZE,
    ) -> ClientSubscription[Any]:
        """The samples of stream ``name`` from now on (an async iterator; also ``async with``).

        ``every`` keeps only every Nth sample of the stream (1..10000); ``max_hz`` caps the
        rate (the daemon sends at most that many a second, the newest each time); both may
        be given. ``maxlen`` bounds the queue here and at the daemon: a reader that falls
        behind loses the oldest, counted in ``dropped``.

        Raises:
            InvalidArgumentError: No such stream, or ``max_hz`` (above 0, at most 1000),
                ``every`` (1..10000) or ``maxlen`` (1..1024) out of range.
            StateError: This connection already has a subscription to it.
        """
        _check_topic(name)
        try:
            Subscribe(id=0, topic=name, max_hz=max_hz, every=every, queue=maxlen)
        except ValidationError as exc:
            problems = "; ".join(
                f"{_OPTION.get(str(e['loc'][0]), e['loc'][0])}={e['input']!r}: {e['msg']}"
                for e in exc.errors(include_url=False)
            )
            raise InvalidArgumentError(f"subscribe {name}: {problems}") from None
        if name in self._subscriptions:
            raise StateError(
                f"already subscribed to {name!r} on this connection: close that subscription "
                "first, or open another connection"
            )
        subscription: ClientSubscription[Any] = ClientSubscription(
            self, name, max_hz, maxlen, every=every
        )
        self._subscriptions[name] = subscription
        return subscription

    async def stats(self) -> RobotStats:
        """The daemon's :meth:`Robot.stats` (its stamps are the daemon's clock)."""
        return stats_from_json(await self._call("stats"))

    async def info(self) -> dict[str, Any]:
        """:meth:`Robot.info`: firmware tags, servo models, the neck kind, present, absent."""
        info: dict[str, Any] = await self._call("info")
        info["servos"] = {int(sid): model for sid, model in info.get("servos", {}).items()}
        return info

    async def schedule(self) -> list[tuple[str, float, float, float]]:
        """:meth:`Robot.schedule`: per stream its rate, phase and line time per cycle."""
        rows = await self._call("schedule")
        return [(str(n), float(hz), float(phase), float(cost)) for n, hz, phase, cost in rows]

    async def config(self) -> RobotConfig:
        """The daemon's Robot's settings (:attr:`Robot.config`)."""
        from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic-settings: when asked

        data: dict[str, Any] = await self._call("config")
        return RobotConfig(**data)

    def latest_received(self, name: str) -> Any:
        """The newest sample of stream ``name`` this connection received (it must subscribe
        to it), or ``None``: no round trip, not awaited.

        Raises:
            InvalidArgumentError: No such stream.
        """
        _check_topic(name)
        return self._latest.get(name)

    async def get_pid(self) -> PidGains:
        """The wheel PIDs' gains (:meth:`Robot.get_pid`; awaited: the daemon is asked)."""
        return PidGains(**await self._call("get_pid"))

    # -- the control lease -------------------------------------------------------------------

    async def acquire(self, *, steal: bool = False) -> str | None:
        """Take the control lease: from now on this connection's commands move the robot.

        Only one client holds it. ``steal`` takes it from the holder (an operator taking
        over a misbehaving script); the loser is told, and the robot stops whenever the
        lease changes hands. Closing the connection releases it (and stops the robot).

        Returns:
            The peer it was stolen from, or ``None``.

        Raises:
            LeaseError: Another client holds it and ``steal`` is not set; ``.holder``
                names it.
            StateError: The daemon takes no commands (started read-only).
        """
        data = await self._call("acquire", {"steal": bool(steal)})
        self._holder = data["holder"]
        stolen_from: str | None = data["stolen_from"]
        return stolen_from

    async def release(self) -> None:
        """Give the control lease back (the robot stops). Without the lease: nothing."""
        if not self.has_lease:
            return
        self._holder = None  # before the daemon's lease message: ours, not a loss
        await self._call("release")

    @asynccontextmanager
    async def lease(self, *, steal: bool = False) -> AsyncIterator[RobotClient]:
        """``async with client.lease():`` — hold the control lease for the block."""
        await self.acquire(steal=steal)
        try:
            yield self
        finally:
            if self._lost is None:
                with contextlib.suppress(TransportError, LeaseError):
                    await self.release()

    # -- commands (as the Robot's: not awaited) ----------------------------------------------

    def drive(self, linear_mps: float, angular_radps: float = 0.0) -> LimitedTwist:
        """:meth:`Robot.drive`: the body velocity target, scaled into the daemon's Robot's
        limits here as it will be there. Repeat it within the watchdog time
        (``hello.motion.watchdog_s``) to keep moving.

        Raises:
            InvalidArgumentError: A value is not a finite number; nothing sent.
            LeaseError: This connection does not hold the control lease; nothing sent.
            OhmniError: An earlier command the daemon refused (see :meth:`confirm`).
        """
        twist = Twist(number("linear_mps", linear_mps), number("angular_radps", angular_radps))
        limited = limit_twist(twist, self._limits, self._drive)
        self._command(
            "drive", {"linear_mps": twist.linear_mps, "angular_radps": twist.angular_radps}
        )
        return limited

    def drive_wheels(self, left_mps: float, right_mps: float) -> WheelSpeeds:
        """:meth:`Robot.drive_wheels`: each wheel's rim speed target; returns what is driven.

        Raises:
            The same as :meth:`drive`.
        """
        asked = WheelSpeeds(number("left_mps", left_mps), number("right_mps", right_mps))
        wheels = saturate_wheel_speeds(asked, self._limits.max_wheel_mps)
        self._command("drive_wheels", {"left_mps": asked.left_mps, "right_mps": asked.right_mps})
        return wheels

    def drive_pwm(self, left: int, right: int) -> None:
        """:meth:`Robot.drive_pwm`: open-loop PWM −1000..1000 for each wheel.

        Raises:
            InvalidArgumentError: Not ints; OutOfRangeError: outside −1000..1000. Nothing sent.
            LeaseError: No control lease; nothing sent.
        """
        for name, value in (("left", left), ("right", right)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise InvalidArgumentError(f"{name} PWM must be an int, not {value!r}")
            if not -PWM_LIMIT <= value <= PWM_LIMIT:
                raise OutOfRangeError(f"{name} PWM", value, -PWM_LIMIT, PWM_LIMIT)
        self._command("drive_pwm", {"left": left, "right": right})

    def stop(self) -> None:
        """:meth:`Robot.stop`: target zero. Anyone may, with or without the lease."""
        self._command("stop", {})

    async def estop(self) -> None:
        """:meth:`Robot.estop`: zero PWM ahead of everything, latched until
        :meth:`clear_estop`. Anyone may, with or without the lease."""
        await self._call("estop")

    def clear_estop(self) -> None:
        """:meth:`Robot.clear_estop` (needs the lease)."""
        self._command("clear_estop", {})

    def enable_controllers(self, enabled: bool = True) -> None:
        """:meth:`Robot.enable_controllers` (needs the lease)."""
        if not isinstance(enabled, bool):
            raise InvalidArgumentError(f"enabled must be True or False, not {enabled!r}")
        self._command("enable_controllers", {"enabled": enabled})

    def set_pid(self, gains: PidGains) -> None:
        """:meth:`Robot.set_pid`: the wheel PIDs' gains, for every client (needs the lease)."""
        if not isinstance(gains, PidGains):
            raise InvalidArgumentError(f"gains must be PidGains, not {type(gains).__name__}")
        self._command(
            "set_pid",
            {n: getattr(gains, n) for n in ("kp", "ki", "kd", "kff", "ff_offset")},
        )

    def reset_odometry(self, x_m: float = 0.0, y_m: float = 0.0, yaw_rad: float = 0.0) -> None:
        """:meth:`Robot.reset_odometry`, for every client (needs the lease)."""
        pose = {
            "x_m": number("x_m", x_m),
            "y_m": number("y_m", y_m),
            "yaw_rad": number("yaw_rad", yaw_rad),
        }
        self._command("reset_odometry", pose)

    def enable_stream(self, name: str, enabled: bool = True) -> None:
        """:meth:`Robot.enable_stream`, for every client (needs the lease)."""
        _check_topic(name)
        if not isinstance(enabled, bool):
            raise InvalidArgumentError(f"enabled must be True or False, not {enabled!r}")
        self._command("enable_stream", {"topic": name, "enabled": enabled})

    def set_rate(self, name: str, hz: float) -> None:
        """:meth:`Robot.set_rate`, for every client (needs the lease; each stream's range is
        its :attr:`~ohmni_tb.robot.StreamSpec.rate_range_hz`)."""
        _check_topic(name)
        self._command("set_rate", {"topic": name, "hz": number("hz", hz)})

    async def light_ring(self, hue: int, saturation: int, value: int) -> None:
        """:meth:`Robot.light_ring` (needs the lease).

        Raises:
            InvalidArgumentError: A component outside 0..255 (the daemon's Robot says so).
        """
        await self._call("light_ring", {"hue": hue, "saturation": saturation, "value": value})

    async def release_port(self, duration_s: float | None = None) -> None:
        """:meth:`Robot.release_port`: the daemon hands the serial port to another program
        (tb-node, a flashing tool) for ``duration_s`` (0.1..3600 s; ``None``: until
        :meth:`reclaim_port`), after stopping the wheels. Streams say ``released`` in
        ``robot_state`` meanwhile. Needs the lease."""
        await self._call("release_port", {"duration_s": duration_s})

    async def reclaim_port(self) -> None:
        """:meth:`Robot.reclaim_port`: the daemon takes the port back (waiting, in the
        background, while the other program still holds it). Needs the lease."""
        await self._call("reclaim_port")

    @property
    def neck(self) -> RemoteServo:
        """The neck, HerkuleX or worm gear (:attr:`Robot.neck`); its commands need the lease."""
        return RemoteServo(self, "neck")

    def servo(self, sid: int) -> RemoteServo:
        """The HerkuleX servo ``sid`` (:meth:`Robot.servo`); its commands need the lease."""
        if isinstance(sid, bool) or not isinstance(sid, int) or not 0 <= sid <= 253:
            raise InvalidArgumentError(f"a servo id is an int 0..253, not {sid!r}")
        return RemoteServo(self, sid)

    async def confirm(self) -> None:
        """Wait until the daemon has answered every command sent so far.

        Raises:
            OhmniError: The first of them it refused (a bad value, the lease gone, an
                emergency stop latched …), if not raised already.
            TransportError: The daemon did not answer in time, or went away.
        """
        if self._commands:
            try:
                async with asyncio.timeout(self._timeout_s):
                    await asyncio.wait(list(self._commands))
            except TimeoutError:
                raise TransportError(
                    f"the daemon at {self._url} did not answer the commands sent within "
                    f"{self._timeout_s:g} s"
                ) from None
        self._raise_refusal()

    # -- internals --------------------------------------------------------------------------

    def _command(self, method: str, args: dict[str, Any]) -> None:
        """Send a command without waiting for its answer, after the checks that can be
        made here: the client open, the connection, an earlier refusal, the lease."""
        self._check_open()
        if self._lost is not None:
            raise self._lost
        self._raise_refusal()
        if METHOD_SPECS[method].lease and not self.has_lease:
            holder = self._holder
            raise LeaseError(
                f"{method} needs the control lease: "
                + (
                    f"{holder} holds it (acquire(steal=True) takes it)"
                    if holder
                    else "call await client.acquire() first"
                ),
                holder=holder,
            )
        id = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[id] = future
        self._commands.add(future)
        future.add_done_callback(self._command_done)
        self._send(encode(Call(id=id, method=method, args=args)))

    def _command_done(self, future: asyncio.Future[Any]) -> None:
        self._commands.discard(future)
        if future.cancelled():
            return
        error = future.exception()
        if error is None or not isinstance(error, OhmniError):
            return
        if isinstance(error, TransportClosedError):
            return  # the connection's own error, raised by the next call
        _log.warning("%s", error)
        if self._refusal is None:
            self._refusal = error

    def _raise_refusal(self) -> None:
        refusal, self._refusal = self._refusal, None
        if refusal is not None:
            raise refusal

    def _send(self, frame: str) -> None:
        if len(self._unsent) >= MAX_UNSENT:
            raise TransportError(
                f"the daemon at {self._url} is not taking messages: {MAX_UNSENT} wait to be sent"
            )
        self._unsent.append(frame)
        self._unsent_ready.set()

    async def _write_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        with contextlib.suppress(ConnectionClosed):
            while True:
                await self._unsent_ready.wait()
                self._unsent_ready.clear()
                while self._unsent:
                    await self._ws.send(self._unsent.popleft())
                if self._closing:
                    return

    async def _call(self, method: str, args: dict[str, Any] | None = None) -> Any:
        return await self._request(lambda id: Call(id=id, method=method, args=args or {}), method)

    def _check_open(self) -> None:
        if self._closing:
            raise RobotClosedError("the client is closed: connect again")

    async def _request(self, make: Any, what: str) -> Any:
        self._check_open()
        if self._lost is not None:
            raise self._lost
        id = next(self._ids)
        message: BaseModel = make(id)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[id] = future  # registered before sending: the reply cannot beat it
        try:
            self._send(encode(message))
            async with asyncio.timeout(self._timeout_s):
                return await future
        except TimeoutError:
            raise TransportError(
                f"the daemon at {self._url} did not answer {what} within {self._timeout_s:g} s"
            ) from None
        finally:
            self._pending.pop(id, None)

    def _start(self) -> None:
        loop = asyncio.get_running_loop()
        self._reader = loop.create_task(self._run(), name=f"ohmni-client {self._url}")
        self._writer = loop.create_task(self._write_loop(), name=f"ohmni-client-writer {self._url}")

    async def _run(self) -> None:
        """Read the connection; with ``reconnect``, make it again each time it ends."""
        delay = _FIRST_RETRY_S
        while True:
            await self._read_loop()
            lost = self._closed_error()
            self._lost = lost
            self._unsent.clear()  # the old connection's; their callers were told
            for future in list(self._pending.values()):
                if not future.done():
                    future.set_exception(lost)
            if self._closing or not self._reconnect:
                for subscription in list(self._subscriptions.values()):
                    subscription._end(None if self._closing else lost)
                return
            _log.warning("%s; connecting again", lost)
            while True:
                await asyncio.sleep(delay)
                delay = min(delay * 2, _MAX_RETRY_S)
                try:
                    ws, hello = await _open(self._url, self._headers, self._timeout_s)
                    break
                except TransportError as exc:
                    _log.info("%s; again in %.1f s", exc, delay)
            delay = _FIRST_RETRY_S
            self._reconnected(ws, hello)

    def _reconnected(self, ws: ClientConnection, hello: Hello) -> None:
        had_lease = self.has_lease
        self._ws = ws
        self._hello = hello
        self._holder = hello.lease
        self._lost = None
        self.reconnects += 1
        _log.warning(
            "connected again to the daemon at %s%s",
            self._url,
            ": the control lease was lost with the connection (acquire it again)"
            if had_lease
            else "",
        )
        if self._writer is None or self._writer.done():
            self._writer = asyncio.get_running_loop().create_task(
                self._write_loop(), name=f"ohmni-client-writer {self._url}"
            )
        for subscription in self._subscriptions.values():
            if subscription._started:
                self._renew(subscription)

    def _renew(self, subscription: ClientSubscription[Any]) -> None:
        """Ask the new connection for a subscription's samples again (told if refused)."""
        id = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[id] = future

        def done(future: asyncio.Future[Any]) -> None:
            self._pending.pop(id, None)
            if not future.cancelled() and future.exception() is not None:
                _log.warning("renewing %s: %s", subscription.name, future.exception())

        future.add_done_callback(done)
        self._send(
            encode(
                Subscribe(
                    id=id,
                    topic=subscription.name,
                    max_hz=subscription._max_hz,
                    every=subscription._every,
                    queue=subscription._maxlen,
                )
            )
        )

    async def _read_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        with contextlib.suppress(ConnectionClosed):
            async for frame in self._ws:
                try:
                    message = parse_server_message(frame)
                except ValueError as exc:
                    _log.warning("the daemon at %s sent a bad message: %s", self._url, exc)
                    continue
                self._dispatch(message)

    def _dispatch(self, message: Any) -> None:
        if isinstance(message, BatchMessage):
            for one in message.samples:
                self._dispatch(one)
            return
        if isinstance(message, SampleMessage):
            sample = sample_from_json(message.topic, message.data)
            self._latest[message.topic] = sample
            subscription = self._subscriptions.get(message.topic)
            if subscription is not None:
                subscription._put(sample, message.dropped)
            return
        if isinstance(message, LeaseMessage):
            had = self.has_lease
            self._holder = message.holder
            if had and not message.you:
                _log.warning("lost the control lease at %s: %s", self._url, message.reason)
            return
        if isinstance(message, Result | ErrorMessage):
            future = self._pending.get(message.id) if message.id is not None else None
            if future is None or future.done():
                if isinstance(message, ErrorMessage):
                    _log.warning(
                        "the daemon at %s: %s (%s)", self._url, message.message, message.code
                    )
                return
            if isinstance(message, Result):
                future.set_result(message.data)
            else:
                text = f"the daemon refused: {message.message}"
                error = _ERRORS.get(message.code, OhmniError)
                future.set_exception(
                    LeaseError(text, holder=self._holder) if error is LeaseError else error(text)
                )

    def _closed_error(self) -> TransportClosedError:
        code, reason = self._ws.close_code, self._ws.close_reason
        how = "no close code" if code is None else f"{code}{' ' + reason if reason else ''}"
        return TransportClosedError(f"the daemon at {self._url} closed the connection ({how})")

    async def _aclose(self) -> None:
        self._closing = True
        self._unsent_ready.set()  # the writer sends what is queued (a last stop), then ends
        if self._writer is not None:
            try:
                async with asyncio.timeout(self._timeout_s):
                    await self._writer
            except TimeoutError:
                self._writer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._writer
        await self._ws.close()
        if self._reader is not None:
            if self._lost is not None:
                self._reader.cancel()  # waiting to connect again: no more
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader
            if self._reader.cancelled():
                for subscription in list(self._subscriptions.values()):
                    subscription._end(None)

    @property
    def connected(self) -> bool:
        """Whether the connection is up (``False`` while connecting again)."""
        return self._lost is None


def _check_url(url: str) -> None:
    """Raises ConfigError: ``url`` is not a daemon's URL (as ``$OHMNI_DAEMON_URL`` is
    checked: :func:`ohmni_tb._checks.ws_address`)."""
    if ws_address(url) is None:
        raise ConfigError(
            f"{url!r} is not a daemon URL: expected ws://HOST:PORT or wss://HOST:PORT "
            "(port 1..65535)"
        )


async def _open(
    url: str, headers: dict[str, str] | None, timeout_s: float
) -> tuple[ClientConnection, Hello]:
    """A connection to the daemon at ``url`` and its ``hello``.

    Raises:
        TransportError: Nothing answers, it refused the handshake, or it is not the daemon.
    """
    from websockets.asyncio.client import connect  # noqa: PLC0415  # loaded when used
    from websockets.exceptions import (  # noqa: PLC0415
        ConnectionClosed,
        InvalidHandshake,
        InvalidStatus,
        InvalidURI,
    )

    try:
        async with asyncio.timeout(timeout_s):
            ws = await connect(
                url, max_size=_MAX_FRAME_BYTES, compression=None, additional_headers=headers
            )
    except InvalidStatus as exc:
        said = exc.response.body.decode("utf-8", "replace").strip() if exc.response.body else ""
        raise TransportError(
            f"the daemon at {url} refused the connection "
            f"(HTTP {exc.response.status_code}){': ' + said if said else ''}"
        ) from exc
    except (OSError, InvalidHandshake, InvalidURI, TimeoutError) as exc:
        raise TransportError(f"cannot connect to the daemon at {url}: {_why(exc)}") from exc
    try:
        try:
            async with asyncio.timeout(timeout_s):
                hello = parse_server_message(await ws.recv())
        except (TimeoutError, ValueError, OSError) as exc:
            raise TransportError(f"{url} did not greet as the ohmni daemon: {_why(exc)}") from exc
        except ConnectionClosed as exc:
            raise TransportError(f"{url} closed the connection at once: {exc}") from exc
        if not isinstance(hello, Hello):
            raise TransportError(f"{url} did not greet as the ohmni daemon ({hello.op} first)")
    except BaseException:
        await ws.close()
        raise
    return ws, hello


class ClientSubscription(Generic[T]):
    """One topic's samples from the daemon: an async iterator, bounded (``dropped``).

    Iteration ends when it is closed or the client closes; it raises
    :class:`~ohmni_tb.errors.TransportClosedError` when the daemon goes away.
    """

    def __init__(
        self,
        client: RobotClient,
        topic: str,
        max_hz: float | None,
        maxlen: int,
        *,
        every: int | None = None,
    ) -> None:
        self._client = client
        self._topic = topic
        self._max_hz = max_hz
        self._every = every
        self._maxlen = maxlen
        self._queue: deque[T] = deque()
        self._waiter: asyncio.Future[None] | None = None
        self._started = False
        self._closed = False
        self._error: TransportClosedError | None = None
        #: Samples lost, at the daemon or here, because the reader did not keep up.
        self.dropped = 0

    @property
    def name(self) -> str:
        """The stream's name."""
        return self._topic

    @property
    def pending(self) -> int:
        """Samples received and not read yet."""
        return len(self._queue)

    async def start(self) -> None:
        """Ask the daemon for the samples (the first iteration does it when not done).

        Raises:
            InvalidArgumentError: The daemon refused the options (the message says why).
        """
        if self._started:
            return
        self._started = True
        try:
            await self._client._request(
                lambda id: Subscribe(
                    id=id,
                    topic=self._topic,
                    max_hz=self._max_hz,
                    every=self._every,
                    queue=self._maxlen,
                ),
                f"subscribe {self._topic}",
            )
        except BaseException:
            self._forget()
            raise

    async def aclose(self) -> None:
        """Stop the samples (tell the daemon, unless the connection is gone)."""
        if self._closed:
            return
        self._end(None)
        if self._started and self._client._lost is None:
            with contextlib.suppress(TransportError, StateError):  # closing anyway
                await self._client._request(
                    lambda id: Unsubscribe(id=id, topic=self._topic), f"unsubscribe {self._topic}"
                )

    def __aiter__(self) -> ClientSubscription[T]:
        return self

    async def __anext__(self) -> T:
        if not self._started:
            await self.start()
        while not self._queue:
            if self._closed:
                if self._error is not None:
                    raise self._error
                raise StopAsyncIteration
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._queue.popleft()

    async def __aenter__(self) -> ClientSubscription[T]:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    def _put(self, sample: T, dropped: int) -> None:
        self.dropped += dropped
        if len(self._queue) >= self._maxlen:
            self._queue.popleft()
            self.dropped += 1
        self._queue.append(sample)
        self._wake()

    def _end(self, error: TransportClosedError | None) -> None:
        if self._closed:
            return
        self._closed = True
        self._error = error
        self._forget()
        self._wake()

    def _forget(self) -> None:
        if self._client._subscriptions.get(self._topic) is self:
            del self._client._subscriptions[self._topic]

    def _wake(self) -> None:
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)


class RemoteServo:
    """The neck or a HerkuleX servo through the daemon (:attr:`RobotClient.neck`,
    :meth:`RobotClient.servo`): the Robot's handle's commands, awaited, with the lease.

    The daemon's Robot checks every target against the servo's range before anything is
    sent; a refusal raises :class:`~ohmni_tb.errors.InvalidArgumentError` naming it.
    """

    def __init__(self, client: RobotClient, target: str | int) -> None:
        self._client = client
        self.target = target

    def __repr__(self) -> str:
        return f"<RemoteServo {self.target!r} at {self._client.url}>"

    async def move(
        self, raw: int | None = None, *, rad: float | None = None, playtime_s: float | None = None
    ) -> None:
        """Move to ``raw`` counts or ``rad`` over ``playtime_s`` (a worm-gear neck: ``raw``
        only); returns when the daemon has sent it."""
        args: dict[str, Any] = {"target": self.target, "raw": raw}
        if rad is not None:
            args["rad"] = rad
        if playtime_s is not None:
            args["playtime_s"] = playtime_s
        await self._client._call("move", args)

    async def torque(self, mode: str) -> None:
        """``"on"``, ``"brake"`` or ``"free"`` (a HerkuleX servo)."""
        await self._client._call("torque", {"target": self.target, "mode": mode})

    async def free(self) -> None:
        """Torque off."""
        await self.torque("free")

    async def rest(self, *, free: bool = True) -> None:
        """Move to the rest position, then (by default) free it; returns when done."""
        await self._client._call("rest", {"target": self.target, "free": free})


def _unlimited(limit: float | None) -> float:
    return math.inf if limit is None else limit


def _check_topic(name: str) -> None:
    if name not in STREAM_NAMES:
        raise InvalidArgumentError(f"no stream {name!r}: the streams are {', '.join(STREAM_NAMES)}")


def _why(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "no answer in time"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
