"""A client of the daemon inside its own process.

::

    client = LocalClient(server, "mqtt:kitchen")
    await client.call("light_ring", {"hue": 0, "saturation": 255, "value": 128})
    client.close()

A bridge to another protocol (MQTT) calls the daemon's services through the same dispatch
as a WebSocket client: the same argument checks, the same control lease (it must
``acquire`` it before a command that needs it, and is refused when another client holds
it), ``read_only``, and whatever else the dispatch applies. Only the transport is left
out: no socket, no JSON frames on the wire. It is a reader like the others for the
lease: when the lease changes hands, :attr:`LocalClient.on_lease` is told.
"""

from __future__ import annotations

import asyncio
import itertools
import json
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb.robot.wire import (
    ErrorMessage,
    LeaseMessage,
    RequestError,
    Result,
    parse_client_message,
    parse_server_message,
)

if TYPE_CHECKING:
    from ohmni_tb.daemon.server import ClientFigures, RobotServer

__all__ = ["LocalClient"]

#: Refusals of one local client logged at most once per this many seconds (the rest
#: counted), as for a WebSocket client.
_REFUSAL_LOG_S: Final = 10.0


class LocalClient:
    """A client of the daemon in its own process: see the module docstring.

    It joins ``server``'s clients when made; :meth:`close` it when done (it releases the
    lease if it holds it, which stops the wheels).

    Args:
        server: The daemon's server, started.
        peer: How the daemon names it, as ``host:port`` names a WebSocket client.

    Attributes:
        peer: How the daemon names it (in ``lease`` messages and its log).
        on_lease: Called with each ``lease`` message (the lease changed hands).
    """

    def __init__(self, server: RobotServer, peer: str) -> None:
        from ohmni_tb.daemon.server import _Throttled  # noqa: PLC0415  # the same log habit

        self.peer = peer
        self.on_lease: Callable[[LeaseMessage], None] | None = None
        #: The dispatch's fields for every client (the server reads and sets them).
        self.subscriptions: dict[str, Any] = {}
        #: The command sources whose leases it holds, and since when (the server keeps it).
        self.leases: dict[str, float] = {}
        #: Not a loopback peer: what it relays comes from the network (a broker), so it
        #: may claim no source above ``remote``.
        self.loopback = False
        self.refusals = _Throttled(_REFUSAL_LOG_S)
        self._server = server
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[Any]] = {}
        self._closed = False
        #: Calls answered, and refused.
        self.calls = 0
        self.refused = 0
        server._attach(self)  # type: ignore[arg-type]  # duck-typed client

    @property
    def holds_lease(self) -> bool:
        """Whether this client holds a control lease (of any command source)."""
        return bool(self.leases)

    async def call(self, method: str, args: dict[str, Any] | None = None) -> Any:
        """Call the daemon's service ``method`` (:data:`~ohmni_tb.robot.wire.METHODS`) with
        ``args``, as a WebSocket client's ``call`` would; the data of its ``result``.

        Raises:
            RequestError: The daemon refused it (``code``: ``no_lease``, ``bad_message``,
                ``bad_value`` …; ``raised``: the Robot's own exception, when it was one),
                or this client is closed (``robot_state``).
        """
        if self._closed:
            raise RequestError("robot_state", f"{method}: {self.peer} is closed")
        ident = next(self._ids)
        # The same parse as a frame from the wire: unknown methods, topics and argument
        # types are refused with the same words.
        frame = json.dumps({"op": "call", "id": ident, "method": method, "args": args or {}})
        try:
            message = parse_client_message(frame)
        except RequestError:
            self.refused += 1
            raise
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        self._waiting[ident] = future  # registered before the dispatch may answer
        try:
            self._server._call(self, message)  # type: ignore[arg-type]  # duck-typed client
            result = await future
        except RequestError:
            self.refused += 1
            raise
        finally:
            self._waiting.pop(ident, None)
        self.calls += 1
        return result

    def close(self) -> None:
        """Leave the daemon: the lease is released if this client holds it (the wheels
        stop, as when any client leaves). Idempotent."""
        if self._closed:
            return
        self._server._detach(self)  # type: ignore[arg-type]  # duck-typed client
        self._closed = True
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(RequestError("robot_state", f"{self.peer} closed"))
        self._waiting.clear()
        self.refusals.close()

    # -- what the dispatch calls on every client ------------------------------------------

    def reply(self, message: Any) -> None:
        """A message the daemon sends this client."""
        if isinstance(message, LeaseMessage):
            if self.on_lease is not None:
                self.on_lease(message)
            return
        if isinstance(message, Result | ErrorMessage) and isinstance(message.id, int):
            future = self._waiting.get(message.id)
            if future is None or future.done():
                return
            if isinstance(message, Result):
                future.set_result(message.data)
            else:
                error = RequestError(message.code, message.message, message.id)
                error.raised = message.raised
                future.set_exception(error)

    def reply_frame(self, frame: str) -> None:
        """A message the daemon encoded already (``stats``)."""
        self.reply(parse_server_message(frame))

    def figures(self) -> ClientFigures:
        """Its figures among the daemon's clients."""
        from ohmni_tb.daemon.server import ClientFigures  # noqa: PLC0415

        return ClientFigures(peer=self.peer, topics=(), sent=self.calls, dropped=0, queued=0)
