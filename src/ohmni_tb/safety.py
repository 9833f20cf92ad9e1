"""Stops that are delivered: send the wheel stop again and again until the wheels show it.

The wheel command is a broadcast that nothing acknowledges, and the drive boards keep
the last PWM they were given: one stop lost on the line and the robot drives on.
:func:`stop_wheels` therefore repeats the stop ahead of everything queued
(:meth:`~ohmni_tb.bus.Bus.send_now`) and reads both wheel counts back until they have
stopped changing; only then does it report success. When it cannot see that within its
time it raises :class:`~ohmni_tb.errors.StopNotConfirmedError`, having sent stops the
whole time::

    import asyncio
    from ohmni_tb.bus import Bus
    from ohmni_tb.protocol.drive import wheel_command
    from ohmni_tb.safety import stop_wheels
    from ohmni_tb.transport import open_transport

    async def main() -> None:
        async with Bus(await open_transport("sim://")) as bus:
            await bus.send(wheel_command(400, 400))
            await asyncio.sleep(0.5)
            report = await stop_wheels(bus)       # or StopNotConfirmedError, loudly
            print(report.stops_sent, f"{report.elapsed_s:.3f} s", report.counts)

    asyncio.run(main())

The rule for "stopped", for each wheel on its own: its count stays within
``tolerance_ticks`` of a reference reading over at least ``settle_s`` and
:data:`SETTLE_READS` readings; a count outside it starts that wheel's window again from
that reading. A read that gets no reply neither confirms nor resets anything. Both wheels'
windows must hold at once.
"""

from __future__ import annotations

import asyncio

from ohmni_tb._checks import check_seconds, integer
from ohmni_tb.bus import BreakerState, Bus
from ohmni_tb.control.encoder import COUNT_BITS, unwrap_delta
from ohmni_tb.errors import (
    BusClosedError,
    DeadlineMissedError,
    OhmniError,
    ProtocolError,
    StopNotConfirmedError,
    StopReport,
    TransportError,
)
from ohmni_tb.protocol import Packet, ReadReply
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import (
    DRIVE_PROFILE,
    DriveProfile,
    parse_count,
    read_count,
    wheel_command,
)

__all__ = [
    "DEFAULT_REPEAT_S",
    "DEFAULT_SETTLE_S",
    "DEFAULT_STOP_TIMEOUT_S",
    "DEFAULT_TOLERANCE_TICKS",
    "SETTLE_READS",
    "SettleWindow",
    "StopReport",
    "stop_wheels",
]

#: How long :func:`stop_wheels` tries before it gives up and raises.
DEFAULT_STOP_TIMEOUT_S = 1.0
#: How often the stop is sent again while the wheels are being watched.
DEFAULT_REPEAT_S = 0.03
#: How long the counts must hold still to count as stopped.
DEFAULT_SETTLE_S = 0.06
#: Count change still taken as standing still (encoder jitter): 2 ticks ≈ 0.02 mm.
DEFAULT_TOLERANCE_TICKS = 2
#: Readings of a wheel's count, the reference included, that must agree over ``settle_s``.
SETTLE_READS = 3
#: Priority of the count reads: above every stream of the schedule.
_READ_PRIORITY = 1000
#: The most a stop under way may still take once the counts have confirmed.
_REPEATER_GRACE_S = 0.5
#: Shortest gap between two readings of the counts.
_READ_PERIOD_S = 0.01
_SIDES = (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE)


class _Progress:
    __slots__ = ("counts", "error", "missed_reads", "reads", "stops_sent")

    def __init__(self) -> None:
        self.stops_sent = 0
        self.reads = 0
        self.missed_reads = 0
        self.counts: tuple[int, int] | None = None
        self.error: OhmniError | None = None

    def report(self, *, confirmed: bool, elapsed_s: float) -> StopReport:
        return StopReport(
            confirmed=confirmed,
            stops_sent=self.stops_sent,
            reads=self.reads,
            missed_reads=self.missed_reads,
            elapsed_s=elapsed_s,
            counts=self.counts,
        )


async def stop_wheels(
    bus: Bus,
    *,
    timeout_s: float = DEFAULT_STOP_TIMEOUT_S,
    repeat_s: float = DEFAULT_REPEAT_S,
    settle_s: float = DEFAULT_SETTLE_S,
    tolerance_ticks: int = DEFAULT_TOLERANCE_TICKS,
    profile: DriveProfile = DRIVE_PROFILE,
) -> StopReport:
    """Stop both wheels and confirm it by reading their counts back.

    The stop (``wheel_command(0, 0)``) goes out at once, ahead of everything queued, and
    again every ``repeat_s`` until the counts confirm it or ``timeout_s`` is up. The
    first stop is queued before this coroutine first waits, so it goes out even if the
    caller is cancelled at once; a caller cancelled later gets one more stop sent before
    the cancellation goes on.

    Args:
        bus: A started bus.
        timeout_s: How long to try, 0.05..60 s.
        repeat_s: Interval of the repeated stop, 0.005..1 s.
        settle_s: How long the counts must hold still, 0.02..10 s and at most half of
            ``timeout_s``.
        tolerance_ticks: Count change still taken as still, 0..1000 ticks.
        profile: The drive boards' table (which registers, which wheel packet).

    Returns:
        The report, with ``confirmed`` true.

    Raises:
        OutOfRangeError: An argument is out of range; nothing was sent.
        StopNotConfirmedError: The counts did not show the wheels still within
            ``timeout_s`` (a board silent, the wheels still turning, the link lost): the
            robot may still be moving. Its ``report`` says what was tried.
    """
    check_seconds("timeout_s", timeout_s, 0.05, 60.0)
    check_seconds("repeat_s", repeat_s, 0.005, 1.0)
    # The counts must have time to hold still before the time is up.
    check_seconds("settle_s", settle_s, 0.02, min(10.0, timeout_s / 2))
    integer("tolerance_ticks", tolerance_ticks, 0, 1000, "ticks")
    stop = wheel_command(0, 0, profile)
    reads = [read_count(sid, profile) for sid in _SIDES]
    loop = asyncio.get_running_loop()
    started = loop.time()
    progress = _Progress()

    def not_confirmed(sid: int, reason: str) -> StopNotConfirmedError:
        report = progress.report(confirmed=False, elapsed_s=loop.time() - started)
        return StopNotConfirmedError(sid=sid, report=report, reason=reason)

    try:
        # send_now queues the packet before it first waits, and shields it from then on.
        await bus.send_now(stop)
    except (BusClosedError, TransportError) as exc:
        raise not_confirmed(_SIDES[0], f"no stop could be sent ({exc})") from exc
    progress.stops_sent += 1
    done = asyncio.Event()
    repeater = asyncio.create_task(
        _repeat(bus, stop, repeat_s, progress, done), name="ohmni_tb.safety.stop_wheels repeat"
    )
    try:
        sid, reason = await _watch(
            bus,
            reads,
            progress=progress,
            deadline=started + timeout_s,
            settle_s=settle_s,
            tolerance_ticks=tolerance_ticks,
            profile=profile,
        )
        if not reason:
            return progress.report(confirmed=True, elapsed_s=loop.time() - started)
        error = not_confirmed(sid, reason)
        raise error from progress.error
    except asyncio.CancelledError:
        # The caller is gone; the wheels still get one more stop (shielded by send_now).
        try:
            await bus.send_now(stop)
            progress.stops_sent += 1
        except (asyncio.CancelledError, OhmniError):
            pass
        raise
    finally:
        # Let a stop under way finish (send_now waits only for the transaction on the
        # wire); a second cancellation cuts that short.
        done.set()
        try:
            # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation
            # that arrives as the repeater ends, and the caller would run on.
            async with asyncio.timeout(_REPEATER_GRACE_S):
                await asyncio.shield(repeater)
        except TimeoutError:
            repeater.cancel()
        except asyncio.CancelledError:
            repeater.cancel()
            raise


async def _repeat(
    bus: Bus, stop: Packet, repeat_s: float, progress: _Progress, done: asyncio.Event
) -> None:
    """Send ``stop`` every ``repeat_s`` until ``done`` is set or the link fails."""
    loop = asyncio.get_running_loop()
    due = loop.time()
    while True:
        # After a wait for the line, the next stop goes a full interval later, not at once.
        due = max(due + repeat_s, loop.time())
        try:
            async with asyncio.timeout(due - loop.time()):
                await done.wait()
        except TimeoutError:
            pass
        else:
            return
        try:
            await bus.send_now(stop)
        except (BusClosedError, TransportError) as exc:
            progress.error = exc
            return
        progress.stops_sent += 1


class SettleWindow:
    """One wheel's count readings against the rule for "stopped" (the module docstring).

    :func:`stop_wheels` keeps one per wheel; anything else that watches counts come in
    (the demo reading the Robot's ``wheel_encoder`` stream) uses the same rule through it:
    :meth:`add` each reading, and the wheel stands still once :meth:`settled`.
    """

    __slots__ = (
        "agreeing",
        "answered",
        "asked",
        "change",
        "change_gap_s",
        "count",
        "latest_at",
        "reference",
        "since",
    )

    def __init__(self) -> None:
        self.asked = 0
        self.answered = 0
        self.count: int | None = None  # the latest reading
        self.reference = 0  # the reading the window started from
        self.since = 0.0  # when the reference reading was taken
        self.latest_at = 0.0  # when the latest reading was taken
        self.agreeing = 0  # readings within tolerance of the reference, itself included
        self.change: int | None = None  # the last change that restarted the window
        self.change_gap_s = 0.0  # the time between the readings that showed it

    def add(self, count: int, at: float, tolerance_ticks: int) -> None:
        """One raw int32 count read at ``at``; a change beyond ``tolerance_ticks`` from
        the reference starts the window again from it."""
        self.answered += 1
        if self.count is not None and self.agreeing:
            moved = unwrap_delta(self.reference, count, COUNT_BITS)
            if abs(moved) <= tolerance_ticks:
                self.agreeing += 1
                self.count = count
                self.latest_at = at
                return
            self.change = moved
            self.change_gap_s = at - self.latest_at
        self.reference = count
        self.count = count
        self.since = self.latest_at = at
        self.agreeing = 1

    def settled(self, settle_s: float) -> bool:
        """Whether the readings since the reference agree and span ``settle_s``."""
        return self.agreeing >= SETTLE_READS and self.latest_at - self.since >= settle_s - 1e-9


async def _watch(
    bus: Bus,
    reads: list[Packet],
    *,
    progress: _Progress,
    deadline: float,
    settle_s: float,
    tolerance_ticks: int,
    profile: DriveProfile,
) -> tuple[int, str]:
    """Read both counts until each has held still: ``(0, "")``, or the board and why not.

    Each board has its own window, so a reading one board missed does not cost the
    other's; a wheel that moves restarts its own window.
    """
    loop = asyncio.get_running_loop()
    windows = (SettleWindow(), SettleWindow())
    while True:
        if progress.error is not None:
            return _SIDES[0], f"the link failed ({progress.error})"
        round_at = loop.time()
        if round_at >= deadline:
            return _verdict(bus, windows, settle_s)
        try:
            # Asked even of a board the bus presumes gone: a stop needs its answer.
            replies = await bus.transact(
                reads, priority=_READ_PRIORITY, deadline=deadline, probe=True
            )
        except DeadlineMissedError:
            return _verdict(bus, windows, settle_s)
        except (BusClosedError, TransportError) as exc:
            progress.error = exc
            return _SIDES[0], f"the link failed ({exc})"
        for window, reply in zip(windows, replies, strict=True):
            window.asked += 1
            if reply is None:
                progress.missed_reads += 1
                continue
            try:
                count = parse_count(ReadReply.parse(reply), profile)
            except ProtocolError:
                progress.missed_reads += 1  # a reply that does not fit: no reading
                continue
            progress.reads += 1
            # The count is of when the request left, not of when the reply came in.
            window.add(count, reply.sent_at, tolerance_ticks)
        left, right = windows
        if left.count is not None and right.count is not None:
            progress.counts = (left.count, right.count)
        if all(window.settled(settle_s) for window in windows):
            return 0, ""
        now = loop.time()
        await asyncio.sleep(max(0.0, min(round_at + _READ_PERIOD_S, deadline) - now))


def _verdict(
    bus: Bus, windows: tuple[SettleWindow, SettleWindow], settle_s: float
) -> tuple[int, str]:
    """Why the counts did not confirm the stop, naming the board it concerns first."""
    devices = bus.stats.devices
    unsettled: list[int] = []
    reasons: list[str] = []
    for side, window in zip(_SIDES, windows, strict=True):
        if window.settled(settle_s):
            continue
        name = f"the {'left' if side == 0 else 'right'} drive board (sid {int(side)})"
        if not window.answered:
            text = f"{name} answered none of {window.asked} count reads"
        elif window.change is not None and window.agreeing == 1:
            text = (
                f"{name}'s count moved {window.change:+d} ticks between its last two readings "
                f"({window.change_gap_s:.3f} s apart)"
            )
        else:
            text = (
                f"{name}'s count was read only {window.agreeing} time(s) alike over "
                f"{window.latest_at - window.since:.3f} s of the {settle_s:.3f} s needed "
                f"({window.answered} of {window.asked} reads answered)"
            )
        stats = devices.get(int(side))
        if stats is not None and stats.breaker is not BreakerState.CLOSED:
            text += (
                " and the bus presumes it gone (its breaker is open; these reads were sent anyway)"
            )
        unsettled.append(int(side))
        reasons.append(text)
    if not unsettled:  # pragma: no cover - a settled pair returns before any verdict
        return int(_SIDES[0]), "the time was up as the counts settled"
    return unsettled[0], "; ".join(reasons)
