"""Simulated core board (sid 20): a 5-cell LiFePO4 pack, the dock, the light ring.

Battery model: each cell has an open-circuit voltage from a LiFePO4 curve of its state of
charge (a flat plateau near 3.27-3.33 V between 20 % and 90 %, steep at both ends) and an
internal resistance, so the pack *sags* under load — the electronics' base load plus the
drive motors' current — and rises while charging. Docked, the charger pushes a constant
current until the highest cell reaches its limit. The cells differ slightly in capacity,
so they drift apart as the pack discharges, as real packs do.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ohmni_tb.protocol.core import CORE_PROFILE, CoreProfile, TbcoreStatus, encode_status
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.sim.board import BoardRegister, SimBoard

__all__ = ["LIFEPO4_OCV", "BatteryPack", "SimCoreBoard"]

#: LiFePO4 open-circuit voltage (V) against state of charge (0..1).
LIFEPO4_OCV = (
    np.array([0.00, 0.05, 0.10, 0.20, 0.30, 0.50, 0.70, 0.90, 0.95, 1.00]),
    np.array([2.80, 3.05, 3.15, 3.22, 3.26, 3.29, 3.31, 3.33, 3.36, 3.45]),
)
#: Charge stops when the highest cell reaches this voltage under charge.
_CHARGE_LIMIT_V = 3.55
_FET_CHARGE = 0x01
_FET_DISCHARGE = 0x02
#: status 1 bits of the simulator (the real layout is not public).
_STATUS1_DOCKED = 0x01
_STATUS1_CHARGING = 0x02


class BatteryPack:
    """Five LiFePO4 cells in series.

    Args:
        capacity_ah: Nominal cell capacity.
        soc: Initial state of charge, 0..1.
        internal_ohm: Internal resistance per cell.
        base_load_a: The robot's draw with the motors idle.
        charge_current_a: The dock's charging current.
    """

    def __init__(
        self,
        *,
        capacity_ah: float = 8.0,
        soc: float = 0.8,
        internal_ohm: float = 0.012,
        base_load_a: float = 1.2,
        charge_current_a: float = 3.0,
    ) -> None:
        # A few percent spread in capacity makes the cells drift apart like a real pack.
        self.capacity_ah = capacity_ah * np.array([1.0, 0.985, 1.01, 0.995, 0.98])
        self.soc = np.full(5, float(soc))
        self.internal_ohm = internal_ohm
        self.base_load_a = base_load_a
        self.charge_current_a = charge_current_a
        self.docked = False
        self.current_a = 0.0  # positive = charging
        self.extra_load: Callable[[], float] = lambda: 0.0

    def cell_voltages(self) -> list[float]:
        """Terminal voltage of each cell under the present current."""
        ocv = np.interp(self.soc, *LIFEPO4_OCV)
        return [float(v) for v in ocv + self.current_a * self.internal_ohm]

    def step(self, dt_s: float) -> None:
        """Draw or charge for ``dt_s`` seconds."""
        load = self.base_load_a + self.extra_load()
        current = -load
        if self.docked:
            ocv_max = float(np.interp(self.soc.max(), *LIFEPO4_OCV))
            # A full cell ends the charge too: the curve tops out at 3.45 V, so under the
            # charging current no cell would ever reach the voltage limit.
            full = self.soc.max() >= 1.0
            if not full and ocv_max + self.charge_current_a * self.internal_ohm < _CHARGE_LIMIT_V:
                current += self.charge_current_a + load  # the dock also feeds the load
            else:
                current += load
        self.current_a = current
        self.soc = np.clip(self.soc + current * dt_s / 3600.0 / self.capacity_ah, 0.0, 1.0)


class SimCoreBoard(SimBoard):
    """The core board: battery/dock status block, light ring, firmware tag.

    The status block sits where ``profile`` says (address, length, layout), as the
    Robot's profile may be told it does.

    Attributes:
        load_sync: Brings the devices whose current the pack carries (the drive train,
            through ``pack.extra_load``) to a time, called with the end of each battery
            step. The line advances a device only when a packet concerns it, so without
            this the pack would see the motors as they were at the last wheel packet.
    """

    #: Integration step of the battery.
    STEP_S = 0.05

    def __init__(
        self,
        pack: BatteryPack | None = None,
        tag: str = "sim-core-1.0",
        profile: CoreProfile = CORE_PROFILE,
    ) -> None:
        super().__init__(DeviceId.CORE, tag)
        self.profile = profile
        self.pack = pack or BatteryPack()
        self.light_ring = bytearray((0, 0, 0))
        self.load_sync: Callable[[float], None] | None = None
        self._now_s = 0.0
        p = profile
        self.ram[p.status_addr] = BoardRegister(p.status_size, self._status_bytes_block)
        self.ram[p.light_ring_addr] = BoardRegister(3, lambda: bytes(self.light_ring), self._ring)

    def status(self) -> TbcoreStatus:
        """The status block as the board would report it now."""
        pack = self.pack
        cells = tuple(round(v * 1000) for v in pack.cell_voltages())
        charging = pack.current_a > 0
        status1 = (_STATUS1_DOCKED if pack.docked else 0) | (_STATUS1_CHARGING if charging else 0)
        return TbcoreStatus(
            cell_mv=(cells[0], cells[1], cells[2], cells[3], cells[4]),
            charging_current_ma=round(pack.current_a * 1000),
            docked=pack.docked,
            fet_status=_FET_DISCHARGE | (_FET_CHARGE if charging else 0),
            status=(status1, 0, 0, 0),
        )

    def advance(self, now_s: float) -> None:
        while self._now_s < now_s:
            dt = min(self.STEP_S, now_s - self._now_s)
            if self.load_sync is not None:
                self.load_sync(self._now_s + dt)
            self.pack.step(dt)
            self._now_s += dt

    def set_docked(self, docked: bool) -> None:
        """Put the robot on its dock, or take it off."""
        self.pack.docked = docked

    def power_cycle(self, now_s: float) -> None:
        self.light_ring[:] = b"\x00\x00\x00"
        self.status_error = type(self.status_error).NONE
        self.status_detail = type(self.status_detail).NONE

    def _status_bytes_block(self) -> bytes:
        # The block in the profile's layout; the bytes past it (a longer block) read 0.
        block = encode_status(self.status(), self.profile.layout)
        return block.ljust(self.profile.status_size, b"\x00")

    def _ring(self, data: bytes) -> None:
        self.light_ring[:] = data
