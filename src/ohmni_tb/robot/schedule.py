"""Fixed-rate cycles on absolute deadlines, each one bus slot, without a task per cycle.

A :class:`Periodic` arms one ``loop.call_at`` timer for its next due time. When it fires
it builds the cycle's packets (so a wheel command is computed at send time, not a period
earlier), submits them as one slot (:meth:`ohmni_tb.bus.Bus.submit`) with a deadline,
and arms the next due time: ``t0 + phase + k · period`` for whole ``k``, so the phase
never drifts. The slot's result comes back through a done-callback. A cycle is skipped
(and counted) when two of its predecessors are still in flight, when its slot cannot
start before its deadline, or when the loop woke more than a period late.

A cycle whose packets do not depend on when they go (``ahead=True``: the feedback
reads) needs no timer of its own: as each cycle completes, the next one is queued on
the bus at once with ``not_before`` its due time. The bus starts it from whatever wakes
it by then — a reply, the line freeing — and sets a timer only when the line is idle at
that time. On a line busy most of the time that is one wake-up of the event loop fewer
for most cycles (``bench/robot.py`` counts them).

Each cycle's slot is one the stream has used before, once it has completed
(:meth:`~ohmni_tb.bus.Bus.resubmit`): a stream makes its two slots once.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from ohmni_tb.bus import Bus, ReplyPacket, Slot
from ohmni_tb.errors import DeadlineMissedError, OhmniError, StateError, TransportError
from ohmni_tb.protocol import Packet

__all__ = ["CycleResult", "Periodic"]

_log = logging.getLogger(__name__)

#: Cycles of one stream in flight at once: a cycle may still wait for its replies (an
#: adapter may hold them 16 ms of a 20 ms period) when the next one is due.
MAX_IN_FLIGHT = 2


@dataclass(frozen=True, slots=True)
class CycleResult:
    """What one cycle brought back.

    Attributes:
        due_s: When the cycle was due.
        started_s: When its first packet went on the wire.
        replies: One reply (or ``None``) per packet.
    """

    due_s: float
    started_s: float
    replies: list[ReplyPacket | None]


Build = Callable[[float], Sequence[Packet] | None]
Handle = Callable[[CycleResult], None]
Fail = Callable[[float, BaseException], None]


class Periodic:
    """One stream's cycles on the bus (module docstring).

    Args:
        bus: The bus the slots go on.
        name: For logs.
        hz: Cycles per second, > 0.
        phase_s: Offset of the cycles from the schedule's origin.
        priority: The slots' bus priority.
        slack_s: How long after its due time a cycle's slot may still start.
        build: Called at the due time with it; returns the packets (``None``: skip).
        handle: Called with the result of a cycle whose slot ran.
        fail: Called with the due time and the error of a cycle that did not run.
        skipped: Called once per cycle skipped without a slot.
        ahead: Queue each cycle on the bus ahead of its due time, from the previous
            cycle's completion (module docstring); for packets that do not depend on
            the time they go.
    """

    def __init__(
        self,
        bus: Bus,
        name: str,
        hz: float,
        *,
        phase_s: float,
        priority: int,
        slack_s: float,
        build: Build,
        handle: Handle,
        fail: Fail,
        skipped: Callable[[int], None],
        ahead: bool = False,
    ) -> None:
        self.bus = bus
        self.ahead = ahead
        self.name = name
        self.period_s = 1.0 / hz
        self.phase_s = phase_s
        self.priority = priority
        self.slack_s = slack_s
        self._build = build
        self._handle = handle
        self._fail = fail
        self._skipped = skipped
        self._t0 = 0.0
        self._k = 0
        self._timer: asyncio.TimerHandle | None = None
        self._in_flight: set[Slot] = set()
        #: Cycles queued ahead: their due times.
        self._ahead_due: dict[Slot, float] = {}
        #: Slots of cycles that have completed, for the next cycles (Bus.resubmit).
        self._spare: list[Slot] = []
        self._on_done = self._done
        self._submitting = False
        self.running = False

    def start(self, t0: float) -> None:
        """Run from the schedule origin ``t0`` (loop time), the first cycle at t0 + phase."""
        self.stop()
        self._t0 = t0 + self.phase_s
        self._k = 0
        now = self.bus.clock.now()
        if now > self._t0:
            self._k = math.ceil((now - self._t0) / self.period_s - 1e-9)
        self.running = True
        self._arm()

    def stop(self) -> None:
        """Stop firing; cycles in flight finish (a cycle queued ahead and not yet due is
        withdrawn: it stands for the timer)."""
        self.running = False
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._ahead_due:
            now = self.bus.clock.now()
            for slot, due in list(self._ahead_due.items()):
                if slot.started_at is None and due > now:
                    self._withdraw(slot)

    def set_rate(self, hz: float) -> None:
        """Change the rate, keeping the phase of the next due time."""
        was = self.running
        self.stop()
        next_due = self._due(self._k)
        self.period_s = 1.0 / hz
        self._t0 = next_due
        self._k = 0
        if was:
            self.running = True
            self._arm()

    def unstarted(self) -> Slot | None:
        """The newest cycle's slot if it is still waiting for the line, else ``None``."""
        newest: Slot | None = None
        for slot in self._in_flight:
            if slot.started_at is None and (newest is None or slot.seq > newest.seq):
                newest = slot
        return newest

    def withdraw_unstarted(self) -> None:
        """Withdraw the slots not yet on the wire (an emergency stop must not be followed
        by a wheel command computed before it)."""
        for slot in list(self._in_flight):
            if slot.started_at is None:
                self._withdraw(slot)
        self._resume()

    def cancel_in_flight(self) -> None:
        """Withdraw the slots still waiting (those on the wire finish)."""
        for slot in list(self._in_flight):
            self._withdraw(slot)
        self._resume()

    def _withdraw(self, slot: Slot) -> None:
        self.bus.cancel(slot)  # its on_done is not called
        self._in_flight.discard(slot)
        due = self._ahead_due.pop(slot, None)
        if due is not None and due > self.bus.clock.now():
            self._k -= 1  # a cycle queued ahead, not yet due: it is the next one again

    def _resume(self) -> None:
        """Cycles queued ahead were the timer: with none left, the timer runs again."""
        if self.ahead and self.running and self._timer is None and not self._in_flight:
            self._arm()

    @property
    def next_due_s(self) -> float:
        """When the next cycle is due."""
        return self._due(self._k)

    def _due(self, k: int) -> float:
        return self._t0 + k * self.period_s

    def _arm(self) -> None:
        # The bus's clock: the line's time, and a timer that does not fire before it.
        self._timer = self.bus.clock.call_at(self._due(self._k), self._fire)

    def _fire(self) -> None:
        self._timer = None
        if not self.running:
            return
        self._cycle(self.bus.clock.now())

    def _cycle(self, now: float) -> None:
        """Submit the next due cycle (at its time, or ahead of it), and arm the timer
        unless the cycle queued ahead stands for it."""
        due = self._due(self._k)
        late_cycles = math.floor((now - due) / self.period_s)
        if late_cycles >= 1:
            # The loop woke more than a period late: skip to the latest due cycle.
            self._skipped(late_cycles)
            self._k += late_cycles
            due = self._due(self._k)
        self._k += 1
        queued = False
        try:
            if len(self._in_flight) >= MAX_IN_FLIGHT:
                self._skipped(1)
                return
            packets = self._build(due)
            if packets is None:
                return
            ahead = self.ahead and due > now
            self._submitting = True
            try:
                spare = self._spare
                if spare:
                    slot = self.bus.resubmit(
                        spare.pop(),
                        packets,
                        deadline=due + self.slack_s,
                        not_before=due if ahead else None,
                        on_done=self._on_done,
                        tag=due,
                    )
                else:
                    slot = self.bus.submit(
                        packets,
                        priority=self.priority,
                        deadline=due + self.slack_s,
                        on_done=self._on_done,
                        not_before=due if ahead else None,
                        tag=due,
                    )
            finally:
                self._submitting = False
            if not slot.finished:
                self._in_flight.add(slot)
                if self.ahead:
                    # Its completion queues the next cycle: no timer needed meanwhile.
                    queued = True
                    if ahead:
                        self._ahead_due[slot] = due
        except (TransportError, StateError) as exc:
            # The link is down or the bus closed: the Robot's link watcher takes over.
            self._fail(due, exc)
            return
        except OhmniError:
            _log.exception("%s: cycle at %.3f could not be built", self.name, due)
            self._skipped(1)
            return
        finally:
            if self.running and not queued:
                self._arm()

    def _done(self, slot: Slot) -> None:
        # Called from inside the bus as the slot completes: no loop pass in between.
        due: float = slot.tag  # type: ignore[assignment]  # _cycle tags each slot with it
        self._in_flight.discard(slot)
        self._ahead_due.pop(slot, None)
        try:
            if slot.cancelled:
                return
            exc = slot.error
            if exc is not None:
                if isinstance(exc, DeadlineMissedError):
                    self._skipped(1)
                else:
                    self._fail(due, exc)
                return
            started = slot.started_at
            self._handle(CycleResult(due, due if started is None else started, slot.results))
        finally:
            # Done with it: the slot of a cycle to come (resubmit resets it).
            self._spare.append(slot)
            if (
                self.ahead
                and self.running
                and not self._submitting  # settled inside submit: _cycle arms the timer
                and self._timer is None
                and not self._in_flight
            ):
                # The next cycle, queued now for its due time.
                self._cycle(self.bus.clock.now())
