"""The contract between a simulated device and the simulated line.

A device is virtual firmware: it sees every packet decoded on the line, in order, and
answers only what the real firmware would. Time is injected: the line passes the virtual
time of each event, so a device never reads a clock and a test can run hours in
microseconds.
"""

from __future__ import annotations

import abc

from ohmni_tb.protocol import Packet, RejectReason

__all__ = ["SimDevice"]


class SimDevice(abc.ABC):
    """Virtual firmware for one bus device."""

    @abc.abstractmethod
    def advance(self, now_s: float) -> None:
        """Advance the device's physics to ``now_s`` (never called with a smaller time)."""

    @abc.abstractmethod
    def handle(self, packet: Packet, now_s: float) -> Packet | None:
        """Process a packet seen on the line at ``now_s``; return the reply, if any.

        Every device sees every packet (broadcasts, and jogs whose per-servo tags name
        it, concern it even when ``packet.sid`` is not its id); a device ignores what is
        not for it. ``advance(now_s)`` has been called first.
        """

    def on_rejected(self, reason: RejectReason, frame: bytes, now_s: float) -> None:
        """A frame on the line failed to decode (``frame`` starts at ``FF FF``).

        Firmware that flags bad packets (HerkuleX sets a checksum-error detail bit) does so
        here when ``frame[3]`` is its id. The default ignores it.
        """
        del reason, frame, now_s

    def power_cycle(self, now_s: float) -> None:
        """The robot's power was cycled: reload defaults and clear latched faults."""
        del now_s
