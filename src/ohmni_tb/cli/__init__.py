"""The ``ohmni`` command line (typer).

Each command lives in its own module, imported only when that command runs: ``ohmni
--help`` lists them from the table below without importing any, so neither the Robot,
numpy nor the simulator loads for a command that does not use them.
"""

from __future__ import annotations

import importlib
import sys
from typing import Annotated, Any, Final

import typer
from typer.core import TyperCommand, TyperGroup

from ohmni_tb._version import __version__

__all__ = ["COMMANDS", "app", "main", "new_app"]

#: name → (module, attribute, one line for ``ohmni --help``). The attribute is a Typer
#: app (a command with subcommands) or a command function.
COMMANDS: Final[dict[str, tuple[str, str, str]]] = {
    "status": (
        "ohmni_tb.cli.status",
        "status",
        "One screen of the robot: battery, wheels, odometry, neck, servos, bus (--watch, --json).",
    ),
    "diag": (
        "ohmni_tb.cli.diag",
        "diag",
        "The robot's health: each device's and the link's level, what is wrong (--watch, --json).",
    ),
    "drive": (
        "ohmni_tb.cli.drive",
        "drive",
        "Drive for a time, a distance or a turn and print the odometry; --teleop: keyboard.",
    ),
    "stop": (
        "ohmni_tb.cli.stop",
        "stop",
        "Stop the wheels, confirmed by their counts (opens the port; e.g. after the daemon).",
    ),
    "neck": (
        "ohmni_tb.cli.neck",
        "neck",
        "Move the neck (HerkuleX or worm gear): up, down, center, rest, free, --raw, --deg.",
    ),
    "odom": ("ohmni_tb.cli.odom", "app", "Stream odometry lines; `ohmni odom reset`."),
    "pid": (
        "ohmni_tb.cli.robot_cmds",
        "pid_app",
        "The wheel PIDs: get or set their gains (per wheel), enable or disable them.",
    ),
    "stream": (
        "ohmni_tb.cli.stream",
        "app",
        "Turn a stream of the running robot on or off: enable|disable NAME.",
    ),
    "light": ("ohmni_tb.cli.robot_cmds", "light", "Set the light ring's colour: H S V."),
    "connect": (
        "ohmni_tb.cli.connect",
        "connect",
        "Switch the running robot to another serial port (the daemon's when it runs).",
    ),
    "disconnect": (
        "ohmni_tb.cli.connect",
        "disconnect",
        "Close the running robot's port until ohmni connect (the daemon's when it runs).",
    ),
    "info": ("ohmni_tb.cli.robot_cmds", "info", "Firmware tags, servo models, neck kind."),
    "config": (
        "ohmni_tb.cli.config_cmd",
        "app",
        "The settings in effect and where each came from; `ohmni config init`: an example file.",
    ),
    "ports": (
        "ohmni_tb.cli.robot_cmds",
        "ports",
        "List serial ports with USB ids; mark the likely bus adapter.",
    ),
    "demo": ("ohmni_tb.cli.demo", "demo", "A tour of the Robot on the simulator (or a robot)."),
    "sim": ("ohmni_tb.cli.sim", "sim", "Serve the simulated robot on a pseudo-terminal."),
    "bus": ("ohmni_tb.cli.bus", "app", "Raw bus requests and a traffic monitor."),
    "servo": ("ohmni_tb.cli.servo", "app", "HerkuleX servos: scan, info, read, write, move."),
    "probe": (
        "ohmni_tb.cli.probe",
        "probe",
        "First contact: find what the robot's boards speak against the profile (--write).",
    ),
    "serve": (
        "ohmni_tb.cli.serve",
        "serve",
        "Serve the robot to many local clients over WebSocket: readers, one driver.",
    ),
    "fleet": (
        "ohmni_tb.cli.fleet",
        "fleet",
        "Every robot on an MQTT broker: online, battery, dock, faults, last seen (--watch).",
    ),
    "record": (
        "ohmni_tb.cli.record",
        "record",
        "Record every stream to an MCAP file for Foxglove (--duration S, or until Ctrl-C).",
    ),
    "replay": (
        "ohmni_tb.cli.replay",
        "replay",
        "Serve an MCAP recording to the Foxglove app as if it were live (--speed X).",
    ),
}


def new_app(**settings: Any) -> typer.Typer:
    """A Typer app with the ``ohmni`` habits: help in plain text, reflowed to the terminal
    (flags shown as flags), no completion options of its own (``ohmni
    --install-completion`` covers every command), no pretty tracebacks."""
    defaults: dict[str, Any] = {
        "add_completion": False,
        "pretty_exceptions_enable": False,
        "rich_markup_mode": None,
    }
    return typer.Typer(**{**defaults, **settings})


class _LazyGroup(TyperGroup):
    """A group whose commands are imported when one is run (or asked for its help)."""

    _listing = False

    # typer keeps its click private: the contexts and commands are typed loosely here.
    def list_commands(self, ctx: Any) -> list[str]:
        return [*COMMANDS, *super().list_commands(ctx)]

    def get_command(self, ctx: Any, cmd_name: str) -> Any:
        command = super().get_command(ctx, cmd_name)
        if command is not None or cmd_name not in COMMANDS:
            return command
        module, attribute, short = COMMANDS[cmd_name]
        if self._listing:
            # The group's help lists names and one line each: import nothing for it.
            return TyperCommand(cmd_name, short_help=short, help=short)
        return _load(cmd_name, module, attribute)

    def format_help(self, ctx: Any, formatter: Any) -> None:
        self._listing = True
        try:
            super().format_help(ctx, formatter)
        finally:
            self._listing = False


def _load(name: str, module: str, attribute: str) -> Any:
    target: Any = getattr(importlib.import_module(module), attribute)
    if not isinstance(target, typer.Typer):
        single = new_app()
        single.command(name=name)(target)
        target = single
    command = typer.main.get_command(target)
    command.name = name
    return command


app = new_app(
    name="ohmni",
    add_completion=True,
    cls=_LazyGroup,
    help="Drive the OhmniLabs Ohmni robot over its serial bus (or the built-in simulator).\n\n"
    "Port: --port URL, else $OHMNI_PORT, else the config file's `port`, else the bus "
    "adapter found by its USB id. Try anything on the simulator with --port sim://.",
    no_args_is_help=True,
)


def _print_version(value: bool) -> None:
    if value:
        typer.echo(__version__)
        raise typer.Exit


@app.callback()
def _root(
    debug: Annotated[
        bool,
        typer.Option("--debug", help="Show the traceback of an error, and debug logs."),
    ] = False,
    verbose: Annotated[
        int,
        typer.Option(
            "--verbose",
            "-v",
            count=True,
            show_default=False,
            help="Log more on stderr: -v the library's info, -vv its debug lines too.",
        ),
    ] = 0,
    quiet: Annotated[
        bool,
        typer.Option(
            "--quiet", "-q", help="Only errors on stderr: no warnings (the output stays)."
        ),
    ] = False,
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            "-V",
            is_eager=True,
            callback=_print_version,
            help="Print the ohmni_tb version and exit.",
        ),
    ] = False,
) -> None:
    del version  # handled by its callback
    if quiet and (verbose or debug):
        raise typer.BadParameter("--quiet and --verbose/--debug ask for opposite things")
    # Every run sets it (a process that runs several commands, a test's, starts afresh).
    if debug or verbose or quiet or "ohmni_tb.cli.common" in sys.modules:
        from ohmni_tb.cli import common  # noqa: PLC0415  # only the command that runs loads it

        common.set_verbosity(-1 if quiet else 2 if debug else verbose, tracebacks=debug)


@app.command()
def version() -> None:
    """Print the ohmni_tb version.

    Example: ohmni version
    """
    typer.echo(__version__)


def main() -> None:
    """Entry point of the ``ohmni`` console script."""
    app()
