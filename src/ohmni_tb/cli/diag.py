"""``ohmni diag``: the robot's health — each device's and the link's — once, or ``--watch``.

It prints the newest sample of the Robot's ``diagnostics`` stream (waiting for the first
one after open, half a period: 0.5 s at ``diagnostics_hz`` 1) as a table: one row per
expected device and one for the link, each with its level (OK, WARN, ERROR), what stands
out in words, and its main figures. ``--json`` prints one object (:func:`diagnostics_json`,
documented in docs/cli.md); ``--watch`` prints each new sample until Ctrl-C (exit code 0).
Through ``ohmni serve`` when it runs, as ``ohmni status``. Nothing moves.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Annotated, Any, Final

import typer

from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    console,
    daemon_for,
    emit_json,
    open_robot,
    plain_table,
    resolve_port,
    run_watch,
    write_line,
)
from ohmni_tb.errors import StateError

if TYPE_CHECKING:
    from rich.table import Table

    from ohmni_tb.robot import DiagnosticsSample, Robot, SampleStream

__all__ = ["FIGURES", "FIRST_SAMPLE_MARGIN_S", "diag", "diagnostics_json", "diagnostics_table"]

#: How long past the first sample's due time (half a period after open) to wait for it.
FIRST_SAMPLE_MARGIN_S: Final = 1.0
#: The figures a row shows, in this order (each when the entry has it): value → words.
FIGURES: Final[tuple[tuple[str, str], ...]] = (
    ("firmware", "{}"),
    ("model", "{}"),
    ("latency_p99_ms", "p99 {:.1f} ms"),
    ("timeouts", "{} timeouts"),
    ("lowest_cell_mv", "lowest cell {} mV"),
    ("cell_spread_mv", "spread {} mV"),
    ("temperature_raw", "temp {}"),
    ("load_share", "load {:.0%}"),
    ("pid_saturated_share", "PID saturated {:.0%}"),
    ("state", "{}"),
    ("wire_utilisation", "wire {:.0%}"),
    ("checksum_errors", "{} checksum errors"),
    ("watchdog_trips", "{} watchdog trips"),
)
_STYLE: Final = {"ok": "green", "warn": "yellow", "error": "bold red"}


def diag(
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
    watch: Annotated[
        bool,
        typer.Option(
            "--watch",
            "-w",
            help="Print each new sample (diagnostics_hz: 1 a second) until Ctrl-C (exit "
            "code 0); with --json, one JSON object per line.",
        ),
    ] = False,
) -> None:
    """The robot's health: each device's and the link's level, what is wrong, the figures.

    One row per device the robot expects (drive boards, core board, neck, external
    servos) and one for the link: OK, WARN or ERROR, in words, with its firmware, reply
    latency, timeouts, battery cells, temperature and load. Nothing moves.

    Examples: ohmni diag --port sim:// ; ohmni diag --port 'sim://?silent=11' --json ;
    ohmni diag --watch
    """

    async def main() -> dict[str, Any] | None:
        from ohmni_tb.cli.robot_cmds import READ_ONLY  # noqa: PLC0415

        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, **READ_ONLY) as robot:
            if watch:
                await _watch(robot, url, as_json=as_json)
                return None
            return {"port": url, **diagnostics_json(await first_sample(robot))}

    result = run_watch(main, watch=watch)
    if result is None:
        return
    if as_json:
        emit_json(result)
    else:
        console.print(diagnostics_table(result))


async def first_sample(robot: Robot) -> DiagnosticsSample:
    """The newest ``diagnostics`` sample, waiting for the first one if need be.

    Raises:
        StateError: The stream is off, or no sample came in time.
    """
    figures = robot.stats().streams["diagnostics"]
    if not figures.enabled or figures.requested_hz <= 0:
        raise StateError(
            "the diagnostics stream is off (diagnostics_hz=0, or `ohmni stream disable "
            "diagnostics`): `ohmni stream enable diagnostics`, or set diagnostics_hz"
        )
    sample = robot.latest("diagnostics")
    if sample is not None:
        return sample
    wait_s = 1.0 / figures.requested_hz + FIRST_SAMPLE_MARGIN_S
    async with robot.subscribe("diagnostics", maxlen=1) as samples:
        try:
            async with asyncio.timeout(wait_s):
                return await anext(samples)
        except (TimeoutError, StopAsyncIteration):
            raise StateError(f"no diagnostics sample within {wait_s:g} s") from None


async def _watch(robot: Robot, url: str, *, as_json: bool) -> None:
    """Print every sample from now on until Ctrl-C, which ends it cleanly."""
    try:
        async with robot.subscribe("diagnostics", maxlen=4) as samples:
            sample: DiagnosticsSample | None = await first_sample(robot)
            while sample is not None:
                data = {"port": url, **diagnostics_json(sample)}
                if as_json:
                    if not write_line(json.dumps(data)):
                        return  # the reader went away (`| head`)
                else:
                    console.print(diagnostics_table(data))
                sample = await _next(samples)
    except (KeyboardInterrupt, asyncio.CancelledError):
        task = asyncio.current_task()
        if task is not None:
            while task.cancelling():
                task.uncancel()


async def _next(samples: SampleStream[DiagnosticsSample]) -> DiagnosticsSample | None:
    """The next sample (``None``: the Robot closed)."""
    return await anext(samples, None)


def diagnostics_json(sample: DiagnosticsSample) -> dict[str, Any]:
    """A ``diagnostics`` sample as ``ohmni diag --json`` and ``ohmni status --json`` print it
    (schema: docs/cli.md)."""
    return {
        "level": sample.level.value,
        "event": sample.event,
        "entries": [
            {
                "name": entry.name,
                "sid": entry.sid,
                "level": entry.level.value,
                "message": entry.message,
                "values": dict(entry.values),
            }
            for entry in sample.entries
        ],
    }


def diagnostics_table(data: Mapping[str, Any], title: str | None = None) -> Table:
    """The table of :func:`diagnostics_json`'s data: a row per entry."""
    from rich.markup import escape  # noqa: PLC0415

    level = data["level"]
    heading = title if title is not None else f"health: [{_STYLE[level]}]{level}[/]"
    table = plain_table(heading)
    for column in ("", "sid", "level", "what", "figures"):
        table.add_column(column, justify="right" if column == "sid" else "left")
    for entry in data["entries"]:
        table.add_row(
            entry["name"],
            "" if entry["sid"] is None else str(entry["sid"]),
            f"[{_STYLE[entry['level']]}]{entry['level']}[/]",
            "" if entry["level"] == "ok" else escape(entry["message"]),
            escape(figures(entry["values"])),
        )
    return table


def figures(values: Mapping[str, Any]) -> str:
    """An entry's main figures in words (:data:`FIGURES`), those it has and knows."""
    shown = []
    for key, form in FIGURES:
        value = values.get(key)
        if value is None or value == "":
            continue
        with contextlib.suppress(ValueError, TypeError):
            shown.append(form.format(value))
    return ", ".join(shown)
