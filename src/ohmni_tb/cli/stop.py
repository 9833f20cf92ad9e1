"""``ohmni stop``: stop the wheels, confirmed by their counts, and nothing else.

What a service manager runs after the daemon has gone (systemd's ``ExecStopPost=``, an
Android init trigger: docs/hardware.md), and what anyone runs when a program left the
robot driving: the drive boards keep their last command until told otherwise.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Annotated

import typer

from ohmni_tb.cli.common import JsonOption, PortOption, emit_json, resolve_port, run, write_line

if TYPE_CHECKING:
    from ohmni_tb.safety import StopReport

__all__ = ["stop"]

#: ``--timeout``'s range, s: :func:`ohmni_tb.safety.stop_wheels`'.
_TIMEOUT_MIN_S, _TIMEOUT_MAX_S = 0.05, 60.0


def stop(
    port: PortOption = None,
    timeout: Annotated[
        float,
        typer.Option(
            "--timeout",
            metavar="S",
            help=f"How long to try to confirm the stop, {_TIMEOUT_MIN_S:g}..{_TIMEOUT_MAX_S:g} s.",
        ),
    ] = 1.0,
    as_json: JsonOption = False,
) -> None:
    """Stop both wheels and confirm it by their counts.

    Opens the port, sends the wheel stop at once and again every 30 ms until both wheel
    counts hold still (ohmni_tb.safety.stop_wheels), sends a last stop and closes the
    port. Exit code 0 when the counts confirmed the stop; 1, with one line saying why, when
    they did not: the robot may still be moving. It always opens the port itself: while
    ohmni serve holds it, this says the port is busy (the daemon stops the wheels when it
    stops, and any of its clients may send a stop).

    Example: ohmni stop --port sim://
    """
    if not (math.isfinite(timeout) and _TIMEOUT_MIN_S <= timeout <= _TIMEOUT_MAX_S):
        raise typer.BadParameter(
            f"--timeout={timeout!r} is out of range: allowed {_TIMEOUT_MIN_S:g}.."
            f"{_TIMEOUT_MAX_S:g} s",
            param_hint="--timeout",
        )
    url = resolve_port(port)

    async def main() -> StopReport:
        from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic: only when run
        from ohmni_tb.daemon.supervisor import stop_wheels_at  # noqa: PLC0415

        config = RobotConfig.load()
        return await stop_wheels_at(
            url,
            timeout_s=timeout,
            bus_timeout_s=config.bus_timeout_s(),
            profile=config.profile().drive,
        )

    report = run(main)
    if as_json:
        emit_json(
            {
                "port": url,
                "confirmed": report.confirmed,
                "elapsed_s": round(report.elapsed_s, 4),
                "stops_sent": report.stops_sent,
                "reads": report.reads,
                "missed_reads": report.missed_reads,
                "counts": None if report.counts is None else list(report.counts),
            }
        )
        return
    write_line(
        f"wheels stopped on {url}: both counts held still {report.elapsed_s:.3f} s after the "
        f"first stop ({report.stops_sent} stops sent, {report.reads} count reads answered, "
        f"{report.missed_reads} missed)"
    )
