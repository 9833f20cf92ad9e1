"""``ohmni demo``: a tour of the Robot on the simulator (or, carefully, on a robot)."""

from __future__ import annotations

import asyncio
import logging
import math
from typing import TYPE_CHECKING, Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from ohmni_tb.cli.common import (
    PortOption,
    RobotWarnings,
    confirm_stop,
    console,
    error_line,
    run,
)
from ohmni_tb.errors import OhmniError, StopNotConfirmedError
from ohmni_tb.protocol import Memory
from ohmni_tb.protocol.devices import NECK_RAW_RANGE, DeviceId, device_name

if TYPE_CHECKING:
    from ohmni_tb.robot import Robot, RobotStats, ServoHandle, WormNeckHandle

__all__ = ["demo"]

#: The drive: forward at this speed for this long, drive() re-sent at 20 Hz (the
#: watchdog stops the wheels 0.5 s after the last one).
_SPEED_MPS = 0.3
_DRIVE_S = 1.0
_COMMAND_PERIOD_S = 0.05
#: How long the demo waits for the wheel counts to confirm the stop, the ramp down
#: included: longer than stop_wheels' default, so a lossy line's lost reads are ridden out.
_STOP_TIMEOUT_S = 2.0
_NECK_FROM, _NECK_TO = NECK_RAW_RANGE
#: A worm-neck target inside its range (−127000 up … 120000 down): tilt down a little.
_WORM_TARGET = 60_000
#: How long to wait for a stream's first sample.
_FIRST_SAMPLE_S = 1.0
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
    """Open the Robot, show its devices and battery, drive, move the neck, show its figures.

    On the built-in simulator (the default, sim://) everything runs. On a real robot the
    wheels stay still unless --allow-motion is given: the robot would drive ~30 cm.

    Example: ohmni demo
    """
    url = port or "sim://"
    motion = allow_motion or url.startswith("sim:")
    run(lambda: _demo(url, motion))


async def _demo(port: str, motion: bool) -> None:
    # Imported here: `ohmni --help` and the other commands start without the Robot.
    from ohmni_tb import Robot, RobotConfig  # noqa: PLC0415

    watch = RobotWarnings()
    logger = logging.getLogger("ohmni_tb")
    logger.addHandler(watch)
    failure: OhmniError | None = None
    try:
        async with Robot.open(port, config=RobotConfig.load()) as robot:
            console.rule(f"ohmni demo on {port}")
            await _devices(robot)
            await _battery(robot)
            if not motion:
                console.print("[yellow]drive skipped[/yellow]: pass --allow-motion on a robot")
            elif silent := [sid for sid in (0, 1) if sid not in robot.state.present]:
                boards = "boards 0 and 1 do" if len(silent) == 2 else f"board {silent[0]} does"
                console.print(f"[yellow]drive skipped[/yellow]: drive {boards} not answer")
            else:
                await _drive(robot)
            await _neck(robot)
            _show_stats(robot.stats())
    except OhmniError as exc:
        failure = exc
    except BaseException:
        # Ctrl-C or a cancellation: still say it if the Robot could not confirm its stop.
        if watch.stop is not None:
            _print_stop(watch.stop)
        raise
    finally:
        logger.removeHandler(watch)
    # The Robot's verdict on closing is the last word on whether the wheels stopped.
    stop = watch.stop or (failure if isinstance(failure, StopNotConfirmedError) else None)
    if stop is None:
        if failure is not None:
            raise failure  # run() prints it as one red line
        return
    if failure is not None and failure is not stop:
        error_line(str(failure))
    _print_stop(stop)
    raise typer.Exit(1) from stop


def _print_stop(exc: StopNotConfirmedError) -> None:
    """The robot may be moving: one line nobody can miss."""
    _err.print(f"[bold red]{escape(str(exc))}[/bold red]", soft_wrap=True)


async def _devices(robot: Robot) -> None:
    info = await robot.info()
    state = robot.state
    firmware: dict[str, str | None] = info["firmware"]
    models: dict[int, str | None] = info["servos"]
    table = Table(title="devices on the bus")
    for column in ("sid", "device", "answer"):
        table.add_column(column)
    for sid in sorted({*state.present, *state.absent}):
        if sid not in state.present:
            answer = "[dim]no answer[/dim]"
        elif sid in models:
            answer = await _servo_answer(robot, sid, models[sid])
        elif sid == DeviceId.WORM_NECK:
            answer = await _worm_answer(robot)
        else:
            tag = firmware.get(DeviceId(sid).name.lower())
            answer = "[dim]no firmware tag[/dim]" if tag is None else f"firmware {tag!r}"
        table.add_row(str(sid), device_name(sid), answer)
    console.print(table)
    faults = f", faults: {', '.join(state.faults)}" if state.faults else ""
    console.print(f"robot: link {state.link}, neck {state.neck}{faults}", highlight=False)


async def _servo_answer(robot: Robot, sid: int, model: str | None) -> str:
    from ohmni_tb.robot import ServoSample  # noqa: PLC0415  # the CLI starts without it

    stream = {int(DeviceId.HERKULEX_NECK): "servo_neck"}.get(sid)
    if stream is None:
        ext = robot.config.ext_servo_ids
        stream = f"servo_ext{ext.index(sid) + 1}" if sid in ext else None
    # Its stream's first sample may still be on its way just after the Robot opened.
    sample = await _first(robot, stream) if stream is not None else None
    where = (
        f" at {sample.position_raw} ({math.degrees(sample.angle_rad):+.1f}°)"
        if isinstance(sample, ServoSample)
        else ""
    )
    return f"{model or 'HerkuleX (model unread)'}{where}"


async def _worm_answer(robot: Robot) -> str:
    # Robot.info() tags the drive and core boards only; the worm neck is read directly
    # (on this process's bus: a daemon's robot has none here).
    from ohmni_tb.robot import LocalRobot  # noqa: PLC0415

    if not isinstance(robot, LocalRobot):
        return "worm-gear neck (its firmware tag is read on the daemon's port)"
    try:
        reply = await robot.bus.read(DeviceId.WORM_NECK, 0xF1, 0, Memory.EEP)
    except OhmniError:
        return "worm-gear neck (no firmware tag)"
    return f"firmware {reply.data.decode('ascii', errors='replace')!r}"


async def _first(robot: Robot, stream: str) -> object | None:
    """The newest sample of ``stream``, waiting up to a second for the first one."""
    sample: object | None = robot.latest(stream)
    if sample is not None:
        return sample
    try:
        async with asyncio.timeout(_FIRST_SAMPLE_S):
            async for first in robot.subscribe(stream, maxlen=1):
                sample = first
                break
    except TimeoutError:
        pass
    return sample


async def _battery(robot: Robot) -> None:
    if DeviceId.CORE not in robot.state.present:
        console.print("battery: [yellow]the core board does not answer[/yellow]")
        return
    from ohmni_tb.robot import TbcoreStatusSample  # noqa: PLC0415

    status = await _first(robot, "tbcore_status")
    if not isinstance(status, TbcoreStatusSample):
        console.print("battery: [yellow]no tbcore_status sample within 1 s[/yellow]")
        return
    cells = " ".join(f"{v:.3f}" for v in status.cell_v)
    console.print(
        f"battery (tbcore_status): cells {cells} V, pack {status.pack_v:.2f} V, "
        f"{status.current_a:+.2f} A, {'docked' if status.docked else 'undocked'}, "
        f"{status.percent} % (vendor rule)"
    )


async def _drive(robot: Robot) -> None:
    console.print(
        f"drive: forward at {_SPEED_MPS:.2f} m/s for {_DRIVE_S:.1f} s "
        f"(robot.drive re-sent at {1 / _COMMAND_PERIOD_S:.0f} Hz), then stop"
    )
    loop = asyncio.get_running_loop()
    try:
        end = loop.time() + _DRIVE_S
        while loop.time() < end:
            robot.drive(_SPEED_MPS, 0.0)
            await asyncio.sleep(_COMMAND_PERIOD_S)
    finally:
        # Whatever happened above, Ctrl-C included: the target goes to zero, the ramp
        # brings the wheels down, and leaving the Robot would stop them anyway.
        robot.stop()
    report = await confirm_stop(robot, _STOP_TIMEOUT_S)
    console.print(
        f"  stop confirmed {report.elapsed_s:.3f} s after the stop by both wheel counts "
        f"holding still ({report.reads} wheel_encoder samples, {report.missed_reads} control "
        "ticks without counts)"
    )
    odom = robot.latest("wheel_odom")
    if odom is not None:
        console.print(
            f"  odometry (wheel_odom): x={odom.x_m:.3f} m, y={odom.y_m:.3f} m, "
            f"yaw={odom.yaw_rad:.4f} rad",
            highlight=False,
        )
    if robot.sim is not None:
        pose = robot.sim.pose
        left_mps, right_mps = robot.sim.wheel_speeds_mps()
        console.print(
            f"  simulator ground truth: x={pose.x:.3f} m, y={pose.y:.3f} m, "
            f"yaw={pose.yaw:.4f} rad, wheels {abs(left_mps):.3f} m/s, {abs(right_mps):.3f} m/s",
            highlight=False,
        )
        if odom is not None:
            error_mm = math.hypot(odom.x_m - pose.x, odom.y_m - pose.y) * 1000
            console.print(f"  odometry is {error_mm:.1f} mm from the truth", highlight=False)


async def _neck(robot: Robot) -> None:
    from ohmni_tb.robot import ServoHandle, WormNeckHandle  # noqa: PLC0415

    if robot.neck_kind == "none":
        console.print("neck: [dim]neither a HerkuleX nor a worm-gear neck answers[/dim]")
        return
    neck = robot.neck
    if isinstance(neck, ServoHandle):
        await _herkulex_neck(robot, neck)
    elif isinstance(neck, WormNeckHandle):
        await _worm_neck(robot, neck)


async def _herkulex_neck(robot: Robot, neck: ServoHandle) -> None:
    loop = asyncio.get_running_loop()
    await neck.move(_NECK_FROM, playtime_s=0.0)
    deadline = loop.time() + 1.5  # the servo needs < 1 s from any start position
    start = _NECK_FROM
    async for sample in robot.subscribe("servo_neck"):
        start = sample.position_raw
        if start == _NECK_FROM or loop.time() > deadline:
            break
    console.print(f"neck: {_NECK_FROM} → {_NECK_TO} over 1.0 s (servo_neck samples)")
    t0 = loop.time()
    await neck.move(_NECK_TO, playtime_s=1.0)
    shown = [f"0.0s:{start}"]
    next_s = 0.1
    async for sample in robot.subscribe("servo_neck"):
        # The stream runs at 30 Hz; one sample every 0.1 s is enough to read.
        t = sample.stamp_s - t0
        if t >= next_s:
            shown.append(f"{max(t, 0.0):.1f}s:{sample.position_raw}")
            next_s += 0.1
        if t > 1.3:
            break
    console.print("  " + "  ".join(shown), highlight=False)


async def _worm_neck(robot: Robot, neck: WormNeckHandle) -> None:
    from ohmni_tb.robot import WormNeckSample  # noqa: PLC0415

    start = await _first(robot, "new_neck")
    position = start.position_raw if isinstance(start, WormNeckSample) else 0
    target = _WORM_TARGET if position != _WORM_TARGET else 0
    console.print(f"worm neck: {position} → {target} (new_neck samples)")
    t0 = asyncio.get_running_loop().time()
    await neck.move(target)
    shown: list[str] = []
    next_s = 0.0
    async for sample in robot.subscribe("new_neck"):
        t = sample.stamp_s - t0
        done = (t > 0.2 and not sample.moving) or t > 1.5
        if t >= next_s or done:
            shown.append(f"{max(t, 0.0):.2f}s:{sample.position_raw}")
            next_s += 0.1
        if done:
            break
    console.print("  " + "  ".join(shown), highlight=False)


def _show_stats(stats: RobotStats) -> None:
    table = Table(
        title="streams (robot.stats())",
        caption="jitter: how late a cycle's first byte went on the wire, p50/p99",
    )
    columns = ("stream", "Hz want", "Hz got", "jitter ms", "samples", "missed", "skipped")
    for column in columns:
        table.add_column(column, justify="left" if column == "stream" else "right")
    for name, s in stats.streams.items():
        if not s.enabled or not s.requested_hz:
            continue
        jitter = "-"
        if s.jitter_p50_ms is not None and s.jitter_p99_ms is not None:
            jitter = f"{s.jitter_p50_ms:.1f}/{s.jitter_p99_ms:.1f}"
        table.add_row(
            name,
            f"{s.requested_hz:.0f}",
            f"{s.achieved_hz:.1f}",
            jitter,
            str(s.samples),
            str(s.missed),
            str(s.skipped),
        )
    console.print(table)
    b = stats.bus
    console.print(
        f"bus: the wire carried bytes {b.wire_utilisation:.0%} of the last second; the "
        f"schedule reserves {b.budget_share:.0%} by the cost model (turnarounds and guards "
        "included); "
        f"{b.transactions_per_s:.0f} transactions/s, {b.timeouts} timeouts, "
        f"{b.deadline_misses} deadline misses",
        highlight=False,
    )
