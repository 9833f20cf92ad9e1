"""The habits users expect of a Python command line: --version, completion, -v/-q, help
that reads as prose with flags shown as flags."""

from __future__ import annotations

import json
import re

import pytest
from typer.testing import CliRunner

from ohmni_tb._version import __version__
from ohmni_tb.cli import app
from ohmni_tb.protocol import write_request
from ohmni_tb.sim.robot import SimRobot

from ._helpers import invoke, spy_on_ports, words
from .test_cli_help import PATHS

runner = CliRunner()


@pytest.mark.parametrize("flag", ["--version", "-V"])
def test_version_flag_prints_the_version_as_the_command_does(flag: str) -> None:
    result = invoke(flag)
    assert result.code == 0
    assert result.stdout == f"{__version__}\n"
    assert invoke("version").stdout == result.stdout


@pytest.mark.parametrize("path", PATHS, ids=lambda p: " ".join(p) or "ohmni")
def test_help_shows_flags_as_flags_and_no_completion_below_the_root(
    path: tuple[str, ...],
) -> None:
    result = invoke(*path, "--help")
    assert result.code == 0
    assert "<bool>" not in result.out
    assert "[default: False]" not in result.out
    if path:  # completion covers every command from the root
        assert "--install-completion" not in result.out


def test_help_text_is_reflowed_not_broken_where_the_source_wraps() -> None:
    text = invoke("serve", "--help").out
    # The docstring breaks its lines after "alone on" and "services"; the help does not.
    assert "alone on the first line of stdout" in text
    assert re.search(
        r"^\s+--json\s+Print JSON instead of a table\.", invoke("stop", "--help").out, re.M
    )


def test_completion_script_and_answers_for_each_shell() -> None:
    for shell in ("bash", "zsh", "fish"):
        script = runner.invoke(app, ["--show-completion", shell])
        assert script.exit_code == 0, script.output
        assert "_OHMNI_COMPLETE" in script.output
    bash = runner.invoke(
        app,
        [],
        prog_name="ohmni",
        env={"_OHMNI_COMPLETE": "complete_bash", "COMP_WORDS": "ohmni ser", "COMP_CWORD": "1"},
    )
    assert bash.output.split() == ["servo", "serve"]
    zsh = runner.invoke(
        app,
        [],
        prog_name="ohmni",
        env={"_OHMNI_COMPLETE": "complete_zsh", "_TYPER_COMPLETE_ARGS": "ohmni drive --dist"},
    )
    assert "--distance" in zsh.output
    fish = runner.invoke(
        app,
        [],
        prog_name="ohmni",
        env={
            "_OHMNI_COMPLETE": "complete_fish",
            "_TYPER_COMPLETE_ARGS": "ohmni servo sc",
            "_TYPER_COMPLETE_FISH_ACTION": "get-args",
        },
    )
    assert fish.output.startswith("scan")


@pytest.mark.usefixtures("virtual_time")
def test_quiet_hides_warnings_and_verbose_shows_info_lines(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_NO_SUCH_SETTING", "1")  # the config warns about it
    plain = invoke("info", "--port", "sim://")
    assert plain.code == 0
    assert "warning: environment variable OHMNI_NO_SUCH_SETTING is ignored" in plain.out
    assert "INFO" not in plain.out
    quiet = invoke("-q", "info", "--port", "sim://")
    assert quiet.code == 0
    assert "warning" not in quiet.out
    assert quiet.stdout == plain.stdout
    verbose = invoke("-v", "info", "--port", "sim://")
    assert "INFO robot: opened" in verbose.out
    assert "DEBUG" not in verbose.out
    # Each run starts afresh: the next one is plain again.
    assert "INFO" not in invoke("info", "--port", "sim://").out


def test_quiet_and_verbose_together_are_refused() -> None:
    result = invoke("-q", "-v", "version")
    assert result.code == 2
    assert "--quiet and --verbose/--debug ask for opposite things" in result.out


@pytest.mark.usefixtures("virtual_time")
def test_scan_names_the_torque_mode_as_status_does(monkeypatch: pytest.MonkeyPatch) -> None:
    def brake_ext1(sim: SimRobot) -> None:
        (servo,) = [s for s in sim.ext_servos if s.sid == 11]
        servo.handle(write_request(11, 52, bytes((0x40,))), 0.0)  # torque_control = BRAKE

    spy_on_ports(monkeypatch, brake_ext1)
    result = invoke("servo", "scan", "--port", "sim://", "--first", "3", "--last", "12", "--json")
    assert result.code == 0, result.out
    modes = {row["sid"]: row["torque"] for row in json.loads(result.stdout)}
    assert modes == {3: "free", 11: "brake", 12: "free"}
    table = words(invoke("servo", "scan", "--port", "sim://", "--first", "11", "--last", "11").out)
    assert "ext1 DRS_0101 512 +0.0 brake" in table
