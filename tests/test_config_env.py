"""Settings from the environment and the config file that are not what they should be:
one line each, naming the variable or the file, and never a traceback; an ``OHMNI_*``
variable that nothing reads is warned about with the closest name that means something."""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import pytest

import ohmni_tb
from cli._helpers import invoke, words
from ohmni_tb.client import RobotClient
from ohmni_tb.config import RobotConfig
from ohmni_tb.errors import ConfigError

SIM = {"OHMNI_PORT": "sim://"}
BAD_URLS = ("ws://[::1", "ws://127.0.0.1:99999", "garbage")


@pytest.fixture(autouse=True)
def hermetic(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """No OHMNI_* variable but the tests' own, no config file anywhere, and no daemon
    (one running on this machine must not answer)."""
    for name in list(os.environ):
        if name.upper().startswith("OHMNI_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("OHMNI_DAEMON_URL", "off")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    monkeypatch.chdir(tmp_path)


def one_error_line(output: str) -> str:
    """The command's one ``error:`` line; nothing else on the way out, no traceback."""
    assert "Traceback" not in output
    (line,) = output.strip().splitlines()
    assert line.startswith("error: ")
    return line


def test_a_config_file_nested_thousands_deep_is_one_line(tmp_path: Path) -> None:
    path = tmp_path / "deep.toml"
    path.write_text("port = " + "[" * 5000 + "]" * 5000 + "\n")
    result = invoke("info", env={**SIM, "OHMNI_CONFIG": str(path)})
    assert result.code == 1
    line = one_error_line(result.out)
    assert f"{path}: not read: its arrays or tables nest too deeply" in line


@pytest.mark.parametrize("command", [("pid", "get"), ("pid", "set", "--kp", "500")])
def test_pid_commands_on_a_file_nested_thousands_deep_say_so_in_one_line(
    tmp_path: Path, command: tuple[str, ...]
) -> None:
    path = tmp_path / "deep.toml"
    text = "pid_kd = " + "[" * 5000 + "]" * 5000 + "\n"
    path.write_text(text)
    result = invoke(*command, "--file", str(path))
    assert result.code == 1, result.out
    line = one_error_line(result.out)
    assert "nest too deeply" in line
    assert path.read_text() == text  # nothing written


@pytest.mark.parametrize("url", BAD_URLS)
def test_a_malformed_daemon_url_is_one_line_naming_it(url: str) -> None:
    result = invoke("info", env={**SIM, "OHMNI_DAEMON_URL": url})
    assert result.code == 1
    line = one_error_line(result.out)
    assert f"OHMNI_DAEMON_URL={url!r} is not a daemon URL: expected ws://HOST:PORT" in line


@pytest.mark.parametrize("url", BAD_URLS)
async def test_the_client_refuses_a_malformed_url_by_name(url: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(f"{url!r} is not a daemon URL")):
        async with RobotClient.connect(url, timeout_s=1.0):
            pass


def test_a_mistyped_variable_is_warned_about_with_the_known_name() -> None:
    result = invoke("info", env={**SIM, "OHMNI_WATCHDOG": "0.1"})
    assert result.code == 0, result.out
    warning = (
        "warning: environment variable OHMNI_WATCHDOG is ignored: nothing reads that name; "
        "did you mean OHMNI_WATCHDOG_S?"
    )
    assert words(result.out).count(warning) == 1


def test_an_unknown_variable_is_warned_about_once(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("OHMNI_MAX_LINEAR", "2")
    monkeypatch.setenv("ohmni_daemon_token", "secret")  # read in capitals only
    with caplog.at_level(logging.WARNING, logger="ohmni_tb"):
        RobotConfig()
        RobotConfig.load(port="sim://")
    said = sorted(r.getMessage() for r in caplog.records)
    assert said == [
        "environment variable OHMNI_MAX_LINEAR is ignored: nothing reads that name; "
        "did you mean OHMNI_MAX_LINEAR_MPS?",
        "environment variable ohmni_daemon_token is ignored: nothing reads that name; "
        "did you mean OHMNI_DAEMON_TOKEN?",
    ]
    assert "secret" not in caplog.text


def test_every_variable_the_package_reads_is_taken_silently(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The settings at their defaults, and every other OHMNI_* name the source names."""
    for name, default, _ in RobotConfig.describe():
        monkeypatch.setenv(f"OHMNI_{name.upper()}", default)
    source = Path(ohmni_tb.__file__).parent
    named = {
        match
        for path in source.rglob("*.py")
        for match in re.findall(r"\bOHMNI_[A-Z0-9_]*[A-Z0-9]\b", path.read_text())
    }
    assert {"OHMNI_CONFIG", "OHMNI_DAEMON_URL", "OHMNI_DAEMON_TOKEN"} <= named
    for name in named - {f"OHMNI_{n.upper()}" for n in RobotConfig.model_fields}:
        monkeypatch.setenv(name, str(Path(ohmni_tb.__file__)))  # an existing file
    with caplog.at_level(logging.WARNING, logger="ohmni_tb"):
        RobotConfig()
    assert caplog.records == []
