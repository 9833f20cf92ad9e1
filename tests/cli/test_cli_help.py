"""Every ``ohmni`` command answers ``--help`` with an example, without touching a port."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
import typer.main
from typer.testing import CliRunner

from ohmni_tb.cli import COMMANDS, app

runner = CliRunner()


def _paths(command: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[str, ...]]:
    yield path
    names = command.list_commands(None) if hasattr(command, "list_commands") else []
    for name in names:
        yield from _paths(command.get_command(None, name), (*path, name))


PATHS = list(_paths(typer.main.get_command(app)))


def test_every_command_in_the_table_is_reachable() -> None:
    assert {path[0] for path in PATHS if path} >= set(COMMANDS)
    assert len(PATHS) >= 25


@pytest.mark.parametrize("path", PATHS, ids=lambda p: " ".join(p) or "ohmni")
def test_help_exits_0_with_an_example(path: tuple[str, ...]) -> None:
    result = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "Usage: ohmni" in result.output
    if path:  # the program's own help lists the commands instead
        assert "Example" in result.output, result.output  # "Example:" or "Examples:"
