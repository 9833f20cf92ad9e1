"""Core board (sid 20): battery and dock status, light ring, firmware tag.

Confirmed: the light ring at RAM 0xC1 (H, S, V bytes), the firmware tag at EEP 0xF1, the
status *fields* (tb_control's ``tbcore_status``), the 5-cell LiFePO4 pack near 3.27 V a
cell, and the vendor's percent rule from the lowest cell. **Assumed**: the status block's
address, length and byte layout (:data:`CORE_PROFILE`), until a capture or ``ohmni probe``
says otherwise; each is a setting (``battery_addr``, ``battery_length``,
``battery_layout``).
"""

from __future__ import annotations

import enum
import struct
from dataclasses import dataclass

from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.framing import Packet
from ohmni_tb.protocol.messages import (
    MAX_READ_LENGTH,
    ReadReply,
    read_request,
    write_request,
)

__all__ = [
    "CELL_COUNT",
    "CELL_MAX_MV",
    "CELL_MIN_MV",
    "CELL_SPREAD_MAX_MV",
    "CORE_PROFILE",
    "BatteryLayout",
    "CoreProfile",
    "TbcoreStatus",
    "cells_plausible",
    "decode_status",
    "encode_status",
    "parse_status",
    "percent_from_cells",
    "read_status",
    "set_light_ring",
]

CELL_COUNT = 5
#: A LiFePO4 cell reads between these, mV (flat ≈3.3 V; 2.5 V empty, 3.65 V charging).
CELL_MIN_MV = 2500
CELL_MAX_MV = 3700
#: The five cells of one pack sit close together: a wider spread is not a pack.
CELL_SPREAD_MAX_MV = 300
#: cells u16 ×5, charging current i16, docked u8, FET status u8, status 1..4 u8 ×4.
_STATUS_LAYOUT = struct.Struct("<5Hh6B")
#: cells u16 ×5 alone.
_CELLS_LAYOUT = struct.Struct("<5H")
#: Status bytes 1..4.
_STATUS_BYTES = range(4)

#: The vendor's rule: lowest cell below 3150 mV → 20 %, below 3250 → 50 %, below 3380 → 80 %.
_PERCENT_STEPS_MV: tuple[tuple[int, int], ...] = ((3150, 20), (3250, 50), (3380, 80))


def _check_int(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidArgumentError(f"{name} must be an int, not {type(value).__name__}")


class BatteryLayout(enum.StrEnum):
    """The byte layout of the battery/dock status block (**assumed**; a capture decides)."""

    #: 18 bytes, tb_control's ``tbcore_status`` fields in order: cell 1..5 mV (u16 LE),
    #: charging current mA (i16 LE), docked (u8), FET status (u8), status 1..4 (u8 each).
    TBCORE = "tbcore"
    #: 10 bytes: the five cells alone (u16 LE). Current, docked and the status bytes are
    #: not in the block: they read as 0, not docked.
    CELLS = "cells"

    @property
    def size(self) -> int:
        """Bytes the layout decodes (the block may be read longer)."""
        return _LAYOUTS[self].size


_LAYOUTS = {BatteryLayout.TBCORE: _STATUS_LAYOUT, BatteryLayout.CELLS: _CELLS_LAYOUT}


@dataclass(frozen=True, slots=True)
class CoreProfile:
    """Where things live on the core board (settings ``battery_addr``,
    ``battery_length``, ``battery_layout``; ``ohmni probe`` finds them).

    Attributes:
        status_addr: RAM address of the status block (**assumed**: 0xA0).
        status_size: Bytes read from it (**assumed**: the 18 bytes of the field list); at
            least the layout's size, the bytes after the layout are read and ignored.
        layout: How the block's bytes decode (**assumed**: :attr:`BatteryLayout.TBCORE`).
        light_ring_addr: RAM address of the light ring H, S, V (confirmed).

    Raises:
        OutOfRangeError: An address is not 0..255, or ``status_size`` is shorter than the
            layout or longer than one read.
        InvalidArgumentError: ``layout`` is not a :class:`BatteryLayout`.
    """

    status_addr: int = 0xA0
    status_size: int = _STATUS_LAYOUT.size
    layout: BatteryLayout = BatteryLayout.TBCORE
    light_ring_addr: int = 0xC1

    def __post_init__(self) -> None:
        layout: object = self.layout  # typed, but a table edited by hand may hold anything
        if not isinstance(layout, BatteryLayout):
            raise InvalidArgumentError(
                f"battery layout must be one of {[v.value for v in BatteryLayout]}, not {layout!r}"
            )
        for name, addr in (
            ("status_addr", self.status_addr),
            ("light_ring_addr", self.light_ring_addr),
        ):
            _check_int(name, addr)
            if not 0 <= addr <= 0xFF:
                raise OutOfRangeError(name, addr, 0, 0xFF)
        _check_int("status_size", self.status_size)
        if not layout.size <= self.status_size <= MAX_READ_LENGTH:
            raise OutOfRangeError(
                "status_size",
                self.status_size,
                layout.size,
                MAX_READ_LENGTH,
                f"bytes (the {layout.value} layout takes {layout.size})",
            )


CORE_PROFILE = CoreProfile()


@dataclass(frozen=True, slots=True)
class TbcoreStatus:
    """The core board's battery and dock status (tb_control's ``tbcore_status``).

    Attributes:
        cell_mv: The five cell voltages, mV.
        charging_current_ma: Pack current, mA; positive while charging.
        docked: Whether the robot sits on its dock.
        fet_status: Charge/discharge FET bits, as the board reports them.
        status: Status bytes 1..4, as the board reports them.
    """

    cell_mv: tuple[int, int, int, int, int]
    charging_current_ma: int
    docked: bool
    fet_status: int
    status: tuple[int, int, int, int]

    @property
    def pack_mv(self) -> int:
        """Pack voltage, the sum of the cells, mV."""
        return sum(self.cell_mv)

    @property
    def min_cell_mv(self) -> int:
        """The lowest cell, mV (the one that limits the pack)."""
        return min(self.cell_mv)

    @property
    def percent(self) -> int:
        """State of charge by the vendor's rule from the lowest cell: 20, 50, 80 or 100."""
        return percent_from_cells(self.cell_mv)

    @property
    def charging(self) -> bool:
        """Whether current flows into the pack."""
        return self.charging_current_ma > 0


def cells_plausible(cell_mv: tuple[int, ...]) -> bool:
    """Whether ``cell_mv`` are five cells of one LiFePO4 pack: each
    :data:`CELL_MIN_MV`..:data:`CELL_MAX_MV`, at most :data:`CELL_SPREAD_MAX_MV` apart.
    Anything else (zeros, a spread of thousands) is not the battery block: the profile's
    ``battery_addr`` or layout is wrong, or the read was.

    Raises:
        InvalidArgumentError: A cell voltage is not an int.
    """
    cells = tuple(cell_mv)
    for mv in cells:
        _check_int("cell_mv", mv)
    return (
        len(cells) == CELL_COUNT
        and all(CELL_MIN_MV <= mv <= CELL_MAX_MV for mv in cells)
        and max(cells) - min(cells) <= CELL_SPREAD_MAX_MV
    )


def percent_from_cells(cell_mv: tuple[int, ...]) -> int:
    """The vendor's coarse state of charge from the lowest cell voltage.

    Raises:
        InvalidArgumentError: No cells, or a cell voltage is not an int.
    """
    cells = tuple(cell_mv)
    if not cells:
        raise InvalidArgumentError("cell_mv is empty: give at least one cell voltage")
    for mv in cells:
        _check_int("cell_mv", mv)
    lowest = min(cells)
    for below_mv, percent in _PERCENT_STEPS_MV:
        if lowest < below_mv:
            return percent
    return 100


def read_status(profile: CoreProfile = CORE_PROFILE) -> Packet:
    """The battery/dock status query (**assumed** address and size)."""
    return read_request(DeviceId.CORE, profile.status_addr, profile.status_size)


def parse_status(reply: ReadReply, profile: CoreProfile = CORE_PROFILE) -> TbcoreStatus:
    """Decode a :func:`read_status` reply, in ``profile.layout``.

    Raises:
        MalformedReplyError: The reply is for another address or has the wrong size.
    """
    if reply.addr != profile.status_addr or reply.length != profile.status_size:
        raise MalformedReplyError(
            f"expected {profile.status_size} status bytes at RAM 0x{profile.status_addr:02X}, "
            f"got {reply.length} at 0x{reply.addr:02X}"
        )
    return decode_status(reply.data, profile.layout)


def decode_status(data: bytes, layout: BatteryLayout = BatteryLayout.TBCORE) -> TbcoreStatus:
    """Decode a status block's bytes in ``layout`` (bytes past the layout are ignored).

    Raises:
        MalformedReplyError: Fewer bytes than the layout takes.
    """
    if len(data) < layout.size:
        raise MalformedReplyError(
            f"the {layout.value} status layout takes {layout.size} bytes, got {len(data)}"
        )
    if layout is BatteryLayout.CELLS:
        c1, c2, c3, c4, c5 = _CELLS_LAYOUT.unpack_from(data)
        return TbcoreStatus(
            cell_mv=(c1, c2, c3, c4, c5),
            charging_current_ma=0,
            docked=False,
            fet_status=0,
            status=(0, 0, 0, 0),
        )
    c1, c2, c3, c4, c5, current, docked, fet, s1, s2, s3, s4 = _STATUS_LAYOUT.unpack_from(data)
    return TbcoreStatus(
        cell_mv=(c1, c2, c3, c4, c5),
        charging_current_ma=current,
        docked=bool(docked),
        fet_status=fet,
        status=(s1, s2, s3, s4),
    )


def encode_status(status: TbcoreStatus, layout: BatteryLayout = BatteryLayout.TBCORE) -> bytes:
    """The status block's bytes in ``layout`` (the simulated core board answers with these).

    Raises:
        InvalidArgumentError: A field is not an int, or there are not five cells.
        OutOfRangeError: A field does not fit its byte layout.
    """
    if len(status.cell_mv) != CELL_COUNT:
        raise InvalidArgumentError(f"cell_mv needs {CELL_COUNT} cells, got {len(status.cell_mv)}")
    for mv in status.cell_mv:
        _check_int("cell_mv", mv)
        if not 0 <= mv <= 0xFFFF:
            raise OutOfRangeError("cell_mv", mv, 0, 0xFFFF, "mV")
    _check_int("charging_current_ma", status.charging_current_ma)
    if not -0x8000 <= status.charging_current_ma <= 0x7FFF:
        raise OutOfRangeError("charging_current_ma", status.charging_current_ma, -32768, 32767)
    for name, value in (("fet_status", status.fet_status), *(("status", v) for v in status.status)):
        _check_int(name, value)
    if len(status.status) != len(_STATUS_BYTES):
        raise InvalidArgumentError(f"status needs 4 bytes, got {len(status.status)}")
    if layout is BatteryLayout.CELLS:
        return _CELLS_LAYOUT.pack(*status.cell_mv)
    return _STATUS_LAYOUT.pack(
        *status.cell_mv,
        status.charging_current_ma,
        int(status.docked),
        status.fet_status & 0xFF,
        *(s & 0xFF for s in status.status),
    )


def set_light_ring(
    hue: int, saturation: int, value: int, profile: CoreProfile = CORE_PROFILE
) -> Packet:
    """Set the light ring colour (confirmed: RAM 0xC1, H, S, V bytes).

    Raises:
        OutOfRangeError: A component is outside 0..255.
    """
    for name, component in (("hue", hue), ("saturation", saturation), ("value", value)):
        if isinstance(component, bool) or not isinstance(component, int):
            raise InvalidArgumentError(f"{name} must be an int 0..255, not {component!r}")
        if not 0 <= component <= 0xFF:
            raise OutOfRangeError(name, component, 0, 255)
    return write_request(DeviceId.CORE, profile.light_ring_addr, bytes((hue, saturation, value)))
