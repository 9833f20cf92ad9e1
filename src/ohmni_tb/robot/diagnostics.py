"""The robot's health: the ``diagnostics`` stream, one entry per device and one for the link.

Every ``1 / diagnostics_hz`` seconds (1 s by default; the first sample half a period after
open) a :class:`~ohmni_tb.robot.samples.DiagnosticsSample` is built from what the Robot
knows already — the bus's counters of each device
(:class:`~ohmni_tb.protocol.connection.DeviceStats`: replies, timeouts, reply latency),
the newest sample of each device's stream, the faults of ``robot_state``, the control
loop's counters, the boards' firmware tags read at open (:mod:`~ohmni_tb.robot.discovery`;
a board found later has its tag once ``Robot.info`` reads it) — and published; nothing
waits for the bus. Two reads of its own go in the bus's free time at the lowest
priority, in the background, to each HerkuleX servo whose stream is on: its model and
firmware version, once (again when it comes back from a silence), and its PWM (its
load), once a period. Both
have replies of a known length, so neither books the line long enough to delay the
control slot.

Each entry's level is the worst of what its checks find, each check against one of the
named thresholds below; every fault of ``robot_state`` is an ERROR of the entry it
names (``thermal:3`` of sid 3's, ``wheel_stall:0`` of the left drive board's,
``battery_implausible`` of the core board's; a fault naming no device, or one the robot
does not expect, of the link's) — but a slipping wheel (``wheel_slip:<sid>``), a WARN:
the robot still drives, only off its curve.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from ohmni_tb.bus import BusStats
from ohmni_tb.errors import OhmniError
from ohmni_tb.herkulex.registers import EEP as SERVO_EEP
from ohmni_tb.herkulex.registers import RAM as SERVO_RAM
from ohmni_tb.herkulex.registers import Model
from ohmni_tb.protocol import Memory, ReadReply, read_request
from ohmni_tb.protocol.connection import DeviceStats
from ohmni_tb.protocol.devices import DeviceId, firmware_known
from ohmni_tb.protocol.messages import StatusError
from ohmni_tb.robot.discovery import EXT_STREAMS, PROBE_PRIORITY
from ohmni_tb.robot.samples import (
    DiagnosticEntry,
    DiagnosticLevel,
    DiagnosticsSample,
    DiagnosticValue,
    Link,
    ServoSample,
    TbcoreStatusSample,
    WormNeckSample,
)
from ohmni_tb.robot.state import RobotState

__all__ = [
    "CELL_SPREAD_WARN_MV",
    "FIRST_SAMPLE_SHARE",
    "LATENCY_WARN_SHARE",
    "LOAD_WARN_SHARE",
    "LOW_CELL_WARN_MV",
    "PID_SATURATION_WARN_SHARE",
    "SILENT_TIMEOUTS",
    "THERMAL_WARN_MARGIN_RAW",
    "TIMEOUT_WARN_SHARE",
    "UNKNOWN_FIRMWARE",
    "UTILISATION_WARN",
    "Diagnostics",
]

_log = logging.getLogger(__name__)

#: Requests in a row a device left unanswered before it is silent (ERROR). One or two
#: are noise on a busy line; three in a row at 30 Hz is 0.1 s of nothing, and a device
#: polled that fast is ERROR well within a second of going silent.
SILENT_TIMEOUTS: Final = 3
#: Share of a device's requests in the last period left unanswered above which it is
#: WARN: one in fifty. A healthy line loses none.
TIMEOUT_WARN_SHARE: Final = 0.02
#: A device whose 99th-percentile reply latency is above this share of the bus's reply
#: timeout (``usb_latency_ms`` + the loop's margin) is WARN: a little slower, and its
#: replies would be counted missing.
LATENCY_WARN_SHARE: Final = 0.8
#: The line's utilisation (share of the last second it carried bytes) above which the link
#: is WARN: the commands have little room left between the schedule's reads.
UTILISATION_WARN: Final = 0.9
#: The lowest cell below this is WARN, mV: the vendor's own 20 % step of its percent rule.
LOW_CELL_WARN_MV: Final = 3150
#: The cells further apart than this are WARN, mV: a LiFePO4 pack in balance stays within
#: a few tens of mV; 300 mV apart it does not read as a pack (``battery_implausible``).
CELL_SPREAD_WARN_MV: Final = 100
#: A HerkuleX servo this close to ``thermal_limit_raw`` (raw degrees) is WARN: the thermal
#: guard frees it at the limit, and clears its fault this far below (its hysteresis).
THERMAL_WARN_MARGIN_RAW: Final = 10
#: A HerkuleX servo whose PWM is above this share of full torque (1023) is WARN: held that
#: hard, it heats.
LOAD_WARN_SHARE: Final = 0.75
#: A wheel whose PID output sat at the PWM limit more than this share of the last period
#: is WARN: the wheel asks more than its motor gives (a slope, a load, a blocked wheel).
PID_SATURATION_WARN_SHARE: Final = 0.5
#: The first sample comes this share of a period after open (then one a period): late
#: enough for every device to have answered a few reads, early enough for ``ohmni status``.
FIRST_SAMPLE_SHARE: Final = 0.5
#: What an unknown firmware tag's entry says (WARN), after the tag.
UNKNOWN_FIRMWARE: Final = "not one the project knows: `ohmni probe --share FILE` and report it"

#: The HerkuleX models this driver knows, by EEP 0.
_MODELS: Final = {int(model): model.name for model in Model}
#: The full torque of a HerkuleX servo's PWM (RAM 64).
_FULL_PWM = 1023
#: Faults that name no device, and the entry they belong to.
_FAULT_OWNERS: Final = {
    "battery_implausible": "core",
    "neck_stalled": "neck",
    "link_lost": "link",
    "stale_feedback": "link",
}
#: Faults that are a WARN of their entry, by the part of their name before ``:``.
_WARN_FAULTS: Final = frozenset({"wheel_slip"})
#: The external servos' entries, in the order of ``ext_servo_ids`` (their streams'
#: order: ``servo_ext1``, ``servo_ext2``).
_EXT_NAMES: Final = tuple(stream.removeprefix("servo_") for stream in EXT_STREAMS)
#: The boards (a firmware tag at EEP 0xF1) by entry name.
_BOARDS: Final = {
    "left_drive": int(DeviceId.LEFT_DRIVE),
    "right_drive": int(DeviceId.RIGHT_DRIVE),
    "core": int(DeviceId.CORE),
}
#: What a finding is: its level and its words.
_Finding = tuple[DiagnosticLevel, str]
_OK = DiagnosticLevel.OK
_WARN = DiagnosticLevel.WARN
_ERROR = DiagnosticLevel.ERROR


@dataclass(frozen=True, slots=True)
class _Model:
    """What a HerkuleX servo's EEP 0..3 say: its model (``None``: one this driver does not
    know) and firmware version."""

    model: str | None
    version: int


@dataclass(eq=False)
class _Before:
    """The counters of the previous sample, for the figures of the last period."""

    stamp_s: float
    devices: dict[int, tuple[int, int]] = field(default_factory=dict)
    checksum_errors: int = 0
    saturated: tuple[int, int] = (0, 0)
    levels: dict[str, DiagnosticLevel] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class _Period:
    """What one sample is built from: the bus's counters now, and the counters of the
    previous sample and of this one (the figures of the last period are their
    difference)."""

    bus: BusStats
    before: _Before
    after: _Before


class Diagnostics:
    """The ``diagnostics`` stream of one Robot (module docstring).

    Args:
        state: The Robot's shared state.
        saturated_steps: Each wheel's PID steps so far whose output sat at its limit
            (the control loop's counters).
        rejected_counts: Each wheel's counts so far refused as implausible.
        guard_trips: Each wheel's stalls and slips so far (the control loop's guards):
            ``((left stalls, right stalls), (left slips, right slips))``.
    """

    def __init__(
        self,
        state: RobotState,
        saturated_steps: Callable[[], tuple[int, int]],
        rejected_counts: Callable[[], tuple[int, int]],
        guard_trips: Callable[[], tuple[tuple[int, int], tuple[int, int]]] | None = None,
    ) -> None:
        self._state = state
        self._saturated_steps = saturated_steps
        self._rejected_counts = rejected_counts
        self._guard_trips = guard_trips
        self._timer: asyncio.TimerHandle | None = None
        self._due_s = 0.0
        self._reads: asyncio.Task[None] | None = None
        self._models: dict[int, _Model] = {}
        self._load_pwm: dict[int, int] = {}
        #: Servos seen silent by the reads: their model is read again once they answer.
        self._silenced: set[int] = set()
        self._before: _Before | None = None

    # -- the timer -------------------------------------------------------------------

    @property
    def period_s(self) -> float:
        """The time between samples (``diagnostics_hz``); ``inf`` when it is off."""
        hz = self._state.config.diagnostics_hz
        return 1.0 / hz if hz > 0 else math.inf

    def start(self) -> None:
        """Publish from now on (``diagnostics_hz`` 0: never)."""
        state = self._state
        topic = state.topics["diagnostics"]
        if self.period_s == math.inf:
            topic.enabled = False
            return
        self._before = _Before(state.loop.time())
        self._due_s = state.loop.time() + self.period_s * FIRST_SAMPLE_SHARE
        self._timer = state.loop.call_at(self._due_s, self._tick)
        self._spawn_reads()

    def close(self) -> None:
        """Publish no more."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _tick(self) -> None:
        state = self._state
        self._timer = None
        if state.closed:
            return
        now = state.loop.time()
        # The next due time on the grid; one late by more than a period skips (no burst).
        self._due_s = max(self._due_s + self.period_s, now)
        self._timer = state.loop.call_at(self._due_s, self._tick)
        if not state.topics["diagnostics"].enabled:
            return
        sample = self.sample(now)
        state.topics["diagnostics"].publish(sample, now)
        self._spawn_reads()

    # -- the sample ------------------------------------------------------------------

    def sample(self, now: float) -> DiagnosticsSample:
        """The robot's health now; the next sample's figures of the last period count
        from here."""
        state = self._state
        bus = state.bus.stats
        before = self._before or _Before(now)
        after = _Before(
            now,
            devices={sid: (d.requests, d.timeouts) for sid, d in bus.devices.items()},
            checksum_errors=bus.decoder.checksum_errors,
            saturated=self._saturated_steps(),
        )
        period = _Period(bus, before, after)
        entries = [*self._device_entries(period), self._link_entry(period)]
        entries = _with_faults(entries, sorted(state.faults))
        after.levels = {entry.name: entry.level for entry in entries}
        changes = [
            f"{entry.name} {before.levels.get(entry.name, _OK)} → {entry.level}: {entry.message}"
            for entry in entries
            if entry.level is not before.levels.get(entry.name, _OK)
        ]
        self._before = after
        return DiagnosticsSample(
            stamp_s=now,
            level=DiagnosticLevel.worst(entry.level for entry in entries),
            entries=tuple(entries),
            event="; ".join(changes) or None,
        )

    def _device_entries(self, period: _Period) -> list[DiagnosticEntry]:
        state = self._state
        config = state.config
        entries = []
        for index, name in enumerate(("left_drive", "right_drive")):
            entries.append(self._drive_entry(name, index, period))
        if int(DeviceId.CORE) in state.expected:
            entries.append(self._core_entry(period))
        neck_sid = self._neck_sid()
        if neck_sid is not None:
            entries.append(self._neck_entry(neck_sid, period))
        for ext, sid in zip(_EXT_NAMES, config.ext_servo_ids, strict=False):
            entries.append(self._servo_entry(ext, sid, period))
        return entries

    def _neck_sid(self) -> int | None:
        """The neck's bus id: the one found, else the one looked for; ``None`` when the
        settings expect no neck."""
        state = self._state
        config = state.config
        if state.neck is not None:
            return state.neck.sid
        if config.neck in ("auto", "herkulex"):
            return config.neck_id
        if config.neck == "worm":
            return int(DeviceId.WORM_NECK)
        return None

    # -- what every device has -----------------------------------------------------------

    def _bus_findings(
        self, sid: int, period: _Period
    ) -> tuple[list[_Finding], dict[str, DiagnosticValue]]:
        """A device's reply figures from the bus's counters: present, silent, timeouts,
        latency."""
        state = self._state
        before, after = period.before, period.after
        stats: DeviceStats | None = period.bus.devices.get(sid)
        present = sid in state.present
        values: dict[str, DiagnosticValue] = {"present": present, "timeout_share": None}
        findings: list[_Finding] = []
        if stats is None:
            values.update(
                requests=0,
                replies=0,
                timeouts=0,
                consecutive_timeouts=0,
                latency_p50_ms=None,
                latency_p99_ms=None,
                last_reply_s=None,
            )
        else:
            values.update(
                requests=stats.requests,
                replies=stats.replies,
                timeouts=stats.timeouts,
                consecutive_timeouts=stats.consecutive_timeouts,
                latency_p50_ms=_ms(stats.latency_p50_s),
                latency_p99_ms=_ms(stats.latency_p99_s),
                last_reply_s=None
                if stats.last_reply_at is None
                else round(max(0.0, after.stamp_s - stats.last_reply_at), 3),
            )
        # Checksum failures are counted for the whole line only (a frame that fails its
        # checksum may carry a wrong sid): the link's entry has them.
        values["checksum_errors"] = None
        if not present:
            findings.append((_ERROR, "absent: it does not answer (asked again every 5 s)"))
            return findings, values
        if stats is None:
            return findings, values
        if stats.consecutive_timeouts >= SILENT_TIMEOUTS:
            since = values["last_reply_s"]
            findings.append(
                (
                    _ERROR,
                    f"silent: {stats.consecutive_timeouts} requests in a row unanswered"
                    + ("" if since is None else f", the last reply {since:.1f} s ago"),
                )
            )
        requests_0, timeouts_0 = before.devices.get(sid, (0, 0))
        asked = stats.requests - requests_0
        missed = stats.timeouts - timeouts_0
        share = missed / asked if asked > 0 else 0.0
        values["timeout_share"] = round(share, 4)
        if share > TIMEOUT_WARN_SHARE and stats.consecutive_timeouts < SILENT_TIMEOUTS:
            findings.append((_WARN, f"{missed} of {asked} requests unanswered in the last period"))
        limit_s = state.bus.timeout_s
        if stats.latency_p99_s is not None and stats.latency_p99_s > LATENCY_WARN_SHARE * limit_s:
            findings.append(
                (
                    _WARN,
                    f"slow replies: p99 {stats.latency_p99_s * 1e3:.1f} ms of a "
                    f"{limit_s * 1e3:.0f} ms timeout",
                )
            )
        return findings, values

    def _board_firmware(
        self, sid: int, findings: list[_Finding], values: dict[str, DiagnosticValue]
    ) -> None:
        tag = self._state.firmware.get(sid)
        values["firmware"] = tag
        values["firmware_known"] = firmware_known(tag)
        if tag is not None and not firmware_known(tag):
            findings.append((_WARN, f"firmware tag {tag!r} is {UNKNOWN_FIRMWARE}"))

    # -- each kind of device ---------------------------------------------------------------

    def _drive_entry(self, name: str, index: int, period: _Period) -> DiagnosticEntry:
        sid = _BOARDS[name]
        findings, values = self._bus_findings(sid, period)
        self._board_firmware(sid, findings, values)
        before, after = period.before, period.after
        span_s = after.stamp_s - before.stamp_s
        control = self._state.periodic.get("wheel_encoder")
        steps = span_s / control.period_s if control is not None and control.period_s > 0 else 0.0
        saturated = after.saturated[index] - before.saturated[index]
        share = min(1.0, saturated / steps) if steps > 0 else 0.0
        values["pid_saturated_share"] = round(share, 3)
        values["rejected_counts"] = self._rejected_counts()[index]
        if self._guard_trips is not None:
            stalls, slips = self._guard_trips()
            values["stalls"] = stalls[index]
            values["slips"] = slips[index]
        if share > PID_SATURATION_WARN_SHARE:
            findings.append(
                (
                    _WARN,
                    f"PID at the PWM limit {share:.0%} of the last period: the wheel "
                    "asks more than its motor gives (a slope, a load, a blocked wheel?)",
                )
            )
        return _entry(name, sid, findings, values)

    def _core_entry(self, period: _Period) -> DiagnosticEntry:
        sid = int(DeviceId.CORE)
        findings, values = self._bus_findings(sid, period)
        self._board_firmware(sid, findings, values)
        battery: TbcoreStatusSample | None = self._state.topics["tbcore_status"].latest
        if battery is None or not battery.cell_v:
            values.update(lowest_cell_mv=None, cell_spread_mv=None, pack_v=None, percent=None)
            return _entry("core", sid, findings, values)
        cells_mv = [round(v * 1000) for v in battery.cell_v]
        lowest, spread = min(cells_mv), max(cells_mv) - min(cells_mv)
        values.update(
            lowest_cell_mv=lowest,
            cell_spread_mv=spread,
            pack_v=round(battery.pack_v, 3),
            percent=battery.percent,
            charging=battery.charging,
            docked=battery.docked,
        )
        if "battery_implausible" not in self._state.faults:
            if lowest < LOW_CELL_WARN_MV:
                findings.append((_WARN, f"battery low: a cell at {lowest} mV"))
            if spread > CELL_SPREAD_WARN_MV:
                findings.append((_WARN, f"cells {spread} mV apart: the pack is out of balance"))
        return _entry("core", sid, findings, values)

    def _neck_entry(self, sid: int, period: _Period) -> DiagnosticEntry:
        state = self._state
        if state.neck_kind == "worm":
            findings, values = self._bus_findings(sid, period)
            self._board_firmware(sid, findings, values)
            values["kind"] = "worm"
            sample: WormNeckSample | None = state.topics["new_neck"].latest
            values["position_raw"] = None if sample is None else sample.position_raw
            values["stalled"] = None if sample is None else sample.stalled
            return _entry("neck", sid, findings, values)
        if state.neck_kind == "none":
            findings, values = self._bus_findings(sid, period)
            config = state.config
            looked = {
                "auto": f"HerkuleX at {config.neck_id}, worm gear at {int(DeviceId.WORM_NECK)}",
                "herkulex": f"HerkuleX at {config.neck_id}",
                "worm": f"worm gear at {int(DeviceId.WORM_NECK)}",
            }.get(config.neck, "")
            findings = [(_ERROR, f"absent: no neck answered (looked for {looked})")]
            values["kind"] = None
            return _entry("neck", sid, findings, values)
        return self._servo_entry("neck", sid, period, kind="herkulex")

    def _servo_entry(
        self,
        name: str,
        sid: int,
        period: _Period,
        *,
        kind: str | None = None,
    ) -> DiagnosticEntry:
        state = self._state
        findings, values = self._bus_findings(sid, period)
        if kind is not None:
            values["kind"] = kind
        read = self._models.get(sid)
        values["model"] = None if read is None else read.model
        values["firmware_version"] = None if read is None else read.version
        values["firmware_known"] = read is not None and read.model is not None
        if read is not None and read.model is None:
            findings.append((_WARN, f"servo model (EEP 0) {UNKNOWN_FIRMWARE}"))
        limit = state.config.thermal_limit_raw
        watch = state.servos.get(sid)
        sample: ServoSample | None = None
        if watch is not None and state.topics[watch.stream].enabled:
            sample = watch.sample
        pwm = self._load_pwm.get(sid) if sample is not None and sid in state.present else None
        values.update(
            temperature_raw=None if sample is None else sample.temperature_raw,
            thermal_limit_raw=limit,
            voltage_v=None if sample is None else round(sample.voltage_v, 3),
            torque=None if sample is None else sample.torque.name.lower(),
            status_error=None if sample is None else _flag_names(sample.status_error),
            load_pwm=pwm,
            load_share=None if pwm is None else round(min(1.0, abs(pwm) / _FULL_PWM), 3),
        )
        if sample is not None and f"thermal:{sid}" not in state.faults:
            if sample.temperature_raw >= limit - THERMAL_WARN_MARGIN_RAW:
                findings.append(
                    (_WARN, f"warm: temperature {sample.temperature_raw} raw, the limit {limit}")
                )
            if sample.status_error:
                findings.append((_WARN, f"status errors {_flag_names(sample.status_error)}"))
        if pwm is not None and abs(pwm) > LOAD_WARN_SHARE * _FULL_PWM:
            findings.append((_WARN, f"loaded: PWM {pwm} of {_FULL_PWM}"))
        return _entry(name, sid, findings, values)

    def _link_entry(self, period: _Period) -> DiagnosticEntry:
        state = self._state
        bus = period.bus
        findings: list[_Finding] = []
        link = state.link
        if link is Link.LOST:
            findings.append((_ERROR, "link lost: reopening the port"))
        elif link is Link.RELEASED:
            findings.append(
                (
                    _WARN,
                    "disconnected: connect() opens the port again"
                    if state.disconnected
                    else "the port is released to another program: nothing is read",
                )
            )
        checksum = bus.decoder.checksum_errors
        new_checksum = checksum - period.before.checksum_errors
        if new_checksum > 0:
            findings.append(
                (_WARN, f"{new_checksum} frames failed their checksum in the last period: noise?")
            )
        if bus.wire_utilisation > UTILISATION_WARN:
            findings.append((_WARN, f"the line is {bus.wire_utilisation:.0%} busy"))
        values: dict[str, DiagnosticValue] = {
            "state": link.value,
            "wire_utilisation": round(bus.wire_utilisation, 4),
            "transactions_per_s": round(bus.transactions_per_s, 1),
            "timeouts": sum(d.timeouts for d in bus.devices.values()),
            "checksum_errors": checksum,
            "bytes_discarded": bus.decoder.bytes_discarded,
            "unmatched_replies": bus.unmatched,
            "deadline_misses": bus.deadline_misses,
            "link_losses": bus.link_losses,
            "reconnects": bus.reconnects,
            "watchdog_trips": state.watchdog_trips,
            "watchdog_tripped": state.watchdog_tripped,
        }
        return _entry("link", None, findings, values)

    # -- the reads ---------------------------------------------------------------------------

    def _spawn_reads(self) -> None:
        state = self._state
        if self._reads is not None and not self._reads.done():
            return
        if state.closed or state.link is not Link.CONNECTED:
            return
        self._reads = state.spawn(self._read(), "diagnostics reads")

    async def _read(self) -> None:
        """Each HerkuleX servo's model (once; again after a silence) and PWM."""
        state = self._state
        bus = state.bus.stats
        pwm = SERVO_RAM["pwm"]
        version = SERVO_EEP["firmware_version"]
        for sid, watch in sorted(state.servos.items()):
            stats = bus.devices.get(sid)
            if sid not in state.present or not state.topics[watch.stream].enabled:
                continue  # a stream turned off reads nothing (enable_stream)
            if stats is not None and stats.consecutive_timeouts >= SILENT_TIMEOUTS:
                self._silenced.add(sid)  # its model is read again once it answers
                continue
            if sid in self._silenced or sid not in self._models:
                reply = await self._read_servo(sid, 0, version.end, Memory.EEP)
                if reply is not None and len(reply.data) == version.end:
                    self._silenced.discard(sid)
                    self._models[sid] = _Model(
                        _MODELS.get(reply.data[0]),
                        version.decode(reply.data[version.addr : version.end]),
                    )
            reply = await self._read_servo(sid, pwm.addr, pwm.size)
            if reply is not None and len(reply.data) == pwm.size:
                self._load_pwm[sid] = pwm.decode(reply.data)

    async def _read_servo(
        self, sid: int, addr: int, length: int, memory: Memory = Memory.RAM
    ) -> ReadReply | None:
        """The reply to a read of ``sid``, or ``None``: no answer, the port gone, a reply
        that is not one (each counted by the bus)."""
        state = self._state
        if state.closed or state.link is not Link.CONNECTED or state.releasing is not None:
            return None
        try:
            reply = await state.bus.request(
                read_request(sid, addr, length, memory),
                expect_reply=True,
                retries=0,
                priority=PROBE_PRIORITY,
            )
            return None if reply is None else ReadReply.parse(reply)
        except OhmniError as exc:
            _log.debug("diagnostics: servo %d: %s", sid, exc)
            return None


def _entry(
    name: str, sid: int | None, findings: list[_Finding], values: dict[str, DiagnosticValue]
) -> DiagnosticEntry:
    """An entry: the worst finding's level, and what was found, worst first."""
    level = DiagnosticLevel.worst(level for level, _ in findings)
    ranked = sorted(findings, key=lambda finding: -finding[0].rank)
    message = "; ".join(text for finding_level, text in ranked if finding_level is not _OK)
    return DiagnosticEntry(name, sid, level, message or "ok", values)


def _with_faults(entries: list[DiagnosticEntry], faults: list[str]) -> list[DiagnosticEntry]:
    """Every fault of ``robot_state`` as an ERROR of the entry it names (by sid, or by
    :data:`_FAULT_OWNERS`; else the link's), a WARN for one of :data:`_WARN_FAULTS`."""
    by_name = {entry.name: index for index, entry in enumerate(entries)}
    by_sid = {entry.sid: index for index, entry in enumerate(entries) if entry.sid is not None}
    owned: dict[int, list[str]] = {}
    for fault in faults:
        _, _, tail = fault.partition(":")
        index = (
            by_sid.get(int(tail)) if tail.isdigit() else by_name.get(_FAULT_OWNERS.get(fault, ""))
        )
        if index is None:
            index = by_name["link"]
        owned.setdefault(index, []).append(fault)
    out = list(entries)
    for index, names in owned.items():
        entry = out[index]
        said = f"fault {', '.join(names)}"
        message = said if entry.level is _OK else f"{said}; {entry.message}"
        values = {**entry.values, "faults": ",".join(names)}
        warn_only = all(name.partition(":")[0] in _WARN_FAULTS for name in names)
        level = DiagnosticLevel.worst((entry.level, _WARN if warn_only else _ERROR))
        out[index] = DiagnosticEntry(entry.name, entry.sid, level, message, values)
    return out


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1e3, 3)


def _flag_names(flags: StatusError) -> str:
    """The set bits' names, ``|``-joined (``""``: none)."""
    value = int(flags)
    return "|".join(
        member.name
        for member in StatusError
        if member.name and member.value and value & member.value
    )
