"""Settings written into a TOML config file in place, keeping its comments and layout.

:func:`write_settings` edits the ``key = value`` lines of a file :class:`RobotConfig`
reads (at top level, or in its ``[robot]`` table) and nothing else, and refuses any edit
that would not read back as intended; ``ohmni pid set`` and ``ohmni probe --write`` are
built on it. Values are numbers, strings, booleans or lists of integers::

    from pathlib import Path
    from ohmni_tb.config_file import write_settings

    outcome = write_settings(Path("ohmni.toml"), {"pid_kp": 650.0, "pid_ki": 300.0})
    print(outcome.previous)        # each setting's value in the file before (None: unset)
    write_settings(Path("ohmni.toml"), {"wheel_form": "i_jog", "ext_servo_ids": [13, 14]})

:func:`default_config_file` is the file such a write goes to when none is named.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ohmni_tb.config import CONFIG_ENV, RobotConfig, config_paths, toml_settings, toml_value
from ohmni_tb.errors import ConfigError

__all__ = [
    "SettingValue",
    "WriteOutcome",
    "default_config_file",
    "loaded_config_file",
    "read_settings",
    "write_settings",
]

#: What :func:`write_settings` writes: a number, a string, a bool or a list of integers.
SettingValue = float | str | bool | Sequence[int]
#: The first line of a file :func:`write_settings` creates, unless told another.
_CREATED_COMMENT = "ohmni settings (ohmni pid set wrote the pid_* gains)"


@dataclass(frozen=True, slots=True)
class WriteOutcome:
    """What :func:`write_settings` did.

    Attributes:
        created: The file did not exist before.
        previous: Each written setting's value in the file before (``None``: not set).
    """

    created: bool
    previous: dict[str, Any]


_HEADER = re.compile(r"^\s*\[")


def _key_line(key: str) -> re.Pattern[str]:
    """A ``key = value`` line (bare or quoted key), with its trailing comment."""
    names = "|".join((re.escape(key), f'"{re.escape(key)}"', f"'{re.escape(key)}'"))
    return re.compile(
        rf"^(?P<indent>[ \t]*)(?P<key>{names})(?P<eq>[ \t]*=[ \t]*)(?P<value>[^#\r\n]*?)"
        rf"(?P<comment>[ \t]*#[^\r\n]*)?(?P<eol>\r?\n)?$"
    )


def read_settings(path: Path) -> dict[str, Any]:
    """The settings of a config file as :meth:`RobotConfig.load` merges them.

    Raises:
        ConfigError: It cannot be read or is not TOML, or ``[robot]`` is not a table.
    """

    try:
        text = _read(path)
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from exc
    return _merged(toml_settings(text, path), path)


def _read(path: Path) -> str:
    """The file's text, line ends as they are."""
    return path.read_bytes().decode("utf-8")


def _merged(data: dict[str, Any], path: Path) -> dict[str, Any]:
    """Top-level settings and the ``[robot]`` table's, merged (as the loader does)."""

    merged = dict(data)
    table = merged.pop("robot", None)
    if table is None:
        return merged
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: robot must be a [robot] table, not {table!r}")
    for key, value in table.items():
        if key in merged:
            raise ConfigError(f"{path}: {key} is set both at top level and in [robot]")
        merged[key] = value
    return merged


def write_settings(
    path: Path, values: Mapping[str, SettingValue], *, comment: str | None = None
) -> WriteOutcome:
    """Set top-level settings in a TOML config file, keeping everything else.

    A value is a number (``650.0``, ``176``), a string (``"i_jog"``), a bool or a list of
    integers (``[13, 14]``), written as TOML writes it; ``comment`` is the first line of
    a file this creates.

    A ``key = value`` line already there (at top level, or in the ``[robot]`` table) is
    rewritten in place, keeping its comment; a new key goes after the last setting before
    the first table (or at the end of ``[robot]`` when the file uses one). The result is
    parsed again before it replaces the file: every other setting must read back the
    same, and these the new values; otherwise nothing is written. A missing file (and its
    directory) is created. The file is replaced atomically.

    Each value is checked first as :class:`~ohmni_tb.config.RobotConfig` checks it: an
    unknown setting, or a value out of its range, is a :class:`ConfigError` naming it and
    the allowed range, and nothing is written.

    Raises:
        ConfigError: A setting is unknown or its value not allowed; the file cannot be
            read or written, is not valid TOML, or holds a setting in a form this line
            editor does not change safely (the message says which: set it by hand).
    """
    _check_values(values)
    shown = {key: toml_value(key, value) for key, value in values.items()}

    created = not path.exists()
    if created:
        text = f"# {comment or _CREATED_COMMENT}\n"
        before: dict[str, Any] = {}
    else:
        if not path.is_file():
            raise ConfigError(f"config file is not a file: {path}")
        before = read_settings(path)
        text = _read(path)
    lower = {key.lower(): key for key in before}
    for key in values:
        other = lower.get(key.lower())
        if other is not None and other != key:
            raise ConfigError(f"{path}: {other} is written in another case than {key}: fix it")
    newline = "\r\n" if "\r\n" in text else "\n"
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += newline
    robot_table = _table_span(lines, "robot")
    for key, text_value in shown.items():
        lines = _set_line(lines, key, text_value, newline, robot_table)
        robot_table = _table_span(lines, "robot")
    result = "".join(lines)
    _check_result(path, result, before, values)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_text(result, encoding="utf-8", newline="")
        if not created:
            os.chmod(temporary, path.stat().st_mode & 0o7777)
        temporary.replace(path)
    except OSError as exc:
        temporary.unlink(missing_ok=True)
        raise ConfigError(f"cannot write config file {path}: {exc}") from exc
    return WriteOutcome(created, {key: before.get(key) for key in values})


def _table_span(lines: list[str], name: str) -> tuple[int, int] | None:
    """Lines ``[start, end)`` of the body of table ``[name]``, or ``None``."""
    header = re.compile(rf"^\s*\[\s*{re.escape(name)}\s*\]\s*(#.*)?$")
    for i, line in enumerate(lines):
        if header.match(line.rstrip("\r\n")):
            end = next((j for j in range(i + 1, len(lines)) if _HEADER.match(lines[j])), len(lines))
            return i + 1, end
    return None


def _set_line(
    lines: list[str],
    key: str,
    value: str,
    newline: str,
    robot_table: tuple[int, int] | None,
) -> list[str]:
    """``lines`` with ``key = value`` set at top level or in ``[robot]``."""
    pattern = _key_line(key)
    first_table = next((i for i, line in enumerate(lines) if _HEADER.match(line)), len(lines))
    spans = [(0, first_table)]
    if robot_table is not None:
        spans.append(robot_table)
    for start, end in spans:
        for i in range(start, end):
            match = pattern.match(lines[i])
            if match is not None:
                comment = match["comment"] or ""
                eol = match["eol"] or ""
                lines = list(lines)
                lines[i] = f"{match['indent']}{match['key']}{match['eq']}{value}{comment}{eol}"
                return lines
    # A key commented out as `ohmni config init` writes it (`# key = default`): that line
    # becomes the setting, under its description.
    commented = re.compile(rf"^# {re.escape(key)} = [^\r\n]*(?P<eol>\r?\n)?$")
    for start, end in spans:
        for i in range(start, end):
            found = commented.match(lines[i])
            if found is not None:
                lines = list(lines)
                lines[i] = f"{key} = {value}{found['eol'] or ''}"
                return lines
    # A new key: after the last setting of [robot] if the file has one, else of the top.
    start, end = robot_table if robot_table is not None else (0, first_table)
    at = end
    while at > start and not lines[at - 1].strip():
        at -= 1
    return [*lines[:at], f"{key} = {value}{newline}", *lines[at:]]


def _check_result(
    path: Path, text: str, before: Mapping[str, Any], values: Mapping[str, SettingValue]
) -> None:
    """Refuse an edit that would not read back as intended."""

    try:
        after = _merged(toml_settings(text, path), path)
    except ConfigError as exc:
        keys = ", ".join(values)
        raise ConfigError(
            f"{path}: cannot set {keys} safely by editing lines ({exc}); nothing was "
            "written: set them by hand"
        ) from exc
    expected = {**before, **{key: _as_read(value) for key, value in values.items()}}
    if after != expected:
        changed = sorted(
            key
            for key in {*after, *expected}
            if key not in after or key not in expected or after[key] != expected[key]
        )
        raise ConfigError(
            f"{path}: cannot set {', '.join(values)} safely by editing lines (it would "
            f"change {', '.join(changed)}); nothing was written: set them by hand"
        )


def _check_values(values: Mapping[str, SettingValue]) -> None:
    """Each value as RobotConfig takes it from a file, or a ConfigError naming it."""
    for key, value in values.items():
        RobotConfig.check_setting(key, _as_read(value))


def _as_read(value: object) -> object:
    """``value`` as it reads back from TOML (a tuple reads as a list)."""
    return list(value) if isinstance(value, tuple) else value


def default_config_file() -> Path:
    """The file a setting is written to when none is named: ``$OHMNI_CONFIG`` (even
    before it exists), else the file :meth:`RobotConfig.load` reads, else the user's
    ``ohmni.toml`` (:func:`~ohmni_tb.config.user_config_dir`)."""
    paths = config_paths()
    if os.environ.get(CONFIG_ENV):
        return paths[0]
    return loaded_config_file() or paths[-1]


def loaded_config_file() -> Path | None:
    """The file :meth:`RobotConfig.load` reads now, or ``None`` (no file, or
    ``$OHMNI_CONFIG`` names one that does not exist, which it refuses)."""
    paths = config_paths()
    if os.environ.get(CONFIG_ENV):
        paths = paths[:1]
    return next((path for path in paths if path.is_file()), None)
