"""``ohmni status``: one screen of the robot — battery, wheels, odometry, neck, servos, bus,
and each device's health (the ``diagnostics`` stream, as ``ohmni diag`` shows it).

The Robot opens, every expected device is asked, and the command waits (up to
:data:`FIRST_SAMPLE_S`) for the first sample of each stream that runs. ``--json`` prints
one object (:func:`snapshot`; its schema is documented in docs/cli.md); ``--watch``
redraws the screen every :data:`FRAME_S` until Ctrl-C, which ends it with exit code 0
after the Robot has closed. Nothing moves, and the neck is left as it was.
"""

from __future__ import annotations

import asyncio
import json
import math
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
    watching,
    write_line,
)

if TYPE_CHECKING:
    from rich.console import RenderableType
    from rich.panel import Panel
    from rich.table import Table

    from ohmni_tb.robot import Robot, RobotStats, ServoSample

__all__ = ["FIRST_SAMPLE_S", "FRAME_S", "SCHEMA_VERSION", "render", "snapshot", "status"]

#: ``schema`` of the JSON object: raised when a key changes meaning or goes away.
SCHEMA_VERSION: Final = 1
#: ``--watch`` redraws this often: 10 Hz.
FRAME_S: Final = 0.1
#: The longest wait for the first sample of every running stream.
FIRST_SAMPLE_S: Final = 1.0
#: A single status waits at least this long after opening, so the rates it shows are
#: measured over several samples (5 of the core board's at 10 Hz).
MEASURE_S: Final = 0.5
_POLL_S = 0.02
#: Streams that carry no device's readings.
_NOT_DEVICES = frozenset({"robot_state", "pid_debug"})
#: Streams with no bus reads of their own (left out of the bus table).
_NOT_READ = _NOT_DEVICES | {"diagnostics"}
_EXT_STREAMS = (("ext1", "servo_ext1"), ("ext2", "servo_ext2"))


def status(
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
    watch: Annotated[
        bool,
        typer.Option(
            "--watch",
            "-w",
            help="Redraw live at 10 Hz until Ctrl-C (exit code 0); with --json, print one "
            "JSON object per line at 10 Hz.",
        ),
    ] = False,
) -> None:
    """One screen of the robot: battery, wheels, odometry, neck, servos, firmware, bus, health.

    Each running stream's first sample is awaited (at most 1 s). Nothing moves.

    Example: ohmni status --port sim:// --watch
    """

    async def main() -> dict[str, Any] | None:
        from ohmni_tb.cli.robot_cmds import READ_ONLY, device_info  # noqa: PLC0415

        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, **READ_ONLY) as robot:
            opened = asyncio.get_running_loop().time()
            found = await device_info(robot)
            await _first_samples(robot, opened + (0.0 if watch else MEASURE_S))
            if watch:
                await _watch(robot, url, found, as_json=as_json)
                return None
            return snapshot(robot, url, found)

    result = run_watch(main, watch=watch)
    if result is None:
        return
    if as_json:
        emit_json(result)
    else:
        console.print(render(result))


async def _first_samples(robot: Robot, not_before_s: float) -> None:
    """Wait until every running device stream has a sample (at most FIRST_SAMPLE_S), and
    the loop's clock has reached ``not_before_s``."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    wanted = [
        name
        for name, figures in robot.stats().streams.items()
        if figures.enabled and name not in _NOT_DEVICES
    ]
    while True:
        waited = loop.time() - start
        missing = [name for name in wanted if robot.latest(name) is None]
        if waited >= FIRST_SAMPLE_S or (not missing and loop.time() >= not_before_s):
            return
        await asyncio.sleep(_POLL_S)


def _clock() -> float:
    """The frames' clock: the loop's (the tests run the frames on a virtual one)."""
    return asyncio.get_running_loop().time()


async def _pause(delay_s: float) -> None:
    """Wait for the next frame."""
    await asyncio.sleep(delay_s)


async def _watch(robot: Robot, url: str, found: Mapping[str, Any], *, as_json: bool) -> None:
    """Redraw (or print a JSON line) every FRAME_S until Ctrl-C, which ends it cleanly."""
    with watching(as_json=as_json) as live:
        due = _clock()
        while True:
            frame = snapshot(robot, url, found)
            if live is None:
                if not write_line(json.dumps(frame)):
                    return  # the reader went away (`| head`): nothing more to say
            else:
                live.update(render(frame), refresh=True)
            now = _clock()
            # Late (a slow terminal): the next frame now, without a burst after.
            due = max(due + FRAME_S, now)
            await _pause(due - now)


# -- the snapshot (the JSON schema) ------------------------------------------------------


def _rounded(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def _flags(flags: Any) -> list[str]:
    """The names of the set bits of an IntFlag (unknown bits as ``0x..``)."""
    value = int(flags)
    names = [m.name for m in type(flags) if m.value and m.name and value & m.value == m.value]
    rest = value
    for member in type(flags):
        rest &= ~member.value
    return names + ([f"0x{rest:02X}"] if rest else [])


def snapshot(robot: Robot, port: str, found: Mapping[str, Any]) -> dict[str, Any]:
    """Everything ``ohmni status`` shows, as one JSON-ready dict (schema: docs/cli.md).

    Args:
        robot: The open Robot.
        port: The port it was opened on.
        found: :func:`ohmni_tb.cli.robot_cmds.device_info` of it (read once).
    """
    now = asyncio.get_running_loop().time()
    stats = robot.stats()
    state = robot.state
    models = {row["sid"]: row["model"] for row in found["servos"]}

    def age(stamp_s: float) -> float:
        return round(max(0.0, now - stamp_s), 3)

    battery = robot.latest("tbcore_status")
    wheels = robot.latest("wheel_encoder")
    odom = robot.latest("wheel_odom")
    return {
        "schema": SCHEMA_VERSION,
        "port": port,
        "uptime_s": round(stats.uptime_s, 3),
        "link": state.link.value,
        "estopped": state.estopped,
        "watchdog_tripped": state.watchdog_tripped,
        "faults": list(state.faults),
        "present": list(state.present),
        "absent": list(state.absent),
        "neck_kind": robot.neck_kind,
        "battery": None
        if battery is None
        else {
            "cell_v": [round(v, 3) for v in battery.cell_v],
            "pack_v": round(battery.pack_v, 3),
            "current_a": round(battery.current_a, 3),
            "percent": battery.percent,
            "docked": battery.docked,
            "charging": battery.charging,
            "fet_status": battery.fet_status,
            "age_s": age(battery.stamp_s),
        },
        "wheels": None
        if wheels is None
        else {
            "left_ticks": wheels.left_ticks,
            "right_ticks": wheels.right_ticks,
            "left_raw": wheels.left_raw,
            "right_raw": wheels.right_raw,
            "left_m": round(wheels.left_m, 4),
            "right_m": round(wheels.right_m, 4),
            "left_mps": round(wheels.left_mps, 4),
            "right_mps": round(wheels.right_mps, 4),
            "age_s": age(wheels.stamp_s),
        },
        "odometry": None
        if odom is None
        else {
            "x_m": round(odom.x_m, 4),
            "y_m": round(odom.y_m, 4),
            "yaw_rad": round(odom.yaw_rad, 5),
            "yaw_deg": round(math.degrees(odom.yaw_rad), 2),
            "heading_rad": round(odom.heading_rad, 5),
            "linear_mps": round(odom.linear_mps, 4),
            "angular_radps": round(odom.angular_radps, 4),
            "age_s": age(odom.stamp_s),
        },
        "neck": _neck(robot, models, age),
        "servos": {
            role: _servo(robot.latest(stream), models, age) for role, stream in _EXT_STREAMS
        },
        "firmware": dict(found["firmware"]),
        "bus": _bus(stats),
        "diagnostics": _diagnostics(robot),
    }


def _diagnostics(robot: Robot) -> dict[str, Any] | None:
    from ohmni_tb.cli.diag import diagnostics_json  # noqa: PLC0415  # with the snapshot

    sample = robot.latest("diagnostics")
    return None if sample is None else diagnostics_json(sample)


def _servo(
    sample: ServoSample | None, models: Mapping[int, str | None], age: Any
) -> dict[str, Any] | None:
    if sample is None:
        return None
    return {
        "sid": sample.sid,
        "model": models.get(sample.sid),
        "position_raw": sample.position_raw,
        "angle_rad": round(sample.angle_rad, 5),
        "angle_deg": round(math.degrees(sample.angle_rad), 2),
        "temperature_raw": sample.temperature_raw,
        "voltage_v": round(sample.voltage_v, 3),
        "torque": sample.torque.name.lower(),
        "status_error": _flags(sample.status_error),
        "status_detail": _flags(sample.status_detail),
        "moving": sample.moving,
        "age_s": age(sample.stamp_s),
    }


def _neck(robot: Robot, models: Mapping[int, str | None], age: Any) -> dict[str, Any] | None:
    if robot.neck_kind == "herkulex":
        servo = _servo(robot.latest("servo_neck"), models, age)
        return None if servo is None else {"kind": "herkulex", **servo, "stalled": None}
    if robot.neck_kind == "worm":
        from ohmni_tb.protocol.devices import DeviceId  # noqa: PLC0415  # loaded by the Robot

        sample = robot.latest("new_neck")
        if sample is None:
            return None
        return {
            "kind": "worm",
            "sid": int(DeviceId.WORM_NECK),
            "model": None,
            "position_raw": sample.position_raw,
            "angle_rad": None,
            "angle_deg": None,
            "temperature_raw": None,
            "voltage_v": None,
            "torque": None,
            "status_error": None,
            "status_detail": _flags(sample.flags),
            "moving": sample.moving,
            "stalled": sample.stalled,
            "age_s": age(sample.stamp_s),
        }
    return None


def _bus(stats: RobotStats) -> dict[str, Any]:
    bus = stats.bus
    return {
        "wire_utilisation": round(bus.wire_utilisation, 4),
        "budget_share": round(bus.budget_share, 4),
        "transactions_per_s": round(bus.transactions_per_s, 1),
        "timeouts": bus.timeouts,
        "deadline_misses": bus.deadline_misses,
        "rejected_samples": bus.rejected_samples,
        "link_losses": bus.link_losses,
        "reconnects": bus.reconnects,
        "streams": {
            name: {
                "enabled": s.enabled,
                "requested_hz": round(s.requested_hz, 2),
                "achieved_hz": round(s.achieved_hz, 2),
                "samples": s.samples,
                "missed": s.missed,
                "skipped": s.skipped,
                "dropped": s.dropped,
                "jitter_p50_ms": _rounded(s.jitter_p50_ms, 2),
                "jitter_p99_ms": _rounded(s.jitter_p99_ms, 2),
            }
            for name, s in stats.streams.items()
        },
    }


# -- the screen --------------------------------------------------------------------------


def _panel(title: str, body: RenderableType | None, missing: str) -> Panel:
    from rich.panel import Panel  # noqa: PLC0415

    shown = f"[dim]{missing}[/dim]" if body is None else body
    return Panel(shown, title=title, title_align="left", expand=False)


def _grid(rows: list[tuple[str, ...]], header: tuple[str, ...] = ()) -> Table:
    from rich.table import Table  # noqa: PLC0415

    grid = Table.grid(padding=(0, 1))
    width = len(rows[0]) if rows else len(header)
    grid.add_column(style="bold")
    for _ in range(width - 1):
        grid.add_column(justify="right" if header else "left")
    if header:
        grid.add_row(*header, style="dim")
    for row in rows:
        grid.add_row(*row)
    return grid


def _missing(snap: Mapping[str, Any], *sids: int) -> str:
    """Why a device has no reading: it does not answer, or it has given none yet."""
    if any(sid in snap["present"] for sid in sids):
        return "no reading yet"
    return "absent"


def render(snap: Mapping[str, Any]) -> RenderableType:
    """The screen of a :func:`snapshot`: the devices' panels, the servos, the bus."""
    from rich.columns import Columns  # noqa: PLC0415
    from rich.console import Group  # noqa: PLC0415
    from rich.markup import escape  # noqa: PLC0415

    faults = ", ".join(snap["faults"]) or "none"
    flags = (" · [bold red]E-STOP latched[/bold red]" if snap["estopped"] else "") + (
        " · watchdog stopped the wheels" if snap["watchdog_tripped"] else ""
    )
    link = snap["link"] if snap["link"] == "connected" else f"[bold red]{snap['link']}[/bold red]"
    header = (
        f"[bold]{escape(snap['port'])}[/bold] · link {link} · up {snap['uptime_s']:.1f} s · "
        f"faults: {escape(faults)}{flags}"
    )
    battery = snap["battery"]
    battery_grid = None
    if battery is not None:
        dock = "docked" if battery["docked"] else "off the dock"
        flow = "charging" if battery["charging"] else "not charging"
        battery_grid = _grid(
            [
                ("pack", f"{battery['pack_v']:.2f} V, {battery['percent']} %"),
                ("cells", " ".join(f"{v:.3f}" for v in battery["cell_v"])),
                ("current", f"{battery['current_a']:+.3f} A"),
                ("dock", f"{dock}, {flow}"),
            ]
        )
    wheels = snap["wheels"]
    wheels_grid = None
    if wheels is not None:
        wheels_grid = _grid(
            [
                ("ticks", f"{wheels['left_ticks']:+d}", f"{wheels['right_ticks']:+d}"),
                ("m", f"{wheels['left_m']:+.3f}", f"{wheels['right_m']:+.3f}"),
                ("m/s", f"{wheels['left_mps']:+.3f}", f"{wheels['right_mps']:+.3f}"),
            ],
            header=("", "left", "right"),
        )
    odom = snap["odometry"]
    odom_grid = None
    if odom is not None:
        odom_grid = _grid(
            [
                ("x, y", f"{odom['x_m']:+.3f} m, {odom['y_m']:+.3f} m"),
                ("yaw", f"{odom['yaw_deg']:+.1f}° ({odom['yaw_rad']:+.4f} rad)"),
                ("speed", f"{odom['linear_mps']:+.3f} m/s"),
                ("turn", f"{odom['angular_radps']:+.3f} rad/s"),
            ]
        )
    firmware_grid = _grid(
        [
            (board.replace("_", " "), "[dim]-[/dim]" if tag is None else escape(tag))
            for board, tag in snap["firmware"].items()
        ]
    )
    panels = Columns(
        [
            _panel("battery", battery_grid, _missing(snap, 20)),
            _panel("wheels", wheels_grid, _missing(snap, 0, 1)),
            _panel("odometry", odom_grid, _missing(snap, 0, 1)),
            _panel("firmware", firmware_grid, "none"),
        ]
    )
    return Group(header, panels, _servo_table(snap), *_bus_table(snap["bus"]), _health(snap))


def _health(snap: Mapping[str, Any]) -> RenderableType:
    from ohmni_tb.cli.diag import diagnostics_table  # noqa: PLC0415

    data = snap.get("diagnostics")
    if data is None:
        return "[dim]health: no diagnostics sample yet (diagnostics_hz)[/dim]"
    return diagnostics_table(data)


def _servo_table(snap: Mapping[str, Any]) -> Table:

    table = plain_table("neck and servos (position, temperature: raw)")
    for column in ("", "sid", "model", "position", "angle", "torque", "temp", "volts"):
        table.add_column(column, justify="left" if column in ("", "model") else "right")
    table.add_column("status")
    neck = snap["neck"]
    kind = snap["neck_kind"]
    rows: list[tuple[str, dict[str, Any] | None, str]] = []
    if kind == "none":
        rows.append(("neck", None, "none answered"))
    else:
        rows.append(("neck", neck, "no reading yet"))  # it answered at open
    rows += [(role, servo, "absent") for role, servo in snap["servos"].items()]

    def shown(value: Any, form: str = "{}") -> str:
        return "-" if value is None else form.format(value)

    for role, servo, missing in rows:
        if servo is None:
            table.add_row(role, "", f"[dim]{missing}[/dim]", *[""] * 6)
            continue
        worm = servo.get("kind") == "worm"
        status = [*(servo["status_error"] or []), *(servo["status_detail"] or [])]
        table.add_row(
            role,
            str(servo["sid"]),
            "worm gear" if worm else shown(servo["model"]),
            str(servo["position_raw"]),
            shown(servo["angle_deg"], "{:+.1f}°"),
            shown(servo["torque"]),
            shown(servo["temperature_raw"]),
            shown(servo["voltage_v"], "{:.2f}"),
            "|".join(status) or "ok",
        )
    return table


def _bus_table(bus: Mapping[str, Any]) -> tuple[Table, str]:

    table = plain_table("bus")
    for column in ("stream", "Hz want", "Hz got", "samples", "missed", "skipped"):
        table.add_column(column, justify="left" if column == "stream" else "right")
    table.add_column("jitter ms", justify="right")

    def ms(value: float | None) -> str:
        return "-" if value is None else f"{value:.1f}"

    for name, s in bus["streams"].items():
        if name in _NOT_READ or not (s["enabled"] or s["samples"]):
            continue  # robot_state, pid_debug and diagnostics are not read on the bus
        table.add_row(
            name,
            f"{s['requested_hz']:.1f}",
            f"{s['achieved_hz']:.1f}",
            str(s["samples"]),
            str(s["missed"]),
            str(s["skipped"]),
            f"{ms(s['jitter_p50_ms'])}/{ms(s['jitter_p99_ms'])}",
        )
    line = (
        f"wire {bus['wire_utilisation']:.0%} (schedule budget {bus['budget_share']:.0%}), "
        f"{bus['transactions_per_s']:.0f} transactions/s, {bus['timeouts']} timeouts, "
        f"{bus['deadline_misses']} deadline misses, {bus['rejected_samples']} rejected samples"
    )
    if bus["link_losses"]:
        line += f", link lost {bus['link_losses']}x, reconnected {bus['reconnects']}x"
    return table, line
