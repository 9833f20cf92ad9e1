"""What every ``ohmni`` command shares: the port option, output, error reporting."""

from __future__ import annotations

import asyncio
import json
import os
import sys
from collections.abc import Callable, Coroutine
from typing import Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from ohmni_tb.bus import DEFAULT_TIMEOUT_S, Bus, BusStats
from ohmni_tb.errors import OhmniError
from ohmni_tb.transport import open_transport

__all__ = [
    "DEFAULT_PORT",
    "JsonOption",
    "PortOption",
    "TimeoutOption",
    "console",
    "emit_json",
    "open_bus",
    "parse_int",
    "run",
    "stats_rows",
]

T = TypeVar("T")

#: The robot's serial adapter; OHMNI_PORT overrides it (``sim://`` for the simulator).
DEFAULT_PORT = os.environ.get("OHMNI_PORT", "/dev/ttyUSB0")

PortOption = Annotated[
    str,
    typer.Option(
        "--port",
        "-p",
        help="Serial device or URL: /dev/ttyUSB0, serial:///dev/ttyUSB0?baudrate=115200, "
        "sim:// (built-in simulator). Default: $OHMNI_PORT or /dev/ttyUSB0.",
    ),
]
JsonOption = Annotated[bool, typer.Option("--json", help="Print JSON instead of a table.")]
TimeoutOption = Annotated[
    float,
    typer.Option("--timeout", help="Reply timeout per attempt, in seconds.", min=0.001, max=10.0),
]

console = Console()
_err = Console(stderr=True)


def run(
    main: Callable[[], Coroutine[Any, Any, T]],
    *,
    on_interrupt: Callable[[], None] | None = None,
) -> T:
    """Run a coroutine for a command; our errors become one red line and exit code 1.

    Ctrl-C exits with code 130, after ``on_interrupt`` (a command's summary) has run.
    """
    try:
        return asyncio.run(main())
    except OhmniError as exc:
        # One line whatever the terminal's width; the text is ours, not markup.
        _err.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)
        raise typer.Exit(1) from exc
    except KeyboardInterrupt:
        if on_interrupt is not None:
            on_interrupt()
        raise typer.Exit(130) from None


async def open_bus(port: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> Bus:
    """Open the port and start a bus on it; the caller closes it (``async with``)."""
    transport = await open_transport(port)
    bus = Bus(transport, timeout_s=timeout_s)
    bus.start()
    return bus


def parse_int(
    text: str, name: str, low: int | None = None, high: int | None = None, *, of: str = ""
) -> int:
    """Parse decimal or 0x-hex ASCII text, in ``low..high`` when they are given.

    Other digits (``٣``, ``３``) are refused: an id is typed, not localised. ``of`` says
    whose range it is (``" for servo 3"``) in the error.

    Raises:
        typer.BadParameter: Names the argument, the text and the allowed range.
    """
    try:
        if not text.isascii():
            raise ValueError(text)
        value = int(text, 0)
    except ValueError:  # also a number of more than 4300 digits
        raise typer.BadParameter(
            f"{name} must be an integer (decimal or 0x..), not {_shown(text)}"
        ) from None
    if low is not None and high is not None and not low <= value <= high:
        # A huge hex number has too many decimal digits to print: show what was typed.
        shown = str(value) if value.bit_length() <= 64 else _shown(text)
        raise typer.BadParameter(f"{name}={shown} is out of range{of}: allowed {low}..{high}")
    return value


def _shown(text: str) -> str:
    """Typed text for an error line, quoted, and cut short when it is long."""
    return repr(text) if len(text) <= 40 else f"{text[:20]!r}… ({len(text)} characters)"


def emit_json(value: Any) -> None:
    """Print one JSON document on stdout."""
    sys.stdout.write(json.dumps(value, indent=2, default=str) + "\n")


def stats_rows(stats: BusStats) -> list[dict[str, Any]]:
    """One row per device of the bus statistics, for tables and JSON."""
    return [
        {
            "sid": dev.sid,
            "requests": dev.requests,
            "replies": dev.replies,
            "timeouts": dev.timeouts,
            "retries": dev.retries,
            "unmatched": dev.unmatched,
            "late": dev.late,
            "breaker": dev.breaker.value,
            "latency_p50_ms": None
            if dev.latency_p50_s is None
            else round(dev.latency_p50_s * 1e3, 3),
            "latency_p99_ms": None
            if dev.latency_p99_s is None
            else round(dev.latency_p99_s * 1e3, 3),
        }
        for dev in stats.devices.values()
    ]
