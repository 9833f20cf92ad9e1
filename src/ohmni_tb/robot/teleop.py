"""Keyboard teleoperation: terminal bytes to drive commands, for any program with a terminal.

``ohmni drive --teleop`` is built on it; so can a script of yours be::

    from ohmni_tb.robot.teleop import KeyParser, KeyTeleop

    parser, teleop = KeyParser(), KeyTeleop(robot)
    for action in parser.feed(os.read(fd, 256)):   # the terminal in raw mode
        teleop.press(action, loop.time())
    teleop.decay(loop.time())                       # every ~0.1 s: a key not held stops

A key press drives at the key speeds (``w``/``s`` or the up/down arrows forward and back,
``a``/``d`` or left/right turn on the spot) until no key came for ``hold_s`` — a
terminal repeats a held key, so holding it keeps the robot going and letting go stops
it; space stops at once; ``+``/``-`` scale the key speeds by 1.25 within the robot's
limits. The Robot's watchdog and limits apply as to any command.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Final

from ohmni_tb._checks import positive
from ohmni_tb.errors import InvalidArgumentError

# Key speeds when none are given: a goal's (the robot's limits cap them).
from ohmni_tb.robot.motion import DEFAULT_ANGULAR_RADPS, DEFAULT_LINEAR_MPS

if TYPE_CHECKING:
    from ohmni_tb.robot.api import Robot

__all__ = [
    "ACTIONS",
    "DEFAULT_ANGULAR_RADPS",
    "DEFAULT_LINEAR_MPS",
    "KEYS",
    "KEY_HOLD_S",
    "SCALE_STEP",
    "KeyParser",
    "KeyTeleop",
]

#: How much ``faster`` and ``slower`` change the key speeds.
SCALE_STEP: Final = 1.25
#: The longest a key press drives without another (the watchdog, when shorter).
KEY_HOLD_S: Final = 0.5
#: Every action a key may mean.
ACTIONS: Final = ("forward", "back", "left", "right", "stop", "faster", "slower", "quit")
#: Key → action. The arrows come as escape sequences (:class:`KeyParser`).
KEYS: Mapping[str, str] = MappingProxyType(
    {
        "w": "forward",
        "W": "forward",
        "s": "back",
        "S": "back",
        "a": "left",
        "A": "left",
        "d": "right",
        "D": "right",
        " ": "stop",
        "+": "faster",
        "=": "faster",
        "-": "slower",
        "_": "slower",
        "q": "quit",
        "Q": "quit",
        "\x03": "quit",  # Ctrl-C in raw mode
        "\x04": "quit",  # Ctrl-D
    }
)
_ARROWS: Final = {"A": "forward", "B": "back", "C": "right", "D": "left"}
#: The slowest the key speeds go with ``slower``.
_MIN_LINEAR_MPS: Final = 0.01
_MIN_ANGULAR_RADPS: Final = 0.05


class KeyParser:
    """Bytes from a terminal in raw mode → actions; an escape sequence may come split.

    The arrows are ``ESC [ A..D`` (``ESC [ 1;5 A`` with a modifier) or ``ESC O A..D``; any
    other escape sequence is skipped whole, so its letters are not taken for keys. Bytes
    of no key are ignored.
    """

    def __init__(self) -> None:
        self._pending = ""

    def feed(self, data: bytes) -> list[str]:
        """The actions of ``data`` (and of a sequence the previous call left cut short)."""
        text = self._pending + data.decode("latin-1")
        self._pending = ""
        actions: list[str] = []
        i = 0
        while i < len(text):
            char = text[i]
            if char != "\x1b":
                if char in KEYS:
                    actions.append(KEYS[char])
                i += 1
                continue
            end = _sequence_end(text, i)
            if end is None:
                self._pending = text[i:]  # the rest of the sequence is still coming
                break
            final = text[end - 1]
            if end - i >= 3 and final in _ARROWS:
                actions.append(_ARROWS[final])
            i = end
        return actions

    def flush(self) -> None:
        """Drop a lone Esc left pending (call when the terminal has been quiet a while)."""
        self._pending = ""


def _sequence_end(text: str, start: int) -> int | None:
    """Where the escape sequence at ``start`` ends (exclusive), ``None`` if cut short.

    A lone Esc followed by another key is one character long.
    """
    if start + 1 >= len(text):
        return None
    kind = text[start + 1]
    if kind == "O":  # SS3: one more character
        return start + 3 if start + 2 < len(text) else None
    if kind != "[":
        return start + 1
    for end in range(start + 2, len(text)):
        if "@" <= text[end] <= "~":  # CSI: parameters, then a final byte
            return end + 1
    return None


class KeyTeleop:
    """The keyboard's state, driving ``robot``: the key speeds and the last key's command.

    Args:
        robot: The robot the keys drive (local or remote).
        linear_mps: The key speed forward and back (default 0.3 m/s within the limits).
        angular_radps: The key speed turning (default 1.0 rad/s within the limits).
        hold_s: How long a key press drives without another; default 0.5 s, or the
            watchdog's time when that is shorter.

    Raises:
        InvalidArgumentError: A speed or ``hold_s`` is not a positive number.
    """

    def __init__(
        self,
        robot: Robot,
        *,
        linear_mps: float | None = None,
        angular_radps: float | None = None,
        hold_s: float | None = None,
    ) -> None:
        config = robot.config
        self._robot = robot
        #: The fastest the keys may go (the robot's limits).
        self.top_linear_mps = config.top_linear_mps()
        self.top_angular_radps = config.top_angular_radps()
        linear = DEFAULT_LINEAR_MPS if linear_mps is None else positive("linear_mps", linear_mps)
        angular = (
            DEFAULT_ANGULAR_RADPS
            if angular_radps is None
            else positive("angular_radps", angular_radps)
        )
        #: The key speeds now.
        self.linear_mps = min(linear, self.top_linear_mps)
        self.angular_radps = min(angular, self.top_angular_radps)
        watchdog = config.watchdog_s
        default_hold = min(watchdog, KEY_HOLD_S) if watchdog > 0 else KEY_HOLD_S
        self.hold_s = default_hold if hold_s is None else positive("hold_s", hold_s)
        #: The command of the last key, (m/s, rad/s); zero when stopped.
        self.command: tuple[float, float] = (0.0, 0.0)
        #: What the last key did, in words.
        self.action = "stopped"
        #: Drive keys pressed, and when the first was.
        self.keys = 0
        self.first_key_s: float | None = None
        #: A quit key was pressed.
        self.quit = False
        self._last_key_s = -math.inf

    def press(self, action: str, now: float) -> None:
        """Do what one key means, at loop time ``now``.

        Raises:
            InvalidArgumentError: Not one of :data:`ACTIONS`.
            OhmniError: What the robot raised for the command (an emergency stop latched,
                the robot closed, a remote robot's lease held by another).
        """
        if action == "quit":
            self.quit = True
            return
        if action in ("faster", "slower"):
            factor = SCALE_STEP if action == "faster" else 1 / SCALE_STEP
            self.linear_mps = min(
                self.top_linear_mps, max(_MIN_LINEAR_MPS, self.linear_mps * factor)
            )
            self.angular_radps = min(
                self.top_angular_radps, max(_MIN_ANGULAR_RADPS, self.angular_radps * factor)
            )
            return
        if action == "stop":
            self._robot.stop()
            self.command, self.action, self._last_key_s = (0.0, 0.0), "stopped (space)", -math.inf
            return
        moves = {
            "forward": (self.linear_mps, 0.0),
            "back": (-self.linear_mps, 0.0),
            "left": (0.0, self.angular_radps),
            "right": (0.0, -self.angular_radps),
        }
        if action not in moves:
            raise InvalidArgumentError(
                f"no teleop action {action!r}: the actions are {', '.join(ACTIONS)}"
            )
        linear, angular = moves[action]
        self._robot.drive(linear, angular)
        self.command, self.action, self._last_key_s = (linear, angular), action, now
        self.keys += 1
        if self.first_key_s is None:
            self.first_key_s = now

    def decay(self, now: float) -> None:
        """No key within ``hold_s`` of ``now``: the command is over and the robot stops."""
        if self.command != (0.0, 0.0) and now - self._last_key_s > self.hold_s:
            self._robot.stop()
            self.command = (0.0, 0.0)
            self.action = f"stopped (no key for {self.hold_s:g} s)"
