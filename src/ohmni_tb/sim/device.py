"""The contract between a simulated device and the simulated line.

A device is virtual firmware: it is handed the packets decoded on the line that concern
it, in order, and answers only what the real firmware would. Time is injected: the line
passes the virtual time of each event, so a device never reads a clock and a test can run
hours in microseconds.

Routing: a device with an integer ``sid`` attribute (the id it answers to *now*) is handed
the packets addressed to that id, broadcasts, and jogs whose tags name it; the line reads
``sid`` again after every packet that may change an id (writes, REBOOT, ROLLBACK) and
after a power cycle. A device without one is handed every packet.
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

        The line hands over the packets that concern the device (see the module
        docstring: a broadcast, or a jog whose tags name it, concerns it even when
        ``packet.sid`` is not its id); a device still ignores what is not for it.
        ``advance(now_s)`` has been called first.
        """

    def on_rejected(self, reason: RejectReason, frame: bytes, now_s: float) -> None:
        """A frame on the line failed to decode (``frame`` starts at ``FF FF``).

        Every device hears it. Firmware that flags bad packets (HerkuleX sets a
        checksum-error detail bit, or garbage-detected for a frame cut short) does so here
        when ``frame[3]`` is its id. The default ignores it.
        """
        del reason, frame, now_s

    def power_cycle(self, now_s: float) -> None:
        """The robot's power was cycled: reload defaults and clear latched faults."""
        del now_s
