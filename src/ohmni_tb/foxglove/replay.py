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

A damaged or hostile file costs bounded memory and ends in one :class:`ReplayError`
naming the file, what is wrong and where: only a regular file is opened (a FIFO or a
device is refused, and opening never waits), a chunk that declares more than 64 MiB
uncompressed (``ohmni record`` writes chunks of at most 1 MiB) is refused before it is
decompressed, and each chunk's CRC is checked. A recording without its index (cut short)
plays in the order it was written, up to where it ends.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Final

import foxglove
from foxglove.websocket import WebSocketServer

from ohmni_tb._checks import bounded, integer
from ohmni_tb.foxglove._recording import Recording, ReplayError
from ohmni_tb.foxglove.bridge import DEFAULT_HOST, DEFAULT_PORT, _Served
from ohmni_tb.foxglove.record import RAW_TOPICS

__all__ = ["MAX_SPEED", "McapReplay", "ReplayError", "raw_bus_bytes"]

#: The fastest replay: a minute of recording in a second and a half.
MAX_SPEED: Final = 40.0


def raw_bus_bytes(path: str | Path) -> Iterator[tuple[float, bool, bytes]]:
    """The bus bytes of a ``ohmni record --raw`` recording, in the order they happened:
    (seconds since the first chunk, whether the host wrote them, the bytes).

    Raises:
        ReplayError: No such file (or not a regular file), not MCAP, no raw bus bytes in
            it, or damaged inside (the message names the file and what is wrong).
    """
    with Recording(path) as recording:
        first_ns: int | None = None
        found = False
        for _, channel, message in recording.messages(topics=RAW_TOPICS):
            found = True
            if first_ns is None:
                first_ns = message.log_time
            try:
                data = bytes.fromhex(json.loads(message.data)["data"])
            # RecursionError: JSON nested thousands deep.
            except (ValueError, KeyError, TypeError, RecursionError) as exc:
                raise ReplayError(
                    f"{path}: a {channel.topic} message is not bus bytes: {message.data[:60]!r}"
                ) from exc
            yield (message.log_time - first_ns) / 1e9, channel.topic == RAW_TOPICS[0], data
        if not found:
            raise ReplayError(
                f"{path} has no raw bus bytes ({', '.join(RAW_TOPICS)}): record them with "
                "ohmni record --raw"
            )


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
        self._recording: Recording | None = None
        #: Messages sent so far, by topic.
        self.sent: dict[str, int] = {}

    @property
    def topics(self) -> list[str]:
        """The recording's topics, as advertised."""
        return sorted(channel.topic() for channel in self._channels.values())

    async def start(self) -> None:
        """Open the file, advertise its channels, listen.

        Raises:
            ReplayError: No such file, not a regular file, or not an MCAP file.
            TransportError: The address cannot be bound.
        """
        recording = Recording(self._path)
        try:
            # Without an index (a cut file) the channels come as they appear.
            for channel, schema in recording.channels:
                self._channel(channel, schema)
            self._server = self._listen(name=self._name, context=self._context)
        except BaseException:
            recording.close()
            raise
        self._recording = recording

    def _channel(self, channel: Any, schema: Any) -> foxglove.Channel:
        made = self._channels.get(channel.id)
        if made is None:
            try:
                made = foxglove.Channel(
                    channel.topic,
                    message_encoding=channel.message_encoding,
                    schema=None
                    if schema is None
                    else foxglove.Schema(
                        name=schema.name, encoding=schema.encoding, data=schema.data
                    ),
                    context=self._context,
                    metadata=dict(channel.metadata) or None,
                )
            # The SDK's refusals: a schemaless channel in another encoding than JSON...
            except (TypeError, ValueError) as exc:
                raise ReplayError(
                    f"{self._path}: channel {channel.topic!r} ({channel.message_encoding}) "
                    f"cannot be served to the app: {exc}"
                ) from exc
            self._channels[channel.id] = made
        return made

    async def run(self) -> int:
        """Send every message on its recorded time (scaled by ``speed``); the count sent.

        Raises:
            ReplayError: The file is damaged or ends inside a record (what came before
                was sent); the message says what and where.
        """
        if self._recording is None:
            raise ReplayError("start() the replay first")
        loop = asyncio.get_running_loop()
        start_at: float | None = None
        first_ns = 0
        count = 0
        try:
            for schema, channel, message in self._recording.messages():
                if start_at is None:
                    start_at, first_ns = loop.time(), message.log_time
                due = start_at + (message.log_time - first_ns) / 1e9 / self._speed
                if (wait := due - loop.time()) > 0:
                    await asyncio.sleep(wait)
                self._channel(channel, schema).log(message.data, log_time=message.log_time)
                self.sent[channel.topic] = self.sent.get(channel.topic, 0) + 1
                count += 1
        except ReplayError as exc:
            raise ReplayError(f"{exc} ({count} messages were replayed before)") from exc
        return count

    async def aclose(self) -> None:
        """Stop listening and close the file. Idempotent."""
        server, self._server = self._server, None
        if server is not None:
            await asyncio.to_thread(server.stop)
        if self._recording is not None:
            self._recording.close()
            self._recording = None

    async def __aenter__(self) -> McapReplay:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()
