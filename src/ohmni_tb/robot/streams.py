"""Fan-out of samples: the newest value, bounded subscriptions, and per-stream figures.

A :class:`Topic` never waits for a subscriber: publishing appends to each subscription's
bounded queue, dropping (and counting) the oldest sample when it is full, and wakes a
reader only if one is waiting. A slow consumer loses samples; the schedule never slows.
"""

from __future__ import annotations

import asyncio
import weakref
from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

from ohmni_tb._checks import integer
from ohmni_tb.protocol.connection import percentile

__all__ = ["DEFAULT_QUEUE_SIZE", "StreamStats", "Subscription", "Topic"]

T = TypeVar("T")

#: Samples a subscription keeps before it drops its oldest: 1 s of a 50 Hz stream.
DEFAULT_QUEUE_SIZE = 64
#: Samples behind the achieved rate and jitter figures.
_WINDOW = 512
#: The achieved rate is measured over this much recent time.
_RATE_WINDOW_S = 5.0


@dataclass(frozen=True, slots=True)
class StreamStats:
    """One stream's figures (part of :meth:`Robot.stats`).

    Attributes:
        enabled: Whether the stream runs.
        requested_hz: Its configured rate (0 for event streams).
        achieved_hz: Samples per second over the last few seconds.
        jitter_p50_ms: Median lateness of a cycle's first byte on the wire after its due time.
        jitter_p99_ms: 99th percentile of that lateness.
        samples: Samples published.
        missed: Cycles that went out but did not bring a usable sample.
        skipped: Cycles not sent: the previous ones were still in flight, the slot could
            not start before its deadline, or the loop was late.
        dropped: Samples subscribers lost because they did not keep up.
        subscribers: Live subscriptions.
    """

    enabled: bool
    requested_hz: float
    achieved_hz: float
    jitter_p50_ms: float | None
    jitter_p99_ms: float | None
    samples: int
    missed: int
    skipped: int
    dropped: int
    subscribers: int


class Subscription(Generic[T]):
    """An async iterator over one stream's samples (:meth:`Robot.subscribe`).

    It holds at most ``maxlen`` samples; when the reader falls behind the oldest is
    dropped and counted in :attr:`dropped`. Iteration ends when the Robot closes or
    :meth:`close` is called. Also an async context manager that closes on exit.
    """

    def __init__(self, topic: Topic[T], maxlen: int) -> None:
        self._topic = topic
        self._queue: deque[T] = deque()
        self._maxlen = maxlen
        self._waiter: asyncio.Future[None] | None = None
        self._closed = False
        #: Samples this subscription lost because it did not keep up.
        self.dropped = 0

    @property
    def name(self) -> str:
        """The stream's name."""
        return self._topic.name

    @property
    def pending(self) -> int:
        """Samples waiting to be read."""
        return len(self._queue)

    def _put(self, sample: T) -> None:
        queue = self._queue
        if len(queue) >= self._maxlen:
            queue.popleft()
            self.dropped += 1
            self._topic.dropped += 1
        queue.append(sample)
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    def close(self) -> None:
        """Stop receiving; a waiting reader's iteration ends."""
        if self._closed:
            return
        self._closed = True
        self._topic._subscriptions.discard(self)
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    @property
    def closed(self) -> bool:
        """Whether it was closed (queued samples can still be read)."""
        return self._closed

    def get_nowait(self) -> T | None:
        """The oldest queued sample, or ``None``."""
        return self._queue.popleft() if self._queue else None

    def __aiter__(self) -> Subscription[T]:
        return self

    async def __anext__(self) -> T:
        while not self._queue:
            if self._closed:
                raise StopAsyncIteration
            self._waiter = asyncio.get_running_loop().create_future()
            try:
                await self._waiter
            finally:
                self._waiter = None
        return self._queue.popleft()

    async def __aenter__(self) -> Subscription[T]:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()


class Topic(Generic[T]):
    """One stream: its newest sample, its subscriptions and its figures."""

    def __init__(self, name: str, requested_hz: float = 0.0, *, enabled: bool = True) -> None:
        self.name = name
        self.requested_hz = requested_hz
        self.enabled = enabled
        self.latest: T | None = None
        self.samples = 0
        self.missed = 0
        self.skipped = 0
        self.dropped = 0
        # Weak, so a subscription its reader abandoned (a `break` out of `async for`)
        # goes away with it instead of filling up forever.
        self._subscriptions: weakref.WeakSet[Subscription[T]] = weakref.WeakSet()
        self._stamps: deque[float] = deque(maxlen=_WINDOW)
        self._lateness: deque[float] = deque(maxlen=_WINDOW)
        self._closed = False

    def publish(self, sample: T, stamp_s: float) -> None:
        """Make ``sample`` the newest and hand it to every subscription."""
        self.latest = sample
        self.samples += 1
        self._stamps.append(stamp_s)
        # Iterating even an empty WeakSet costs a guard object, and asking its len() a
        # call: its set of references (dead ones are dropped as it is iterated) tells.
        if self._subscriptions.data:  # type: ignore[attr-defined]  # CPython's WeakSet keeps it
            for subscription in self._subscriptions:
                subscription._put(sample)

    def note_lateness(self, late_s: float) -> None:
        """Record how late a cycle started after its due time."""
        self._lateness.append(late_s)

    def subscribe(self, maxlen: int = DEFAULT_QUEUE_SIZE) -> Subscription[T]:
        """A new subscription holding at most ``maxlen`` samples.

        Raises:
            OutOfRangeError: ``maxlen`` is not 1..100000.
        """
        integer("maxlen", maxlen, 1, 100_000)
        subscription = Subscription(self, maxlen)
        if self._closed:
            subscription.close()  # the stream has ended: iteration ends at once
        else:
            self._subscriptions.add(subscription)
        return subscription

    def close(self) -> None:
        """End every subscription's iteration, and any made later."""
        self._closed = True
        for subscription in list(self._subscriptions):
            subscription.close()

    def stats(self, now_s: float) -> StreamStats:
        """The figures now."""
        stamps = [t for t in self._stamps if t > now_s - _RATE_WINDOW_S]
        if len(stamps) >= 2 and stamps[-1] > stamps[0]:
            span = stamps[-1] - stamps[0]
            if now_s - stamps[-1] > 2 * span / (len(stamps) - 1):
                # The stream stopped: count the silence, so the rate decays to zero
                # instead of showing its last value for ever.
                span = now_s - stamps[0]
            achieved = (len(stamps) - 1) / span
        else:
            achieved = 0.0
        late = sorted(self._lateness)
        p50 = percentile(late, 0.50)
        p99 = percentile(late, 0.99)
        return StreamStats(
            enabled=self.enabled,
            requested_hz=self.requested_hz if self.enabled else 0.0,
            achieved_hz=achieved,
            jitter_p50_ms=None if p50 is None else p50 * 1e3,
            jitter_p99_ms=None if p99 is None else p99 * 1e3,
            samples=self.samples,
            missed=self.missed,
            skipped=self.skipped,
            dropped=self.dropped,
            subscribers=len(self._subscriptions),
        )
