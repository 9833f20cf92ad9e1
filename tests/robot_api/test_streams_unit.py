"""The Robot's plumbing on its own: :class:`Topic` / :class:`Subscription` fan-out, and
:class:`Periodic` cycles against a fake bus on the virtual clock.

The fake bus resolves each slot after a set time and can make the event loop late (it
moves the virtual clock inside a callback, as a slow callback would), so drift, skipping
and the in-flight limit show exactly.
"""

from __future__ import annotations

import asyncio
import gc
import itertools
import random
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, TypeVar, cast

import pytest

from ohmni_tb.bus import Bus, ReplyPacket
from ohmni_tb.errors import DeadlineMissedError, OutOfRangeError
from ohmni_tb.eventloop import line_clock
from ohmni_tb.protocol import Packet
from ohmni_tb.protocol.drive import read_count
from ohmni_tb.robot.schedule import MAX_IN_FLIGHT, CycleResult, Periodic
from ohmni_tb.robot.streams import Subscription, Topic
from ohmni_tb.sim.clock import VirtualClockLoop, run_virtual

T = TypeVar("T")

PACKET = read_count(0)


def virtual(main: Callable[[], Coroutine[Any, Any, T]]) -> T:
    return run_virtual(main())


def drain(subscription: Subscription[T]) -> list[T]:
    out = []
    while (item := subscription.get_nowait()) is not None:
        out.append(item)
    return out


# -- Topic and Subscription ------------------------------------------------------------------


def test_a_full_subscription_drops_its_oldest_and_counts_it() -> None:
    topic: Topic[int] = Topic("wheel_encoder", 50.0)
    small = topic.subscribe(maxlen=3)
    big = topic.subscribe(maxlen=100)
    for i in range(10):
        topic.publish(i, stamp_s=i * 0.02)

    assert drain(small) == [7, 8, 9]
    assert small.dropped == 7
    assert drain(big) == list(range(10))
    assert big.dropped == 0
    stats = topic.stats(now_s=0.2)
    assert stats.dropped == 7
    assert stats.samples == 10
    assert stats.subscribers == 2
    assert topic.latest == 9


def test_get_nowait_is_none_when_empty_and_pending_counts() -> None:
    topic: Topic[str] = Topic("robot_state")
    subscription = topic.subscribe()
    assert subscription.get_nowait() is None
    assert subscription.pending == 0
    topic.publish("a", 0.0)
    topic.publish("b", 0.1)
    assert subscription.pending == 2
    assert subscription.get_nowait() == "a"
    assert subscription.pending == 1
    assert subscription.name == "robot_state"


def test_a_subscription_sees_only_samples_after_it_subscribed() -> None:
    topic: Topic[int] = Topic("tbcore_status")
    topic.publish(1, 0.0)
    subscription = topic.subscribe()
    topic.publish(2, 0.1)
    assert drain(subscription) == [2]
    assert topic.latest == 2


def test_maxlen_out_of_range_is_refused() -> None:
    topic: Topic[int] = Topic("wheel_odom")
    with pytest.raises(OutOfRangeError, match="maxlen"):
        topic.subscribe(maxlen=0)
    with pytest.raises(OutOfRangeError, match="maxlen"):
        topic.subscribe(maxlen=100_001)


def test_close_ends_a_waiting_reader_after_the_queued_samples() -> None:
    async def main() -> list[int]:
        topic: Topic[int] = Topic("wheel_encoder")
        subscription = topic.subscribe()
        got: list[int] = []

        async def read() -> None:
            got.extend([sample async for sample in subscription])

        async with asyncio.TaskGroup() as tg:
            reader = tg.create_task(read())
            await asyncio.sleep(0.1)  # the reader now waits for a sample
            topic.publish(1, 0.0)
            topic.publish(2, 0.0)
            topic.close()
            topic.publish(3, 0.0)  # after close: not delivered
            await asyncio.sleep(0.1)
            assert reader.done()
        assert subscription.closed
        assert topic.stats(0.2).subscribers == 0
        return got

    assert virtual(main) == [1, 2]


def test_a_reader_waiting_wakes_on_publish() -> None:
    async def main() -> None:
        topic: Topic[int] = Topic("wheel_encoder")
        subscription = topic.subscribe()
        loop = asyncio.get_running_loop()
        loop.call_later(0.5, topic.publish, 7, 0.5)
        t0 = loop.time()
        assert await anext(subscription) == 7
        assert loop.time() - t0 == pytest.approx(0.5)

    virtual(main)


def test_the_async_context_manager_closes_the_subscription() -> None:
    async def main() -> None:
        topic: Topic[int] = Topic("wheel_encoder")
        async with topic.subscribe() as subscription:
            topic.publish(1, 0.0)
            assert topic.stats(0.0).subscribers == 1
        assert subscription.closed
        assert topic.stats(0.0).subscribers == 0
        topic.publish(2, 0.0)
        assert drain(subscription) == [1]
        subscription.close()  # idempotent

    virtual(main)


def test_an_abandoned_subscription_is_released() -> None:
    topic: Topic[int] = Topic("wheel_encoder")
    kept = topic.subscribe()
    abandoned = topic.subscribe(maxlen=2)
    topic.publish(0, 0.0)
    assert topic.stats(0.0).subscribers == 2
    del abandoned
    gc.collect()
    assert topic.stats(0.0).subscribers == 1
    for i in range(1, 10):
        topic.publish(i, i * 0.02)
    # Nobody holds the abandoned one any more: it no longer costs drops.
    assert topic.stats(0.2).dropped == 0
    assert drain(kept) == list(range(10))


def test_the_achieved_rate_decays_to_zero_after_the_stream_stops() -> None:
    topic: Topic[int] = Topic("wheel_encoder", 50.0)
    period = 0.02
    for k in range(101):  # 2 s at 50 Hz, the last at t = 2.0
        topic.publish(k, k * period)
    running = topic.stats(now_s=2.0 + period / 2).achieved_hz
    assert running == pytest.approx(50.0, rel=1e-6)

    rates = [topic.stats(now_s=2.0 + dt).achieved_hz for dt in (0.1, 0.5, 1.0, 2.0, 4.0)]
    assert all(a > b for a, b in itertools.pairwise(rates)), rates
    assert rates[0] < running
    assert topic.stats(now_s=2.0 + 5.1).achieved_hz == 0.0
    assert topic.stats(now_s=100.0).achieved_hz == 0.0


def test_stats_report_lateness_percentiles_and_the_requested_rate() -> None:
    topic: Topic[int] = Topic("servo_neck", 30.0)
    assert topic.stats(0.0).jitter_p50_ms is None
    for late_ms in range(1, 101):
        topic.note_lateness(late_ms / 1000)
    stats = topic.stats(0.0)
    assert stats.jitter_p50_ms is not None
    assert stats.jitter_p99_ms is not None
    assert 45 <= stats.jitter_p50_ms <= 55
    assert 95 <= stats.jitter_p99_ms <= 100
    assert stats.requested_hz == 30.0
    topic.enabled = False
    assert topic.stats(0.0).requested_hz == 0.0


# -- Periodic against a fake bus ---------------------------------------------------------------


class FakeSlot:
    """What Periodic reads of a slot: started, finished, cancelled, its error or results."""

    def __init__(self) -> None:
        self.started_at: float | None = None
        self.finished = False
        self.cancelled = False
        self.error: BaseException | None = None
        self.results: list[ReplyPacket | None] = []
        self.tag: object = None
        self.seq = 0
        self.on_done: Callable[[FakeSlot], None] | None = None


class FakeBus:
    """Answers every slot ``busy_s`` after its submission (``None`` per packet).

    ``stall_s`` (a callable of the submission count) moves the virtual clock forward
    inside ``submit``: the event loop spent that long before it got round to the next
    timer, as a slow callback would make it.
    """

    def __init__(
        self,
        loop: VirtualClockLoop,
        *,
        busy_s: float = 0.005,
        stall_s: Callable[[int], float] = lambda n: 0.0,
        fail: BaseException | None = None,
    ) -> None:
        self.loop = loop
        self.clock = line_clock(loop)
        self.busy_s = busy_s
        self.stall_s = stall_s
        self.fail = fail
        self.submitted: list[tuple[float, float | None, int]] = []  # (now, deadline, prio)
        self.not_before: list[float | None] = []
        self.slots_made = 0
        self._priority: dict[int, int] = {}

    def submit(
        self,
        packets: Sequence[Packet],
        *,
        priority: int = 0,
        deadline: float | None = None,
        on_done: Callable[[FakeSlot], None] | None = None,
        not_before: float | None = None,
        tag: object = None,
    ) -> FakeSlot:
        self.slots_made += 1
        slot = FakeSlot()
        self._priority[id(slot)] = priority
        return self.resubmit(
            slot, packets, deadline=deadline, not_before=not_before, on_done=on_done, tag=tag
        )

    def resubmit(
        self,
        slot: FakeSlot,
        packets: Sequence[Packet],
        *,
        deadline: float | None = None,
        not_before: float | None = None,
        on_done: Callable[[FakeSlot], None] | None = None,
        tag: object = None,
    ) -> FakeSlot:
        now = self.loop.time()
        self.submitted.append((now, deadline, self._priority[id(slot)]))
        self.not_before.append(not_before)
        start = now if not_before is None else max(now, not_before)
        slot.seq += 1
        seq = slot.seq
        slot.started_at = now if start == now else None
        slot.finished = slot.cancelled = False
        slot.error = None
        slot.results = []
        slot.tag = tag
        slot.on_done = on_done

        def begin() -> None:
            if slot.seq == seq and not slot.finished:
                slot.started_at = self.loop.time()

        def complete() -> None:
            # As the bus does: the slot finishes, then on_done runs at once.
            if slot.seq != seq or slot.finished:
                return
            slot.finished = True
            if self.fail is not None:
                slot.error = self.fail
            else:
                slot.results = [None] * len(packets)
            if slot.on_done is not None:
                slot.on_done(slot)

        if start > now:
            self.loop.call_at(start, begin)
        self.loop.call_at(start + self.busy_s, complete)
        self.loop.advance(self.stall_s(len(self.submitted)))
        return slot

    def cancel(self, slot: FakeSlot) -> None:
        if not slot.finished:
            slot.finished = slot.cancelled = True
            slot.on_done = None


class Recorder:
    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self.built: list[tuple[float, float]] = []  # (due, loop time at build)
        self.results: list[CycleResult] = []
        self.failures: list[tuple[float, BaseException]] = []
        self.skipped = 0

    def build(self, due: float) -> list[Packet]:
        self.built.append((due, self.loop.time()))
        return [PACKET]

    def skip(self, n: int) -> None:
        self.skipped += n

    def periodic(
        self, bus: FakeBus, hz: float, phase_s: float = 0.003, *, ahead: bool = False
    ) -> Periodic:
        return Periodic(
            cast("Bus", bus),
            "test",
            hz,
            phase_s=phase_s,
            priority=10,
            slack_s=0.5 / hz,
            build=self.build,
            handle=self.results.append,
            fail=lambda due, exc: self.failures.append((due, exc)),
            skipped=self.skip,
            ahead=ahead,
        )


def running_loop() -> VirtualClockLoop:
    loop = asyncio.get_running_loop()
    assert isinstance(loop, VirtualClockLoop)
    return loop


def test_the_phase_never_drifts_over_ten_thousand_cycles() -> None:
    hz = 50.0
    period = 1 / hz
    cycles = 10_000

    async def main() -> tuple[Recorder, float, int]:
        loop = running_loop()
        rng = random.Random(1)
        # Every wake-up costs the loop up to 40 % of a period: a schedule that adds the
        # period to the time it woke would lose about 20 % of a period a cycle.
        bus = FakeBus(loop, stall_s=lambda n: rng.uniform(0.0, 0.4 * period))
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, hz)
        t0 = loop.time() + 0.001
        periodic.start(t0)
        await asyncio.sleep(0.001 + 0.003 + (cycles - 0.5) * period)
        periodic.stop()
        await asyncio.sleep(0.1)
        return recorder, t0 + 0.003, bus.slots_made

    recorder, first_due, slots_made = virtual(main)
    assert len(recorder.built) == cycles
    assert slots_made <= 2  # each cycle goes in a slot used before (at most two in flight)
    assert recorder.skipped == 0
    assert len(recorder.results) == cycles
    for k, (due, built_at) in enumerate(recorder.built):
        expected = first_due + k * period
        assert due == pytest.approx(expected, abs=1e-9), k
        assert 0.0 <= built_at - due < period / 2, k
    last_due = recorder.built[-1][0]
    assert last_due - first_due == pytest.approx((cycles - 1) * period, abs=1e-9)
    # Each result carries its due time and the slot's start.
    assert [r.due_s for r in recorder.results] == [due for due, _ in recorder.built]


def test_a_late_loop_skips_the_missed_cycles_and_counts_them() -> None:
    hz = 50.0
    period = 1 / hz

    async def main() -> Recorder:
        loop = running_loop()
        # On the 10th cycle the loop stalls for 2.5 periods.
        bus = FakeBus(loop, stall_s=lambda n: 2.5 * period if n == 10 else 0.0)
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, hz, phase_s=0.0)
        periodic.start(loop.time())
        await asyncio.sleep(20.5 * period)
        periodic.stop()
        await asyncio.sleep(0.1)
        return recorder

    recorder = virtual(main)
    first = recorder.built[0][0]
    ks = [round((due - first) / period) for due, _ in recorder.built]
    # The loop woke at 11.5 periods: cycle 10 is skipped and counted, the latest due
    # one (11) goes at once, and the grid carries on; no burst of the missed cycles.
    assert ks == [k for k in range(21) if k != 10]
    assert recorder.skipped == 1
    built_at = {k: at - first for k, (_, at) in zip(ks, recorder.built, strict=True)}
    assert built_at[11] == pytest.approx(11.5 * period)
    assert built_at[12] == pytest.approx(12 * period)
    gaps = [b - a for a, b in itertools.pairwise(built_at.values())]
    assert min(gaps) >= period / 2 - 1e-9


def test_a_third_cycle_is_skipped_while_two_are_in_flight() -> None:
    hz = 50.0
    period = 1 / hz

    async def main() -> Recorder:
        loop = running_loop()
        # Each slot takes 2.5 periods to come back: cycles k and k+1 are still out at k+2.
        bus = FakeBus(loop, busy_s=2.5 * period)
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, hz, phase_s=0.0)
        periodic.start(loop.time())
        await asyncio.sleep(29.5 * period)
        periodic.stop()
        await asyncio.sleep(0.2)
        return recorder

    recorder = virtual(main)
    assert MAX_IN_FLIGHT == 2
    assert len(recorder.built) == 20  # two of every three cycles went out
    assert recorder.skipped == 10
    assert len(recorder.results) == 20


def test_a_missed_deadline_counts_as_skipped_and_other_errors_as_failures() -> None:
    async def main() -> tuple[Recorder, Recorder]:
        loop = running_loop()
        late = Recorder(loop)
        late_bus = FakeBus(loop, fail=DeadlineMissedError(deadline=0.0, late_s=0.001))
        broken = Recorder(loop)
        broken_bus = FakeBus(loop, fail=OSError("boom"))
        a = late.periodic(late_bus, 10.0)
        b = broken.periodic(broken_bus, 10.0)
        a.start(loop.time())
        b.start(loop.time())
        await asyncio.sleep(0.95)
        a.stop()
        b.stop()
        await asyncio.sleep(0.1)
        return late, broken

    late, broken = virtual(main)
    assert late.skipped == 10
    assert late.results == []
    assert late.failures == []
    assert broken.skipped == 0
    assert len(broken.failures) == 10
    assert all(isinstance(exc, OSError) for _, exc in broken.failures)


def test_set_rate_keeps_the_next_due_time_and_uses_the_new_period() -> None:
    async def main() -> tuple[list[float], float]:
        loop = running_loop()
        recorder = Recorder(loop)
        periodic = recorder.periodic(FakeBus(loop), 10.0, phase_s=0.0)
        periodic.start(loop.time())
        await asyncio.sleep(0.25)  # due 0, 0.1, 0.2 done; next 0.3
        next_due = periodic.next_due_s
        periodic.set_rate(5.0)
        assert periodic.next_due_s == pytest.approx(next_due)
        await asyncio.sleep(1.0)
        periodic.stop()
        return [due for due, _ in recorder.built], next_due

    dues, switch = virtual(main)
    before = [d for d in dues if d < switch - 1e-9]
    after = [d for d in dues if d >= switch - 1e-9]
    assert len(before) == 3
    assert after[0] == pytest.approx(switch)
    assert [b - a for a, b in itertools.pairwise(after)] == pytest.approx([0.2] * (len(after) - 1))


def test_a_stopped_periodic_sends_nothing_and_its_slots_finish() -> None:
    async def main() -> Recorder:
        loop = running_loop()
        recorder = Recorder(loop)
        periodic = recorder.periodic(FakeBus(loop, busy_s=0.015), 50.0, phase_s=0.0)
        periodic.start(loop.time())
        await asyncio.sleep(0.101)
        periodic.stop()
        assert not periodic.running
        sent = len(recorder.built)
        await asyncio.sleep(1.0)
        assert len(recorder.built) == sent
        return recorder

    recorder = virtual(main)
    assert len(recorder.built) == 6  # due at 0, 20, 40, 60, 80, 100 ms
    assert len(recorder.results) == 6


# -- cycles queued on the bus ahead of their due times ---------------------------------------


def test_cycles_queued_ahead_keep_the_grid_and_need_no_timer_between_them() -> None:
    hz = 30.0
    period = 1 / hz
    cycles = 300

    async def main() -> tuple[Recorder, FakeBus, float, list[bool]]:
        loop = running_loop()
        bus = FakeBus(loop, busy_s=0.004)
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, hz, ahead=True)
        t0 = loop.time() + 0.001
        periodic.start(t0)
        timers: list[bool] = []
        for _ in range(10):
            await asyncio.sleep(cycles * period / 10)
            timers.append(periodic._timer is not None)
        periodic.stop()
        await asyncio.sleep(0.1)
        return recorder, bus, t0 + 0.003, timers

    recorder, bus, first_due, timers = virtual(main)
    dues = [due for due, _ in recorder.built]
    assert dues == pytest.approx([first_due + k * period for k in range(len(dues))], abs=1e-9)
    # The first cycle goes from the timer; each later one is queued as its predecessor
    # completes, to start at its due time: no timer of the stream's own in between.
    assert bus.not_before[0] is None
    assert bus.not_before[1:] == pytest.approx(dues[1:], abs=1e-9)
    assert timers == [False] * 10
    assert all(built_at < due for due, built_at in recorder.built[1:])
    assert [r.started_s for r in recorder.results] == pytest.approx(dues[: len(recorder.results)])
    assert recorder.skipped == 0
    assert len(recorder.results) >= cycles - 1


def test_stop_withdraws_the_cycle_queued_ahead_and_start_goes_on_from_the_grid() -> None:
    hz = 50.0
    period = 1 / hz

    async def main() -> tuple[Recorder, FakeBus, float, int]:
        loop = running_loop()
        bus = FakeBus(loop, busy_s=0.004)
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, hz, phase_s=0.0, ahead=True)
        t0 = loop.time()
        periodic.start(t0)
        await asyncio.sleep(10.5 * period)  # cycles 0..10 done, 11 queued ahead
        periodic.stop()
        await asyncio.sleep(5 * period)
        results_while_stopped = len(recorder.results)
        periodic.start(t0)  # the same origin: from the next due cycle on
        await asyncio.sleep(4.2 * period)
        periodic.stop()
        await asyncio.sleep(0.1)
        return recorder, bus, t0, results_while_stopped

    recorder, bus, t0, results_while_stopped = virtual(main)
    assert results_while_stopped == 11  # the cycle queued ahead never ran
    done = [round((r.due_s - t0) / period) for r in recorder.results]
    # After the restart at 15.5 periods: cycles 16..19 (and 20, queued, withdrawn at 19.7).
    assert done == [*range(11), 16, 17, 18, 19]
    assert len(bus.submitted) == 17  # 11 and 20 were queued, and withdrawn unrun
    assert recorder.skipped == 0


def test_set_rate_with_a_cycle_queued_ahead_keeps_its_due_time() -> None:
    async def main() -> tuple[list[float], float]:
        loop = running_loop()
        bus = FakeBus(loop, busy_s=0.002)
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, 10.0, phase_s=0.0, ahead=True)
        t0 = loop.time()
        periodic.start(t0)
        await asyncio.sleep(0.25)  # cycles at 0, 0.1, 0.2 done; 0.3 queued
        periodic.set_rate(20.0)
        await asyncio.sleep(0.24)
        periodic.stop()
        await asyncio.sleep(0.1)
        return [r.due_s - t0 for r in recorder.results], t0

    dues, _ = virtual(main)
    # 0.3 stays the next due time (queued anew), then every 0.05 s.
    assert dues == pytest.approx([0.0, 0.1, 0.2, 0.3, 0.35, 0.4, 0.45])


def test_a_cycle_queued_ahead_that_comes_back_late_starts_the_next_at_once() -> None:
    hz = 50.0
    period = 1 / hz

    async def main() -> tuple[Recorder, float]:
        loop = running_loop()
        # Each slot takes 1.55 periods: one cycle at a time, as identical reads go.
        bus = FakeBus(loop, busy_s=1.55 * period)
        recorder = Recorder(loop)
        periodic = recorder.periodic(bus, hz, phase_s=0.0, ahead=True)
        t0 = loop.time()
        periodic.start(t0)
        await asyncio.sleep(11.9 * period)
        periodic.stop()
        await asyncio.sleep(0.2)
        return recorder, t0

    recorder, t0 = virtual(main)
    done = [round((r.due_s - t0) / period) for r in recorder.results]
    started = [(r.started_s - r.due_s) / period for r in recorder.results]
    # Cycle 0 comes back at 1.55: cycle 1 goes at once (0.55 of a period late) and comes
    # back at 3.1; cycle 2 is then over a period late: skipped and counted, 3 goes at once.
    assert done == [0, 1, 3, 4, 6, 7, 9, 10]
    assert started == pytest.approx([0.0, 0.55, 0.1, 0.65, 0.2, 0.75, 0.3, 0.85])
    assert recorder.skipped == 3  # 2, 5 and 8


def test_cycles_queued_ahead_report_failures_and_go_on() -> None:
    async def main() -> Recorder:
        loop = running_loop()
        broken = Recorder(loop)
        periodic = broken.periodic(FakeBus(loop, fail=OSError("boom")), 10.0, ahead=True)
        periodic.start(loop.time())
        await asyncio.sleep(0.95)
        periodic.stop()
        await asyncio.sleep(0.1)
        return broken

    broken = virtual(main)
    assert broken.skipped == 0
    assert len(broken.failures) == 10
    assert all(isinstance(exc, OSError) for _, exc in broken.failures)
