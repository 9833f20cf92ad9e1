"""Who is on the bus: device ids and names (sans-IO).

The ids of the drive boards, the necks and the core board are confirmed by the vendor's
public Node driver. The external servo ids are not public: 11 and 12 are **assumed**.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

__all__ = [
    "DEFAULT_EXT_SERVO_IDS",
    "DEVICE_MAP",
    "KNOWN_FIRMWARE_TAGS",
    "NECK_RAW_RANGE",
    "DeviceId",
    "DeviceInfo",
    "device_name",
    "firmware_known",
]


class DeviceId(enum.IntEnum):
    """Bus ids of the Ohmni's own boards."""

    LEFT_DRIVE = 0
    RIGHT_DRIVE = 1
    HERKULEX_NECK = 3
    WORM_NECK = 4
    CORE = 20
    BROADCAST = 0xFE


#: The HerkuleX neck's safe raw range: beyond it the head hits its stops.
NECK_RAW_RANGE: tuple[int, int] = (280, 650)

#: The vendor API lets clients address ids 11..19 as accessories; which two the external
#: HerkuleX servos use is not public. **assumed**, configurable.
DEFAULT_EXT_SERVO_IDS: tuple[int, ...] = (11, 12)


@dataclass(frozen=True, slots=True)
class DeviceInfo:
    """One entry of the device map.

    Attributes:
        sid: Bus id.
        name: Short name used in logs and the bus monitor.
        description: What the device is.
        confirmed: Whether the id is confirmed by a public source (else assumed).
    """

    sid: int
    name: str
    description: str
    confirmed: bool


DEVICE_MAP: dict[int, DeviceInfo] = {
    d.sid: d
    for d in (
        DeviceInfo(0, "left", "left drive board", True),
        DeviceInfo(1, "right", "right drive board", True),
        DeviceInfo(3, "neck", "HerkuleX DRS-0101/0201 neck servo", True),
        DeviceInfo(4, "worm-neck", "worm-gear neck", True),
        DeviceInfo(20, "core", "core board: battery, dock, light ring", True),
        DeviceInfo(11, "ext1", "external HerkuleX servo (assumed id)", False),
        DeviceInfo(12, "ext2", "external HerkuleX servo (assumed id)", False),
        DeviceInfo(0xFE, "broadcast", "every device", True),
    )
}


def device_name(sid: int) -> str:
    """A short name for ``sid``: the map's name, or ``sid<N>``."""
    info = DEVICE_MAP.get(sid)
    return info.name if info is not None else f"sid{sid}"


#: The boards' firmware tags (EEP 0xF1, ASCII) the project knows, each with where it is
#: known from: the simulator's, and only tags public sources show. A tag not listed is
#: not wrong, only unseen: ``ohmni probe --share FILE`` makes a report an owner can send.
KNOWN_FIRMWARE_TAGS: Mapping[str, str] = MappingProxyType(
    {
        "stable": "public notes on the vendor's boards, read at EEP 0xF1",
        "sim-drive-1.0": "the simulator's drive boards",
        "sim-core-1.0": "the simulator's core board",
        "sim-worm-1.0": "the simulator's worm-gear neck",
    }
)


def firmware_known(tag: str | None) -> bool:
    """Whether ``tag`` is one of :data:`KNOWN_FIRMWARE_TAGS` (``None``: unread, not known)."""
    return tag is not None and tag in KNOWN_FIRMWARE_TAGS
