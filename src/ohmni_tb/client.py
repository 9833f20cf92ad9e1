"""The Robot's read-only API over the daemon (``ohmni serve``).

::

    from ohmni_tb.client import RobotClient

    async with RobotClient.connect("ws://127.0.0.1:8766") as robot:
        odom = await robot.latest("wheel_odom")        # the same WheelOdomSample
        async with robot.subscribe("tbcore_status", max_hz=2) as status:
            async for sample in status:
                print(sample.pack_v)
        print(await robot.stats())

Samples are the Robot's own frozen dataclasses, rebuilt from the daemon's JSON, so code
written against :class:`~ohmni_tb.Robot`'s samples reads them unchanged. What differs from
the embedded Robot: ``latest`` and ``stats`` are awaited (they may ask the daemon), and
there is one subscription per topic and connection. Motion commands come with the
daemon's control lease (not in this version).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
from collections import deque
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any, Final, Generic, Literal, TypeVar, overload

from pydantic import ValidationError

from ohmni_tb.daemon.protocol import (
    Call,
    ErrorMessage,
    Hello,
    LatestArgs,
    NoArgs,
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
    InvalidArgumentError,
    OhmniError,
    ProtocolError,
    StateError,
    TransportClosedError,
    TransportError,
)
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

    from ohmni_tb.robot.core import RobotStats

__all__ = ["DEFAULT_TIMEOUT_S", "DEFAULT_URL", "ClientSubscription", "RobotClient"]

#: Where ``ohmni serve`` listens by default.
DEFAULT_URL: Final = "ws://127.0.0.1:8766"
#: How long connecting, and each call, may take.
DEFAULT_TIMEOUT_S: Final = 5.0
#: The server's messages are samples and small results; a stats reply is a few KiB.
_MAX_FRAME_BYTES = 1024 * 1024

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
    "not_subscribed": StateError,
    "rate_limited": ProtocolError,
}


class RobotClient:
    """A connection to the daemon: the Robot's streams and read-only services.

    Open it with ``async with RobotClient.connect(url) as robot:``.
    """

    def __init__(self, ws: ClientConnection, url: str, hello: Hello, timeout_s: float) -> None:
        self._ws = ws
        self._url = url
        self._hello = hello
        self._timeout_s = timeout_s
        self._ids = itertools.count(1)
        self._pending: dict[int | str, asyncio.Future[Any]] = {}
        self._latest: dict[str, Any] = {}
        self._subscriptions: dict[str, ClientSubscription[Any]] = {}
        self._reader: asyncio.Task[None] | None = None
        self._closing = False
        self._lost: TransportClosedError | None = None

    @classmethod
    @asynccontextmanager
    async def connect(
        cls, url: str = DEFAULT_URL, *, timeout_s: float = DEFAULT_TIMEOUT_S
    ) -> AsyncIterator[RobotClient]:
        """Connect to the daemon at ``url``; leaving the block closes the connection.

        Raises:
            TransportError: Nothing answers at ``url``, or it is not the daemon.
        """
        from websockets.asyncio.client import connect  # noqa: PLC0415  # loaded when used
        from websockets.exceptions import (  # noqa: PLC0415
            ConnectionClosed,
            InvalidHandshake,
            InvalidURI,
        )

        try:
            async with asyncio.timeout(timeout_s):
                ws = await connect(url, max_size=_MAX_FRAME_BYTES, compression=None)
        except (OSError, InvalidHandshake, InvalidURI, TimeoutError) as exc:
            raise TransportError(f"cannot connect to the daemon at {url}: {_why(exc)}") from exc
        try:
            try:
                async with asyncio.timeout(timeout_s):
                    hello = parse_server_message(await ws.recv())
            except (TimeoutError, ValueError, OSError) as exc:
                raise TransportError(
                    f"{url} did not greet as the ohmni daemon: {_why(exc)}"
                ) from exc
            except ConnectionClosed as exc:
                raise TransportError(f"{url} closed the connection at once: {exc}") from exc
            if not isinstance(hello, Hello):
                raise TransportError(f"{url} did not greet as the ohmni daemon ({hello.op} first)")
            client = cls(ws, url, hello, timeout_s)
            client._reader = asyncio.get_running_loop().create_task(
                client._read_loop(), name=f"ohmni-client {url}"
            )
            try:
                yield client
            finally:
                await client._aclose()
        finally:
            await ws.close()

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
        data = await self._call("latest", LatestArgs(topic=name))
        return None if data is None else sample_from_json(name, data)

    def subscribe(
        self, name: str, *, max_hz: float | None = None, maxlen: int = DEFAULT_QUEUE_SIZE
    ) -> ClientSubscription[Any]:
        """The samples of stream ``name`` from now on (an async iterator; also ``async with``).

        ``max_hz`` caps the rate (the daemon sends at most that many a second, the newest
        each time); ``maxlen`` bounds the queue here and at the daemon: a reader that
        falls behind loses the oldest, counted in ``dropped``.

        Raises:
            InvalidArgumentError: No such stream, or ``max_hz`` (above 0, at most 1000) or
                ``maxlen`` (1..1024) out of range.
            StateError: This connection already has a subscription to it.
        """
        _check_topic(name)
        try:
            Subscribe(id=0, topic=name, max_hz=max_hz, queue=maxlen)
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
        subscription: ClientSubscription[Any] = ClientSubscription(self, name, max_hz, maxlen)
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

    # -- internals --------------------------------------------------------------------------

    async def _call(self, method: str, args: LatestArgs | NoArgs | None = None) -> Any:
        return await self._request(
            lambda id: Call(id=id, method=method, args=args or NoArgs()), method
        )

    async def _request(self, make: Any, what: str) -> Any:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        if self._lost is not None:
            raise self._lost
        id = next(self._ids)
        message: BaseModel = make(id)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[id] = future  # registered before sending: the reply cannot beat it
        try:
            await self._ws.send(encode(message))
            async with asyncio.timeout(self._timeout_s):
                return await future
        except TimeoutError:
            raise TransportError(
                f"the daemon at {self._url} did not answer {what} within {self._timeout_s:g} s"
            ) from None
        except ConnectionClosed:
            raise self._closed_error() from None
        finally:
            self._pending.pop(id, None)

    async def _read_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        try:
            async for frame in self._ws:
                try:
                    message = parse_server_message(frame)
                except ValueError as exc:
                    _log.warning("the daemon at %s sent a bad message: %s", self._url, exc)
                    continue
                self._dispatch(message)
        except ConnectionClosed:
            pass
        finally:
            self._lost = self._closed_error()
            for future in self._pending.values():
                if not future.done():
                    future.set_exception(self._lost)
            for subscription in list(self._subscriptions.values()):
                subscription._end(None if self._closing else self._lost)

    def _dispatch(self, message: Any) -> None:
        if isinstance(message, SampleMessage):
            sample = sample_from_json(message.topic, message.data)
            self._latest[message.topic] = sample
            subscription = self._subscriptions.get(message.topic)
            if subscription is not None:
                subscription._put(sample, message.dropped)
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
                error = _ERRORS.get(message.code, OhmniError)
                future.set_exception(error(f"the daemon refused: {message.message}"))

    def _closed_error(self) -> TransportClosedError:
        code, reason = self._ws.close_code, self._ws.close_reason
        how = "no close code" if code is None else f"{code}{' ' + reason if reason else ''}"
        return TransportClosedError(f"the daemon at {self._url} closed the connection ({how})")

    async def _aclose(self) -> None:
        self._closing = True
        await self._ws.close()
        if self._reader is not None:
            await self._reader


class ClientSubscription(Generic[T]):
    """One topic's samples from the daemon: an async iterator, bounded (``dropped``).

    Iteration ends when it is closed or the client closes; it raises
    :class:`~ohmni_tb.errors.TransportClosedError` when the daemon goes away.
    """

    def __init__(self, client: RobotClient, topic: str, max_hz: float | None, maxlen: int) -> None:
        self._client = client
        self._topic = topic
        self._max_hz = max_hz
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
                    id=id, topic=self._topic, max_hz=self._max_hz, queue=self._maxlen
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


def _check_topic(name: str) -> None:
    if name not in STREAM_NAMES:
        raise InvalidArgumentError(f"no stream {name!r}: the streams are {', '.join(STREAM_NAMES)}")


def _why(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "no answer in time"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
