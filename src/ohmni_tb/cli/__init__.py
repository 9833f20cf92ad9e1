"""The ``ohmni`` command line (typer)."""

from __future__ import annotations

import typer

from ohmni_tb import __version__
from ohmni_tb.cli import bus as bus_cli
from ohmni_tb.cli import servo as servo_cli
from ohmni_tb.cli.demo import demo
from ohmni_tb.cli.sim import sim

__all__ = ["app", "main"]

app = typer.Typer(
    name="ohmni",
    help="Drive the OhmniLabs Ohmni robot over its serial bus (or the built-in simulator).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(bus_cli.app, name="bus")
app.add_typer(servo_cli.app, name="servo")
app.command()(sim)
app.command()(demo)


@app.command()
def version() -> None:
    """Print the ohmni_tb version."""
    typer.echo(__version__)


def main() -> None:
    """Entry point of the ``ohmni`` console script."""
    app()
