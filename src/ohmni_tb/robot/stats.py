"""The Robot's figures: every stream's rate and jitter, and the bus's (:meth:`Robot.stats`).

Plain data, apart from the Robot, so that what carries them (the daemon's protocol, the
client) needs nothing of the Robot itself.
"""

from __future__ import annotations

from dataclasses import dataclass

from ohmni_tb.robot.streams import StreamStats

__all__ = ["BusFigures", "RobotStats"]


@dataclass(frozen=True, slots=True)
class BusFigures:
    """The line's figures (part of :meth:`Robot.stats`).

    Attributes:
        wire_utilisation: Share of the last second the line carried bytes.
        budget_share: The schedule's share of the line by the cost model, computed at
            open from the enabled streams.
        transactions_per_s: Replies per second.
        timeouts: Requests that got no reply.
        rejected_samples: Wheel counts refused as implausible.
        clamped_commands: Drive commands scaled into the limits, and wheel PWM the speed
            governor capped or cut (a wheel over ``max_wheel_mps``).
        deadline_misses: Slots dropped because they could not start in time.
        link_losses: Times the link was lost.
        reconnects: Times it was reopened.
    """

    wire_utilisation: float
    budget_share: float
    transactions_per_s: float
    timeouts: int
    rejected_samples: int
    clamped_commands: int
    deadline_misses: int
    link_losses: int
    reconnects: int


@dataclass(frozen=True, slots=True)
class RobotStats:
    """Every stream's figures and the bus's (:meth:`Robot.stats`)."""

    streams: dict[str, StreamStats]
    bus: BusFigures
    uptime_s: float

    def __str__(self) -> str:
        lines = [
            f"{'stream':<14} {'Hz want':>7} {'Hz got':>7} {'jit p50':>8} {'p99 ms':>7} "
            f"{'samples':>8} {'missed':>6} {'skipped':>7} {'dropped':>7}"
        ]
        for name, s in self.streams.items():
            if not s.enabled and not s.samples:
                continue

            def ms(value: float | None) -> str:
                return "-" if value is None else f"{value:.1f}"

            lines.append(
                f"{name:<14} {s.requested_hz:7.1f} {s.achieved_hz:7.1f} "
                f"{ms(s.jitter_p50_ms):>8} {ms(s.jitter_p99_ms):>7} {s.samples:8d} "
                f"{s.missed:6d} {s.skipped:7d} {s.dropped:7d}"
            )
        b = self.bus
        lines.append(
            f"bus: wire {b.wire_utilisation:.0%} (schedule budget {b.budget_share:.0%}), "
            f"{b.transactions_per_s:.0f} transactions/s, {b.timeouts} timeouts, "
            f"{b.rejected_samples} rejected samples, {b.deadline_misses} deadline misses"
        )
        return "\n".join(lines)
