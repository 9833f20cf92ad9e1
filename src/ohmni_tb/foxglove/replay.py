"""Serve a recording to the Foxglove app as if it were live: ``ohmni replay FILE.mcap``.

::

    async with McapReplay("run.mcap", port=0, speed=2.0) as replay:
        print(replay.url)                             # ws://127.0.0.1:…
        sent = await replay.run()                     # every message, on its recorded time

The file's channels are advertised as they were recorded (topic, message encoding,
schema), so the app shows a replay exactly as the live view: the 3D view's transforms,
the plots, the battery. Each message goes out with its recorded log time, paced by the
recorded gaps (divided by ``speed``); a client that connects late sees the rest. The
file is read on the event loop as the messages are due, a chunk at a time: this process
drives no robot, and a chunk (about a second of the streams) reads in a millisecond or
two.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any, Final

import foxglove
from foxglove.websocket import WebSocketServer
from mcap.exceptions import McapError
from mcap.reader import make_reader

from ohmni_tb._checks import bounded, integer
from ohmni_tb.errors import OhmniError, TransportError
from ohmni_tb.foxglove.bridge import DEFAULT_HOST, DEFAULT_PORT, _Served
from ohmni_tb.foxglove.record import RAW_TOPICS

__all__ = ["MAX_SPEED", "McapReplay", "ReplayError", "raw_bus_bytes"]

#: The fastest replay: a minute of recording in a second and a half.
MAX_SPEED: Final = 40.0


class ReplayError(OhmniError):
    """A recording that cannot be replayed: not found, not MCAP, or cut short inside."""


def raw_bus_bytes(path: str | Path) -> Iterator[tuple[float, bool, bytes]]:
    """The bus bytes of a ``ohmni record --raw`` recording, in the order they happened:
    (seconds since the first chunk, whether the host wrote them, the bytes).

    Raises:
        ReplayError: No such file, not MCAP, no raw bus bytes in it, or a chunk that is
            not one (the message names the file).
    """
    with _open(path) as file:
        try:
            reader = make_reader(file)
            first_ns: int | None = None
            found = False
            for _, channel, message in reader.iter_messages(
                topics=list(RAW_TOPICS), log_time_order=True
            ):
                found = True
                if first_ns is None:
                    first_ns = message.log_time
                try:
                    data = bytes.fromhex(json.loads(message.data)["data"])
                except (ValueError, KeyError, TypeError) as exc:
                    raise ReplayError(
                        f"{path}: a {channel.topic} message is not bus bytes: {message.data[:60]!r}"
                    ) from exc
                yield (message.log_time - first_ns) / 1e9, channel.topic == RAW_TOPICS[0], data
        except (McapError, EOFError) as exc:
            raise ReplayError(
                f"{path} is not an MCAP recording (or ends inside a record): {exc}"
            ) from exc
        if not found:
            raise ReplayError(
                f"{path} has no raw bus bytes ({', '.join(RAW_TOPICS)}): record them with "
                "ohmni record --raw"
            )


def _open(path: str | Path) -> IO[bytes]:
    """The recording, open for reading.

    Raises:
        ReplayError: It cannot be opened; the message names it and why.
    """
    try:
        return Path(path).open("rb")
    except OSError as exc:
        raise ReplayError(f"cannot open {path}: {exc.strerror or exc}") from exc


class McapReplay(_Served):
    """A Foxglove WebSocket server playing an MCAP recording (module docstring).

    Args:
        path: The ``.mcap`` file.
        host: Address to listen on (loopback by default; the protocol has no
            authentication).
        port: TCP port; 0 picks a free one (see :attr:`port`).
        speed: Playback speed, 0.01..:data:`MAX_SPEED` (1: as recorded).
        name: The server's name, shown by the app.

    Raises:
        OutOfRangeError: ``port`` not 0..65535, or ``speed`` not 0.01..40.
        InvalidArgumentError: ``speed`` not a number.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        speed: float = 1.0,
        name: str = "ohmni_tb replay",
    ) -> None:
        self._speed = bounded("speed", speed, 0.01, MAX_SPEED)
        self._path = Path(path)
        self._host = host
        self._port = integer("port", port, 0, 65535)
        self._name = name
        self._context = foxglove.Context()
        self._channels: dict[int, foxglove.Channel] = {}
        self._server: WebSocketServer | None = None
        self._file: IO[bytes] | None = None
        #: Messages sent so far, by topic.
        self.sent: dict[str, int] = {}

    @property
    def topics(self) -> list[str]:
        """The recording's topics, as advertised."""
        return sorted(channel.topic() for channel in self._channels.values())

    async def start(self) -> None:
        """Open the file, advertise its channels, listen.

        Raises:
            ReplayError: No such file, or not an MCAP file.
            TransportError: The address cannot be bound.
        """
        self._file = _open(self._path)
        try:
            summary = make_reader(self._file).get_summary()
        except (McapError, ValueError, EOFError) as exc:
            self._file.close()
            raise ReplayError(f"{self._path} is not an MCAP recording: {exc}") from exc
        if summary is not None:  # without one (a cut file) channels come as they appear
            for channel in summary.channels.values():
                self._channel(channel, summary.schemas.get(channel.schema_id))
        try:
            self._server = self._listen(name=self._name, context=self._context)
        except TransportError:
            self._file.close()
            raise

    def _channel(self, channel: Any, schema: Any) -> foxglove.Channel:
        made = self._channels.get(channel.id)
        if made is None:
            made = foxglove.Channel(
                channel.topic,
                message_encoding=channel.message_encoding,
                schema=None
                if schema is None
                else foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data),
                context=self._context,
                metadata=dict(channel.metadata) or None,
            )
            self._channels[channel.id] = made
        return made

    async def run(self) -> int:
        """Send every message on its recorded time (scaled by ``speed``); the count sent.

        Raises:
            ReplayError: The file ends inside a record (what came before was sent).
        """
        if self._file is None:
            raise ReplayError("start() the replay first")
        self._file.seek(0)
        loop = asyncio.get_running_loop()
        start_at: float | None = None
        first_ns = 0
        count = 0
        try:
            for schema, channel, message in make_reader(self._file).iter_messages(
                log_time_order=True
            ):
                if start_at is None:
                    start_at, first_ns = loop.time(), message.log_time
                due = start_at + (message.log_time - first_ns) / 1e9 / self._speed
                if (wait := due - loop.time()) > 0:
                    await asyncio.sleep(wait)
                self._channel(channel, schema).log(message.data, log_time=message.log_time)
                self.sent[channel.topic] = self.sent.get(channel.topic, 0) + 1
                count += 1
        except (McapError, ValueError, EOFError) as exc:
            raise ReplayError(f"{self._path} ends inside a record after {count} messages") from exc
        return count

    async def aclose(self) -> None:
        """Stop listening and close the file. Idempotent."""
        server, self._server = self._server, None
        if server is not None:
            await asyncio.to_thread(server.stop)
        if self._file is not None:
            self._file.close()
            self._file = None

    async def __aenter__(self) -> McapReplay:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
