"""Which serial port is the robot's bus: the ``auto`` port.

The Ohmni's bus hangs off an FTDI USB-serial adapter (USB id ``0403:6015``, an FT230X);
on the robot's own Android system the adapter also appears as ``/dev/usb/tty1-2.1``.
``open_transport("auto")`` (and so ``Robot.open()`` with the default config, and every
``ohmni`` command without ``--port``) opens the one this module finds::

    from ohmni_tb.transport.ports import find_bus_port, list_ports

    for port in list_ports():
        print(port.device, port.usb_id, "<- the bus" if port.likely_bus else "")
    print(find_bus_port())          # '/dev/ttyUSB0', or None when there is none
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any, Final

from ohmni_tb.errors import TransportError

__all__ = [
    "AUTO_PORT",
    "BUS_USB_ID",
    "ROBOT_BUS_LINK",
    "NoBusPortError",
    "PortInfo",
    "find_bus_port",
    "list_ports",
    "resolve_port",
]

#: The port name that means "find the bus adapter".
AUTO_PORT: Final = "auto"
#: USB vendor and product id of the bus adapter (FTDI FT230X, the FT-X series id).
BUS_USB_ID: Final = (0x0403, 0x6015)
#: The adapter's device node on the robot's Android system.
ROBOT_BUS_LINK: Final = "/dev/usb/tty1-2.1"


class NoBusPortError(TransportError):
    """``auto`` found no bus adapter; the message says what was looked for."""


@dataclass(frozen=True, slots=True)
class PortInfo:
    """One serial port as the system lists it.

    Attributes:
        device: Its path.
        description: What the system says it is.
        vid: USB vendor id, or ``None`` for a port that is not on USB.
        pid: USB product id, or ``None``.
        serial_number: The adapter's serial number, if any.
        likely_bus: Whether it looks like the Ohmni's bus adapter.
    """

    device: str
    description: str
    vid: int | None
    pid: int | None
    serial_number: str | None
    likely_bus: bool

    @property
    def usb_id(self) -> str:
        """``vvvv:pppp`` in hex, or ``""`` for a port that is not on USB."""
        if self.vid is None or self.pid is None:
            return ""
        return f"{self.vid:04x}:{self.pid:04x}"

    def as_dict(self) -> dict[str, Any]:
        """The fields and ``usb_id``, for JSON."""
        return {**asdict(self), "usb_id": self.usb_id}


def list_ports() -> list[PortInfo]:
    """Every serial port on this machine with its USB ids, the likely bus adapter first.

    The robot's ``/dev/usb/tty1-2.1`` is listed when it exists even if the system's list
    misses it (Android's node is not where pyserial looks).
    """
    from serial.tools import list_ports as serial_ports  # noqa: PLC0415  # slow: when asked

    found = [
        PortInfo(
            device=port.device,
            description=port.description or "",
            vid=port.vid,
            pid=port.pid,
            serial_number=port.serial_number,
            likely_bus=(port.vid, port.pid) == BUS_USB_ID,
        )
        for port in serial_ports.comports()
    ]
    if os.path.exists(ROBOT_BUS_LINK) and all(p.device != ROBOT_BUS_LINK for p in found):
        found.append(
            PortInfo(
                device=ROBOT_BUS_LINK,
                description="the robot's bus adapter node",
                vid=None,
                pid=None,
                serial_number=None,
                likely_bus=True,
            )
        )
    found.sort(key=lambda p: (not p.likely_bus, p.device))
    return found


def find_bus_port() -> str | None:
    """The device path of the bus adapter, or ``None`` when none is plugged in.

    The USB id decides; the robot's ``/dev/usb/tty1-2.1`` node is the fallback. With
    several adapters of that id, the first by path.
    """
    for port in list_ports():
        if port.likely_bus:
            return port.device
    return None


def resolve_port(port: str) -> str:
    """``port`` itself, or for ``auto`` the bus adapter's path.

    Raises:
        NoBusPortError: ``auto`` and no adapter was found; the message says what to pass.
    """
    if port != AUTO_PORT:
        return port
    found = find_bus_port()
    if found is None:
        vid, pid = BUS_USB_ID
        raise NoBusPortError(
            f"no Ohmni bus adapter found (USB {vid:04x}:{pid:04x} or {ROBOT_BUS_LINK}); "
            "pass --port /dev/ttyUSB0 (see `ohmni ports`), or --port sim:// for the simulator"
        )
    return found
