"""The tb-node capture log: every byte the vendor's driver wrote to the bus and read from it.

The log is the contract between the tb-node plugin this package ships (``tbnode_plugin.js``;
``ohmni bus tbnode-plugin`` prints it) and this module; the simulator writes the same
format (``sim://?tbnode_log=PATH``). The format:

* UTF-8 text, one JSON object a line (NDJSON), each line ending in a newline. The lines
  are in the order the bytes were written or received.
* ``"t"``: when, in seconds: a JSON number, 0 ≤ t ≤ :data:`MAX_T_S`. The plugin writes
  seconds since the Unix epoch with microseconds (a monotonic clock anchored to the wall
  clock once, when it loads), the simulator its line's time from 0: only differences
  matter.
* ``"dir"``: ``"tx"`` for bytes the host wrote to the port, ``"rx"`` for bytes it read
  from it.
* ``"hex"``: the bytes, two hex digits each (either case), optionally separated by
  spaces; ``""`` for none.
* Other keys are ignored.

A request for the left wheel count and its reply::

    {"t":1718000000.000125,"dir":"tx","hex":"ffff09000432cc3b04"}
    {"t":1718000000.001790,"dir":"rx","hex":"ffff0f00447c823b04393000000000"}

:class:`LogReader` reads a log sans-IO: feed it the file's bytes as they come, get
:class:`LogRecord` objects back, and a :class:`LogSummary` of what it held. A line that
breaks the format is skipped and counted, never silently: its number and the reason (the
field that is wrong and its value) are kept for the first :data:`MAX_SKIPPED_KEPT`.

A record whose time is earlier than the one before it keeps its place (the file's order
is the order the plugin saw the bytes: only the clock jumped, as a wall clock set back
between two runs of tb-node does) and takes the time before it, so times never go back;
:attr:`LogSummary.backwards` counts it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from importlib import resources
from typing import Final

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.protocol import PacketDecoder

__all__ = [
    "FIELDS",
    "MAX_LINE_BYTES",
    "MAX_SKIPPED_KEPT",
    "MAX_T_S",
    "PLUGIN_FILE",
    "RX",
    "TX",
    "LogReader",
    "LogRecord",
    "LogSummary",
    "SkippedLine",
    "format_record",
    "parse_record",
    "plugin_source",
]

#: ``"dir"`` of bytes the host wrote to the port.
TX: Final = "tx"
#: ``"dir"`` of bytes the host read from the port.
RX: Final = "rx"
#: The keys every record has (the plugin's header names the same ones).
FIELDS: Final = ("t", "dir", "hex")
#: The latest time a record may carry, s: an MCAP recording stamps nanoseconds in 64 bits
#: (up to 1.8e10 s), and Unix time stays below this until the year 2286.
MAX_T_S: Final = 1e10
#: The longest line read, in bytes. A record is one write or one read of the port: a few
#: hundred bytes as hex on this bus (a packet is at most 223 bytes); a line this long is
#: not a record, and a reader does not hold it.
MAX_LINE_BYTES: Final = 1 << 18
#: Skipped lines kept with their number and reason for the report; the rest are counted.
MAX_SKIPPED_KEPT: Final = 20
#: The plugin's file name in this package.
PLUGIN_FILE: Final = "tbnode_plugin.js"


def plugin_source() -> str:
    """The tb-node plugin that writes the log (JavaScript), as shipped with the package."""
    return resources.files(__package__).joinpath(PLUGIN_FILE).read_text(encoding="utf-8")


@dataclass(frozen=True, slots=True)
class LogRecord:
    """One chunk of bytes the host wrote or read.

    Attributes:
        line: Its line in the log (from 1).
        t_s: When, in seconds (never earlier than the record before it).
        sent: ``True`` for bytes written to the port (``"tx"``), ``False`` for bytes read.
        data: The bytes.
    """

    line: int
    t_s: float
    sent: bool
    data: bytes


@dataclass(frozen=True, slots=True)
class SkippedLine:
    """A line that is not a record: its number (from 1) and why."""

    line: int
    reason: str


@dataclass(slots=True)
class LogSummary:
    """What a log held, so far.

    Attributes:
        lines: Lines read.
        records: Records among them.
        tx_bytes: Bytes written by the host.
        rx_bytes: Bytes read by the host.
        tx_packets: Whole packets in the bytes written.
        rx_packets: Whole packets in the bytes read.
        first_t_s: The first record's time, if any.
        last_t_s: The last record's time, if any.
        skipped: Lines that are not records.
        skipped_lines: The first :data:`MAX_SKIPPED_KEPT` of them, with the reason.
        backwards: Records whose time was earlier than the record's before (given that
            time instead).
        first_backwards_line: The line of the first of them.
    """

    lines: int = 0
    records: int = 0
    tx_bytes: int = 0
    rx_bytes: int = 0
    tx_packets: int = 0
    rx_packets: int = 0
    first_t_s: float | None = None
    last_t_s: float | None = None
    skipped: int = 0
    skipped_lines: list[SkippedLine] = field(default_factory=list)
    backwards: int = 0
    first_backwards_line: int | None = None

    @property
    def span_s(self) -> float:
        """Seconds from the first record to the last (0 without records)."""
        if self.first_t_s is None or self.last_t_s is None:
            return 0.0
        return self.last_t_s - self.first_t_s


def format_record(t_s: float, sent: bool, data: bytes) -> str:
    """One line of the log (with its newline): ``data`` written (``sent``) or read at
    ``t_s``, with microseconds.

    Raises:
        OutOfRangeError: ``t_s`` is not within 0..:data:`MAX_T_S`.
    """
    if not 0.0 <= t_s <= MAX_T_S:  # NaN fails this too
        raise OutOfRangeError("t_s", t_s, 0.0, MAX_T_S, "s")
    return f'{{"t":{t_s:.6f},"dir":"{TX if sent else RX}","hex":"{data.hex()}"}}\n'


def parse_record(text: str | bytes, line: int) -> LogRecord:
    """The record on line number ``line`` of a log (its text, with or without the newline).

    Raises:
        InvalidArgumentError: It is not a record: the message names the line, the field
            and its value ("line 7: field 'dir' must be "tx" or "rx", not "up"").
    """
    parsed = _parse(text.encode() if isinstance(text, str) else text)
    if isinstance(parsed, str):
        raise InvalidArgumentError(f"line {line}: {parsed}")
    t_s, sent, data = parsed
    return LogRecord(line, t_s, sent, data)


class LogReader:
    """Reads a log from its bytes, fed as they come (sans-IO).

    ``feed`` returns the records the bytes complete; ``finish`` reads a last line that
    has no newline (a log cut short while it was written). :attr:`summary` keeps the
    counts, the skipped lines and the times. A line longer than :data:`MAX_LINE_BYTES`
    is skipped without being held.
    """

    def __init__(self) -> None:
        self.summary = LogSummary()
        self._held = bytearray()
        self._overlong = False
        self._tx = PacketDecoder()
        self._rx = PacketDecoder()

    def feed(self, data: bytes) -> list[LogRecord]:
        """The next bytes of the log: the records of the lines they complete, in order."""
        records: list[LogRecord] = []
        pos, size = 0, len(data)
        while pos < size:
            end = data.find(b"\n", pos)
            stop = size if end < 0 else end
            if not self._overlong:
                self._held += data[pos:stop]
                if len(self._held) > MAX_LINE_BYTES:
                    self._overlong = True
                    self._held.clear()
            if end < 0:
                break
            self._end_line(records)
            pos = end + 1
        return records

    def finish(self) -> list[LogRecord]:
        """The log ended: the record of a last line without a newline, if it is one."""
        records: list[LogRecord] = []
        if self._held or self._overlong:
            self._end_line(records)
        return records

    def _end_line(self, records: list[LogRecord]) -> None:
        summary = self.summary
        summary.lines += 1
        number = summary.lines
        if self._overlong:
            self._overlong = False
            self._skip(number, f"longer than {MAX_LINE_BYTES} bytes")
            return
        parsed = _parse(bytes(self._held))
        self._held.clear()
        if isinstance(parsed, str):
            self._skip(number, parsed)
            return
        t_s, sent, data = parsed
        last = summary.last_t_s
        if last is not None and t_s < last:
            summary.backwards += 1
            if summary.first_backwards_line is None:
                summary.first_backwards_line = number
            t_s = last
        if summary.first_t_s is None:
            summary.first_t_s = t_s
        summary.last_t_s = t_s
        summary.records += 1
        if sent:
            summary.tx_bytes += len(data)
            summary.tx_packets += len(self._tx.feed(data))
        else:
            summary.rx_bytes += len(data)
            summary.rx_packets += len(self._rx.feed(data))
        records.append(LogRecord(number, t_s, sent, data))

    def _skip(self, line: int, reason: str) -> None:
        summary = self.summary
        summary.skipped += 1
        if len(summary.skipped_lines) < MAX_SKIPPED_KEPT:
            summary.skipped_lines.append(SkippedLine(line, reason))


# -- private helpers ---------------------------------------------------------------------

#: How much of a bad value a reason quotes.
_SHOWN = 40


def _parse(raw: bytes) -> tuple[float, bool, bytes] | str:
    """A line's (time, sent, bytes), or why it is not a record."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        return f"not UTF-8 text (byte {exc.start})"
    if not text.strip():
        return "empty line"
    try:
        obj = json.loads(text, parse_constant=_no_constant)
    # RecursionError: JSON nested thousands deep.
    except (ValueError, RecursionError) as exc:
        return f"bad JSON: {exc}"
    if not isinstance(obj, dict):
        return f"not a JSON object: {_shown(obj)}"
    missing = [key for key in FIELDS if key not in obj]
    if missing:
        return "missing field " + ", ".join(f"{key!r}" for key in missing)
    t, direction, hex_text = obj["t"], obj["dir"], obj["hex"]
    if isinstance(t, bool) or not isinstance(t, int | float):
        return f"field 't' must be a number of seconds, not {_shown(t)}"
    if not 0 <= t <= MAX_T_S:
        return f"field 't' = {_shown(t)} is out of range: allowed 0..{MAX_T_S:.0e} s"
    if direction not in (TX, RX):
        return f'field \'dir\' must be "{TX}" or "{RX}", not {_shown(direction)}'
    if not isinstance(hex_text, str):
        return f"field 'hex' must be a string of hex digits, not {_shown(hex_text)}"
    try:
        data = bytes.fromhex(hex_text)
    except ValueError:
        return f"field 'hex' is not hex bytes: {_shown(hex_text)}"
    return float(t), direction == TX, data


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number")


def _shown(value: object) -> str:
    """``value`` as JSON, shortened for a one-line reason."""
    text = json.dumps(value)
    return text if len(text) <= _SHOWN else text[: _SHOWN - 1] + "…"
