"""``ohmni config``: the settings in effect and where each came from; ``ohmni config init``
writes a commented example file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape
from rich.table import Table

from ohmni_tb.cli import new_app
from ohmni_tb.cli.common import JsonOption, console, emit_json, error_line

app = new_app(
    help="The settings in effect and where each came from (argument, OHMNI_*, the config "
    "file, the default); `ohmni config init` writes a commented example file.\n\n"
    "Example: ohmni config --changed",
    invoke_without_command=True,
)

ConfigFileOption = Annotated[
    Path | None,
    typer.Option(
        "--config",
        help="Read this config file (default: $OHMNI_CONFIG, ./ohmni.toml, then "
        "~/.config/ohmni/ohmni.toml: the first that exists).",
        dir_okay=False,
        metavar="FILE",
        show_default=False,
    ),
]


@app.callback()
def show(
    ctx: typer.Context,
    config_file: ConfigFileOption = None,
    changed: Annotated[
        bool, typer.Option("--changed", help="Only the settings that are not the default.")
    ] = False,
    as_json: JsonOption = False,
) -> None:
    """Show every setting's value and where it came from.

    A setting comes from the environment (OHMNI_<NAME>) when set there, else from the
    config file, else its default (a command's own options, such as --port, beat all
    three). An invalid setting is an error naming it and where it came from.

    Example: ohmni config --changed
    """
    if ctx.invoked_subcommand is not None:
        return
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic: only when run
    from ohmni_tb.errors import ConfigError  # noqa: PLC0415

    try:
        config, path, origins = RobotConfig.load_explained(config_file)
    except ConfigError as exc:
        error_line(str(exc))
        raise typer.Exit(1) from None
    values = config.model_dump(mode="json")
    rows = [
        {"name": name, "value": values[name], "source": origins[name]}
        for name in RobotConfig.model_fields
        if not changed or origins[name] != "default"
    ]
    if as_json:
        emit_json({"config_file": None if path is None else str(path), "settings": rows})
        return
    console.print(
        f"config file: {escape(str(path)) if path is not None else 'none'}", highlight=False
    )
    if not rows:
        console.print("every setting is at its default", highlight=False)
        return
    table = Table()
    for column in ("setting", "value", "from"):
        table.add_column(column)
    for row in rows:
        table.add_row(row["name"], escape(_text(row["value"])), escape(row["source"]))
    console.print(table)


@app.command()
def init(
    file: Annotated[
        Path | None,
        typer.Argument(
            help="Where to write it (default: $OHMNI_CONFIG, else the file the settings are "
            "read from, else ~/.config/ohmni/ohmni.toml).",
            dir_okay=False,
            show_default=False,
        ),
    ] = None,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace the file if it exists.")
    ] = False,
) -> None:
    """Write a config file with every setting commented out, its default and what it does.

    It changes nothing until a line is uncommented. An existing file is kept unless
    --overwrite.

    Example: ohmni config init ./ohmni.toml
    """
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415
    from ohmni_tb.config_file import default_config_file  # noqa: PLC0415

    target = file or default_config_file()
    if target.exists() and not overwrite:
        error_line(f"{target} exists: keep it, or give --overwrite to replace it")
        raise typer.Exit(1)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(RobotConfig.example_file(), encoding="utf-8")
    except OSError as exc:
        error_line(f"cannot write {target}: {exc.strerror or exc}")
        raise typer.Exit(1) from None
    console.print(f"wrote {escape(str(target))}", highlight=False)


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return ",".join(map(str, value)) or "none"
    return str(value)
