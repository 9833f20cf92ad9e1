"""Every numeric argument of every ``ohmni`` command, driven with extreme values.

The parameters are read from the typer app itself, so a new option is fuzzed as soon as
it exists: a parameter is numeric unless it is a flag or listed in :data:`TEXT_PARAMS`,
and every command with a numeric parameter needs a valid baseline in :data:`BASELINES`.

For every value, against ``--port sim://``: the exit code is 0, 1 or 2; no exception
escapes (no traceback); a refusal (exit 2) is one line that names the parameter, and
nothing was written on the wire; an error (exit 1) is one ``error:`` line. A value no
parameter can take (NaN, infinity, 1e308, a huge integer, non-ASCII digits) is refused.
"""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import typer.main
from hypothesis import HealthCheck, assume, event, example, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from ohmni_tb.cli import app
from test_cli_servo import Wire, spy_on_cli


@pytest.fixture
def wire(monkeypatch: pytest.MonkeyPatch) -> Wire:
    return spy_on_cli(monkeypatch)


runner = CliRunner()
#: Wide enough that rich never wraps a message: "one line" means one line.
WIDE = {"COLUMNS": "4000"}

#: Parameters whose values are text, not numbers: names, URLs, paths, hex bytes, addresses.
TEXT_PARAMS = frozenset(
    {
        "port",
        "url",
        "register",
        "mode",
        "data",
        "capture",
        "file",
        "listen",
        "allow_origin",
        "token_file",
        "foxglove",
        "wheel",
        "stream",
        "target",  # ohmni connect PORT
        "log",  # ohmni bus convert LOG OUTPUT
        "output",
        "config_file",  # ohmni config --config FILE
        "config",  # ohmni probe --config FILE
        "share",  # ohmni probe --share FILE
        "robot_id",  # ohmni serve --robot-id ID: any name (a number is a name too)
    }
)

#: A valid invocation of each command that has numeric parameters (``--port sim://`` is
#: added): parameter name -> value, True for a flag.
BASELINES: dict[tuple[str, ...], dict[str, str | bool]] = {
    ("bus", "send"): {"sid": "0", "cmd": "STAT", "timeout": "0.01"},
    ("bus", "monitor"): {"duration": "0.01", "quiet": True},
    ("servo", "scan"): {"first": "0x0B", "last": "0x0C"},
    ("servo", "info"): {"timeout": "0.01"},
    ("servo", "read"): {"register": "temperature", "timeout": "0.01"},
    ("servo", "write"): {"register": "led_control", "value": "1", "timeout": "0.01"},
    ("servo", "move"): {"position": "400", "torque_on": True, "timeout": "0.01"},
    ("servo", "torque"): {"mode": "on", "timeout": "0.01"},
    ("servo", "stat"): {"timeout": "0.01"},
    ("servo", "clear"): {"timeout": "0.01"},
    ("servo", "set-id"): {"new_id": "12", "sid": "11", "timeout": "0.01"},
    ("servo", "zero-offset"): {"raw": "0"},
    # The right board's id for the left one: refused in one line, nothing sent. (A board
    # really moved away is not followed by the wheel reads: its stop is reported
    # unconfirmed at close, which this table would read as a crash.)
    ("servo", "board-id"): {"board": "0", "new_id": "1", "confirm": True},
    ("drive",): {"linear": "0.1", "duration": "0.1"},
    ("stop",): {"timeout": "0.5"},
    # Two ids, no motion: a few bus timeouts on the simulator.
    ("probe",): {"ids": "11..12", "pwm": "80"},
    ("light",): {"hue": "0", "saturation": "0", "value": "0"},
    ("neck",): {"raw": "400", "playtime": "0.2"},
    ("odom",): {"rate": "20", "duration": "0.2", "count": "2"},
    ("odom", "reset"): {"x": "0.5", "y": "-0.5", "yaw": "1"},
    ("odom", "set"): {"x": "0.5", "y": "-0.5", "yaw": "1"},
    # Asks a daemon on a port where none listens: never a developer's own daemon.
    ("serve",): {"handoff": "1", "listen": "127.0.0.1:1"},
    # A broker where none listens: its one error line (exit 1).
    ("fleet",): {"mqtt": "mqtt://127.0.0.1:1"},
    # A file of its own, replaced each time (FILE is text: not fuzzed).
    ("record",): {
        "file": str(Path(tempfile.gettempdir(), "ohmni-extreme-record.mcap")),
        "duration": "0.2",
        "overwrite": True,
    },
    # No such file: a valid speed and linger end in its one error line (exit 1).
    ("replay",): {
        "file": str(Path(tempfile.gettempdir(), "ohmni-extreme-no-such-recording.mcap")),
        "foxglove": "127.0.0.1:0",
        "linger": "0",
    },
    # Never the developer's own config file: the fuzz writes where --file points.
    ("pid", "set"): {
        "kp": "600",
        "file": str(Path(tempfile.gettempdir(), "ohmni-extreme-pid.toml")),
    },
}
#: Changes to the baseline while one parameter is fuzzed, to keep each run short: a scan
#: whose other bound is fuzzed covers at most a dozen ids.
CONTEXT: dict[tuple[tuple[str, ...], str], dict[str, str | bool]] = {
    (("servo", "scan"), "first"): {"last": "0x0C"},
    (("servo", "scan"), "last"): {"first": "0xF0"},
    # A new id is parsed and range-checked before the port opens; a board that is not a
    # drive board's then refuses it in one line, with nothing sent.
    (("servo", "board-id"), "new_id"): {"board": "5"},
}
#: Values a parameter accepts but that would keep the test waiting: a long live monitor.
TOO_SLOW: dict[tuple[tuple[str, ...], str], float] = {
    (("bus", "monitor"), "duration"): 0.05,
    (("drive",), "duration"): 0.5,
    (("neck",), "playtime"): 0.5,
    (("odom",), "duration"): 0.5,
    (("record",), "duration"): 0.5,
}


def _commands(command: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    # Through list_commands/get_command: the top group imports its commands lazily.
    names = command.list_commands(None) if hasattr(command, "list_commands") else []
    if not names:
        yield path, command
        return
    if path and any(p.name != "help" for p in command.params):
        yield path, command  # a group that runs by itself (`ohmni odom --rate 5`)
    for name in sorted(names):
        yield from _commands(command.get_command(None, name), (*path, name))


@dataclass(frozen=True)
class Target:
    """One numeric parameter of one command."""

    path: tuple[str, ...]
    name: str
    opt: str | None  # the long option, or None for an argument
    params: tuple[Any, ...]

    def __str__(self) -> str:
        return f"{' '.join(self.path)} {self.opt or self.name.upper()}"

    def names(self) -> tuple[str, ...]:
        """How an error message may name the parameter."""
        return (self.opt,) if self.opt else (self.name.upper(),)

    def argv(self, value: str) -> list[str]:
        values: dict[str, str | bool] = {
            **BASELINES[self.path],
            **CONTEXT.get((self.path, self.name), {}),
            self.name: value,
        }
        options: list[str] = []
        arguments: list[str] = []
        for param in self.params:
            given = values.get(param.name)
            if param.name == "port":
                options.append("--port=sim://")
            elif given is None:
                continue
            elif param.param_type_name == "argument":
                assert isinstance(given, str)
                arguments.append(given)
            elif given is True:
                options.append(_long(param))
            else:
                options.append(f"{_long(param)}={given}")
        # "--" keeps an argument such as -1 from being read as an option.
        return [*self.path, *options, "--", *arguments]


def _long(param: Any) -> str:
    opts = [opt for opt in param.opts if opt.startswith("--")]
    assert opts, param.name
    return str(opts[0])


def _targets() -> list[Target]:
    targets = []
    for path, command in _commands(typer.main.get_command(app)):
        for param in command.params:
            if getattr(param, "is_flag", False) or param.name in TEXT_PARAMS:
                continue
            opt = None if param.param_type_name == "argument" else _long(param)
            targets.append(Target(path, param.name, opt, tuple(command.params)))
    return targets


TARGETS = _targets()


def test_every_numeric_parameter_is_covered() -> None:
    # A command that grows a numeric parameter needs a baseline here to be fuzzed.
    missing = sorted({" ".join(t.path) for t in TARGETS if t.path not in BASELINES})
    assert not missing, f"add a valid invocation to BASELINES for: {missing}"
    fuzzed = {str(t) for t in TARGETS}
    for must in ("servo move POSITION", "servo move --playtime", "bus monitor --duration"):
        assert must in fuzzed
    assert len(TARGETS) >= 20


# -- values -------------------------------------------------------------------------------

FIXED = [
    "inf",
    "-inf",
    "nan",
    "NaN",
    "1e308",
    "-1e308",
    "1e309",
    "-0.0",
    "0",
    "5e-324",
    "-5e-324",
    "0x0B",
    "0xFF",
    "-0x1",
    "0x",
    "1_0",
    " 3 ",
    "",
    "9" * 5000,
    "0x" + "F" * 5000,
    "٣",
    "\uff13",  # fullwidth 3
    "१२",  # Devanagari 12
]
unicode_digits = st.text(
    st.characters(categories=["Nd"], min_codepoint=128), min_size=1, max_size=6
)
huge_ints = st.integers(min_value=2**64, max_value=10**400) | st.integers(
    min_value=-(10**400), max_value=-(2**64)
)
hex_ints = st.integers(min_value=-(2**80), max_value=2**80).map(
    lambda n: ("-" if n < 0 else "") + hex(abs(n))
)
VALUES = st.one_of(
    st.sampled_from(FIXED),
    huge_ints.map(str),
    hex_ints,
    unicode_digits,
    st.floats().map(repr),
    st.integers(min_value=-5, max_value=1100).map(str),
)


def never_valid(text: str) -> bool:
    """Whether no parameter of the CLI can take ``text``: NaN, ±inf, huge, non-ASCII."""
    if not text.isascii():
        return True
    try:
        if abs(int(text, 0)) >= 2**64:
            return True
    except ValueError:  # not an integer, or one of more than 4300 digits
        pass
    try:
        number = float(text)
    except ValueError:
        return False
    return not math.isfinite(number) or abs(number) >= 2**64


# -- the wire -----------------------------------------------------------------------------


# -- the property -------------------------------------------------------------------------


def too_slow(target: Target, value: str) -> bool:
    """Whether the command would accept ``value`` and then run for long."""
    limit = TOO_SLOW.get((target.path, target.name))
    if limit is None or never_valid(value):
        return False
    try:
        return float(value) > limit
    except ValueError:
        return False


def check(target: Target, value: str, wire: Wire) -> int:
    """Run ``target`` with ``value`` and check the outcome; return the exit code."""
    wire.opened.clear()
    wire.written.clear()
    argv = target.argv(value)
    result = runner.invoke(app, argv, env=WIDE)
    out = result.output
    context = f"{argv} -> {result.exit_code}\n{out}"
    assert result.exit_code in (0, 1, 2), context
    assert result.exception is None or isinstance(result.exception, SystemExit), context
    assert "Traceback" not in out, context
    lines = [line for line in out.splitlines() if line.strip()]
    if result.exit_code == 2:
        message = [line for line in lines if line.startswith("Error: ")]
        assert len(message) == 1, context  # one line under the usage
        assert any(name in message[0] for name in target.names()), context
        assert wire.written == [], context
    elif result.exit_code == 1:
        assert len(lines) == 1, context
        assert lines[0].startswith("error: "), context
    if never_valid(value):
        assert result.exit_code == 2, context
    return result.exit_code


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize("target", TARGETS, ids=str)
@pytest.mark.parametrize("value", ["nan", "-1e308", "9" * 30, "٣"])
def test_each_parameter_refuses_what_none_can_take(target: Target, value: str, wire: Wire) -> None:
    check(target, value, wire)


@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@pytest.mark.usefixtures("virtual_time")
@given(target=st.sampled_from(TARGETS), value=VALUES)
@example(target=TARGETS[0], value="inf")
def test_extreme_values_never_crash_the_cli(target: Target, value: str, wire: Wire) -> None:
    assume(not too_slow(target, value))
    event(f"exit {check(target, value, wire)}")  # --hypothesis-show-statistics
