"""The connection under a :class:`~ohmni_tb.robot.RemoteRobot`: one WebSocket to the daemon.

It greets (``hello``), sends every message through one queue in the order of the calls,
reads in one task (and, with ``reconnect``, connects again each time the daemon goes
away), answers each request's waiter, and hands samples and lease changes to its owner.
A command sent without waiting that the daemon refuses is kept and raised by the next
command or :meth:`DaemonConnection.confirm`.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb._version import __version__
from ohmni_tb.errors import (
    InvalidArgumentError,
    LeaseError,
    OhmniError,
    ProtocolError,
    RobotClosedError,
    StateError,
    TransportClosedError,
    TransportError,
)
from ohmni_tb.robot.wire import (
    PROTOCOL_VERSION,
    BatchMessage,
    Call,
    ErrorMessage,
    Hello,
    LeaseMessage,
    Result,
    SampleMessage,
    encode,
    parse_server_message,
    raised_error,
)

if TYPE_CHECKING:
    from pydantic import BaseModel
    from websockets.asyncio.client import ClientConnection

__all__ = ["DEFAULT_TIMEOUT_S", "MAX_UNSENT", "DaemonConnection", "open_websocket"]

#: How long connecting, and each call, may take.
DEFAULT_TIMEOUT_S: Final = 5.0
#: Messages waiting to be sent to a daemon that does not take them; one more is an error.
MAX_UNSENT: Final = 256
#: The server's messages are samples and small results; a stats reply is a few KiB.
_MAX_FRAME_BYTES = 1024 * 1024
#: Connecting again: the first wait, then doubling up to the last.
_FIRST_RETRY_S = 0.05
_MAX_RETRY_S = 2.0

_log = logging.getLogger("ohmni_tb.client")

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
    "source_forbidden": LeaseError,
    "rate_limited": ProtocolError,
}
#: The codes whose message is the daemon's Robot's own (after ``method: ``): raised as the
#: Robot raised it, word for word.
_ROBOT_CODES = frozenset({"bad_value", "robot_state", "robot_error"})


class DaemonConnection:
    """One connection to the daemon (module docstring). Start it with :meth:`start`."""

    def __init__(
        self,
        ws: ClientConnection,
        url: str,
        hello: Hello,
        timeout_s: float,
        *,
        headers: dict[str, str] | None = None,
        reconnect: bool = False,
        source: str = "remote",
    ) -> None:
        self._ws = ws
        self.url = url
        self.hello = hello
        self.timeout_s = timeout_s
        self._headers = headers
        self._reconnect = reconnect
        #: Times the connection was made again after the daemon went away.
        self.reconnects = 0
        #: The command source this connection drives as (the lease it takes).
        self.source = source
        #: Who holds each command source's lease (a peer), as last told by the daemon.
        self.holders: dict[str, str] = dict(hello.leases)
        #: Called with each sample message, each lease message, and the new ``hello``
        #: after connecting again.
        self.on_sample: Callable[[SampleMessage], None] = lambda message: None
        self.on_lease: Callable[[LeaseMessage], None] = lambda message: None
        self.on_reconnected: Callable[[Hello], None] = lambda hello: None
        #: Called once when the connection ends for good: with its error, or ``None``
        #: when it was closed on purpose.
        self.on_ended: Callable[[TransportClosedError | None], None] = lambda error: None
        self._ids = itertools.count(1)
        self._pending: dict[int | str, tuple[asyncio.Future[Any], str]] = {}
        self._reader: asyncio.Task[None] | None = None
        self._writer: asyncio.Task[None] | None = None
        self.closing = False
        #: Why the connection is down (``None``: it is up).
        self.lost: TransportClosedError | None = None
        self._unsent: deque[str] = deque()
        self._unsent_ready = asyncio.Event()
        # Commands sent without waiting: their answers, and the first refusal not raised.
        self._commands: set[asyncio.Future[Any]] = set()
        self._refusal: OhmniError | None = None

    @property
    def peer(self) -> str:
        """This connection as the daemon names it (``host:port``)."""
        return self.hello.peer

    @property
    def holder(self) -> str | None:
        """Who holds the lease of this connection's command source, as last told."""
        return self.holders.get(self.source)

    @holder.setter
    def holder(self, peer: str | None) -> None:
        if peer is None:
            self.holders.pop(self.source, None)
        else:
            self.holders[self.source] = peer

    @property
    def has_lease(self) -> bool:
        """Whether this connection holds the lease of its command source."""
        return self.holds(self.source)

    def holds(self, source: str) -> bool:
        """Whether this connection holds the lease of command source ``source``."""
        return self.holders.get(source) == self.hello.peer

    @property
    def connected(self) -> bool:
        """Whether the connection is up (``False`` while connecting again)."""
        return self.lost is None

    def start(self) -> None:
        """Start reading and writing."""
        loop = asyncio.get_running_loop()
        self._reader = loop.create_task(self._run(), name=f"ohmni-client {self.url}")
        self._writer = loop.create_task(self._write_loop(), name=f"ohmni-client-writer {self.url}")

    # -- requests --------------------------------------------------------------------------

    def check(self) -> None:
        """Raises RobotClosedError, or the connection's loss: nothing can be sent."""
        if self.closing:
            raise RobotClosedError
        if self.lost is not None:
            raise self.lost

    async def call(
        self, method: str, args: BaseModel | None = None, *, until_done: bool = False
    ) -> Any:
        """Call ``method`` and wait for its answer (within the connection's ``timeout_s``,
        or as long as it takes with ``until_done``).

        Raises:
            OhmniError: The daemon refused it (its code as one of our errors).
            TransportError: No answer in time, or the daemon went away.
        """
        data = {} if args is None else args.model_dump()
        return await self.request(
            lambda id: Call(id=id, method=method, args=data), method, until_done=until_done
        )

    async def request(
        self, make: Callable[[int], BaseModel], what: str, *, until_done: bool = False
    ) -> Any:
        """Send the message ``make(id)`` and wait for the answer to ``id``."""
        future = self.send_request(make, what)
        timeout = None if until_done else self.timeout_s
        try:
            async with asyncio.timeout(timeout):
                return await future
        except TimeoutError:
            raise TransportError(
                f"the daemon at {self.url} did not answer {what} within {self.timeout_s:g} s"
            ) from None
        finally:
            if not future.done():
                future.cancel()

    def send_request(self, make: Callable[[int], BaseModel], what: str) -> asyncio.Future[Any]:
        """Send the message ``make(id)``; the future of its answer (not waited for)."""
        self.check()
        id = next(self._ids)
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._pending[id] = (future, what)  # registered before sending: the reply cannot beat it
        future.add_done_callback(lambda _: self._pending.pop(id, None))
        try:
            self._send(encode(make(id)))
        except BaseException:
            future.cancel()
            raise
        return future

    def command(self, method: str, args: BaseModel | None = None) -> asyncio.Future[Any]:
        """Send a call without waiting: its refusal is raised by the next command (or
        :meth:`confirm`), after an earlier refusal not raised yet is."""
        self.check()
        self.raise_refusal()
        data = {} if args is None else args.model_dump()
        future = self.send_request(lambda id: Call(id=id, method=method, args=data), method)
        self._commands.add(future)
        future.add_done_callback(self._command_done)
        return future

    async def confirm(self) -> None:
        """Wait until the daemon has answered every command sent so far; raise the first
        refusal not raised yet."""
        if self._commands:
            try:
                async with asyncio.timeout(self.timeout_s):
                    await asyncio.wait(list(self._commands))
            except TimeoutError:
                raise TransportError(
                    f"the daemon at {self.url} did not answer the commands sent within "
                    f"{self.timeout_s:g} s"
                ) from None
        self.raise_refusal()

    def raise_refusal(self) -> None:
        """Raise the first command the daemon refused, if not raised yet."""
        refusal, self._refusal = self._refusal, None
        if refusal is not None:
            raise refusal

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

    def _send(self, frame: str) -> None:
        if len(self._unsent) >= MAX_UNSENT:
            raise TransportError(
                f"the daemon at {self.url} is not taking messages: {MAX_UNSENT} wait to be sent"
            )
        self._unsent.append(frame)
        self._unsent_ready.set()

    # -- reading and writing ---------------------------------------------------------------

    async def _write_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        with contextlib.suppress(ConnectionClosed):
            while True:
                await self._unsent_ready.wait()
                self._unsent_ready.clear()
                while self._unsent:
                    await self._ws.send(self._unsent.popleft())
                if self.closing:
                    return

    async def _run(self) -> None:
        """Read the connection; with ``reconnect``, make it again each time it ends."""
        delay = _FIRST_RETRY_S
        while True:
            await self._read_loop()
            lost = self._closed_error()
            self.lost = lost
            self._unsent.clear()  # the old connection's; their callers were told
            for future, _ in list(self._pending.values()):
                if not future.done():
                    future.set_exception(lost)
            if self.closing or not self._reconnect:
                self.on_ended(None if self.closing else lost)
                return
            _log.warning("%s; connecting again", lost)
            while True:
                await asyncio.sleep(delay)
                delay = min(delay * 2, _MAX_RETRY_S)
                try:
                    ws, hello = await open_websocket(self.url, self._headers, self.timeout_s)
                    break
                except TransportError as exc:
                    _log.info("%s; again in %.1f s", exc, delay)
            delay = _FIRST_RETRY_S
            self._reconnected(ws, hello)

    def _reconnected(self, ws: ClientConnection, hello: Hello) -> None:
        had_lease = any(peer == self.hello.peer for peer in self.holders.values())
        self._ws = ws
        self.hello = hello
        self.holders = dict(hello.leases)
        self.lost = None
        self.reconnects += 1
        _log.warning(
            "connected again to the daemon at %s%s",
            self.url,
            ": the control lease was lost with the connection" if had_lease else "",
        )
        if self._writer is None or self._writer.done():
            self._writer = asyncio.get_running_loop().create_task(
                self._write_loop(), name=f"ohmni-client-writer {self.url}"
            )
        self.on_reconnected(hello)

    async def _read_loop(self) -> None:
        from websockets.exceptions import ConnectionClosed  # noqa: PLC0415

        with contextlib.suppress(ConnectionClosed):
            async for frame in self._ws:
                try:
                    message = parse_server_message(frame)
                except ValueError as exc:
                    _log.warning("the daemon at %s sent a bad message: %s", self.url, exc)
                    continue
                self._dispatch(message)

    def _dispatch(self, message: Any) -> None:
        if isinstance(message, BatchMessage):
            for one in message.samples:
                self.on_sample(one)
        elif isinstance(message, SampleMessage):
            self.on_sample(message)
        elif isinstance(message, LeaseMessage):
            had = self.holds(message.source)
            if message.holder is None:
                self.holders.pop(message.source, None)
            else:
                self.holders[message.source] = message.holder
            if had and not message.you:
                which = "" if message.source == self.source else f" of {message.source}"
                _log.warning("lost the control lease%s at %s: %s", which, self.url, message.reason)
            self.on_lease(message)
        elif isinstance(message, Result | ErrorMessage):
            waiting = self._pending.get(message.id) if message.id is not None else None
            if waiting is None or waiting[0].done():
                if isinstance(message, ErrorMessage):
                    _log.warning(
                        "the daemon at %s: %s (%s)", self.url, message.message, message.code
                    )
                return
            future, what = waiting
            if isinstance(message, Result):
                future.set_result(message.data)
            else:
                future.set_exception(self._error(message, what))

    def _error(self, message: ErrorMessage, what: str) -> OhmniError:
        """The daemon's ``error`` as ours: the Robot's own refusal as the Robot raised it,
        the daemon's with what it refused."""
        error = _ERRORS.get(message.code, OhmniError)
        if message.code in _ROBOT_CODES:
            said = message.message.removeprefix(f"{what}: ")
            return raised_error(message.raised, said) or error(said)
        text = f"the daemon refused: {message.message}"
        return LeaseError(text, holder=self.holder) if error is LeaseError else error(text)

    def _closed_error(self) -> TransportClosedError:
        code, reason = self._ws.close_code, self._ws.close_reason
        how = "no close code" if code is None else f"{code}{' ' + reason if reason else ''}"
        return TransportClosedError(f"the daemon at {self.url} closed the connection ({how})")

    async def aclose(self) -> None:
        """Send what is queued (a last stop), close the connection, stop reading."""
        self.closing = True
        self._unsent_ready.set()  # the writer sends what is queued, then ends
        if self._writer is not None:
            try:
                async with asyncio.timeout(self.timeout_s):
                    await self._writer
            except TimeoutError:
                self._writer.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await self._writer
        await self._ws.close()
        if self._reader is not None:
            if self.lost is not None:
                self._reader.cancel()  # waiting to connect again: no more
            with contextlib.suppress(asyncio.CancelledError):
                await self._reader
            if self._reader.cancelled():
                self.on_ended(None)


async def open_websocket(
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
                first = await ws.recv()
            _check_protocol(url, first)
            hello = parse_server_message(first)
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


def _check_protocol(url: str, first: str | bytes) -> None:
    """Refuse a daemon of another protocol version, naming both (before its hello is
    read as this version's: its fields may differ).

    Raises:
        TransportError: The hello names another protocol version.
    """
    try:
        doc = json.loads(first)
    except ValueError:
        return  # not JSON: parse_server_message says so
    if not isinstance(doc, dict) or doc.get("op") != "hello":
        return
    theirs = doc.get("protocol")
    if theirs != PROTOCOL_VERSION:
        raise TransportError(
            f"the daemon at {url} speaks protocol {theirs!r} (ohmni_tb "
            f"{doc.get('version', '?')}), this client protocol {PROTOCOL_VERSION} (ohmni_tb "
            f"{__version__}): run the same ohmni_tb version on both sides"
        )


def _why(exc: BaseException) -> str:
    if isinstance(exc, TimeoutError):
        return "no answer in time"
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__
