"""Simulated worm-gear neck (sid 4).

The neck travels to its target at a finite speed. A target outside −127000…120000 drives
it past its end stop: it stalls there, reports STALLED, and ignores every target until
the robot is power-cycled — as the hardware does, which is why the host refuses such
targets before sending them.
"""

from __future__ import annotations

from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.worm_neck import (
    WORM_MAX,
    WORM_MIN,
    WORM_PROFILE,
    WormFeedback,
    WormFlags,
    WormProfile,
    encode_feedback,
)
from ohmni_tb.sim.board import BoardRegister, SimBoard

__all__ = ["SimWormNeck"]


class SimWormNeck(SimBoard):
    """The worm-gear neck.

    Args:
        speed_per_s: Travel speed in raw units per second.
        profile: Where its target and feedback registers are.
    """

    def __init__(
        self,
        *,
        speed_per_s: float = 80_000.0,
        tag: str = "sim-worm-1.0",
        profile: WormProfile = WORM_PROFILE,
    ) -> None:
        super().__init__(DeviceId.WORM_NECK, tag)
        self.speed_per_s = speed_per_s
        self.position = 0.0
        self.target = 0
        self.stalled = False
        self._now_s = 0.0
        p = profile
        self.ram[p.target_addr] = BoardRegister(
            4, lambda: self.target.to_bytes(4, "little", signed=True), self._set_target
        )
        self.ram[p.feedback_addr] = BoardRegister(5, self._feedback)

    def feedback(self) -> WormFeedback:
        """What the neck reports now."""
        flags = WormFlags.NONE
        if self.stalled:
            flags |= WormFlags.STALLED
        elif round(self.position) != self.target:
            flags |= WormFlags.MOVING
        return WormFeedback(position=round(self.position), flags=flags)

    def advance(self, now_s: float) -> None:
        dt = now_s - self._now_s
        self._now_s = now_s
        if self.stalled or dt <= 0:
            return
        step = self.speed_per_s * dt
        goal = float(self.target)
        if goal > WORM_MAX or goal < WORM_MIN:
            # It runs into the end stop and stalls there.
            stop = WORM_MAX if goal > WORM_MAX else WORM_MIN
            if abs(stop - self.position) <= step:
                self.position = float(stop)
                self.stalled = True
            else:
                self.position += step if stop > self.position else -step
            return
        if abs(goal - self.position) <= step:
            self.position = goal
        else:
            self.position += step if goal > self.position else -step

    def power_cycle(self, now_s: float) -> None:
        self.advance(now_s)
        self.stalled = False
        self.target = round(self.position)
        self.status_error = type(self.status_error).NONE
        self.status_detail = type(self.status_detail).NONE

    def _set_target(self, data: bytes) -> None:
        if self.stalled:
            return
        self.target = int.from_bytes(data, "little", signed=True)

    def _feedback(self) -> bytes:
        return encode_feedback(self.feedback())
