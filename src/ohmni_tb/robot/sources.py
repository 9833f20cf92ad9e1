"""The Robot's command sources: which source's drive commands are taken, on the loop's time.

The table and the rule are :mod:`ohmni_tb.control.sources` (sans-IO); this part feeds it
each drive command's and goal's source with the loop's clock, refuses a command from
a lower source with :class:`~ohmni_tb.errors.SourceOverriddenError` before anything is
sent, and publishes ``robot_state`` when the source that drives changes: at once when a
source takes over, and on a timer of its own when one lapses (nothing runs in the
control tick).

The watchdog and the sources agree: no source live means the robot stands. A source
whose timeout is ``watchdog_s`` or longer (the default table's) lapses as the watchdog
stops the robot or after. One whose timeout is shorter lapses first: if the robot still
follows its last command then, the target goes to zero at once, as the watchdog would
later. With the watchdog off (``watchdog_s=0``) a lapse changes only who may drive.
"""

from __future__ import annotations

import asyncio
import logging
import math

from ohmni_tb.control.sources import DEFAULT_SOURCE
from ohmni_tb.errors import ConfigError, InvalidArgumentError, SourceOverriddenError
from ohmni_tb.robot.control_loop import ControlLoop
from ohmni_tb.robot.state import RobotState

__all__ = ["CommandSources"]

_log = logging.getLogger(__name__)


class CommandSources:
    """The command sources' part of the Robot (module docstring).

    Args:
        state: The Robot's shared state (its ``sources`` mux, its loop, ``robot_state``).
        control: The control loop, stopped when the source that drives lapses.
    """

    def __init__(self, state: RobotState, control: ControlLoop) -> None:
        self._state = state
        self._mux = state.sources
        self._loop = state.loop
        self._control = control
        watchdog_s = state.config.watchdog_s
        #: The sources that lapse before the watchdog would stop the robot: a lapse of
        #: one of them stops it.
        self._stop_on_lapse = frozenset(
            row.name for row in self._mux.table if watchdog_s > 0 and row.timeout_s < watchdog_s
        )
        #: The source a command names when it names none (``Robot.open(source=…)``).
        self.default = DEFAULT_SOURCE
        # The active source as last published, and the timer of its lapse.
        self._shown: str | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._timer_due = math.inf

    def set_default(self, source: str) -> None:
        """The source of the commands that name none.

        Raises:
            ConfigError: Not a source of the table.
        """
        try:
            self.default = self._mux.check_name(source)
        except InvalidArgumentError as exc:
            raise ConfigError(str(exc)) from None

    def name(self, source: str | None) -> str:
        """The source a command names (the default for ``None``), checked.

        Raises:
            InvalidArgumentError: Not a source of the table; the message lists them.
        """
        return self.default if source is None else self._mux.check_name(source)

    def check(self, source: str, what: str) -> None:
        """Refuse ``what`` from ``source`` while a higher source drives; nothing changes.

        Raises:
            SourceOverriddenError: A higher source is live.
        """
        now = self._loop.time()
        blocker = self._mux.blocker(source, now)
        if blocker is not None:
            raise self._refusal(source, blocker, what, now)

    def take(self, source: str, what: str) -> None:
        """A drive command ``what`` from ``source``: taken (the source is live from now),
        or refused with nothing changed.

        Raises:
            SourceOverriddenError: A higher source is live.
        """
        now = self._loop.time()
        blocker = self._mux.take(source, now)
        if blocker is not None:
            raise self._refusal(source, blocker, what, now)
        if source != self._shown:
            self._changed(now)
        elif self._timer is None:
            self._arm(now)

    def stop(self, source: str) -> None:
        """A stop from ``source``: never refused (the caller obeys it); it takes over like
        a drive command when no higher source is live, else changes nothing here."""
        now = self._loop.time()
        if self._mux.take(source, now) is None:
            self._changed(now)

    def hold(self, source: str) -> None:
        """A motion goal of ``source`` starts: the source stays live until it ends."""
        self._mux.hold(source)
        self._changed(self._loop.time())

    def release(self, source: str) -> None:
        """That goal ended: the source lives its timeout from now."""
        now = self._loop.time()
        self._mux.release(source, now)
        self._changed(now)

    def close(self) -> None:
        """The Robot closes: no more lapse events."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    # -- internals -------------------------------------------------------------------------

    def _refusal(self, source: str, active: str, what: str, now: float) -> SourceOverriddenError:
        lapses = self._mux.lapses_at(active)
        if math.isinf(lapses):
            lapses_in = None
            when = "while its motion goal runs"
        else:
            lapses_in = max(0.0, lapses - now)
            when = f"until it lapses, {lapses_in:.2f} s from now without another command of it"
        return SourceOverriddenError(
            f"{what} from source {source!r} refused: source {active!r}, of higher priority, "
            f"drives {when}; nothing was sent",
            source=source,
            active=active,
            lapses_in_s=lapses_in,
        )

    def _changed(self, now: float) -> None:
        """The mux changed: publish a new active source, and time its lapse."""
        active = self._mux.active(now)
        if active != self._shown:
            previous, self._shown = self._shown, active
            if active is None:
                self._state.publish("no command source drives")
            elif previous is None or self._mux.outranks(active, previous):
                over = "" if previous is None else f" (over {previous})"
                self._state.publish(f"command source {active} drives{over}")
            else:
                self._state.publish(f"command source {active} drives ({previous} ended)")
        self._arm(now)

    def _arm(self, now: float) -> None:
        """The timer at the lapse of the source that drives (none while it is held)."""
        active = self._mux.active(now)
        if active is None or self._state.closed:
            return
        due = self._mux.lapses_at(active)
        if math.isinf(due) or (self._timer is not None and self._timer_due <= due):
            return  # held; or the timer comes first and looks again then
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self._loop.call_at(due, self._due)
        self._timer_due = due

    def _due(self) -> None:
        """The timer: the source that drove may have lapsed (or commanded again since)."""
        self._timer = None
        self._timer_due = math.inf
        state = self._state
        if state.closed:
            return
        now = self._loop.time()
        active = self._mux.active(now)
        lapsed = self._shown
        if active != lapsed and lapsed is not None:
            self._shown = active
            timeout = self._mux.table[self._mux.names.index(lapsed)].timeout_s
            after = f"command source {lapsed} lapsed (no command for {timeout:g} s)"
            stopping = ""
            if lapsed in self._stop_on_lapse and self._control.moving():
                # Its last command still drives: no live source, no motion.
                self._control.stop()
                stopping = ", stopping"
            now_drives = f"{active} drives" if active is not None else "no source drives"
            state.publish(f"{after}{stopping}: {now_drives}")
        self._arm(now)
