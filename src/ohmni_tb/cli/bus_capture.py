"""``ohmni bus tbnode-plugin`` and ``ohmni bus convert``: capture the vendor's traffic on
the robot with a tb-node plugin, then turn its log into a capture the monitor decodes."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Annotated, Final

import typer

from ohmni_tb._files import open_regular
from ohmni_tb.capture.tbnode import LogReader, LogRecord, LogSummary, plugin_source
from ohmni_tb.cli.common import JsonOption, console, emit_json, error_line
from ohmni_tb.errors import OhmniError

__all__ = ["convert", "tbnode_plugin"]

#: The log is read this much at a time: the converter holds a block, not the file.
_READ_BLOCK: Final = 1 << 16

OverwriteOption = Annotated[
    bool, typer.Option("--overwrite", help="Replace the output file if it exists.")
]


def tbnode_plugin(
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", help="Write the plugin to this file [default: stdout]."),
    ] = None,
    overwrite: OverwriteOption = False,
) -> None:
    """Print the tb-node plugin that logs every byte of the robot's bus (JavaScript).

    Copy it into tb-node's plugins directory on the robot and restart tb-node: it logs
    what the vendor's software writes and reads, with times, for `ohmni bus convert`
    (docs/hardware.md, "Capturing the real bytes"). Its header says what it assumes and
    how to remove it.

    Example: ohmni bus tbnode-plugin --output ohmni-bus-capture.js
    """
    source = plugin_source()
    if output is None:
        typer.echo(source, nl=False)
        return
    try:
        with open(output, "w" if overwrite else "x", encoding="utf-8") as file:
            file.write(source)
    except FileExistsError:
        raise typer.BadParameter(
            f"{output} exists: choose another name, or replace it with --overwrite",
            param_hint="--output",
        ) from None
    except OSError as exc:
        error_line(f"cannot write {output}: {exc.strerror or exc}")
        raise typer.Exit(1) from None
    console.print(f"wrote the tb-node plugin to {output}", highlight=False)


def convert(
    log: Annotated[
        Path,
        typer.Argument(help="The log the tb-node plugin wrote on the robot."),
    ],
    output: Annotated[
        Path,
        typer.Argument(
            help="The capture to write: a .mcap file keeps each chunk's time and direction "
            "(needs the foxglove extra); any other name gets the bytes alone."
        ),
    ],
    overwrite: OverwriteOption = False,
    as_json: JsonOption = False,
) -> None:
    """Convert a tb-node capture log into a capture for `ohmni bus monitor --capture`.

    An OUTPUT ending in .mcap is a recording as `ohmni record --raw` writes it: the
    monitor then shows each packet's time, the rates and the reply latencies. Any other
    OUTPUT gets the raw bytes, both directions in the order they happened, without times.
    A line of the log that is not a record is skipped and counted; the first ones are
    listed on stderr with their line number and what is wrong. Times that go back (a
    clock set back between two runs of tb-node) keep the file's order and are held at
    the time before them.

    Example: ohmni bus convert capture.ndjson capture.mcap
    """
    as_mcap = output.suffix.lower() == ".mcap"
    if as_mcap and importlib.util.find_spec("foxglove") is None:
        error_line("an MCAP output needs the foxglove extra: pip install 'ohmni_tb[foxglove]'")
        raise typer.Exit(1)
    source = _open_log(log)
    with source:
        _check_output(log, output, overwrite)
        reader = LogReader()
        partial = _partial_file(output)
        try:
            if as_mcap:
                _write_mcap(partial, _records(source, reader, log), log)
            else:
                _write_raw(partial, _records(source, reader, log))
            summary = reader.summary
            _report_skipped(log, summary)
            if not summary.records:
                error_line(
                    f"{log} holds no records ({summary.lines} lines, {summary.skipped} "
                    "skipped): nothing to convert"
                )
                raise typer.Exit(1)
            os.replace(partial, output)
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(partial)
    if as_json:
        emit_json(_summary_json(log, output, as_mcap, summary))
    else:
        console.print(_summary_text(output, as_mcap, summary), highlight=False)


def _open_log(log: Path) -> IO[bytes]:
    """The log, open for reading, if it is a regular file.

    Raises:
        typer.BadParameter: It cannot be opened (exit code 2).
        typer.Exit: Code 1, after one line, when it is not a regular file.
    """
    try:
        return open_regular(log)
    except OSError as exc:
        raise typer.BadParameter(
            f"cannot read {log}: {exc.strerror or exc}", param_hint="LOG"
        ) from None
    except ValueError as exc:  # not a regular file, or a NUL in the path
        error_line(f"cannot read {log}: {exc}")
        raise typer.Exit(1) from None


def _check_output(log: Path, output: Path, overwrite: bool) -> None:
    """Refuse to replace a file by accident, and the log itself ever.

    Raises:
        typer.BadParameter: OUTPUT exists (without ``--overwrite``), or is the log.
    """
    if not output.exists():
        return
    with contextlib.suppress(OSError):
        if output.samefile(log):
            raise typer.BadParameter(
                f"{output} is the log itself: choose another name", param_hint="OUTPUT"
            )
    if output.is_dir():
        raise typer.BadParameter(f"{output} is a directory", param_hint="OUTPUT")
    if not overwrite:
        raise typer.BadParameter(
            f"{output} exists: choose another name, or replace it with --overwrite",
            param_hint="OUTPUT",
        )


def _partial_file(output: Path) -> Path:
    """A new empty file beside ``output``: the capture is written there, then renamed,
    so an interrupted conversion leaves neither half a capture nor a lost old one.

    Raises:
        typer.Exit: Code 1, after one line, when the directory cannot take it.
    """
    try:
        fd, name = tempfile.mkstemp(prefix=f".{output.name}.", suffix=".partial", dir=output.parent)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        if not output.parent.is_dir():
            reason = f"the directory {output.parent} does not exist"
        error_line(f"cannot write {output}: {reason}")
        raise typer.Exit(1) from None
    os.close(fd)
    return Path(name)


def _records(source: IO[bytes], reader: LogReader, log: Path) -> Iterator[LogRecord]:
    """The log's records, read a block at a time."""
    try:
        while block := source.read(_READ_BLOCK):
            yield from reader.feed(block)
    except OSError as exc:
        error_line(f"cannot read {log}: {exc.strerror or exc}")
        raise typer.Exit(1) from None
    yield from reader.finish()


def _write_raw(path: Path, records: Iterator[LogRecord]) -> None:
    try:
        with open(path, "wb") as file:
            for record in records:
                file.write(record.data)
    except OSError as exc:
        error_line(f"cannot write {path}: {exc.strerror or exc}")
        raise typer.Exit(1) from None


def _write_mcap(path: Path, records: Iterator[LogRecord], log: Path) -> None:
    from ohmni_tb.foxglove.record import write_raw_recording  # noqa: PLC0415  # the extra

    chunks = ((round(r.t_s * 1e9), r.sent, r.data) for r in records)
    try:
        write_raw_recording(
            path,
            chunks,
            overwrite=True,  # the partial file made for it
            metadata={
                "source": f"tb-node capture log {log.name}, converted by ohmni bus convert",
                "log_time": "the log's t (seconds), in ns",
            },
        )
    except OhmniError as exc:
        error_line(str(exc))
        raise typer.Exit(1) from None


def _report_skipped(log: Path, summary: LogSummary) -> None:
    for skipped in summary.skipped_lines:
        typer.echo(f"warning: {log} line {skipped.line}: {skipped.reason} (skipped)", err=True)
    more = summary.skipped - len(summary.skipped_lines)
    if more:
        typer.echo(f"warning: {log}: {more} more lines skipped", err=True)


def _summary_text(output: Path, as_mcap: bool, s: LogSummary) -> str:
    kind = "an MCAP recording" if as_mcap else "raw bytes"
    text = (
        f"{output}: {kind}; tx {s.tx_packets} packets / {s.tx_bytes} bytes, "
        f"rx {s.rx_packets} packets / {s.rx_bytes} bytes, over {s.span_s:.3f} s; "
        f"{s.skipped} lines skipped"
    )
    if s.backwards:
        text += (
            f"; the time went back {s.backwards} times (first at line "
            f"{s.first_backwards_line}): held, in the file's order"
        )
    return text


def _summary_json(log: Path, output: Path, as_mcap: bool, s: LogSummary) -> dict[str, object]:
    return {
        "log": str(log),
        "output": str(output),
        "format": "mcap" if as_mcap else "raw",
        "lines": s.lines,
        "records": s.records,
        "tx": {"packets": s.tx_packets, "bytes": s.tx_bytes},
        "rx": {"packets": s.rx_packets, "bytes": s.rx_bytes},
        "span_s": s.span_s,
        "skipped": s.skipped,
        "skipped_lines": [{"line": k.line, "reason": k.reason} for k in s.skipped_lines],
        "time_went_back": s.backwards,
        "first_time_back_line": s.first_backwards_line,
    }
