"""``ohmni demo``: a tour of the bus on the simulator (or, carefully, on a robot)."""

from __future__ import annotations

import asyncio
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from ohmni_tb.bus import Bus
from ohmni_tb.cli.common import PortOption, console, run, stats_rows
from ohmni_tb.control import EncoderConfig
from ohmni_tb.errors import BusTimeoutError, OhmniError, StopNotConfirmedError
from ohmni_tb.herkulex import (
    TorqueControl,
    angle_deg_from_raw,
)
from ohmni_tb.herkulex.servo import Servo
from ohmni_tb.protocol import Memory
from ohmni_tb.protocol.core import parse_status, read_status
from ohmni_tb.protocol.devices import (
    DEFAULT_EXT_SERVO_IDS,
    NECK_RAW_RANGE,
    DeviceId,
    device_name,
)
from ohmni_tb.protocol.drive import wheel_command
from ohmni_tb.protocol.worm_neck import parse_feedback, read_feedback, set_target
from ohmni_tb.safety import StopReport, stop_wheels
from ohmni_tb.transport import open_transport

__all__ = ["demo"]

#: Ticks to metres with the configured wheel radius and ticks per wheel turn.
_ENCODER = EncoderConfig()
_NECK_FROM, _NECK_TO = NECK_RAW_RANGE
#: A worm-neck target inside its range (−127000 up … 120000 down): tilt down a little.
_WORM_TARGET = 60_000
#: How long the demo keeps stopping the wheels until their counts confirm it: longer
#: than stop_wheels' default, so a lossy line's lost count reads are ridden out.
_STOP_TIMEOUT_S = 2.0
_err = Console(stderr=True)


def demo(
    port: PortOption = "sim://",
    allow_motion: Annotated[
        bool,
        typer.Option(
            "--allow-motion",
            help="Let the demo drive the wheels on a real robot (always on for sim://).",
        ),
    ] = False,
) -> None:
    """Scan the bus, read the battery, drive the wheels, move the neck, show bus figures.

    On the built-in simulator (the default, sim://) everything runs. On a real robot the
    wheels stay still unless --allow-motion is given: the robot would drive ~40 cm.
    """
    motion = allow_motion or port.startswith("sim:")
    run(lambda: _demo(port, motion))


async def _demo(port: str, motion: bool) -> None:
    transport = await open_transport(port)
    robot = getattr(transport, "robot", None)  # the simulator's ground truth, if any
    bus = Bus(transport)
    bus.start()
    try:
        console.rule(f"ohmni demo on {port}")
        await _scan(bus)
        await _battery(bus)
        if motion:
            await _drive(bus, robot)
        else:
            console.print("[yellow]drive skipped[/yellow]: pass --allow-motion on a robot")
        await _neck(bus)
        _show_stats(bus)
    except StopNotConfirmedError as exc:
        # The robot may be moving: one line nobody can miss, and a failed exit.
        _err.print(f"[bold red]{exc}[/bold red]", soft_wrap=True)
        raise typer.Exit(1) from exc
    finally:
        # One more stop on the way out, after whatever happened.
        await bus.aclose(final=[wheel_command(0, 0)] if motion else ())


async def _scan(bus: Bus) -> None:
    table = Table(title="devices on the bus")
    for column in ("sid", "device", "answer"):
        table.add_column(column)
    for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE, DeviceId.WORM_NECK):
        try:
            tag = await bus.read(sid, 0xF1, 0, Memory.EEP)
            answer = f"firmware {tag.data.decode('ascii', errors='replace')!r}"
        except BusTimeoutError:
            answer = "[dim]no answer[/dim]"
        table.add_row(str(int(sid)), device_name(sid), answer)
    for servo_id in (DeviceId.HERKULEX_NECK, *DEFAULT_EXT_SERVO_IDS):
        servo = Servo(bus, servo_id)
        try:
            model = await servo.model()
            pos = await servo.position_raw()
            answer = f"{model.name} at {pos} ({angle_deg_from_raw(pos):+.1f}°)"
        except BusTimeoutError:
            answer = "[dim]no answer[/dim]"
        table.add_row(str(servo_id), device_name(servo_id), answer)
    console.print(table)


async def _battery(bus: Bus) -> None:
    try:
        status = parse_status(await bus.query(read_status()))
    except OhmniError as exc:
        console.print(f"battery: [yellow]{exc}[/yellow]")
        return
    cells = " ".join(f"{mv / 1000:.3f}" for mv in status.cell_mv)
    console.print(
        f"battery: cells {cells} V, pack {status.pack_mv / 1000:.2f} V, "
        f"{status.charging_current_ma / 1000:+.2f} A, "
        f"{'docked' if status.docked else 'undocked'}, {status.percent} % (vendor rule)"
    )


async def _stop(bus: Bus) -> tuple[StopReport, tuple[int, int]]:
    """Stop the wheels until their counts confirm it; the report and the counts."""
    report = await stop_wheels(bus, timeout_s=_STOP_TIMEOUT_S)
    assert report.counts is not None  # a confirmed stop has read both counts
    return report, report.counts


async def _drive(bus: Bus, robot: object) -> None:
    # From rest to rest: the counts the wheels stand at before and after.
    _, start = await _stop(bus)
    console.print(
        "drive: forward at PWM 400 for 1.0 s (the command is re-sent at 10 Hz), then stop"
    )
    try:
        for _ in range(10):
            await bus.send(wheel_command(400, 400))
            await asyncio.sleep(0.1)
    finally:
        # Stop whatever happened above, Ctrl-C included: repeated until the counts hold
        # still, or StopNotConfirmedError.
        report, end = await _stop(bus)
    console.print(
        f"  stop confirmed in {report.elapsed_s:.3f} s after {report.stops_sent} stops "
        f"(wheel counts held still; {report.missed_reads} count reads unanswered)"
    )
    # The right wheel counts mirrored: negate before converting forward-positive ticks.
    d_left = _ENCODER.ticks_to_m(end[0] - start[0])
    d_right = _ENCODER.ticks_to_m(-(end[1] - start[1]))
    console.print(
        f"  wheel counts: left {end[0] - start[0]:+d}, right {end[1] - start[1]:+d} "
        f"(mirrored) → left {d_left:.3f} m, right {d_right:.3f} m"
    )
    pose = getattr(robot, "pose", None)
    speeds = getattr(robot, "wheel_speeds_mps", None)
    if pose is not None and callable(speeds):
        left_mps, right_mps = speeds()
        console.print(
            f"  simulator ground truth: x={pose.x:.3f} m, y={pose.y:.3f} m, "
            f"yaw={pose.yaw:.4f} rad, wheels {abs(left_mps):.3f} m/s, {abs(right_mps):.3f} m/s"
        )


async def _neck(bus: Bus) -> None:
    neck = Servo(bus, DeviceId.HERKULEX_NECK, min_raw=_NECK_FROM, max_raw=_NECK_TO)
    try:
        await neck.status()  # STAT is always answered: is a HerkuleX neck there?
    except BusTimeoutError:
        await _worm_neck(bus)
        return
    await neck.torque(TorqueControl.ON)
    try:
        await neck.move_to(_NECK_FROM, playtime_ticks=0)
        for _ in range(60):  # the servo needs < 1 s from any start position
            if await neck.position_raw() == _NECK_FROM:
                break
            await asyncio.sleep(0.05)
        console.print(f"neck: {_NECK_FROM} → {_NECK_TO} over 1.0 s")
        await neck.move_to(_NECK_TO, playtime_s=1.0)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        samples = []
        while loop.time() - t0 < 1.3:
            samples.append((loop.time() - t0, await neck.position_raw()))
            await asyncio.sleep(0.1)
        line = "  ".join(f"{t:.1f}s:{pos}" for t, pos in samples)
        console.print("  " + line, highlight=False)
    finally:
        # Holding torque overheats the neck: free it whatever happened, Ctrl-C included.
        await asyncio.shield(neck.torque(TorqueControl.FREE))


async def _worm_neck(bus: Bus) -> None:
    try:
        start = parse_feedback(await bus.query(read_feedback()))
    except BusTimeoutError:
        console.print("neck: [dim]neither a HerkuleX nor a worm-gear neck answers[/dim]")
        return
    target = _WORM_TARGET if start.position != _WORM_TARGET else 0
    console.print(f"worm neck: {start.position} → {target}")
    await bus.send(set_target(target))
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    samples = []
    while loop.time() - t0 < 1.5:
        feedback = parse_feedback(await bus.query(read_feedback()))
        samples.append(f"{loop.time() - t0:.1f}s:{feedback.position}")
        if not feedback.moving:
            break
        await asyncio.sleep(0.1)
    console.print("  " + "  ".join(samples), highlight=False)


def _show_stats(bus: Bus) -> None:
    rows = stats_rows(bus.stats)
    table = Table(title="bus statistics")
    columns = ("sid", "device", "requests", "replies", "timeouts", "p50 ms", "p99 ms", "breaker")
    for column in columns:
        table.add_column(column, justify="right")
    for row in rows:
        table.add_row(
            str(row["sid"]),
            device_name(row["sid"]),
            str(row["requests"]),
            str(row["replies"]),
            str(row["timeouts"]),
            "-" if row["latency_p50_ms"] is None else f"{row['latency_p50_ms']:.2f}",
            "-" if row["latency_p99_ms"] is None else f"{row['latency_p99_ms']:.2f}",
            str(row["breaker"]),
        )
    console.print(table)
    dec = bus.stats.decoder
    console.print(
        f"decoder: {dec.packets} packets, {dec.bytes_discarded} bytes discarded, "
        f"{dec.checksum_errors} checksum errors; unmatched replies {bus.stats.unmatched}"
    )
    stats = bus.stats
    console.print(
        f"line: {stats.wire_utilisation:.0%} of the last second carried bytes "
        f"({stats.reserved_utilisation:.0%} reserved by the cost model), "
        f"{stats.transactions_per_s:.0f} replies/s; queue wait p99 "
        f"{(stats.queue_wait_p99_s or 0.0) * 1e3:.1f} ms"
    )
