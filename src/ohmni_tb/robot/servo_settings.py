"""The HerkuleX neck's own settings: written to the servo, read back, and kept there.

tb_control writes the neck servo's parameters (``~servo_neck_min_pos`` … ``_max_pwm``)
every time it connects, so the servo itself holds the limits even if the host
misbehaves. The Robot does the same with :class:`~ohmni_tb.config.RobotConfig`'s
``neck_*`` settings (:data:`SETTINGS` maps each to its register):

* when it opens, and when a neck found late answers;
* after the servo comes back from a silence — a REBOOT (the servo is deaf while it
  restarts), a power cut, a lost or released link: the first ``servo_neck`` sample after
  a missed read has the servo's RAM read, and the settings are written again if a
  restart left its EEP values there (a RAM write does not survive one);
* with ``neck_use_eeprom``, to EEP too (only the registers that differ, since EEP wears),
  so the servo powers up with them.

Each load writes two gapless RAM blocks (RAM 6..7, RAM 16..29) and reads RAM 6..29 back.
What was read back is :attr:`NeckSettings.report` (``Robot.info()["neck_settings"]``); a
read-back that differs from the settings, or none at all, is the ``neck_settings:<sid>``
fault in ``robot_state`` until a later load reads back right, and every load is an
event there.
"""

from __future__ import annotations

import logging
from typing import Any, Final

from ohmni_tb.config import RobotConfig
from ohmni_tb.errors import OhmniError
from ohmni_tb.herkulex import (
    EEP,
    RAM,
    eep_read,
    eep_write_many,
    parse_reply,
    ram_read,
    ram_write_many,
)
from ohmni_tb.protocol import Memory
from ohmni_tb.robot.devices import COMMAND_PRIORITY, ServoHandle
from ohmni_tb.robot.samples import ServoSample
from ohmni_tb.robot.state import RobotState

__all__ = ["SETTINGS", "NeckSettings"]

_log = logging.getLogger(__name__)

#: Each setting of RobotConfig and the servo register it is written to, in address order.
SETTINGS: Final[dict[str, str]] = {
    "neck_min_voltage_raw": "min_voltage",
    "neck_max_voltage_raw": "max_voltage",
    "neck_max_pwm": "max_pwm",
    "neck_overload_pwm": "overload_pwm_threshold",
    "neck_min_raw": "min_position",
    "neck_max_raw": "max_position",
    "neck_kp": "position_kp",
    "neck_kd": "position_kd",
    "neck_ki": "position_ki",
}
#: The writes of one load: gapless runs of registers (one packet each).
_BLOCKS: Final = (
    ("min_voltage", "max_voltage"),
    (
        "max_pwm",
        "overload_pwm_threshold",
        "min_position",
        "max_position",
        "position_kp",
        "position_kd",
        "position_ki",
    ),
)
#: A sample this many stream periods after the one before means reads were missed.
_GAP_PERIODS = 1.5


class NeckSettings:
    """Loads the neck servo's settings and watches for the servo losing them."""

    def __init__(self, state: RobotState) -> None:
        self._state = state
        #: What the last load did (``Robot.info()["neck_settings"]``); ``None`` before one.
        self.report: dict[str, Any] | None = None
        self._loads = 0
        self._last_stamp_s: float | None = None
        self._busy = False

    @staticmethod
    def wanted(config: RobotConfig) -> dict[str, int]:
        """The register values the settings ask for, by register name."""
        return {register: int(getattr(config, name)) for name, register in SETTINGS.items()}

    def handle(self) -> ServoHandle | None:
        """The HerkuleX neck's handle, if the Robot has one."""
        neck = self._state.neck
        return neck if isinstance(neck, ServoHandle) else None

    async def load(self, why: str) -> None:
        """Write the settings to the neck servo (and EEP with ``neck_use_eeprom``), read
        them back, and report (``robot_state`` event, the fault, :attr:`report`).

        A bus error is reported the same way, not raised: the neck keeps its own values.
        """
        handle = self.handle()
        if handle is None:
            return
        state = self._state
        sid = handle.sid
        config = state.config
        wanted = self.wanted(config)
        memory = "eep" if config.neck_use_eeprom else "ram"
        self._loads += 1
        report: dict[str, Any] = {
            "sid": sid,
            "memory": memory,
            "loads": self._loads,
            "why": why,
            "wanted": wanted,
            "read_back": None,
            "eep_written": [],
            "ok": False,
            "error": None,
        }
        self.report = report
        self._busy = True
        try:
            state.check_port()
            if config.neck_use_eeprom:
                report["eep_written"] = await self._write_eep(sid, wanted)
            for block in _BLOCKS:
                packet = ram_write_many(sid, {name: wanted[name] for name in block})
                await state.bus.request(packet, priority=COMMAND_PRIORITY)
            read_back = await self._read(sid, Memory.RAM)
        except OhmniError as exc:
            report["error"] = str(exc)
            self._fault(sid, True, f"neck servo {sid}: settings not loaded ({why}): {exc}")
            return
        finally:
            self._busy = False
        report["read_back"] = read_back
        # A silence from here on (the first sample included) is measured from this load.
        self._last_stamp_s = state.loop.time()
        differ = {
            name: (read_back[name], value)
            for name, value in wanted.items()
            if read_back[name] != value
        }
        report["ok"] = not differ
        if differ:
            shown = ", ".join(f"{n} {got} (set {want})" for n, (got, want) in differ.items())
            self._fault(sid, True, f"neck servo {sid}: settings read back differ ({why}): {shown}")
            return
        where = "RAM and EEP" if config.neck_use_eeprom else "RAM"
        self._fault(
            sid,
            False,
            f"neck servo {sid}: settings loaded to {where} and read back ({why}): "
            f"position {wanted['min_position']}..{wanted['max_position']}, "
            f"kp/ki/kd {wanted['position_kp']}/{wanted['position_ki']}/"
            f"{wanted['position_kd']}",
        )

    def check(self, sample: ServoSample) -> None:
        """A ``servo_neck`` sample: after a silence, check that the servo kept its settings."""
        state = self._state
        handle = self.handle()
        if handle is None or sample.sid != handle.sid:
            return
        last, self._last_stamp_s = self._last_stamp_s, sample.stamp_s
        periodic = state.periodic.get("servo_neck")
        if last is None or periodic is None or self._busy:
            return
        silent_s = sample.stamp_s - last
        if silent_s <= _GAP_PERIODS * periodic.period_s:
            return
        self._busy = True
        state.spawn(self._verify(silent_s), f"neck servo {handle.sid} settings check")

    async def _verify(self, silent_s: float) -> None:
        """Read the servo's RAM; load the settings again if it lost them."""
        handle = self.handle()
        try:
            if handle is None:
                return
            try:
                self._state.check_port()
                read_back = await self._read(handle.sid, Memory.RAM)
            except OhmniError as exc:
                _log.info("neck servo %d: settings not checked: %s", handle.sid, exc)
                return
        finally:
            self._busy = False
        if read_back != self.wanted(self._state.config):
            await self.load(f"after {silent_s:.2f} s of silence the servo had lost them")

    async def _read(self, sid: int, memory: Memory) -> dict[str, int]:
        """The settings' registers as the servo holds them in ``memory``."""
        table = RAM if memory is Memory.RAM else EEP
        first, last = table[_BLOCKS[0][0]], table[_BLOCKS[-1][-1]]
        build = ram_read if memory is Memory.RAM else eep_read
        reply = await self._state.bus.request(
            build(sid, first, through=last), expect_reply=True, priority=COMMAND_PRIORITY
        )
        assert reply is not None  # expect_reply=True
        parsed = parse_reply(reply)
        return {name: parsed.value(table[name]) for name in SETTINGS.values()}

    async def _write_eep(self, sid: int, wanted: dict[str, int]) -> list[str]:
        """Write the EEP blocks that differ from ``wanted``; the registers written."""
        held = await self._read(sid, Memory.EEP)
        written: list[str] = []
        for block in _BLOCKS:
            if all(held[name] == wanted[name] for name in block):
                continue
            packet = eep_write_many(sid, {name: wanted[name] for name in block})
            await self._state.bus.request(packet, priority=COMMAND_PRIORITY)
            written.extend(name for name in block if held[name] != wanted[name])
        return written

    def _fault(self, sid: int, on: bool, event: str) -> None:
        """Set or clear the ``neck_settings:<sid>`` fault; publish ``event``."""
        fault = f"neck_settings:{sid}"
        if on:
            self._state.faults.add(fault)
            _log.warning("%s", event)
        else:
            self._state.faults.discard(fault)
        self._state.publish(event)
