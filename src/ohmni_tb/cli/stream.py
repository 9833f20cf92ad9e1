"""``ohmni stream enable|disable NAME``: turn a stream of the running robot on or off.

tb_control's ``enable_sensor_stream``: ``robot.enable_stream(name, enabled)`` on the
daemon's robot when ``ohmni serve`` runs (every client sees the change), else on the port's
(the change lasts while the command runs). An off stream stops its bus reads.
"""

from __future__ import annotations

from typing import Annotated, Any

import typer

from ohmni_tb.cli import new_app
from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    console,
    daemon_for,
    emit_json,
    open_robot,
    resolve_port,
    run,
)

__all__ = ["app"]

app = new_app(
    help="Turn a stream of the running robot on or off (the daemon's when ohmni serve "
    "runs, else the port's).\n\nExample: ohmni stream disable tbcore_status",
    no_args_is_help=True,
)

StreamArgument = Annotated[
    str,
    typer.Argument(
        metavar="NAME",
        help="The stream: wheel_encoder, wheel_odom, tbcore_status, servo_neck, servo_ext1, "
        "servo_ext2, new_neck, robot_state or pid_debug.",
        show_default=False,
    ),
]


@app.command("enable")
def enable(
    stream: StreamArgument,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Turn stream NAME on (robot.enable_stream(NAME, True)).

    A stream whose device did not answer cannot be turned on (exit 1).

    Example: ohmni stream enable pid_debug
    """
    _switch(stream, True, port, direct, as_json)


@app.command("disable")
def disable(
    stream: StreamArgument,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Turn stream NAME off (robot.enable_stream(NAME, False)): its samples and bus reads stop.

    Turning off wheel_encoder stops its samples only: the control slot keeps running.

    Example: ohmni stream disable tbcore_status
    """
    _switch(stream, False, port, direct, as_json)


def _switch(stream: str, enabled: bool, port: str | None, direct: bool, as_json: bool) -> None:
    from ohmni_tb.robot.samples import STREAM_NAMES  # noqa: PLC0415

    if stream not in STREAM_NAMES:
        raise typer.BadParameter(
            f"no stream {stream!r}: the streams are {', '.join(STREAM_NAMES)}",
            param_hint="'NAME'",
        )

    async def main() -> tuple[str, str | None, list[str]]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, control=True, on_exit_neck="keep") as robot:
            robot.enable_stream(stream, enabled)
            await robot.confirm()
            return url, via, [row[0] for row in robot.schedule()]

    url, via, scheduled = run(main)
    report: dict[str, Any] = {
        "port": url,
        "via_daemon": via is not None,
        "stream": stream,
        "enabled": enabled,
        "scheduled": scheduled,
    }
    if as_json:
        emit_json(report)
        return
    where = (
        f"the daemon's robot at {via}, for every client"
        if via is not None
        else "this command's own robot: the change ended with it (ohmni serve keeps one)"
    )
    console.print(
        f"{stream} {'enabled' if enabled else 'disabled'} on {where}",
        highlight=False,
        soft_wrap=True,
    )
