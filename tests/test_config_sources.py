"""The command sources setting: one setting from arguments, ``OHMNI_COMMAND_SOURCES`` or
the config file, each bad entry refused in one line naming it and where it came from,
and a ``source=`` the table has not refused before any port opens."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from ohmni_tb import Robot, RobotConfig
from ohmni_tb.control.sources import CommandSource
from ohmni_tb.errors import ConfigError

#: Every test here without the machine's own settings (conftest's ``hermetic``).
pytestmark = pytest.mark.usefixtures("hermetic")


def test_the_default_table_and_its_rows() -> None:
    config = RobotConfig()
    assert config.command_sources == ("safety:0.5", "local:0.5", "remote:0.5", "autonomy:1")
    assert config.source_table()[1] == CommandSource("local", 0.5)
    described = {name: default for name, default, _ in RobotConfig.describe()}
    assert described["command_sources"] == "safety:0.5,local:0.5,remote:0.5,autonomy:1"


def test_the_environment_and_the_file_give_a_table_in_their_order(
    monkeypatch: pytest.MonkeyPatch, hermetic: Path
) -> None:
    (hermetic / "ohmni.toml").write_text(
        'command_sources = ["local:0.3", "safety:0.25", "remote:2", "autonomy:1.5"]\n'
    )
    assert [s.name for s in RobotConfig.load().source_table()] == [
        "local",
        "safety",
        "remote",
        "autonomy",
    ]
    monkeypatch.setenv("OHMNI_COMMAND_SOURCES", "remote:0.5, local:0.5 ,autonomy:1")
    assert RobotConfig.load().command_sources == ("remote:0.5", "local:0.5", "autonomy:1")


def test_a_bad_entry_from_the_environment_is_one_line_naming_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_COMMAND_SOURCES", "local:0.5,remote:soon,autonomy:1")
    with pytest.raises(ConfigError) as caught:
        RobotConfig()
    assert str(caught.value) == (
        "command_sources entry 2 'remote:soon': 'soon' is not a number of seconds: allowed "
        "name:seconds, each 0.05..60 s (from OHMNI_COMMAND_SOURCES)"
    )


def test_a_bad_entry_in_the_file_names_the_file(hermetic: Path) -> None:
    path = hermetic / "ohmni.toml"
    path.write_text('command_sources = ["local:0.5", "remote:0.5", "autonomy:120"]\n')
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load()
    assert str(caught.value) == (
        "command_sources entry 3 'autonomy:120': the timeout 120 s is out of range: allowed "
        f"0.05..60 s (in {path})"
    )


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (
            "local:0.5,remote:0.5",
            "command_sources lacks autonomy: the table needs local, remote, autonomy (the "
            "package's own sources), in any order, e.g. "
            "safety:0.5,local:0.5,remote:0.5,autonomy:1 (argument)",
        ),
        (
            ["local:0.5", "remote:0.5", "Nav:1", "autonomy:1"],
            "command_sources entry 3 'Nav:1': 'Nav' is not a source name: allowed lower case "
            "letters, digits and _, starting with a letter (at most 32) (argument)",
        ),
        (
            "local:0.5,remote:0.5,remote:1,autonomy:1",
            "command_sources entry 3 'remote' repeats a source: each name once, in the order "
            "of priority (argument)",
        ),
        (
            "local=0.5,remote:0.5,autonomy:1",
            "command_sources entry 1 'local=0.5' is not name:seconds: e.g. "
            "safety:0.5,local:0.5,remote:0.5,autonomy:1, highest priority first (argument)",
        ),
        (
            ["local:0.5", 2, "autonomy:1"],
            "command_sources[1]=2 is not a string: allowed name:seconds entries, highest "
            "priority first (argument)",
        ),
    ],
)
def test_a_bad_table_is_refused_naming_the_entry(value: object, message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        RobotConfig(command_sources=value)  # type: ignore[arg-type]  # bad kinds on purpose
    assert str(caught.value) == message


def test_a_source_not_in_the_table_is_refused_before_the_port_opens() -> None:
    async def main() -> None:
        with pytest.raises(ConfigError) as caught:
            async with Robot.open("/dev/ohmni-no-such-port", source="operator"):
                pass
        assert str(caught.value) == (
            "source='operator' is not a command source of command_sources: allowed safety, "
            "local, remote, autonomy"
        )

    asyncio.run(main())


def test_the_example_file_holds_the_table_and_loads_as_the_default(hermetic: Path) -> None:
    text = RobotConfig.example_file()
    line = '# command_sources = ["safety:0.5", "local:0.5", "remote:0.5", "autonomy:1"]'
    assert line in text.splitlines()
    (hermetic / "ohmni.toml").write_text(line.removeprefix("# ") + "\n")
    assert RobotConfig.load().command_sources == RobotConfig().command_sources
