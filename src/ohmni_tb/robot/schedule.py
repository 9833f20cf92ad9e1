"""Fixed-rate cycles on absolute deadlines, each one bus slot, without a task per cycle.

A :class:`Periodic` arms one ``loop.call_at`` timer for its next due time. When it fires
it builds the cycle's packets (so a wheel command is computed at send time, not a period
earlier), submits them as one slot (:meth:`ohmni_tb.bus.Bus.submit`) with a deadline,
and arms the next due time: ``t0 + phase + k · period`` for whole ``k``, so the phase
never drifts. The slot's result comes back through a done-callback. A cycle is skipped
(and counted) when two of its predecessors are still in flight, when its slot cannot
start before its deadline, or when the loop woke more than a period late.
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
    ) -> None:
        self.bus = bus
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
        self.running = False

    def start(self, t0: float) -> None:
        """Run from the schedule origin ``t0`` (loop time), the first cycle at t0 + phase."""
        self.stop()
        self._t0 = t0 + self.phase_s
        self._k = 0
        now = asyncio.get_running_loop().time()
        if now > self._t0:
            self._k = math.ceil((now - self._t0) / self.period_s - 1e-9)
        self.running = True
        self._arm()

    def stop(self) -> None:
        """Stop firing; cycles in flight finish."""
        self.running = False
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def set_rate(self, hz: float) -> None:
        """Change the rate, keeping the phase of the next due time."""
        was = self.running
        next_due = self._due(self._k)
        self.stop()
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
                self.bus.cancel(slot)
                self._in_flight.discard(slot)

    def cancel_in_flight(self) -> None:
        """Withdraw the slots still waiting (those on the wire finish)."""
        for slot in list(self._in_flight):
            self.bus.cancel(slot)
        self._in_flight.clear()

    @property
    def next_due_s(self) -> float:
        """When the next cycle is due."""
        return self._due(self._k)

    def _due(self, k: int) -> float:
        return self._t0 + k * self.period_s

    def _arm(self) -> None:
        loop = asyncio.get_running_loop()
        self._timer = loop.call_at(self._due(self._k), self._fire)

    def _fire(self) -> None:
        self._timer = None
        if not self.running:
            return
        loop = asyncio.get_running_loop()
        now = loop.time()
        due = self._due(self._k)
        late_cycles = math.floor((now - due) / self.period_s)
        if late_cycles >= 1:
            # The loop woke more than a period late: skip to the latest due cycle.
            self._skipped(late_cycles)
            self._k += late_cycles
            due = self._due(self._k)
        self._k += 1
        try:
            if len(self._in_flight) >= MAX_IN_FLIGHT:
                self._skipped(1)
                return
            packets = self._build(due)
            if packets is None:
                return
            slot = self.bus.submit(
                packets,
                priority=self.priority,
                deadline=due + self.slack_s,
                on_done=lambda done: self._done(done, due),
            )
        except (TransportError, StateError) as exc:
            # The link is down or the bus closed: the Robot's link watcher takes over.
            self._fail(due, exc)
            return
        except OhmniError:
            _log.exception("%s: cycle at %.3f could not be built", self.name, due)
            self._skipped(1)
            return
        finally:
            if self.running:
                self._arm()
        if not slot.future.done():
            self._in_flight.add(slot)

    def _done(self, slot: Slot, due: float) -> None:
        # Called from inside the bus as the slot completes: no loop pass in between.
        self._in_flight.discard(slot)
        future = slot.future
        if future.cancelled():
            return
        exc = future.exception()
        if exc is not None:
            if isinstance(exc, DeadlineMissedError):
                self._skipped(1)
            else:
                self._fail(due, exc)
            return
        started = slot.started_at if slot.started_at is not None else due
        self._handle(CycleResult(due, started, future.result()))
