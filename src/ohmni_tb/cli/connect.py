"""``ohmni connect [PORT]`` and ``ohmni disconnect``: switch the running robot's port.

tb_control's ``connect`` service (``connect``, ``port_name`` → ``is_connected``,
``port_name``): ``robot.connect(port)`` / ``robot.disconnect()`` on the daemon's robot when
``ohmni serve`` runs (every client follows it; it needs the control lease), else on the
robot this command opens with ``--port`` (the switch lasts while the command runs: it
checks that PORT opens and answers).
"""

from __future__ import annotations

from typing import Annotated, Any

import typer

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

__all__ = ["connect", "disconnect"]


def connect(
    target: Annotated[
        str | None,
        typer.Argument(
            metavar="PORT",
            help="The port to switch to: /dev/ttyUSB1, serial:///dev/ttyUSB1?baudrate=115200, "
            "sim://, auto. Default: the one the robot had (open it again after ohmni "
            "disconnect).",
            show_default=False,
        ),
    ] = None,
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Switch the running robot to PORT (robot.connect; tb_control's connect).

    Through ohmni serve (when it runs) the daemon's robot closes its port (the wheels
    stopped and confirmed first) and opens PORT on the daemon's machine: every client
    follows. Without it, the robot this command opens with --port switches to PORT, which
    checks that PORT opens (exit 1 when it cannot); the switch ends with the command.

    Example: ohmni connect /dev/ttyUSB1 ; ohmni connect sim:// --port sim://
    """

    async def main() -> tuple[str, str | None, str | None]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, control=True, on_exit_neck="keep") as robot:
            await robot.connect(target)
            return url, via, robot.port

    _report(*run(main), as_json=as_json)


def disconnect(
    port: PortOption = None,
    direct: DirectOption = False,
    as_json: JsonOption = False,
) -> None:
    """Close the running robot's port until ohmni connect (robot.disconnect).

    Through ohmni serve (when it runs) the daemon keeps serving with its port closed (the
    wheels stopped and confirmed first); its clients' commands are refused until ohmni
    connect. Without it, this command's own robot disconnects and the command ends.

    Example: ohmni disconnect ; ohmni connect
    """

    async def main() -> tuple[str, str | None, str | None]:
        via = daemon_for(port, direct)
        url = via or resolve_port(port)
        async with open_robot(url, via=via, control=True, on_exit_neck="keep") as robot:
            await robot.disconnect()
            return url, via, robot.port

    _report(*run(main), as_json=as_json)


def _report(url: str, via: str | None, now: str | None, *, as_json: bool) -> None:
    """tb_control's reply: ``is_connected``, ``port_name``; and whose robot it was."""
    report: dict[str, Any] = {
        "port": url,
        "via_daemon": via is not None,
        "is_connected": now is not None,
        "port_name": now,
    }
    if as_json:
        emit_json(report)
        return
    whose = (
        f"the daemon's robot at {via}, for every client"
        if via is not None
        else "this command's own robot: the change ended with it (ohmni serve keeps one)"
    )
    said = f"connected to {now}" if now is not None else "disconnected"
    console.print(f"{said}: {whose}", highlight=False, soft_wrap=True)
