"""The tb-node capture log (``ohmni_tb.capture.tbnode``) and ``ohmni bus convert``: the
log read line by line, every bad line refused with its number and counted, the records
turned into a capture ``ohmni bus monitor --capture`` decodes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner, Result

from ohmni_tb.capture.tbnode import (
    MAX_LINE_BYTES,
    MAX_T_S,
    LogReader,
    LogRecord,
    format_record,
    parse_record,
    plugin_source,
)
from ohmni_tb.cli import app
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.protocol import REPLY_FLAG, Packet, encode_packet
from ohmni_tb.protocol.drive import read_count

runner = CliRunner()

#: A left wheel count read and its reply (count 12345), as the plugin logs them.
REQUEST = encode_packet(read_count(0))
REPLY = encode_packet(
    Packet(0, read_count(0).cmd | REPLY_FLAG, b"\x3b\x04" + (12345).to_bytes(4, "little") + b"\0\0")
)


def _invoke(*args: str) -> Result:
    return runner.invoke(app, list(args), env={"COLUMNS": "300"})


def _line(t: float, direction: str, data: bytes) -> str:
    return json.dumps({"t": t, "dir": direction, "hex": data.hex()}) + "\n"


def _read(data: bytes, chunk: int | None = None) -> tuple[list[LogRecord], LogReader]:
    reader = LogReader()
    step = chunk or max(1, len(data))
    records = [r for i in range(0, len(data), step) for r in reader.feed(data[i : i + step])]
    return records + reader.finish(), reader


# -- the format ---------------------------------------------------------------------------


@given(
    t_s=st.floats(0.0, MAX_T_S),
    sent=st.booleans(),
    data=st.binary(max_size=300),
)
def test_a_record_reads_back_as_written(t_s: float, sent: bool, data: bytes) -> None:
    line = format_record(t_s, sent, data)
    assert line.endswith("\n")
    assert line.count("\n") == 1
    record = parse_record(line, 7)
    assert record.line == 7
    assert record.sent is sent
    assert record.data == data
    # Microseconds are written; near MAX_T_S a float itself only holds about that much.
    assert record.t_s == pytest.approx(t_s, abs=2e-6)


@pytest.mark.parametrize("t_s", [-0.001, MAX_T_S * 2, float("nan"), float("inf")])
def test_a_time_out_of_range_is_not_written(t_s: float) -> None:
    with pytest.raises(OutOfRangeError, match="t_s"):
        format_record(t_s, True, b"\xff")


def test_the_log_reads_the_same_whole_in_halves_and_byte_by_byte() -> None:
    log = (
        format_record(1718000000.000125, True, REQUEST)
        + format_record(1718000000.00179, False, REPLY[:5])
        + format_record(1718000000.00181, False, REPLY[5:])
    ).encode()
    whole, reader = _read(log)
    assert [(r.line, r.sent, r.data) for r in whole] == [
        (1, True, REQUEST),
        (2, False, REPLY[:5]),
        (3, False, REPLY[5:]),
    ]
    assert [r.t_s for r in whole] == pytest.approx(
        [1718000000.000125, 1718000000.00179, 1718000000.00181], abs=1e-6
    )
    for chunk in (len(log) // 2 + 1, 1):
        again, _ = _read(log, chunk)
        assert again == whole
    summary = reader.summary
    assert (summary.lines, summary.records, summary.skipped) == (3, 3, 0)
    assert (summary.tx_packets, summary.tx_bytes) == (1, len(REQUEST))
    assert (summary.rx_packets, summary.rx_bytes) == (1, len(REPLY))
    assert summary.span_s == pytest.approx(0.001685, abs=1e-6)


#: One bad line of each kind, and the words its reason must hold.
BAD_LINES = [
    (b'{"t": 1.0, "dir": "tx", "hex": "ffff"\n', "bad JSON"),
    (b'{"t": 1.0, "dir": "tx", "hex": "ffzz"}\n', "field 'hex' is not hex bytes: \"ffzz\""),
    (b'{"t": 1.0, "dir": "tx", "hex": "fff"}\n', "field 'hex' is not hex bytes"),
    (b'{"t": 1.0, "dir": "up", "hex": "ff"}\n', 'field \'dir\' must be "tx" or "rx", not "up"'),
    (b'{"dir": "tx", "hex": "ff"}\n', "missing field 't'"),
    (b'{"t": 1.0}\n', "missing field 'dir', 'hex'"),
    (b'{"t": "soon", "dir": "tx", "hex": "ff"}\n', "field 't' must be a number"),
    (b'{"t": true, "dir": "tx", "hex": "ff"}\n', "field 't' must be a number"),
    (b'{"t": -1, "dir": "tx", "hex": "ff"}\n', "field 't' = -1 is out of range"),
    (b'{"t": NaN, "dir": "tx", "hex": "ff"}\n', "bad JSON: NaN is not a number"),
    (b'{"t": 1.0, "dir": "tx", "hex": 255}\n', "field 'hex' must be a string"),
    (b'["t", "dir", "hex"]\n', "not a JSON object"),
    (b'{"t": 1.0, "dir": "tx", "hex": "\xff"}\n', "not UTF-8 text"),
    (b"   \n", "empty line"),
]


@pytest.mark.parametrize(("line", "reason"), BAD_LINES, ids=[r for _, r in BAD_LINES])
def test_a_bad_line_is_refused_naming_its_number_and_field(line: bytes, reason: str) -> None:
    with pytest.raises(InvalidArgumentError, match=r"^line 12: ") as caught:
        parse_record(line, 12)
    assert reason in str(caught.value)


def test_bad_lines_are_skipped_and_counted_never_dropped_silently() -> None:
    good = format_record(1.0, True, REQUEST).encode()
    log = good + b"".join(line for line, _ in BAD_LINES) + good
    records, reader = _read(log)
    assert [r.line for r in records] == [1, len(BAD_LINES) + 2]
    summary = reader.summary
    assert summary.lines == len(BAD_LINES) + 2
    assert summary.skipped == len(BAD_LINES)
    assert [s.line for s in summary.skipped_lines] == list(range(2, len(BAD_LINES) + 2))
    for skipped, (_, reason) in zip(summary.skipped_lines, BAD_LINES, strict=True):
        assert reason in skipped.reason


def test_an_overlong_line_is_skipped_without_being_held() -> None:
    reader = LogReader()
    assert reader.feed(b'{"t": 1, "dir": "tx", "hex": "') == []
    for _ in range(4):
        assert reader.feed(b"ff" * (MAX_LINE_BYTES // 4)) == []
    assert len(reader._held) == 0  # what it would have held is gone already
    records = reader.feed(b'"}\n' + format_record(2.0, False, REPLY).encode())
    assert [r.line for r in records] == [2]
    assert reader.summary.skipped_lines[0].line == 1
    assert f"longer than {MAX_LINE_BYTES} bytes" in reader.summary.skipped_lines[0].reason


def test_a_last_line_without_its_newline_is_read_and_a_cut_one_is_skipped() -> None:
    last = format_record(3.0, False, REPLY).encode().rstrip(b"\n")
    records, reader = _read(format_record(1.0, True, REQUEST).encode() + last)
    assert [r.data for r in records] == [REQUEST, REPLY]
    records, reader = _read(format_record(1.0, True, REQUEST).encode() + last[:-9])
    assert [r.data for r in records] == [REQUEST]
    assert reader.summary.skipped_lines[0].line == 2
    assert "bad JSON" in reader.summary.skipped_lines[0].reason


def test_times_that_go_back_keep_the_file_order_and_are_counted() -> None:
    log = "".join(
        [
            format_record(100.0, True, REQUEST),
            format_record(100.002, False, REPLY),
            # A second run of tb-node after the wall clock was set back a minute.
            format_record(40.0, True, REQUEST),
            format_record(40.002, False, REPLY),
            format_record(100.5, True, REQUEST),
        ]
    ).encode()
    records, reader = _read(log)
    assert [r.line for r in records] == [1, 2, 3, 4, 5]
    assert [r.t_s for r in records] == pytest.approx([100.0, 100.002, 100.002, 100.002, 100.5])
    assert reader.summary.backwards == 2
    assert reader.summary.first_backwards_line == 3


# -- ohmni bus convert --------------------------------------------------------------------


def _write_log(path: Path, *lines: str | bytes) -> Path:
    path.write_bytes(b"".join(ln.encode() if isinstance(ln, str) else ln for ln in lines))
    return path


def test_convert_to_raw_bytes_keeps_both_directions_in_order(tmp_path: Path) -> None:
    log = _write_log(
        tmp_path / "capture.ndjson",
        _line(5.0, "tx", REQUEST),
        _line(5.0015, "rx", REPLY[:4]),
        _line(5.0017, "rx", REPLY[4:]),
        _line(5.1, "tx", REQUEST),
    )
    out = tmp_path / "capture.bin"
    result = _invoke("bus", "convert", str(log), str(out))
    assert result.exit_code == 0, result.output
    assert out.read_bytes() == REQUEST + REPLY + REQUEST
    assert result.stdout.strip() == (
        f"{out}: raw bytes; tx 2 packets / {2 * len(REQUEST)} bytes, rx 1 packets / "
        f"{len(REPLY)} bytes, over 0.100 s; 0 lines skipped"
    )
    assert not list(tmp_path.glob(".*partial"))
    decoded = _invoke("bus", "monitor", "--capture", str(out), "--json")
    assert decoded.exit_code == 0, decoded.output
    events = [json.loads(ln) for ln in decoded.stdout.splitlines() if '"t_s"' in ln]
    assert [e["text"] for e in events] == [
        "RAM_READ count len 4",
        "RAM_READ reply count = 12345",
        "RAM_READ count len 4",
    ]


def test_convert_to_mcap_keeps_the_times_for_the_monitor(tmp_path: Path) -> None:
    pytest.importorskip("foxglove")
    log = _write_log(
        tmp_path / "capture.ndjson",
        _line(1718000000.25, "tx", REQUEST),
        _line(1718000000.2517, "rx", REPLY),
        _line(1718000000.75, "tx", REQUEST),
        _line(1718000000.7516, "rx", REPLY),
    )
    out = tmp_path / "capture.mcap"
    result = _invoke("bus", "convert", str(log), str(out), "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["format"] == "mcap"
    assert summary["tx"] == {"packets": 2, "bytes": 2 * len(REQUEST)}
    assert summary["rx"] == {"packets": 2, "bytes": 2 * len(REPLY)}
    assert summary["span_s"] == pytest.approx(0.5016)
    decoded = _invoke("bus", "monitor", "--capture", str(out), "--json")
    assert decoded.exit_code == 0, decoded.output
    lines = [json.loads(ln) for ln in decoded.stdout.splitlines()]
    events = [e for e in lines if "t_s" in e]
    assert [e["t_s"] for e in events] == pytest.approx([0.0, 0.0017, 0.5, 0.5016], abs=1e-6)
    assert [e["latency_ms"] for e in events if e["latency_ms"] is not None] == pytest.approx(
        [1.7, 1.6], abs=1e-3
    )
    (left,) = lines[-1]["devices"]
    assert (left["requests"], left["replies"], left["rate_hz"]) == (2, 2, 2.0)


def test_convert_reports_each_bad_line_and_converts_the_rest(tmp_path: Path) -> None:
    log = _write_log(
        tmp_path / "capture.ndjson",
        _line(1.0, "tx", REQUEST),
        b"not json\n",
        b'{"t": 1.001, "dir": "sideways", "hex": "ff"}\n',
        b'{"dir": "rx", "hex": "ff"}\n',
        _line(1.002, "rx", REPLY),
        b'{"t": 1.003, "dir": "tx", "hex": "xyz"}\n',
    )
    out = tmp_path / "capture.bin"
    result = _invoke("bus", "convert", str(log), str(out))
    assert result.exit_code == 0, result.output
    assert out.read_bytes() == REQUEST + REPLY
    assert result.stderr.splitlines() == [
        f"warning: {log} line 2: bad JSON: Expecting value: line 1 column 1 (char 0) (skipped)",
        f'warning: {log} line 3: field \'dir\' must be "tx" or "rx", not "sideways" (skipped)',
        f"warning: {log} line 4: missing field 't' (skipped)",
        f"warning: {log} line 6: field 'hex' is not hex bytes: \"xyz\" (skipped)",
    ]
    assert result.stdout.strip().endswith("; 4 lines skipped")


def test_convert_says_when_the_time_went_back(tmp_path: Path) -> None:
    log = _write_log(
        tmp_path / "capture.ndjson",
        _line(9.0, "tx", REQUEST),
        _line(2.0, "rx", REPLY),
    )
    result = _invoke("bus", "convert", str(log), str(tmp_path / "c.bin"))
    assert result.exit_code == 0, result.output
    assert result.stdout.strip().endswith(
        "; the time went back 1 times (first at line 2): held, in the file's order"
    )


@pytest.mark.parametrize("content", [b"", b"\n\n", b"garbage\n"], ids=["empty", "blank", "bad"])
def test_a_log_without_records_is_refused_and_writes_nothing(
    tmp_path: Path, content: bytes
) -> None:
    log = _write_log(tmp_path / "capture.ndjson", content)
    out = tmp_path / "capture.bin"
    result = _invoke("bus", "convert", str(log), str(out))
    assert result.exit_code == 1
    lines = content.count(b"\n")
    assert result.stderr.splitlines()[-1] == (
        f"error: {log} holds no records ({lines} lines, {lines} skipped): nothing to convert"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture.ndjson"]


def test_convert_refuses_to_replace_a_file_unless_told(tmp_path: Path) -> None:
    log = _write_log(tmp_path / "capture.ndjson", _line(1.0, "tx", REQUEST))
    out = tmp_path / "capture.bin"
    out.write_bytes(b"precious")
    refused = _invoke("bus", "convert", str(log), str(out))
    assert refused.exit_code == 2
    assert "exists: choose another name, or replace it with --overwrite" in refused.output
    assert out.read_bytes() == b"precious"
    replaced = _invoke("bus", "convert", str(log), str(out), "--overwrite")
    assert replaced.exit_code == 0, replaced.output
    assert out.read_bytes() == REQUEST
    itself = _invoke("bus", "convert", str(log), str(log), "--overwrite")
    assert itself.exit_code == 2
    assert "is the log itself" in itself.output
    assert log.read_bytes() == _line(1.0, "tx", REQUEST).encode()


def test_convert_refuses_a_missing_log_and_a_missing_directory(tmp_path: Path) -> None:
    missing = _invoke("bus", "convert", str(tmp_path / "nope.ndjson"), str(tmp_path / "c.bin"))
    assert missing.exit_code == 2
    assert "cannot read" in missing.output
    log = _write_log(tmp_path / "capture.ndjson", _line(1.0, "tx", REQUEST))
    nowhere = tmp_path / "no" / "c.bin"
    result = _invoke("bus", "convert", str(log), str(nowhere))
    assert result.exit_code == 1
    assert result.stderr.strip() == (
        f"error: cannot write {nowhere}: the directory {nowhere.parent} does not exist"
    )


# -- ohmni bus tbnode-plugin --------------------------------------------------------------


def test_tbnode_plugin_prints_the_shipped_plugin_or_writes_it(tmp_path: Path) -> None:
    printed = _invoke("bus", "tbnode-plugin")
    assert printed.exit_code == 0, printed.output
    assert printed.stdout == plugin_source()
    assert "module.exports = BusCapturePlugin;" in printed.stdout
    out = tmp_path / "ohmni-bus-capture.js"
    written = _invoke("bus", "tbnode-plugin", "--output", str(out))
    assert written.exit_code == 0, written.output
    assert out.read_text(encoding="utf-8") == plugin_source()
    again = _invoke("bus", "tbnode-plugin", "--output", str(out))
    assert again.exit_code == 2
    assert "exists" in again.output
    assert _invoke("bus", "tbnode-plugin", "-o", str(out), "--overwrite").exit_code == 0


@pytest.mark.parametrize("kind", ["device", "fifo", "directory"])
def test_convert_reads_regular_files_only_and_never_waits(tmp_path: Path, kind: str) -> None:
    if kind == "device":
        log, what = Path("/dev/zero"), "a character device"
    elif kind == "fifo":
        log, what = tmp_path / "pipe", "a named pipe (FIFO)"
        os.mkfifo(log)
    else:
        log, what = tmp_path, "a directory"
    out = tmp_path / "c.bin"
    result = _invoke("bus", "convert", str(log), str(out))
    assert result.exit_code == 1
    assert result.stderr.strip() == f"error: cannot read {log}: it is {what}, not a regular file"
    assert not out.exists()
