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
"""

from __future__ import annotations

from typing import Final

import foxglove
from foxglove.websocket import WebSocketServer

from ohmni_tb._checks import integer
from ohmni_tb.errors import TransportError
from ohmni_tb.foxglove._pump import DEFAULT_QUEUE, ChannelStats, Pump, StreamSource

__all__ = ["DEFAULT_BACKLOG", "DEFAULT_HOST", "DEFAULT_PORT", "FoxgloveBridge"]

#: Loopback: the Foxglove protocol has no authentication, so the default is this machine.
DEFAULT_HOST: Final = "127.0.0.1"
#: The Foxglove app's default connection (ws://localhost:8765); ``ohmni serve`` uses 8766.
DEFAULT_PORT: Final = 8765
#: Messages the SDK queues per client before it drops that client's oldest: 2 s of every
#: stream (about 500 messages a second when a client subscribes to all of them).
DEFAULT_BACKLOG: Final = 1024


class FoxgloveBridge:
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

    Raises:
        OutOfRangeError: ``port`` not 0..65535, or ``message_backlog`` / ``queue`` not
            1..100000.
    """

    def __init__(
        self,
        robot: StreamSource,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        name: str = "ohmni_tb",
        message_backlog: int = DEFAULT_BACKLOG,
        queue: int = DEFAULT_QUEUE,
    ) -> None:
        self._robot = robot
        self._host = host
        self._port = integer("port", port, 0, 65535)
        self._name = name
        self._backlog = integer("message_backlog", message_backlog, 1, 100_000)
        self._queue = integer("queue", queue, 1, 100_000)
        self._context = foxglove.Context()
        self._pump: Pump | None = None
        self._server: WebSocketServer | None = None
        self._closed = False

    @property
    def host(self) -> str:
        """The address it listens on."""
        return self._host

    @property
    def port(self) -> int:
        """The TCP port (the one chosen, when 0 was asked)."""
        return self._port

    @property
    def url(self) -> str:
        """``ws://host:port``: the Foxglove app's "Foxglove WebSocket" connection."""
        host = f"[{self._host}]" if ":" in self._host else self._host
        return f"ws://{host}:{self._port}"

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

    async def start(self) -> None:
        """Make the channels, listen, and start reading the streams.

        Raises:
            TransportError: The address cannot be bound (in use, not this machine's).
        """
        # The channels exist before the server, so a client sees them all at once.
        self._pump = Pump(self._robot, self._context, queue=self._queue)
        try:
            self._server = foxglove.start_server(
                name=self._name,
                host=self._host,
                port=self._port,
                context=self._context,
                message_backlog_size=self._backlog,
            )
        except RuntimeError as exc:  # the SDK's FoxgloveError: "Failed to bind port: …"
            reason = str(exc).removeprefix("FoxgloveError: ").removeprefix("Failed to bind port: ")
            await self._pump.aclose()
            raise TransportError(f"cannot listen on {self.url}: {reason}") from exc
        self._port = self._server.port
        self._pump.start()

    async def aclose(self) -> None:
        """Stop reading the streams, close the clients, stop listening. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._pump is not None:
            await self._pump.aclose()
        if self._server is not None:
            self._server.stop()
            self._server = None

    async def __aenter__(self) -> FoxgloveBridge:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
