"""The host's end of a simulated line: what ``open_transport("sim://")`` returns.

:class:`SimTransport` keeps the transport contract in both modes (pull ``read()`` and push
``start_receiving``) with no task of its own: a write goes to the line at once, and the
line hands the devices' bytes over from event-loop timers at the times the wire and the
USB adapter say.
"""

from __future__ import annotations

import asyncio

from ohmni_tb.errors import TransportClosedError, TransportError
from ohmni_tb.sim.line import SimLine
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.transport.base import LostHandler, ReceiveBuffer, Receiver, Transport

__all__ = ["SimTransport"]


class SimTransport(Transport):
    """The host's end of ``line``.

    One host at a time: a new ``SimTransport(line, robot=robot)`` can be opened on the
    same line once the previous one is closed or lost, and finds the robot as it was (a
    reconnect). :meth:`unplug_usb` loses the link the way pulling the USB adapter does.

    Args:
        line: The simulated line.
        robot: The robot whose devices are on the line, for tests and tools
            (:attr:`robot`); it takes its clock from the line.
        name: How errors and ``repr`` name this end.

    Raises:
        StateError: Another transport is connected to ``line``.
    """

    def __init__(self, line: SimLine, *, robot: SimRobot | None = None, name: str = "sim") -> None:
        self.line = line
        self.robot = robot
        self.name = name
        self.baudrate = line.baudrate
        self._rx = ReceiveBuffer(name)
        self._closed = False
        self._lost = False
        self._lost_handle: asyncio.Handle | None = None
        line.attach(self._rx.deliver)
        if robot is not None:
            robot.attach_clock(line.now_s)

    @property
    def closed(self) -> bool:
        return self._closed or self._lost

    @property
    def can_reopen(self) -> bool:
        return True

    async def reopen(self) -> SimTransport:
        """Plug back into the same line: the robot is found as it was (a reconnect).

        Raises:
            StateError: This end is still connected to the line (close it first).
        """
        return SimTransport(self.line, robot=self.robot, name=self.name)

    @property
    def simulated(self) -> SimRobot | None:
        return self.robot

    def write_nowait(self, data: bytes) -> None:
        if self._closed:
            raise TransportClosedError(f"{self.name} is closed")
        if self._lost:
            raise TransportError(f"{self.name}: the USB adapter was unplugged")
        self.line.host_write(bytes(data))

    async def read(self) -> bytes:
        return await self._rx.read()

    def start_receiving(self, on_data: Receiver, on_lost: LostHandler) -> None:
        self._rx.start(on_data, on_lost)

    def unplug_usb(self) -> None:
        """Pull the host's USB adapter: this end loses its link; the robot keeps running.

        Writes raise at once; a pending or later :meth:`read` raises
        :class:`~ohmni_tb.errors.TransportError`, and a receiver's ``on_lost`` is called
        on the next pass of the event loop, as a serial port notices a vanished device.
        Bytes on their way to the host are lost. Open a new :class:`SimTransport` on the
        same line to plug back in.
        """
        if self._closed or self._lost:
            return
        self._lost = True
        self.line.detach()
        error = TransportError(f"{self.name}: the USB adapter was unplugged")
        self._lost_handle = asyncio.get_running_loop().call_soon(self._rx.lose, error)

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._lost_handle is not None:
            self._lost_handle.cancel()
            self._lost_handle = None
        if not self._lost:
            self.line.detach()
        self._rx.close()

    def __repr__(self) -> str:
        names = ", ".join(type(d).__name__ for d in self.line.devices)
        return f"<SimTransport [{names}] @{self.baudrate}>"
