"""Command sources with priorities: who may drive the wheels now (sans-IO, no clock).

Several programs may want to drive one robot: a safety layer, a person at the robot, a
remote operator, a script. Each names its **command source**; the table of sources
(:data:`DEFAULT_SOURCES`, the ``command_sources`` setting) gives each a priority — its
place in the table, the first highest — and a timeout::

    safety    0.5 s   a safety layer of yours (a bumper or cliff reaction)
    local     0.5 s   a person at the robot: ohmni drive on its own computer
    remote    0.5 s   a daemon client elsewhere, Foxglove's Teleop panel
    autonomy  1.0 s   a script or planner: the library's default

A source is **live** from a command of it taken until its timeout passes with no other
(and all the while one of its motion goals runs: :meth:`SourceMux.hold`). The highest
live source drives; a command from a lower one is refused (:meth:`SourceMux.take`
names the source in the way) and changes nothing: a refused command does not make its
source live. So when the source that drives lapses, the next command of any other is
taken. This is kobuki's ``cmd_vel_mux`` — each input a priority and a timeout, the
highest input that is publishing wins — save that a lower source is told why it was
refused instead of being dropped unheard.

:class:`SourceMux` takes the time as an argument (the Robot gives it its loop's clock);
:func:`parse_sources` reads a table from the setting's text, each bad entry named.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Final

from ohmni_tb.errors import InvalidArgumentError

__all__ = [
    "DEFAULT_SOURCE",
    "DEFAULT_SOURCES",
    "LOOPBACK_SOURCES",
    "REQUIRED_SOURCES",
    "TIMEOUT_RANGE_S",
    "CommandSource",
    "SourceMux",
    "claimable_beyond_loopback",
    "format_sources",
    "format_text",
    "parse_sources",
]


@dataclass(frozen=True, slots=True)
class CommandSource:
    """One row of the table: a source's name and how long it stays live after a command.

    Attributes:
        name: The source's name (lower case letters, digits, ``_``).
        timeout_s: Seconds it stays live after its last command taken.
    """

    name: str
    timeout_s: float


#: The default table, highest priority first. The teleop kinds live 0.5 s: the motion
#: watchdog's time (``watchdog_s``) and the keyboard teleop's hold (``KEY_HOLD_S``), so a
#: person who lets go hands the robot back as the watchdog stops it. ``autonomy`` lives
#: 1.0 s: a planner that commands at 2 Hz, or a script between two motion goals of the
#: same run, stays the source that drives; as the lowest it holds back no one.
DEFAULT_SOURCES: Final = (
    CommandSource("safety", 0.5),
    CommandSource("local", 0.5),
    CommandSource("remote", 0.5),
    CommandSource("autonomy", 1.0),
)
#: A command's source when none is named: a script's, or a library user's.
DEFAULT_SOURCE: Final = "autonomy"
#: The sources the package itself uses (a script's default, ``ohmni drive`` on the robot
#: and elsewhere, daemon clients and Foxglove): every table has them.
REQUIRED_SOURCES: Final = ("local", "remote", "autonomy")
#: The sources only a program on the robot's own computer may claim through the daemon
#: (a loopback or unix-socket client), whatever their place in the table.
LOOPBACK_SOURCES: Final = frozenset({"safety", "local"})
#: A source's timeout, s: no shorter than a few control periods, no longer than a minute
#: (a source that lapses later holds every lower one off that long).
TIMEOUT_RANGE_S: Final = (0.05, 60.0)
#: The most sources a table may have.
_MAX_SOURCES = 16
#: A source's name: a short word, as it appears in robot_state and in messages.
_NAME = re.compile(r"[a-z][a-z0-9_]{0,31}")
_FORMAT = "name:seconds"


def parse_sources(entries: str | Iterable[object]) -> tuple[CommandSource, ...]:
    """A table from its text: ``"safety:0.5,local:0.5,remote:0.5,autonomy:1"``, or a list
    of such entries (highest priority first), or of :class:`CommandSource`.

    Raises:
        ValueError: An entry is not ``name:seconds``, a name is not a word or repeats, a
            timeout is outside :data:`TIMEOUT_RANGE_S`, or a required source is missing;
            the message names the entry and what is allowed.
    """
    items: list[object] = (
        [part.strip() for part in entries.split(",")] if isinstance(entries, str) else list(entries)
    )
    if len(items) > _MAX_SOURCES:
        raise ValueError(f"command_sources has {len(items)} entries: at most {_MAX_SOURCES}")
    table: list[CommandSource] = []
    for number, item in enumerate(items, start=1):
        source = _entry(number, item)
        if any(known.name == source.name for known in table):
            raise ValueError(
                f"command_sources entry {number} {source.name!r} repeats a source: each "
                "name once, in the order of priority"
            )
        table.append(source)
    missing = [name for name in REQUIRED_SOURCES if all(s.name != name for s in table)]
    if missing:
        raise ValueError(
            f"command_sources lacks {', '.join(missing)}: the table needs "
            f"{', '.join(REQUIRED_SOURCES)} (the package's own sources), in any order, e.g. "
            f"{format_text(DEFAULT_SOURCES)}"
        )
    return tuple(table)


def format_sources(table: Sequence[CommandSource]) -> tuple[str, ...]:
    """The table as the setting's entries: ``("safety:0.5", "local:0.5", …)``."""
    return tuple(f"{source.name}:{_seconds(source.timeout_s)}" for source in table)


def format_text(table: Sequence[CommandSource]) -> str:
    """The table as one line of text, as ``OHMNI_COMMAND_SOURCES`` takes it."""
    return ",".join(format_sources(table))


def claimable_beyond_loopback(table: Sequence[CommandSource], name: str) -> bool:
    """Whether a daemon client beyond loopback may claim source ``name``: not one of
    :data:`LOOPBACK_SOURCES`, and no higher in ``table`` than ``remote``."""
    names = [source.name for source in table]
    if name in LOOPBACK_SOURCES or name not in names:
        return False
    return "remote" not in names or names.index(name) >= names.index("remote")


class SourceMux:
    """Which source drives (module docstring): fed each command's source and the time.

    Args:
        table: The sources, highest priority first.
    """

    __slots__ = ("_held", "_index", "_timeout", "_until", "names", "table")

    def __init__(self, table: Sequence[CommandSource]) -> None:
        self.table = tuple(table)
        #: The sources' names, highest priority first.
        self.names = tuple(source.name for source in self.table)
        self._index = {name: index for index, name in enumerate(self.names)}
        self._timeout = tuple(source.timeout_s for source in self.table)
        # Each source is live while now < _until, or while it holds a goal (_held > 0).
        self._until = [-math.inf] * len(self.table)
        self._held = [0] * len(self.table)

    def check_name(self, name: object) -> str:
        """``name`` if it is a source of the table.

        Raises:
            InvalidArgumentError: It is not; the message lists the sources.
        """
        if not isinstance(name, str) or name not in self._index:
            shown = repr(name) if len(repr(name)) <= 40 else f"{repr(name)[:30]}…"
            raise InvalidArgumentError(
                f"source={shown} is not a command source: allowed {', '.join(self.names)}"
            )
        return name

    def blocker(self, name: str, now: float) -> str | None:
        """The live source of higher priority than ``name`` that drives, if any."""
        held, until = self._held, self._until
        for index in range(self._index[name]):
            if held[index] or now < until[index]:
                return self.names[index]
        return None

    def take(self, name: str, now: float) -> str | None:
        """A command from ``name`` at ``now``: taken (``name`` is live for its timeout from
        now; returns ``None``) unless a higher source is live (returns that source, and
        nothing changes)."""
        index = self._index[name]
        held, until = self._held, self._until
        for higher in range(index):
            if held[higher] or now < until[higher]:
                return self.names[higher]
        until[index] = max(until[index], now + self._timeout[index])
        return None

    def hold(self, name: str) -> None:
        """``name`` stays live whatever the time, until as many :meth:`release` (a motion
        goal of it runs)."""
        self._held[self._index[name]] += 1

    def release(self, name: str, now: float) -> None:
        """One :meth:`hold` of ``name`` ends at ``now``: it lives its timeout from then."""
        index = self._index[name]
        if self._held[index]:
            self._held[index] -= 1
            self._until[index] = max(self._until[index], now + self._timeout[index])

    def active(self, now: float) -> str | None:
        """The source that drives at ``now``: the highest live one, or ``None``."""
        held, until = self._held, self._until
        for index, name in enumerate(self.names):
            if held[index] or now < until[index]:
                return name
        return None

    def lapses_at(self, name: str) -> float:
        """When ``name`` lapses without another command: ``inf`` while it holds a goal,
        a past time when it is not live."""
        index = self._index[name]
        return math.inf if self._held[index] else self._until[index]

    def outranks(self, first: str, second: str) -> bool:
        """Whether source ``first`` has a higher priority than ``second``."""
        return self._index[first] < self._index[second]


def _entry(number: int, item: object) -> CommandSource:
    """One entry of the table, checked; ``number`` counts from 1 for the messages."""
    if isinstance(item, CommandSource):
        name, seconds = item.name, item.timeout_s
        shown = f"{name}:{seconds}"
    else:
        shown = str(item)
        if not isinstance(item, str) or item.count(":") != 1:
            raise ValueError(
                f"command_sources entry {number} {_shown(item)} is not {_FORMAT}: e.g. "
                f"{format_text(DEFAULT_SOURCES)}, highest priority first"
            )
        name, _, text = (part.strip() for part in item.partition(":"))
        try:
            seconds = float(text)
        except ValueError:
            raise ValueError(
                f"command_sources entry {number} {shown!r}: {text!r} is not a number of "
                f"seconds: allowed {_FORMAT}, each {_range()}"
            ) from None
    if not isinstance(name, str) or _NAME.fullmatch(name) is None:
        raise ValueError(
            f"command_sources entry {number} {shown!r}: {name!r} is not a source name: "
            "allowed lower case letters, digits and _, starting with a letter (at most 32)"
        )
    low, high = TIMEOUT_RANGE_S
    if not (math.isfinite(seconds) and low <= seconds <= high):
        raise ValueError(
            f"command_sources entry {number} {shown!r}: the timeout {_seconds(seconds)} s is "
            f"out of range: allowed {_range()}"
        )
    return CommandSource(name, float(seconds))


def _range() -> str:
    low, high = TIMEOUT_RANGE_S
    return f"{_seconds(low)}..{_seconds(high)} s"


def _seconds(value: float) -> str:
    """A timeout as text: ``1`` not ``1.0``, ``0.5``."""
    return str(int(value)) if float(value).is_integer() else format(value, "g")


def _shown(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 40 else f"{text[:30]}…({len(text)} chars)"
