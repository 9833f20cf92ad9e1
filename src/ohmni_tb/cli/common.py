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


def run(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    """Run a coroutine for a command; our errors become one red line and exit code 1."""
    try:
        return asyncio.run(main())
    except OhmniError as exc:
        _err.print(f"[red]error:[/red] {exc}")
        raise typer.Exit(1) from exc
    except KeyboardInterrupt:
        raise typer.Exit(130) from None


async def open_bus(port: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> Bus:
    """Open the port and start a bus on it; the caller closes it (``async with``)."""
    transport = await open_transport(port)
    bus = Bus(transport, timeout_s=timeout_s)
    bus.start()
    return bus


def parse_int(text: str, name: str) -> int:
    """Parse decimal or 0x-hex text.

    Raises:
        typer.BadParameter: Names the argument and the text.
    """
    try:
        return int(text, 0)
    except ValueError:
        raise typer.BadParameter(
            f"{name} must be an integer (decimal or 0x..), not {text!r}"
        ) from None


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
