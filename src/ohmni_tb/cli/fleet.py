"""``ohmni fleet``: every robot an MQTT broker knows — online, battery, dock, faults, last
seen (``--watch``, ``--json``)."""

from __future__ import annotations

import json
import time
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.markup import escape

from ohmni_tb.cli.common import (
    JsonOption,
    console,
    emit_json,
    plain_table,
    run_watch,
    watching,
    write_line,
)

if TYPE_CHECKING:
    from rich.table import Table

    from ohmni_tb.fleet import FleetRobot

__all__ = ["fleet", "render", "rows"]


def fleet(
    mqtt: Annotated[
        str | None,
        typer.Option(
            "--mqtt",
            metavar="URL",
            help="The broker: mqtt://HOST[:PORT] or mqtts://HOST[:PORT] (default: the "
            "mqtt_url setting). Credentials and TLS files come from the settings "
            "(mqtt_username, OHMNI_MQTT_PASSWORD …).",
            show_default=False,
        ),
    ] = None,
    as_json: JsonOption = False,
    watch: Annotated[
        bool,
        typer.Option(
            "--watch",
            "-w",
            help="Keep the list live until Ctrl-C (exit code 0); with --json, print the list "
            "as one JSON line on every change.",
        ),
    ] = False,
) -> None:
    """Every robot the broker knows: id, online, battery, docked, faults, last seen.

    The robots are those that published with ohmni serve --mqtt (their retained state
    and availability): a robot gone for good stays, offline, with the time it was last
    seen. Needs the mqtt extra (docs/fleet.md).

    Example: ohmni fleet --mqtt mqtt://localhost:1883 --json
    """
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic: only when run
    from ohmni_tb.errors import ConfigError  # noqa: PLC0415

    try:
        if mqtt is not None:
            RobotConfig.check_setting("mqtt_url", mqtt)
        config = RobotConfig.load(**({} if mqtt is None else {"mqtt_url": mqtt}))
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--mqtt") from None
    if not config.mqtt_url:
        raise typer.BadParameter(
            "no broker: give --mqtt URL, or set mqtt_url (OHMNI_MQTT_URL)", param_hint="--mqtt"
        )

    async def main() -> list[FleetRobot] | None:
        from ohmni_tb.fleet import Fleet  # noqa: PLC0415  # the extra: when run

        async with Fleet.from_config(config) as view:
            if not watch:
                return view.robots
            await _watch(view, as_json=as_json)
            return None

    robots = run_watch(main, watch=watch)
    if robots is None:
        return
    if as_json:
        emit_json([robot.as_json() for robot in robots])
    else:
        console.print(render(robots, time.time()))


def rows(robots: list[FleetRobot], now_s: float) -> list[dict[str, str]]:
    """The table's cells, a row per robot (``now_s``: Unix time, for the ages)."""
    return [
        {
            "robot": robot.robot_id,
            "online": "yes" if robot.online else "no" if robot.online is False else "?",
            "battery": "-" if robot.battery_percent is None else f"{robot.battery_percent} %",
            "docked": "-" if robot.docked is None else "yes" if robot.docked else "no",
            "faults": ", ".join(robot.faults) or "none",
            "last seen": _age(robot.last_seen, now_s),
        }
        for robot in robots
    ]


def render(robots: list[FleetRobot], now_s: float) -> Table | str:
    """The fleet as a table (or a line saying the broker knows no robot)."""
    if not robots:
        return "the broker knows no robot (none published with ohmni serve --mqtt)"
    table = plain_table()
    cells = rows(robots, now_s)
    for column in cells[0]:
        table.add_column(column)
    for row in cells:
        table.add_row(*(escape(value) for value in row.values()))
    return table


async def _watch(view: Any, *, as_json: bool) -> None:
    """The list on every change until Ctrl-C, which ends it cleanly."""
    with watching(as_json=as_json) as live:
        async for robots in view.changes():
            if live is None:
                if not write_line(json.dumps([robot.as_json() for robot in robots])):
                    return  # the reader went away (`| head`)
            else:
                live.update(render(robots, time.time()), refresh=True)


def _age(stamp: float | None, now_s: float) -> str:
    """How long ago ``stamp`` was, for people: ``4 s ago``, ``3 min ago``, ``2 h ago``."""
    if stamp is None:
        return "never"
    age = max(0.0, now_s - stamp)
    if age < 120:
        return f"{age:.0f} s ago"
    if age < 7200:
        return f"{age / 60:.0f} min ago"
    if age < 172800:
        return f"{age / 3600:.0f} h ago"
    return f"{age / 86400:.0f} d ago"
