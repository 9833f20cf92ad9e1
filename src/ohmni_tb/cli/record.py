"""``ohmni record FILE.mcap``: every stream of the robot to an MCAP file, for Foxglove.

The channels are the live view's (:mod:`ohmni_tb.foxglove.channels`). ``--duration S``
records the samples stamped in the first S seconds; without it the recording runs until
Ctrl-C (or SIGTERM), which ends it normally: the file is closed and the summary printed,
exit code 0. A write that fails (a full disk) is one ``error:`` line, exit code 1, and
the file is closed readable up to its last finished chunk (one second before).
While ``ohmni serve`` runs the streams come through it (``--direct``: open the port).
"""

from __future__ import annotations

import asyncio
import importlib.util
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Final

import typer

from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    daemon_for,
    emit_json,
    error_line,
    open_robot,
    resolve_port,
    run,
    write_line,
)

if TYPE_CHECKING:
    from ohmni_tb.foxglove import ChannelStats, McapRecorder

__all__ = ["MAX_DURATION_S", "record"]

#: The longest --duration: a week (as McapRecorder's).
MAX_DURATION_S: Final = 7 * 24 * 3600.0
#: Exit codes of the signals that end an open-ended recording normally (Ctrl-C, SIGTERM).
_STOPPED = (130, 143)


def record(
    file: Annotated[
        str,
        typer.Argument(metavar="FILE.mcap", help="The MCAP file to create.", show_default=False),
    ],
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration",
            metavar="S",
            help="Record this many seconds (at most a week); by default until Ctrl-C.",
            show_default=False,
        ),
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace FILE if it exists.")
    ] = False,
    raw: Annotated[
        bool,
        typer.Option(
            "--raw",
            help="Also record the bus's bytes as written and read, for ohmni bus monitor "
            "--capture (needs the port itself: not through ohmni serve).",
        ),
    ] = False,
    as_json: JsonOption = False,
    port: PortOption = None,
    direct: DirectOption = False,
) -> None:
    """Record every stream to an MCAP file that the Foxglove app opens.

    The odometry as 3D transforms and poses, the wheels, battery, neck, servos and the
    robot's state as JSON, on tb_control's topic names (docs/foxglove.md has the table).
    At the end a table says how many messages each channel got; --json prints it as one
    object. Nothing moves, and the neck is left as it was.

    Examples: ohmni record run.mcap --port sim:// --duration 10 ;
    ohmni record drive-test.mcap   (Ctrl-C to stop) ;
    ohmni record bus.mcap --raw --duration 5 then ohmni bus monitor --capture bus.mcap
    """
    if duration is not None and not (math.isfinite(duration) and 0 < duration <= MAX_DURATION_S):
        raise typer.BadParameter(
            f"--duration={duration!r} is out of range: allowed >0..{MAX_DURATION_S:g} s"
        )
    if importlib.util.find_spec("foxglove") is None or importlib.util.find_spec("mcap") is None:
        error_line("ohmni record needs foxglove-sdk and mcap: pip install 'ohmni_tb[foxglove]'")
        raise typer.Exit(1)
    via = daemon_for(port, direct)
    if raw and via is not None:
        raise typer.BadParameter(
            f"--raw needs the serial port, and ohmni serve holds it ({via}): stop it, or lend "
            "the port with ohmni serve --handoff S and record with --direct",
            param_hint="--raw",
        )
    where = via or resolve_port(port)
    outcome = _Outcome(duration_s=duration)
    try:
        run(lambda: _record(where, via, file, duration, overwrite, as_json, outcome, raw))
    except typer.Exit as exc:
        if exc.exit_code not in _STOPPED or outcome.recorder is None:
            raise
        if outcome.recorder.error is not None:  # the disk filled while stopping
            error_line(str(outcome.recorder.error))
            raise typer.Exit(1) from None
        _report(outcome, as_json)
        return
    _report(outcome, as_json)


@dataclass
class _Outcome:
    """What a recording left, for the summary (also after Ctrl-C ended it)."""

    recorder: McapRecorder | None = None
    duration_s: float | None = None
    started_s: float = 0.0
    stopped_s: float = 0.0
    stats: dict[str, ChannelStats] = field(default_factory=dict)


async def _record(
    port: str,
    via: str | None,
    path: str,
    duration_s: float | None,
    overwrite: bool,
    as_json: bool,
    outcome: _Outcome,
    raw: bool = False,
) -> None:
    from ohmni_tb.foxglove import McapRecorder  # noqa: PLC0415  # the SDK loads here

    loop = asyncio.get_running_loop()
    # A read-only command: the neck stays as it is on exit (no rest, no free).
    async with open_robot(port, via=via, on_exit_neck="keep") as robot:
        recorder = McapRecorder(robot, path, overwrite=overwrite, duration_s=duration_s, raw=raw)
        outcome.recorder = recorder
        try:
            async with recorder:
                outcome.started_s = loop.time()
                if duration_s is None and not as_json:
                    typer.echo(f"recording to {path}: Ctrl-C to stop", err=True)
                await recorder.wait()
        finally:
            outcome.stopped_s = loop.time()
            outcome.stats = recorder.stats()


def _report(outcome: _Outcome, as_json: bool) -> None:
    recorder = outcome.recorder
    if recorder is None:
        return
    seconds = max(0.0, outcome.stopped_s - outcome.started_s)
    if outcome.duration_s is not None:  # the window; the wait after it is not recorded
        seconds = min(seconds, outcome.duration_s)
    channels = outcome.stats
    if as_json:
        emit_json(
            {
                "path": recorder.path,
                "seconds": round(seconds, 3),
                "bytes": recorder.bytes_written,
                "channels": {
                    topic: {
                        "schema": stats.schema_name,
                        "messages": stats.messages,
                        "dropped": stats.dropped,
                    }
                    for topic, stats in channels.items()
                },
            }
        )
        return
    total = sum(stats.messages for stats in channels.values())
    dropped = sum(stats.dropped for stats in channels.values())
    lines = [
        f"recorded {seconds:.1f} s to {recorder.path}: {total} messages, "
        f"{_size(recorder.bytes_written)}" + (f", {dropped} samples dropped" if dropped else ""),
        f"{'topic':30} {'schema':28} {'messages':>8} {'dropped':>7}",
        *(
            f"{topic:30} {stats.schema_name:28} {stats.messages:8d} {stats.dropped:7d}"
            for topic, stats in channels.items()
        ),
    ]
    for line in lines:
        if not write_line(line):
            return


def _size(count: int) -> str:
    if count < 1000:
        return f"{count} bytes"
    for unit, scale in (("kB", 1e3), ("MB", 1e6)):
        if count < 1000 * scale:
            return f"{count / scale:.1f} {unit}"
    return f"{count / 1e9:.1f} GB"
