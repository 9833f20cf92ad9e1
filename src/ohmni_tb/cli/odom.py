"""``ohmni odom``: stream the wheel odometry; ``ohmni odom reset``, ``ohmni odom set X Y YAW``.

The odometry is integrated by the Robot in the process that opened the port, from the
wheel counts it reads at 50 Hz. With ``ohmni serve`` running both commands act on the
daemon's Robot, whose odometry every client shares; without it every ``ohmni`` command opens
the port itself, so each one starts at the origin: ``odom reset`` sets the pose of its own
Robot only, and shows it.
"""

from __future__ import annotations

import asyncio
import json
import math
import sys
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ohmni_tb.cli import new_app
from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    daemon_for,
    load_config,
    open_robot,
    parse_int,
    quiet_stdout,
    resolve_port,
    run,
)
from ohmni_tb.errors import OhmniError

if TYPE_CHECKING:
    from ohmni_tb.robot import WheelOdomSample

__all__ = ["app"]

#: Lines per second when --rate is not given.
DEFAULT_RATE_HZ = 10.0
MIN_RATE_HZ = 0.1
#: The longest --duration: a week.
MAX_DURATION_S = 7 * 24 * 3600.0
MAX_COUNT = 10**9
#: The first sample must come within this (the drive boards answer, or they do not).
FIRST_SAMPLE_S = 2.0
#: Largest --x / --y of a reset, metres.
MAX_POSITION_M = 10_000.0

_SCOPE = (
    "odometry is integrated in the process that opened the port: this pose was this "
    "command's own, and the next ohmni command starts at the origin (run ohmni serve to keep "
    "one odometry for every command)"
)

app = new_app()


class OdomError(OhmniError):
    """No odometry to show (exit code 1)."""


@app.callback(invoke_without_command=True)
def stream(
    ctx: typer.Context,
    rate: Annotated[
        float,
        typer.Option(
            "--rate",
            metavar="HZ",
            help="Lines per second, 0.1 up to the wheel_odom stream's rate (wheel_hz, 50).",
        ),
    ] = DEFAULT_RATE_HZ,
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration",
            metavar="S",
            help="Stop after this many seconds (at most a week).",
            show_default=False,
        ),
    ] = None,
    count: Annotated[
        str | None,
        typer.Option(
            "--count",
            metavar="N",
            help="Stop after N lines (1..10^9). With --duration too: whichever comes first.",
            show_default=False,
        ),
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="JSON lines: one object per sample.")
    ] = False,
    port: PortOption = None,
    direct: DirectOption = False,
) -> None:
    """Stream odometry lines: time, x, y, yaw, linear and angular speed.

    Runs until Ctrl-C (exit 0), --duration or --count. One wheel_odom sample a line, at
    --rate; --json prints one object a line with t_s (since the first line), x_m, y_m,
    yaw_rad, linear_mps, angular_radps.

    Odometry is integrated in the process that opened the port. While ohmni serve runs,
    the commands go through it and share its odometry; without it every ohmni command
    starts at the origin, and `ohmni odom reset` resets the pose of its own process only.

    Examples: ohmni odom --port sim:// --count 5 ; ohmni odom --rate 50 --json --duration 10 ;
    ohmni odom reset --x 1 --yaw 1.57 --port sim:// ; ohmni odom set 1 -0.5 1.57 --port sim://
    """
    ctx.obj = {"port": port, "direct": direct}
    if ctx.invoked_subcommand is not None:
        given = [
            name
            for name, value, default in (
                ("--rate", rate, DEFAULT_RATE_HZ),
                ("--duration", duration, None),
                ("--count", count, None),
                ("--json", as_json, False),
            )
            if value != default
        ]
        if given:
            raise typer.BadParameter(
                f"{', '.join(given)} apply to streaming, not to `odom {ctx.invoked_subcommand}`"
            )
        return
    lines = None if count is None else parse_int(count, "--count", 1, MAX_COUNT)
    if duration is not None and not (math.isfinite(duration) and 0 < duration <= MAX_DURATION_S):
        raise typer.BadParameter(
            f"--duration={duration!r} is out of range: allowed >0..{MAX_DURATION_S:g} s"
        )
    if not math.isfinite(rate) or rate < MIN_RATE_HZ:
        raise typer.BadParameter(f"--rate={rate!r} is out of range: allowed {MIN_RATE_HZ:g}..")
    config = load_config()
    if rate > config.wheel_hz:
        raise typer.BadParameter(
            f"--rate={rate!r} is out of range: allowed {MIN_RATE_HZ:g}..{config.wheel_hz:g} Hz "
            "(the wheel_odom stream's rate, wheel_hz)"
        )
    via = daemon_for(port, direct)
    where = via or resolve_port(port)
    try:
        run(lambda: _stream(where, via, rate, duration, lines, as_json))
    except typer.Exit as exc:
        if exc.exit_code != 130:  # Ctrl-C: the lines so far were the point, exit 0
            raise
    except BrokenPipeError:  # `ohmni odom | head -3`: the reader is done
        quiet_stdout()


async def _stream(
    port: str,
    via: str | None,
    rate_hz: float,
    duration_s: float | None,
    count: int | None,
    as_json: bool,
) -> int:
    """Print samples at ``rate_hz`` until the duration or count; the lines printed."""
    loop = asyncio.get_running_loop()
    period_s = 1.0 / rate_hz
    printed = 0
    # A read-only command: the neck stays as it is on exit (no rest, no free).
    async with open_robot(port, via=via, on_exit_neck="keep") as robot:
        # A sample a little early still counts for its slot: stamps jitter by a few ms.
        slack_s = 0.5 / robot.config.wheel_hz
        start = loop.time()
        end = None if duration_s is None else start + duration_s
        first_t: float | None = None
        next_due = -math.inf
        async with robot.subscribe("wheel_odom", maxlen=64) as samples:
            while count is None or printed < count:
                until = end
                if first_t is None:
                    until = min(end or math.inf, start + FIRST_SAMPLE_S)
                try:
                    async with asyncio.timeout_at(until):
                        sample = await anext(samples)
                except TimeoutError:
                    if first_t is None and (end is None or loop.time() < end):
                        raise OdomError(
                            f"no wheel_odom sample within {FIRST_SAMPLE_S:g} s: do the drive "
                            "boards (ids 0 and 1) answer? (`ohmni info`)"
                        ) from None
                    break
                except StopAsyncIteration:
                    break
                if sample.stamp_s < next_due - slack_s:
                    continue
                if first_t is None:
                    first_t = sample.stamp_s
                if sample.stamp_s - next_due > period_s:  # the first, or fell behind
                    next_due = sample.stamp_s
                next_due += period_s
                _write(_line(sample, sample.stamp_s - first_t, as_json))
                printed += 1
    return printed


def _row(sample: WheelOdomSample, t_s: float) -> dict[str, float]:
    return {
        "t_s": round(t_s, 4),
        "x_m": round(sample.x_m, 5),
        "y_m": round(sample.y_m, 5),
        "yaw_rad": round(sample.yaw_rad, 5),
        "linear_mps": round(sample.linear_mps, 4),
        "angular_radps": round(sample.angular_radps, 4),
    }


def _line(sample: WheelOdomSample, t_s: float, as_json: bool) -> str:
    row = _row(sample, t_s)
    if as_json:
        return json.dumps(row)
    return (
        f"t {row['t_s']:8.3f} s  x {row['x_m']:+8.3f} m  y {row['y_m']:+8.3f} m  "
        f"yaw {row['yaw_rad']:+7.4f} rad ({math.degrees(sample.yaw_rad):+7.2f}°)  "
        f"linear {row['linear_mps']:+6.3f} m/s  angular {row['angular_radps']:+7.4f} rad/s"
    )


def _write(line: str) -> None:
    # A line at a time, flushed: a pipe's reader sees each sample as it comes.
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


@app.command()
def reset(
    ctx: typer.Context,
    x: Annotated[float, typer.Option("--x", metavar="M", help="x of the new pose, metres.")] = 0.0,
    y: Annotated[float, typer.Option("--y", metavar="M", help="y of the new pose, metres.")] = 0.0,
    yaw: Annotated[
        float,
        typer.Option("--yaw", metavar="RAD", help="Heading of the new pose, radians (±2π)."),
    ] = 0.0,
    as_json: JsonOption = False,
    port: PortOption = None,
    direct: DirectOption = False,
) -> None:
    """Reset the odometry pose (default: the origin) and print it.

    Through ohmni serve (when it runs) this resets the daemon's odometry, which every
    client sees. Without it, odometry is integrated in the process that opened the port:
    this resets the pose of this command's own Robot only, and the next ohmni command
    starts at the origin again.

    Example: ohmni odom reset --x 1.5 --y -0.5 --yaw 1.5708 --port sim://
    """
    _check_pose(("--x", x), ("--y", y), ("--yaw", yaw))
    _set_pose(ctx, "reset", x, y, yaw, as_json, port, direct)


@app.command(name="set", context_settings={"ignore_unknown_options": True})
def set_pose(
    ctx: typer.Context,
    x: Annotated[float, typer.Argument(metavar="X", help="x of the pose, metres.")],
    y: Annotated[float, typer.Argument(metavar="Y", help="y of the pose, metres.")],
    yaw: Annotated[float, typer.Argument(metavar="YAW", help="Heading, radians (±2π).")],
    as_json: JsonOption = False,
    port: PortOption = None,
    direct: DirectOption = False,
) -> None:
    """Set the odometry pose to X Y YAW (metres, metres, radians) and print it.

    The robot's set_odometry: to put the odometry where a map says the robot is. As
    `ohmni odom reset --x X --y Y --yaw YAW`; a negative value needs no `--`. Through
    ohmni serve (when it runs) it sets the daemon's odometry, which every client sees.

    Example: ohmni odom set 1.5 -0.5 1.5708 --port sim://
    """
    _check_pose(("X", x), ("Y", y), ("YAW", yaw))
    _set_pose(ctx, "set", x, y, yaw, as_json, port, direct)


def _check_pose(*given: tuple[str, float]) -> None:
    """The pose's values within the command's ranges: x, y ±10 km; yaw ±2π."""
    (x_name, x), (y_name, y), (yaw_name, yaw) = given
    for name, value in ((x_name, x), (y_name, y)):
        if not (math.isfinite(value) and abs(value) <= MAX_POSITION_M):
            raise typer.BadParameter(
                f"{name}={value!r} is out of range: allowed "
                f"-{MAX_POSITION_M:g}..{MAX_POSITION_M:g} m"
            )
    if not (math.isfinite(yaw) and abs(yaw) <= 2 * math.pi):
        raise typer.BadParameter(
            f"{yaw_name}={yaw!r} is out of range: allowed -6.2832..6.2832 rad (±2π)"
        )


def _set_pose(
    ctx: typer.Context,
    verb: str,
    x: float,
    y: float,
    yaw: float,
    as_json: bool,
    port: str | None,
    direct: bool,
) -> None:
    """``odom reset`` and ``odom set``: the pose set on the robot, then printed."""
    parent = ctx.obj if isinstance(ctx.obj, dict) else {}
    port = port or parent.get("port")
    via = daemon_for(port, direct or bool(parent.get("direct")))
    where = via or resolve_port(port)
    pose = run(lambda: _reset(where, via, x, y, yaw, verb=verb))
    if as_json:
        sys.stdout.write(json.dumps(pose, indent=2) + "\n")
        return
    sys.stdout.write(
        f"odometry {verb}: x {pose['x_m']:+.3f} m  y {pose['y_m']:+.3f} m  "
        f"yaw {pose['yaw_rad']:+.4f} rad ({math.degrees(pose['yaw_rad']):+.2f}°)\n"
        + ("the daemon's odometry, for every client\n" if via else f"note: {_SCOPE}\n")
    )


async def _reset(
    port: str, via: str | None, x: float, y: float, yaw: float, *, verb: str = "reset"
) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    async with (
        open_robot(port, via=via, control=True, on_exit_neck="keep") as robot,
        robot.subscribe("wheel_odom", maxlen=8) as samples,
    ):
        if verb == "set":
            robot.set_odometry(x, y, yaw)
        else:
            robot.reset_odometry(x, y, yaw)
        after = loop.time()
        try:
            async with asyncio.timeout(FIRST_SAMPLE_S):
                async for sample in samples:
                    if sample.stamp_s >= after:
                        row: dict[str, Any] = _row(sample, 0.0)
                        del row["t_s"]
                        return row
        except TimeoutError:
            pass
    raise OdomError(
        f"no wheel_odom sample within {FIRST_SAMPLE_S:g} s of the {verb}: do the drive "
        "boards (ids 0 and 1) answer? (`ohmni info`)"
    )
