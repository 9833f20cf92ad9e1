"""Record a Robot's streams to an MCAP file, on the same channels the live view has.

::

    async with Robot.open("sim://") as robot:
        async with McapRecorder(robot, "run.mcap", duration_s=10) as recording:
            await recording.wait()                    # 10 s of every stream
        print(recording.stats()["/tb_control/wheel_odom"].messages)     # 500

The file is foxglove-sdk's MCAP writer's (zstd chunks, a summary with statistics and
indexes); the Foxglove app and the ``mcap`` tools open it. The control tick never waits
for the disk:

- The SDK encodes and compresses on the event loop (it holds the interpreter's lock
  while it does, so a thread would not take that off the loop): a chunk is finished
  every ``flush_interval_s`` (1 s, about 100 kB of messages), so each finish is short
  (0.7–1.2 ms measured with every stream and pid_debug on) and a crash loses at most
  that much.
- The bytes go to a writer thread through memory; the file is written there, never on
  the loop. If the disk falls behind by :data:`MAX_BACKLOG_BYTES` the recorder drops
  samples (counted per channel) instead of growing.
- A write that fails (a full disk, a file-size limit, an I/O error) stops the recording
  with a :class:`RecordingError` naming the reason, and the file is cut back to its last
  complete record and closed as a valid MCAP (without a summary: readers scan it), so
  everything up to the last finished chunk (≤ ``flush_interval_s`` before the error)
  stays readable.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import errno
import io
import json
import logging
import os
import threading
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Final

import foxglove
from foxglove.mcap import MCAPCompression, MCAPWriteOptions, MCAPWriter

from ohmni_tb._checks import bounded, integer, positive
from ohmni_tb._version import __version__
from ohmni_tb.bus import Bus
from ohmni_tb.errors import InvalidArgumentError, OhmniError
from ohmni_tb.foxglove._pump import DEFAULT_QUEUE, ChannelStats, Pump
from ohmni_tb.foxglove.channels import WallClock

if TYPE_CHECKING:
    from ohmni_tb.robot import Robot

__all__ = [
    "DEFAULT_FLUSH_INTERVAL_S",
    "MAX_BACKLOG_BYTES",
    "MAX_DURATION_S",
    "RAW_SCHEMA_NAME",
    "RAW_TOPICS",
    "McapRecorder",
    "RecordingError",
    "write_raw_recording",
]

_log = logging.getLogger("ohmni_tb.foxglove")

#: A chunk is finished and handed to the disk this often: the most a crash loses, and
#: what bounds one compression's time on the event loop.
DEFAULT_FLUSH_INTERVAL_S: Final = 1.0
#: Bytes waiting for the disk before samples are dropped instead: minutes of recording
#: (the streams make about 20 kB/s compressed), far more than a healthy disk ever lags.
MAX_BACKLOG_BYTES: Final = 64 << 20
#: The longest ``duration_s``: a week.
MAX_DURATION_S: Final = 7 * 24 * 3600.0
#: After the window ends, how long the samples stamped inside it may still be arriving:
#: a reply held by a USB adapter's latency timer, a servo read on the line.
_LATE_SAMPLES_S: Final = 0.25

_MAGIC: Final = b"\x89MCAP0\r\n"
_OP_HEADER: Final = 0x01
_OP_FOOTER: Final = 0x02
_OP_CHUNK: Final = 0x06
_OP_DATA_END: Final = 0x0F
_OP_MAGIC: Final = -1  # the closing magic after the footer (not a record)
#: A record's opcode and length; a chunk's also its first and last message times.
_RECORD_HEAD: Final = 9
_CHUNK_HEAD: Final = 25


class RecordingError(OhmniError):
    """The recording cannot be written: the path, or a write that failed (a full disk).

    Attributes:
        path: The file.
    """

    def __init__(self, message: str, path: str) -> None:
        super().__init__(message)
        self.path = path


class McapRecorder:
    """Records an open Robot's streams to an MCAP file (an async context manager).

    Args:
        robot: An open :class:`~ohmni_tb.Robot`, or a daemon's
            :class:`~ohmni_tb.client.RobotClient`.
        path: The file to create.
        overwrite: Replace the file if it exists (by default an existing file is refused).
        duration_s: Record the samples stamped in the first ``duration_s`` seconds only
            (0 < s ≤ a week); :meth:`wait` returns when they are in. ``None``: until closed.
        flush_interval_s: Finish a chunk this often (0.05..60 s).
        queue: Samples each stream's subscription holds before its oldest are dropped.
        raw: Also record the bus's bytes as they are written and read
            (:data:`RAW_TOPICS`: JSON ``{"data": "ff ff 09 …"}``, one message a chunk,
            stamped when the port took or gave it), for ``ohmni bus monitor --capture``.
            Needs the Robot itself: a daemon's client has no port.

    Raises:
        InvalidArgumentError: ``duration_s`` or ``flush_interval_s`` not a finite positive
            number in range; ``raw`` with something that is not a Robot.
    """

    def __init__(
        self,
        robot: Robot,
        path: str | os.PathLike[str],
        *,
        overwrite: bool = False,
        duration_s: float | None = None,
        flush_interval_s: float = DEFAULT_FLUSH_INTERVAL_S,
        queue: int = DEFAULT_QUEUE,
        raw: bool = False,
    ) -> None:
        from ohmni_tb.robot import LocalRobot  # noqa: PLC0415  # the Robot's package: when used

        bus: Bus | None = None
        if raw:
            if not isinstance(robot, LocalRobot):
                raise InvalidArgumentError(
                    "raw bus bytes need the Robot that owns the port, not a daemon's "
                    "(ohmni record --raw --direct, after ohmni serve --handoff)"
                )
            bus = robot.bus
        self._bus = bus
        self._raw: dict[bool, _RawChannel] = {}
        self._untap: Callable[[], None] | None = None
        self._robot = robot
        self._path = os.fspath(path)
        self._overwrite = overwrite
        self._duration_s = None
        if duration_s is not None:
            positive("duration_s", duration_s, "s")
            self._duration_s = bounded("duration_s", duration_s, 0.0, MAX_DURATION_S, "s")
        self._flush_s = bounded("flush_interval_s", flush_interval_s, 0.05, 60.0, "s")
        self._queue = integer("queue", queue, 1, 100_000)
        self._context = foxglove.Context()
        self._sink: _FileSink | None = None
        self._writer: MCAPWriter | None = None
        self._pump: Pump | None = None
        self._flusher: asyncio.Task[None] | None = None
        self._failed = asyncio.Event()
        self._failed_s: float | None = None
        self._start_s = 0.0
        self._end_s: float | None = None
        self._closed = False
        #: Why the recording stopped early, once it has.
        self.error: RecordingError | None = None

    @property
    def path(self) -> str:
        """The file."""
        return self._path

    @property
    def start_ns(self) -> int | None:
        """When the recording starts, wall clock (ns since the Unix epoch): no message is
        stamped earlier. ``None`` before :meth:`start`."""
        clock = None if self._pump is None else self._pump.clock
        return None if clock is None else clock.ns(self._start_s)

    @property
    def bytes_written(self) -> int:
        """Bytes on disk so far."""
        return 0 if self._sink is None else self._sink.written

    def stats(self) -> dict[str, ChannelStats]:
        """Every channel's figures, by topic: messages recorded, samples dropped."""
        figures = {} if self._pump is None else self._pump.stats()
        for raw in self._raw.values():
            figures[raw.topic] = ChannelStats(raw.topic, RAW_SCHEMA_NAME, raw.messages, raw.dropped)
        return figures

    async def start(self) -> None:
        """Create the file and start recording.

        Raises:
            RecordingError: The file cannot be created: it exists (and not ``overwrite``),
                it is a directory, its directory is missing or not writable.
        """
        loop = asyncio.get_running_loop()
        fd = _create(self._path, overwrite=self._overwrite)
        self._sink = _FileSink(fd, loop, self._note_failure)
        self._sink.start()
        try:
            self._begin(loop)
        except BaseException:
            await self.aclose()  # the thread and the file go too
            raise

    def _begin(self, loop: asyncio.AbstractEventLoop) -> None:
        assert self._sink is not None
        self._writer = foxglove.open_mcap(
            self._sink,
            context=self._context,
            writer_options=MCAPWriteOptions(
                compression=MCAPCompression.Zstd,
                # Only appends: the file is written by another thread, in order.
                disable_seeking=True,
                # One chunk a flush; this only caps a burst.
                chunk_size=1 << 20,
                # Compression runs in the calling thread, holding the interpreter's lock
                # anyway: worker threads would add wake-ups, not take it off the loop.
                compression_threads=0,
            ),
        )
        self._start_s = loop.time()
        if self._duration_s is not None:
            self._end_s = self._start_s + self._duration_s
        self._pump = Pump(
            self._robot,
            self._context,
            admit=self._sink.accepting,
            window=(self._start_s, self._end_s if self._end_s is not None else float("inf")),
            queue=self._queue,
        )
        self._pump.start()
        assert self._pump.clock is not None
        if self._bus is not None:
            self._tap_bus(self._bus, self._pump.clock, self._sink)
        started = datetime.datetime.fromtimestamp(
            self._pump.clock.ns(self._start_s) / 1e9, datetime.UTC
        )
        self._writer.write_metadata(
            "ohmni_tb",
            {
                "library": f"ohmni_tb {__version__}",
                "started": started.isoformat(timespec="milliseconds"),
                "log_time": "wall clock, ns since the Unix epoch: the sample's stamp_s "
                "(the event loop's monotonic clock) + clock_offset_ns, taken once",
                "clock_offset_ns": str(self._pump.clock.offset_ns),
            },
        )
        self._flusher = loop.create_task(self._flush_loop(), name="ohmni-mcap-flush")

    async def wait(self) -> None:
        """Until the ``duration_s`` window is recorded (for ever without one), or the
        streams ended (the Robot closed), or the recording failed.

        Raises:
            RecordingError: A write failed (a full disk …); the file was closed readable.
            OhmniError: The streams failed (the daemon went away, for a daemon client).
        """
        if self._pump is None:
            raise RecordingError("the recorder was not started", self._path)
        loop = asyncio.get_running_loop()
        waits = [
            loop.create_task(self._failed.wait(), name="ohmni-mcap-failed"),
            loop.create_task(self._pump.wait(), name="ohmni-mcap-streams"),
        ]
        if self._end_s is not None:
            delay = self._end_s + _LATE_SAMPLES_S - loop.time()
            waits.append(loop.create_task(asyncio.sleep(delay), name="ohmni-mcap-window"))
        try:
            await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in waits:
                task.cancel()
            await asyncio.gather(*waits, return_exceptions=True)
        if self._failed.is_set():
            await self.aclose()
            assert self.error is not None
            raise self.error
        if self._pump.error is not None:
            raise self._pump.error

    async def aclose(self) -> None:
        """Stop recording and close the file (shielded: a cancellation cannot leave it
        half-written). Idempotent.

        A write failure found here is kept in :attr:`error` (``async with`` raises it).
        """
        if self._closed:
            return
        self._closed = True
        await asyncio.shield(self._close())

    async def __aenter__(self) -> McapRecorder:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object
    ) -> None:
        await self.aclose()
        if exc is None and self.error is not None:
            raise self.error

    def _tap_bus(self, bus: Bus, clock: WallClock, sink: _FileSink) -> None:
        """Record every chunk the bus writes and reads, inside the window."""
        for sent, topic in ((True, RAW_TOPICS[0]), (False, RAW_TOPICS[1])):
            self._raw[sent] = _RawChannel(topic, self._context)
        start, end = self._start_s, self._end_s if self._end_s is not None else float("inf")
        raw = self._raw

        def tap(sent: bool, data: bytes, t_s: float) -> None:
            if not start <= t_s < end:
                return
            channel = raw[sent]
            if not sink.accepting():
                channel.dropped += 1
                return
            channel.channel.log(_raw_message(data), log_time=clock.ns(t_s))
            channel.messages += 1

        self._untap = bus.add_tap(tap)

    async def _close(self) -> None:
        if self._untap is not None:
            self._untap()
            self._untap = None
        loop = asyncio.get_running_loop()
        if self._flusher is not None:
            self._flusher.cancel()
            await asyncio.gather(self._flusher, return_exceptions=True)
        if self._pump is not None:
            await self._pump.aclose()
        try:
            if self._writer is not None:
                # The summary and footer, into memory: the sink never fails the SDK.
                self._writer.close()
        finally:
            if self._sink is not None:
                await self._sink.finish()
                failure = self._sink.error
                if failure is not None and self.error is None:
                    failed_s = loop.time() if self._failed_s is None else self._failed_s
                    self.error = RecordingError(
                        self._failure_text(failure, failed_s - self._start_s), self._path
                    )

    def _note_failure(self) -> None:
        """The writer thread's news of a failed write (on the loop)."""
        self._failed_s = asyncio.get_running_loop().time()
        self._failed.set()

    async def _flush_loop(self) -> None:
        loop = asyncio.get_running_loop()
        due = loop.time()
        while True:
            due += self._flush_s
            await asyncio.sleep(due - loop.time())
            if self._writer is not None and self._sink is not None and self._sink.error is None:
                self._writer.flush()
            due = max(due, loop.time() - self._flush_s)  # late: no burst of flushes

    def _failure_text(self, failure: OSError, elapsed_s: float) -> str:
        assert self._sink is not None
        reason = failure.strerror or str(failure)
        if failure.errno in (errno.ENOSPC, errno.EDQUOT):
            reason = f"the disk is full ({reason})"
        text = f"recording to {self._path} stopped after {elapsed_s:.1f} s: {reason}"
        repair = self._sink.repair_error
        if repair is not None:
            return (
                f"{text}; the file could not be closed ({repair.strerror or repair}): "
                f"`mcap recover {self._path}` restores what it holds"
            )
        kept, start = self._sink.kept_until_ns, self.start_ns
        if kept is None or start is None:
            return f"{text}; the file is a valid, empty recording"
        kept_s = max(0.0, (kept - start) / 1e9)
        return f"{text}; the file is closed and readable, with the first {kept_s:.1f} s"


#: The raw recording's channels: bytes the host wrote, bytes it read.
RAW_TOPICS: Final = ("/ohmni/bus/tx", "/ohmni/bus/rx")
#: Their schema: one chunk of bytes as hex.
RAW_SCHEMA_NAME: Final = "ohmni_tb.BusBytes"
_RAW_SCHEMA: Final = {
    "title": RAW_SCHEMA_NAME,
    "type": "object",
    "properties": {
        "data": {"type": "string", "description": "the bytes, two hex digits each, spaced"}
    },
}


def write_raw_recording(
    path: str | os.PathLike[str],
    chunks: Iterable[tuple[int, bool, bytes]],
    *,
    overwrite: bool = False,
    metadata: Mapping[str, str] | None = None,
) -> dict[str, ChannelStats]:
    """Write bus bytes to an MCAP file as ``ohmni record --raw`` records them, without a
    Robot: the same channels (:data:`RAW_TOPICS`), schema and messages, one message a
    chunk, and the ``ohmni_tb`` metadata record (with ``metadata`` in it).
    ``ohmni bus convert`` writes a tb-node capture this way, for ``ohmni bus monitor``.

    Args:
        path: The file to create.
        chunks: ``(log_time_ns, sent, data)`` in time order: when, in ns (the
            recording's ``log_time``), whether the host wrote the bytes, the bytes.
        overwrite: Replace the file if it exists (by default an existing file is refused).
        metadata: More entries for the ``ohmni_tb`` metadata record (where the bytes
            came from).

    Returns:
        The two raw channels' figures, by topic.

    Raises:
        RecordingError: The file cannot be created (it exists, its directory is missing
            or not writable) or written.
    """
    text_path = os.fspath(path)
    fd = _create(text_path, overwrite=overwrite)
    context = foxglove.Context()
    channels = {
        sent: _RawChannel(topic, context)
        for sent, topic in zip((True, False), RAW_TOPICS, strict=True)
    }
    try:
        with os.fdopen(fd, "wb") as file:
            writer = foxglove.open_mcap(
                file,
                context=context,
                writer_options=MCAPWriteOptions(compression=MCAPCompression.Zstd),
            )
            try:
                writer.write_metadata(
                    "ohmni_tb", {"library": f"ohmni_tb {__version__}", **(metadata or {})}
                )
                for log_time_ns, sent, data in chunks:
                    raw = channels[sent]
                    raw.channel.log(_raw_message(data), log_time=log_time_ns)
                    raw.messages += 1
            finally:
                writer.close()
    except OSError as exc:
        raise RecordingError(f"cannot write {text_path}: {exc.strerror or exc}", text_path) from exc
    return {
        raw.topic: ChannelStats(raw.topic, RAW_SCHEMA_NAME, raw.messages, raw.dropped)
        for raw in channels.values()
    }


def _raw_message(data: bytes) -> bytes:
    """A raw channel's message: the bytes as spaced hex, in JSON."""
    return b'{"data":"' + data.hex(" ").encode() + b'"}'


class _RawChannel:
    """One direction of the bus's bytes, on its channel, with its counts."""

    def __init__(self, topic: str, context: foxglove.Context) -> None:
        self.topic = topic
        self.channel = foxglove.Channel(
            topic,
            message_encoding="json",
            schema=foxglove.Schema(
                name=RAW_SCHEMA_NAME, encoding="jsonschema", data=json.dumps(_RAW_SCHEMA).encode()
            ),
            context=context,
        )
        self.messages = 0
        self.dropped = 0


def _create(path: str, *, overwrite: bool) -> int:
    """Open ``path`` for writing, refusing to clobber a recording by accident."""
    if os.path.isdir(path):
        raise RecordingError(f"cannot record to {path}: it is a directory", path)
    flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_CLOEXEC", 0)
    flags |= os.O_TRUNC if overwrite else os.O_EXCL
    try:
        return os.open(path, flags, 0o644)
    except FileExistsError:
        raise RecordingError(
            f"{path} exists: choose another name, or overwrite it (ohmni record --overwrite)",
            path,
        ) from None
    except OSError as exc:
        where = Path(path).parent
        if exc.errno == errno.ENOENT:
            reason = f"the directory {where} does not exist"
        else:
            reason = exc.strerror or str(exc)
        raise RecordingError(f"cannot record to {path}: {reason}", path) from exc


class _FileSink:
    """Where the SDK's writer puts the file's bytes (its ``McapWritable``): into memory on
    the event loop; a thread writes them, in order, and repairs the file if a write fails.
    """

    def __init__(
        self, fd: int, loop: asyncio.AbstractEventLoop, on_failure: Callable[[], None]
    ) -> None:
        self._fd = fd
        self._loop = loop
        self._on_failure = on_failure
        self._pending: deque[bytes] = deque()
        self._pending_bytes = 0
        self._offered = 0
        self._first = bytearray()
        self._condition = threading.Condition()
        self._closing = False
        self._scanner = _McapScanner()
        self._thread = threading.Thread(target=self._run, name="ohmni-mcap-writer", daemon=True)
        #: Bytes on disk.
        self.written = 0
        #: The write that failed, if one did.
        self.error: OSError | None = None
        #: Why the file could not be closed properly after that, if it could not.
        self.repair_error: OSError | None = None
        #: After a repair: the last message time the file keeps (ns), if any.
        self.kept_until_ns: int | None = None

    def start(self) -> None:
        self._thread.start()

    def accepting(self) -> bool:
        """Whether a sample may be recorded: no failure, and the disk keeps up."""
        return self.error is None and self._pending_bytes < MAX_BACKLOG_BYTES

    # -- the SDK's side (the event loop's thread) ---------------------------------------

    def write(self, data: bytes | bytearray) -> int:
        size = len(data)
        if len(self._first) < _PREFIX_BYTES:
            self._first += data[: _PREFIX_BYTES - len(self._first)]
        self._offered += size
        if self.error is None:  # after a failure the bytes have nowhere to go
            with self._condition:
                self._pending.append(bytes(data))
                self._pending_bytes += size
                self._condition.notify()
        return size

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        # The SDK only asks where it is (disable_seeking): the stream goes out in order.
        if (whence == io.SEEK_CUR and offset == 0) or (
            whence == io.SEEK_SET and offset == self._offered
        ):
            return self._offered
        raise io.UnsupportedOperation("an MCAP recording is written in order")

    def flush(self) -> None:
        """Nothing to do: the thread writes as the bytes come."""

    async def finish(self) -> None:
        """Write what is left, then close the file (repaired after a failure)."""
        with self._condition:
            self._closing = True
            self._condition.notify()
        # Joined from an executor thread: the loop goes on meanwhile (and a loop on
        # virtual time, which waits for its executor jobs, does not race ahead of it).
        await asyncio.shield(asyncio.to_thread(self._thread.join))

    # -- the writer thread ---------------------------------------------------------------

    def _run(self) -> None:
        while True:
            with self._condition:
                while not self._pending and not self._closing:
                    self._condition.wait()
                if not self._pending:
                    break
                batch = list(self._pending)
                self._pending.clear()
            for data in batch:
                if self.error is None:
                    self._write(data)
                with self._condition:
                    self._pending_bytes -= len(data)
        self._close_file()

    def _write(self, data: bytes) -> None:
        try:
            _write_all(self._fd, data)
        except OSError as exc:
            self.error = exc
            with contextlib.suppress(RuntimeError):
                self._loop.call_soon_threadsafe(self._on_failure)
            return
        self.written += len(data)
        self._scanner.feed(data)

    def _close_file(self) -> None:
        try:
            if self.error is not None:
                self._repair()
            else:
                with contextlib.suppress(OSError):  # not a file that can sync (a pipe)
                    os.fsync(self._fd)
        finally:
            os.close(self._fd)

    def _repair(self) -> None:
        """Cut the file back to a record boundary and close it as a valid MCAP there.

        The last boundary first; when the closing bytes do not fit there (the disk is
        still full, a size limit is that close), an earlier one, which frees more: in
        the end the header alone, a valid empty recording."""
        scanner = self._scanner
        if scanner.prefix is None:
            # Not even the header made it: start again from the SDK's first bytes.
            first = _McapScanner()
            first.feed(bytes(self._first))
            cuts = [(0, (first.prefix or b"") + _McapScanner.empty_closing())]
        else:
            cuts = [(at, scanner.closing(at)) for at in scanner.cuts()]
        failure: OSError | None = None
        for keep, tail in cuts:
            try:
                os.ftruncate(self._fd, keep)
                os.lseek(self._fd, keep, os.SEEK_SET)
                _write_all(self._fd, tail)
            except OSError as exc:
                failure = exc
                continue
            self.written = keep + len(tail)
            self.kept_until_ns = scanner.chunk_end_before(keep)
            with contextlib.suppress(OSError):
                os.fsync(self._fd)
            return
        self.repair_error = failure
        with contextlib.suppress(OSError):  # the longest valid prefix, for `mcap recover`
            os.ftruncate(self._fd, scanner.safe_end)


#: The SDK's first bytes kept to rebuild a file whose header never reached the disk (the
#: magic and the header record: under a hundred bytes).
_PREFIX_BYTES: Final = 4096
#: Record boundaries the scanner remembers for a repair to fall back to: tens of seconds
#: of chunks and their message indexes.
_REMEMBERED_CUTS: Final = 256


class _McapScanner:
    """Follows the record framing of an MCAP byte stream as it is written (sans-IO).

    It knows where the complete records end (:attr:`safe_end`, the last; :meth:`cuts`,
    the recent ones: a cut there keeps every record before it whole), the last message
    time of the chunks before a cut, and what must follow a cut for the file to be a
    valid MCAP (:meth:`closing`).
    """

    def __init__(self) -> None:
        self.offset = 0
        self._next = len(_MAGIC)
        self._head = bytearray()
        self._open: deque[tuple[int, int, int | None]] = deque()
        self._prefix = bytearray()
        self._after_footer = False
        self._ends: deque[tuple[int, int | None]] = deque(maxlen=_REMEMBERED_CUTS)
        self._data_end_at: int | None = None
        self._footer_at: int | None = None
        self._complete_at: int | None = None
        #: End of the last complete record (0 until the header record is whole).
        self.safe_end = 0
        #: The magic and header record, once whole.
        self.prefix: bytes | None = None

    @property
    def complete(self) -> bool:
        """The closing magic is written: the file is whole."""
        return self._complete_at is not None

    @property
    def chunk_end_ns(self) -> int | None:
        """The last complete chunk's last message time (log_time, ns)."""
        return self.chunk_end_before(self.offset)

    def feed(self, data: bytes) -> None:
        """Note ``data``, the next bytes of the stream."""
        base = self.offset
        self.offset = base + len(data)
        if self.prefix is None:
            self._prefix += data
        while not self._after_footer:
            index = self._next + len(self._head) - base
            if index >= len(data):
                break
            opcode = self._head[0] if self._head else data[index]
            wanted = _CHUNK_HEAD if opcode == _OP_CHUNK else _RECORD_HEAD
            self._head += data[index : index + wanted - len(self._head)]
            if len(self._head) < wanted:
                break  # the rest comes with a later write
            end = self._next + _RECORD_HEAD + int.from_bytes(self._head[1:9], "little")
            chunk_end = int.from_bytes(self._head[17:25], "little") if opcode == _OP_CHUNK else None
            self._open.append((end, opcode, chunk_end))
            self._head.clear()
            self._next = end
            if opcode == _OP_FOOTER:
                self._open.append((end + len(_MAGIC), _OP_MAGIC, None))
                self._after_footer = True
        while self._open and self._open[0][0] <= self.offset:
            end, opcode, chunk_end = self._open.popleft()
            if opcode == _OP_HEADER and self.prefix is None:
                self.prefix = bytes(self._prefix[:end])
                self._prefix = bytearray()
            if self.prefix is None:
                continue
            self.safe_end = end
            self._ends.append((end, chunk_end))
            if opcode == _OP_DATA_END:
                self._data_end_at = end
            elif opcode == _OP_FOOTER:
                self._footer_at = end
            elif opcode == _OP_MAGIC:
                self._complete_at = end

    def cuts(self) -> list[int]:
        """Where the file may be cut, the latest first: the remembered record ends, and
        in the end the header's (an empty recording)."""
        ends = [end for end, _ in reversed(self._ends)]
        if self.prefix is not None and (not ends or ends[-1] != len(self.prefix)):
            ends.append(len(self.prefix))
        return ends

    def chunk_end_before(self, at: int) -> int | None:
        """The last message time of the last complete chunk ending at or before ``at``."""
        for end, chunk_end in reversed(self._ends):
            if end <= at and chunk_end is not None:
                return chunk_end
        return None

    def closing(self, at: int | None = None) -> bytes:
        """The bytes to append after a cut at ``at`` (:attr:`safe_end` by default) for a
        valid MCAP: a data end (no CRC), a footer without a summary, the magic — those
        of them the file does not already hold before the cut."""
        at = self.safe_end if at is None else at
        if self._complete_at is not None and self._complete_at <= at:
            return b""
        out = b"" if self._data_end_at is not None and self._data_end_at <= at else _data_end()
        out += b"" if self._footer_at is not None and self._footer_at <= at else _footer()
        return out + _MAGIC

    @staticmethod
    def empty_closing() -> bytes:
        """What follows the header alone: an empty, valid recording."""
        return _data_end() + _footer() + _MAGIC


def _data_end() -> bytes:
    # DataEnd: data_section_crc 0 = "not available".
    return bytes([_OP_DATA_END]) + (4).to_bytes(8, "little") + bytes(4)


def _footer() -> bytes:
    # Footer: summary_start 0 and summary_offset_start 0 = no summary; summary_crc 0.
    return bytes([_OP_FOOTER]) + (20).to_bytes(8, "little") + bytes(20)


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        view = view[written:]
