"""An MCAP recording read within bounds, for ``ohmni replay`` and ``ohmni bus monitor``.

The ``mcap`` package's reader trusts the file it reads: a chunk's header may ask the
zstd decoder for gigabytes, and a damaged chunk surfaces as the decoder's own exception.
This reader takes the package's record layouts but reads the file itself:

- only a regular file is opened, and ``open()`` never waits (a FIFO, a device or a
  directory is refused by name);
- a record is read only when its length is at most :data:`MAX_CHUNK_BYTES` (plus the
  compressor's worst-case growth), a chunk is decompressed only when it declares at most
  :data:`MAX_CHUNK_BYTES` (its zstd frame must agree), into at most that much, and its
  CRC is checked;
- messages come in log-time order through the file's chunk index (as the ``mcap``
  reader gives them), holding at most about :data:`MAX_CHUNK_BYTES` of messages at once;
  chunks that overlap in time by more than that come in the order they are read. A file
  without its index (cut short) is read from the start, in the order it was written.

So a damaged or hostile file costs a few times :data:`MAX_CHUNK_BYTES` of memory at
most, and whatever is wrong with it is one :class:`ReplayError` naming the file, what is
wrong and where (the byte offset).
"""

from __future__ import annotations

import heapq
import io
import itertools
import os
import struct
import zlib
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Final

import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, Footer, Message, Schema

from ohmni_tb import _files
from ohmni_tb.errors import OhmniError

try:
    import lz4.frame as lz4_frame  # type: ignore[import-untyped]  # lz4 ships no type hints
except ImportError:  # pragma: no cover - mcap depends on lz4
    lz4_frame = None

__all__ = ["MAX_CHUNK_BYTES", "MessageTuple", "Recording", "ReplayError", "open_regular"]

#: The most one chunk of a recording may hold uncompressed: 64 MiB. ``ohmni record`` and
#: the mcap writers cut a chunk at 1 MiB (a message larger than that gets a chunk of its
#: own), so real recordings stay far below; a chunk that declares more is refused before
#: anything is decompressed.
MAX_CHUNK_BYTES: Final = 64 << 20
#: The longest record read: a chunk's compressed bytes may exceed its contents by the
#: compressor's worst-case growth (zstd and lz4: well under 1/64), plus its header.
_MAX_RECORD_BYTES: Final = MAX_CHUNK_BYTES + (MAX_CHUNK_BYTES >> 6) + 4096
#: Messages held for log-time order: a further chunk is opened only while they stay
#: within this (or when none are held).
_MAX_HELD_BYTES: Final = MAX_CHUNK_BYTES
#: What a held message costs besides its data (its objects and its place in the heap).
_MESSAGE_COST: Final = 200

_MAGIC: Final = b"\x89MCAP0\r\n"
_RECORD_HEAD: Final = struct.Struct("<BQ")  # opcode, length of what follows
_MESSAGE_HEAD: Final = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_FOOTER_BODY: Final = 20  # summary start, summary offset start, summary CRC
_TAIL: Final = _RECORD_HEAD.size + _FOOTER_BODY + len(_MAGIC)
_ZSTD_FRAME_HEAD: Final = 18  # the longest zstd frame header

#: (schema, channel, message), as the ``mcap`` reader's ``iter_messages`` gives them.
MessageTuple = tuple[Schema | None, Channel, Message]


class ReplayError(OhmniError):
    """A recording that cannot be replayed: not found, not a regular file, not MCAP, or
    damaged or cut short inside."""


def open_regular(path: str | Path) -> IO[bytes]:
    """``path`` open for reading, if it is a regular file; never blocks in ``open()``.

    Raises:
        ReplayError: It cannot be opened, or it is a FIFO, a device, a directory...
    """
    try:
        return _files.open_regular(path)
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path, or not regular
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise ReplayError(f"cannot open {path}: {why}") from exc


@dataclass
class _Index:
    """The summary section: every schema, channel and chunk of the file."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[ChunkIndex] = field(default_factory=list)


class Recording:
    """An MCAP file, open: its channels, then its messages (module docstring).

    Raises:
        ReplayError: It cannot be opened, or it is not an MCAP file.
    """

    def __init__(self, path: str | Path) -> None:
        self._name = str(path)
        self._file = open_regular(path)
        try:
            self._size = os.fstat(self._file.fileno()).st_size
            self._check_start()
            self._index = self._read_index()
        except BaseException:
            self._file.close()
            raise
        self._schemas = dict(self._index.schemas) if self._index else {}
        self._channels = dict(self._index.channels) if self._index else {}

    @property
    def channels(self) -> list[tuple[Channel, Schema | None]]:
        """The channels the file's index lists (none when it has no index), with schemas."""
        return [(c, self._schemas.get(c.schema_id)) for c in self._channels.values()]

    def messages(self, topics: Collection[str] | None = None) -> Iterator[MessageTuple]:
        """Every message (on ``topics`` only, when given), in log-time order.

        Raises:
            ReplayError: The file is damaged or ends inside a record; the message says
                what and where (the messages before it came).
        """
        if self._index is not None and self._index.chunks:
            return self._indexed(self._index.chunks, topics)
        return self._in_file_order(topics)

    def close(self) -> None:
        """Close the file. Idempotent."""
        self._file.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- reading ---------------------------------------------------------------------

    def _error(self, what: str) -> ReplayError:
        return ReplayError(f"{self._name}: {what}")

    def _read(self, size: int) -> bytes:
        try:
            return self._file.read(size)
        except OSError as exc:
            raise ReplayError(f"cannot read {self._name}: {exc.strerror or exc}") from exc

    def _seek(self, offset: int) -> None:
        try:
            self._file.seek(offset)
        except OSError as exc:
            raise ReplayError(f"cannot read {self._name}: {exc.strerror or exc}") from exc

    def _check_start(self) -> None:
        """The magic bytes, then a header record."""
        not_mcap = f"{self._name} is not an MCAP recording"
        start = self._read(len(_MAGIC) + _RECORD_HEAD.size)
        if start[: len(_MAGIC)] != _MAGIC:
            raise ReplayError(f"{not_mcap}: it does not start with the MCAP magic bytes")
        if len(start) < len(_MAGIC) + _RECORD_HEAD.size:
            raise ReplayError(f"{not_mcap}: it ends after {len(start)} bytes, before its header")
        opcode, _ = _RECORD_HEAD.unpack_from(start, len(_MAGIC))
        if opcode != Opcode.HEADER:
            raise ReplayError(f"{not_mcap}: its first record is not a header (opcode {opcode})")

    def _record_at(self, offset: int) -> tuple[int, bytes]:
        """The opcode and body of the record at ``offset``."""
        if offset > self._size:  # an index or footer that points nowhere
            raise self._error(f"byte {offset} is past the end of the file ({self._size} bytes)")
        self._seek(offset)
        head = self._read(_RECORD_HEAD.size)
        if not head:
            raise self._error(
                f"the file ends at byte {offset}, before its footer: it was cut short"
            )
        if len(head) < _RECORD_HEAD.size:
            raise self._error(f"the file ends inside the record at byte {offset}: cut short")
        opcode, length = _RECORD_HEAD.unpack(head)
        if length > _MAX_RECORD_BYTES:
            raise self._error(
                f"the record at byte {offset} claims {length} bytes: at most "
                f"{_MAX_RECORD_BYTES} are read (chunks up to {MAX_CHUNK_BYTES >> 20} MiB)"
            )
        body = self._read(length)
        if len(body) < length:
            raise self._error(f"the file ends inside the record at byte {offset}: cut short")
        return opcode, body

    def _records(self, offset: int) -> Iterator[tuple[int, int, bytes]]:
        """(offset, opcode, body) of each record from ``offset`` to the footer."""
        while True:
            opcode, body = self._record_at(offset)
            yield offset, opcode, body
            if opcode == Opcode.FOOTER:
                return
            offset += _RECORD_HEAD.size + len(body)

    def _parse(self, offset: int, kind: Any, body: bytes | memoryview) -> Any:
        """``kind.read`` (an ``mcap.records`` class) on ``body``, damage named."""
        try:
            return kind.read(ReadDataStream(io.BytesIO(body)))
        except (McapError, ValueError, OverflowError, struct.error) as exc:
            raise self._error(f"the {kind.__name__} record at byte {offset} is damaged") from exc

    def _read_index(self) -> _Index | None:
        """The summary section, or None when the file has none or its footer is gone
        (cut short): then it is read from the start."""
        if self._size < len(_MAGIC) + _TAIL:
            return None
        self._seek(self._size - _TAIL)
        tail = self._read(_TAIL)
        opcode, length = _RECORD_HEAD.unpack_from(tail)
        if tail[-len(_MAGIC) :] != _MAGIC or opcode != Opcode.FOOTER or length != _FOOTER_BODY:
            return None
        footer: Footer = self._parse(self._size - _TAIL, Footer, tail[_RECORD_HEAD.size : -8])
        start = footer.summary_start
        if start == 0:
            return None
        if not len(_MAGIC) <= start <= self._size - _TAIL:
            raise self._error(f"the footer points outside the file (to byte {start})")
        index = _Index()
        for offset, opcode, body in self._records(start):
            if opcode == Opcode.SCHEMA:
                schema: Schema = self._parse(offset, Schema, body)
                index.schemas[schema.id] = schema
            elif opcode == Opcode.CHANNEL:
                channel: Channel = self._parse(offset, Channel, body)
                index.channels[channel.id] = channel
            elif opcode == Opcode.CHUNK_INDEX:
                index.chunks.append(self._parse(offset, ChunkIndex, body))
        return index

    def _indexed(
        self, chunks: list[ChunkIndex], topics: Collection[str] | None
    ) -> Iterator[MessageTuple]:
        """Messages in log-time order: chunks by their first message's time, opened as
        their time comes, their messages merged (ties: file order, as ``mcap`` does)."""
        wanted = self._wanted_channels(topics)
        order = sorted(chunks, key=lambda c: (c.message_start_time, c.chunk_start_offset))
        order = [c for c in order if _may_hold(c, wanted)]
        # (log time, chunk offset, place in the chunk, serial, cost, message): the serial
        # keeps a file that indexes one chunk twice from comparing two messages.
        held: list[tuple[int, int, int, int, int, MessageTuple]] = []
        serial = itertools.count()
        held_bytes = 0
        next_chunk = 0
        while next_chunk < len(order) or held:
            if next_chunk < len(order):
                chunk = order[next_chunk]
                first = (chunk.message_start_time, chunk.chunk_start_offset, -1)
                if not held or (
                    first < held[0][:3] and held_bytes + chunk.uncompressed_size <= _MAX_HELD_BYTES
                ):
                    next_chunk += 1
                    offset = chunk.chunk_start_offset
                    opcode, body = self._record_at(offset)
                    if opcode != Opcode.CHUNK:
                        raise self._error(
                            f"the index points to byte {offset}, where no chunk starts"
                        )
                    for position, item in self._chunk_messages(offset, body, topics):
                        cost = len(item[2].data) + _MESSAGE_COST
                        key = (item[2].log_time, offset, position, next(serial))
                        heapq.heappush(held, (*key, cost, item))
                        held_bytes += cost
                    continue
            *_, cost, item = heapq.heappop(held)
            held_bytes -= cost
            yield item

    def _in_file_order(self, topics: Collection[str] | None) -> Iterator[MessageTuple]:
        """Every message from the start of the file to its footer, as written."""
        for offset, opcode, body in self._records(len(_MAGIC)):
            if opcode == Opcode.CHUNK:
                for _, item in self._chunk_messages(offset, body, topics):
                    yield item
            elif (item_ := self._record(offset, opcode, body, topics)) is not None:
                yield item_

    def _chunk_messages(
        self, offset: int, body: bytes, topics: Collection[str] | None
    ) -> Iterator[tuple[int, MessageTuple]]:
        """The messages of the chunk record at ``offset``, with their place among the
        chunk's schemas, channels and messages."""
        data = memoryview(self._decompress(offset, self._parse(offset, Chunk, body)))
        position = pos = 0
        while pos < len(data):
            if pos + _RECORD_HEAD.size > len(data):
                raise self._error(f"a record inside the chunk at byte {offset} is cut short")
            opcode, length = _RECORD_HEAD.unpack_from(data, pos)
            start, end = pos + _RECORD_HEAD.size, pos + _RECORD_HEAD.size + length
            if end > len(data):
                raise self._error(f"a record inside the chunk at byte {offset} is cut short")
            pos = end
            if opcode not in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE):
                continue
            item = self._record(offset, opcode, data[start:end], topics)
            if item is not None:
                yield position, item
            position += 1

    def _record(
        self, offset: int, opcode: int, body: bytes | memoryview, topics: Collection[str] | None
    ) -> MessageTuple | None:
        """A message record as its (schema, channel, message); a schema or channel is
        kept for the messages that follow."""
        if opcode == Opcode.SCHEMA:
            schema: Schema = self._parse(offset, Schema, body)
            self._schemas.setdefault(schema.id, schema)
            return None
        if opcode == Opcode.CHANNEL:
            channel: Channel = self._parse(offset, Channel, body)
            self._channels.setdefault(channel.id, channel)
            return None
        if opcode != Opcode.MESSAGE:
            return None
        if len(body) < _MESSAGE_HEAD.size:
            raise self._error(f"the Message record at byte {offset} is damaged")
        channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(body)
        known = self._channels.get(channel_id)
        if known is None:
            raise self._error(
                f"the record at byte {offset} holds a message on channel {channel_id}, "
                "which the file never declares"
            )
        if topics is not None and known.topic not in topics:
            return None
        schema_ = self._schemas.get(known.schema_id)
        if schema_ is None and known.schema_id != 0:
            raise self._error(
                f"channel {known.topic} (at byte {offset}) has schema {known.schema_id}, "
                "which the file never declares"
            )
        message = Message(
            channel_id=channel_id,
            log_time=log_time,
            data=bytes(body[_MESSAGE_HEAD.size :]),
            publish_time=publish_time,
            sequence=sequence,
        )
        return schema_, known, message

    def _decompress(self, offset: int, chunk: Chunk) -> bytes:
        """A chunk's records: refused before decompressing when it declares more than
        MAX_CHUNK_BYTES, decompressed into at most what it declares, CRC-checked."""
        size = chunk.uncompressed_size
        if size > MAX_CHUNK_BYTES:
            raise self._error(
                f"the chunk at byte {offset} declares {size} bytes uncompressed: at most "
                f"{MAX_CHUNK_BYTES} ({MAX_CHUNK_BYTES >> 20} MiB) are read"
            )
        compression = chunk.compression
        if compression == "":
            data = chunk.data
        elif compression == "zstd":
            data = self._unzstd(offset, chunk.data, size)
        elif compression == "lz4" and lz4_frame is not None:
            try:
                data = lz4_frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
            except RuntimeError as exc:  # lz4's error for damaged data
                raise self._error(
                    f"the chunk at byte {offset} does not decompress (lz4: {exc})"
                ) from exc
        else:
            raise self._error(
                f"the chunk at byte {offset} has an unknown compression: {compression!r}"
            )
        if len(data) != size:
            more = "more than " if len(data) > size else ""
            raise self._error(
                f"the chunk at byte {offset} decompresses to {more}{len(data)} bytes, not "
                f"the {size} it declares"
            )
        if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
            raise self._error(f"the chunk at byte {offset} fails its CRC check: it is damaged")
        return bytes(data)

    def _unzstd(self, offset: int, data: bytes, size: int) -> bytes:
        """A zstd frame, decompressed into at most ``size + 1`` bytes."""
        try:
            declared = zstandard.frame_content_size(data[:_ZSTD_FRAME_HEAD])
            if declared not in (-1, size):
                raise self._error(
                    f"the chunk at byte {offset} declares {size} bytes uncompressed, its "
                    f"zstd frame {declared}"
                )
            decompressor = zstandard.ZstdDecompressor(max_window_size=MAX_CHUNK_BYTES)
            with decompressor.stream_reader(data) as reader:
                parts: list[bytes] = []
                left = size + 1
                while left > 0 and (part := reader.read(left)):
                    parts.append(part)
                    left -= len(part)
            return b"".join(parts)
        except zstandard.ZstdError as exc:
            raise self._error(
                f"the chunk at byte {offset} does not decompress (zstd: {exc})"
            ) from exc

    def _wanted_channels(self, topics: Collection[str] | None) -> set[int] | None:
        if topics is None:
            return None
        return {cid for cid, channel in self._channels.items() if channel.topic in topics}


def _may_hold(chunk: ChunkIndex, wanted: set[int] | None) -> bool:
    """Whether a chunk may hold messages of the ``wanted`` channels (all: None); its
    index lists its channels, or none when it was written without message indexes."""
    listed = chunk.message_index_offsets
    return wanted is None or not listed or any(cid in wanted for cid in listed)
