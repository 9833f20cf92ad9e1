"""The serial port's USB adapter as Linux shows it: sysfs and the tty's serial flags.

:func:`read_adapter` finds the adapter behind a port path — through symlinks such as the
robot's ``/dev/usb/tty1-2.1``, or by the device number when the path is a device node of
its own — under ``<sysfs>/bus/usb-serial/devices/<tty>``, and reads its latency timer and
USB identity. Every read tolerates absence (another OS, a pseudo-terminal, a sysfs it may
not read): what cannot be read is ``None``. The sysfs root is an argument, so tests give
a tree of their own.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ohmni_tb.probe.findings import AdapterInfo

__all__ = ["ASYNC_LOW_LATENCY", "SYSFS_ROOT", "read_adapter", "read_low_latency"]

#: Where Linux shows its devices.
SYSFS_ROOT = Path("/sys")
#: The ASYNC_LOW_LATENCY bit of ``serial_struct.flags`` (linux/tty_flags.h).
ASYNC_LOW_LATENCY = 1 << 13
#: ``struct serial_struct``: ``int type, line; unsigned port; int irq, flags; ...``; the
#: kernel writes 72 bytes on 64-bit Linux, a larger buffer takes it whole.
_SERIAL_STRUCT_SIZE = 128
_FLAGS_OFFSET = 16
#: How far above the tty's sysfs directory the USB device (with idVendor) may sit:
#: tty → interface → device.
_USB_DEPTH = 4


def read_adapter(
    port: str, *, sysfs_root: Path = SYSFS_ROOT, low_latency: bool | None = None
) -> AdapterInfo:
    """What the OS shows of the adapter behind ``port`` (a device path).

    Args:
        port: The port's path as opened.
        sysfs_root: The sysfs mount (tests give a tree of their own).
        low_latency: The low-latency flag when the caller read it already; otherwise
            it is read from the port (:func:`read_low_latency`).
    """
    tty = _tty_name(port, sysfs_root)
    if tty is None:
        return AdapterInfo(port=port, usb=False)
    node = sysfs_root / "bus" / "usb-serial" / "devices" / tty
    timer = _read_int(node / "latency_timer")
    usb = _usb_device(node)
    usb_id = product = serial = None
    if usb is not None:
        vendor, product_id = _read_text(usb / "idVendor"), _read_text(usb / "idProduct")
        if vendor and product_id:
            usb_id = f"{vendor}:{product_id}"
        product = _read_text(usb / "product")
        serial = _read_text(usb / "serial")
    return AdapterInfo(
        port=port,
        usb=True,
        tty=tty,
        latency_timer_ms=timer,
        low_latency=read_low_latency(port) if low_latency is None else low_latency,
        usb_id=usb_id,
        product=product,
        serial_number=serial,
        sysfs_path=str(node),
    )


def read_low_latency(port: str) -> bool | None:
    """The tty's ASYNC_LOW_LATENCY flag (TIOCGSERIAL), or ``None`` where it cannot be
    read: not Linux, not a serial tty, a driver without the call, no permission.

    The port is opened read-only and non-blocking beside the bus's own descriptor, which
    changes none of its settings.
    """
    try:
        import fcntl  # noqa: PLC0415  # POSIX only
        import termios  # noqa: PLC0415
    except ImportError:
        return None
    request = getattr(termios, "TIOCGSERIAL", None)
    if request is None:
        return None
    try:
        fd = os.open(port, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
    except OSError:
        return None
    try:
        buffer = bytearray(_SERIAL_STRUCT_SIZE)
        fcntl.ioctl(fd, request, buffer)
    except OSError:
        return None
    finally:
        os.close(fd)
    flags = int.from_bytes(buffer[_FLAGS_OFFSET : _FLAGS_OFFSET + 4], "little", signed=True)
    return bool(flags & ASYNC_LOW_LATENCY)


def _tty_name(port: str, sysfs_root: Path) -> str | None:
    """The kernel name of the USB serial tty behind ``port``, or ``None``."""
    devices = sysfs_root / "bus" / "usb-serial" / "devices"
    name = os.path.basename(os.path.realpath(port))
    if name and (devices / name).exists():
        return name
    # A device node of its own (Android's /dev/usb/tty1-2.1 may be one): match its
    # device number against the ttys' in sysfs.
    try:
        rdev = os.stat(port).st_rdev
    except OSError:
        return None
    if not rdev:
        return None
    wanted = f"{os.major(rdev)}:{os.minor(rdev)}"
    with contextlib.suppress(OSError):
        for tty in sorted(p.name for p in devices.iterdir()):
            if _read_text(sysfs_root / "class" / "tty" / tty / "dev") == wanted:
                return tty
    return None


def _usb_device(node: Path) -> Path | None:
    """The USB device directory above a tty's sysfs node (the one with ``idVendor``)."""
    try:
        here = node.resolve()
    except OSError:
        return None
    for _ in range(_USB_DEPTH):
        here = here.parent
        if (here / "idVendor").exists():
            return here
    return None


def _read_text(path: Path) -> str | None:
    try:
        return path.read_text(encoding="ascii", errors="replace").strip() or None
    except OSError:
        return None


def _read_int(path: Path) -> int | None:
    text = _read_text(path)
    if text is None:
        return None
    try:
        return int(text)
    except ValueError:
        return None
