"""docs/robot.md keeps up with the code: every RobotConfig setting is in its table."""

from __future__ import annotations

import re
from pathlib import Path

from ohmni_tb import RobotConfig
from ohmni_tb.robot import STREAMS

PAGE = Path(__file__).resolve().parent.parent / "docs" / "robot.md"
#: A row of the settings table: | `name` | default | meaning |
_ROW = re.compile(r"^\| `(?P<name>\w+)` \| (?P<default>[^|]*) \| (?P<meaning>.*) \|$", re.M)


def documented() -> dict[str, str]:
    """The settings table of docs/robot.md: name → default as written."""
    text = PAGE.read_text(encoding="utf-8")
    section = text.split("## Configuration", 1)[1].split("\n## ", 1)[0]
    return {m["name"]: m["default"].strip() for m in _ROW.finditer(section)}


def row(name: str, default: str, meaning: str) -> str:
    return f"| `{name}` | {default} | {meaning} |"


def test_every_setting_is_in_the_table_with_its_default() -> None:
    table = documented()
    described = RobotConfig.describe()
    missing = [row(*entry) for entry in described if entry[0] not in table]
    assert not missing, "docs/robot.md lacks these settings' rows:\n" + "\n".join(missing)
    stale = [row(*entry) for entry in described if table[entry[0]] != entry[1]]
    assert not stale, "docs/robot.md shows other defaults; the rows now:\n" + "\n".join(stale)
    unknown = sorted(set(table) - {name for name, _, _ in described})
    assert not unknown, f"docs/robot.md lists settings RobotConfig does not have: {unknown}"


def test_the_table_is_in_the_order_of_describe() -> None:
    assert list(documented()) == [name for name, _, _ in RobotConfig.describe()]


def test_the_row_pattern_reads_a_row() -> None:
    # The check must be able to see a row, or it would pass on an empty table.
    assert len(documented()) >= 40
    assert documented()["watchdog_s"] == "0.5"


#: A row of the streams table: | `name`[, `name`] | rate | `Sample` | fields | tb_control |
_STREAM_ROW = re.compile(
    r"^\| (?P<names>`\w+`(?:, `\w+`)*) \| (?P<rate>[^|]*) \| `(?P<sample>\w+)` \| [^|]* \| "
    r"(?P<topic>[^|]*) \|$",
    re.M,
)


def test_the_streams_table_is_the_streams_declaration() -> None:
    section = PAGE.read_text(encoding="utf-8").split("## Streams", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for match in _STREAM_ROW.finditer(section):
        for name in re.findall(r"`(\w+)`", match["names"]):
            rows[name] = match
    assert list(rows) == list(STREAMS), "docs/robot.md's streams table lists other streams"
    for name, spec in STREAMS.items():
        match = rows[name]
        assert match["sample"] == spec.sample_type.__name__, name
        if spec.tb_control:
            assert f"`{spec.tb_control}`" in match["topic"], name
        assert f"`{spec.rate_setting}`" in match["rate"], name
