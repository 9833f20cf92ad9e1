"""What ``ohmni probe`` concludes from the bytes it read (sans-IO: no bus, no clock).

Each function here takes replies already read and returns a :class:`Finding`: a status
(``confirmed``, ``differs`` from the assumed profile with the found value, or ``not
found``), the assumed and the found value, the raw bytes it rests on, and the profile
settings it measured. :class:`ProbeReport` gathers them with the devices and the USB
adapter, and gives the profile found (:meth:`ProbeReport.found_settings`), the settings
that differ, the report as JSON and the report to share (:func:`shareable`).
"""

from __future__ import annotations

import dataclasses
import enum
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from ohmni_tb.control.encoder import COUNT_BITS, unwrap_delta
from ohmni_tb.errors import InvalidArgumentError
from ohmni_tb.protocol.core import (
    CELL_COUNT,
    CELL_MAX_MV,
    CELL_MIN_MV,
    CELL_SPREAD_MAX_MV,
    BatteryLayout,
    CoreProfile,
    TbcoreStatus,
    cells_plausible,
    decode_status,
)
from ohmni_tb.protocol.devices import DeviceId, device_name
from ohmni_tb.protocol.drive import DriveProfile, DriveTorque, WheelJogForm
from ohmni_tb.protocol.messages import ReadReply, StatusDetail
from ohmni_tb.protocol.profile import ADDRESS_SETTINGS, PROFILE_SETTINGS, BusProfile
from ohmni_tb.protocol.worm_neck import WORM_MAX, WORM_MIN, WormProfile

__all__ = [
    "CELL_MAX_MV",
    "CELL_MIN_MV",
    "CELL_SPREAD_MAX_MV",
    "HERKULEX_MODELS",
    "LATENCY_READS",
    "LOW_LATENCY_TIMER_MS",
    "MOTION_PWM",
    "MOTION_RESEND_S",
    "MOTION_S",
    "MOVED_TICKS",
    "SAME_CELLS_MV",
    "SEARCH_LENGTH",
    "TORQUE_VALUES",
    "WORM_FLAGS_MAX",
    "AdapterInfo",
    "Device",
    "Finding",
    "ProbeReport",
    "RawRead",
    "Skipped",
    "Status",
    "WheelTrial",
    "battery_candidates",
    "firmware_tag",
    "judge_adapter",
    "judge_battery",
    "judge_devices",
    "judge_ext_servos",
    "judge_torque",
    "judge_wheel_form",
    "judge_worm",
    "model_name",
    "plausible_cells",
    "shareable",
]

# -- the rules, as named constants ---------------------------------------------------------

#: Bytes read at each core-board address while searching for the battery block: the
#: five cells (u16 LE each), the part every layout starts with.
SEARCH_LENGTH = 2 * CELL_COUNT
#: A 10-byte and an 18-byte read of one block show the same cells within this, mV
#: (the pack sags and recovers between the reads).
SAME_CELLS_MV = 50
#: The values of a HerkuleX-like torque register: free, brake, on.
TORQUE_VALUES = frozenset(int(t) for t in DriveTorque)
#: The worm neck's flags byte holds two bits (moving, stalled).
WORM_FLAGS_MAX = 3
#: HerkuleX models by EEP 0 (model no1) when EEP 1 (model no2) is 1.
HERKULEX_MODELS: Mapping[int, str] = {1: "DRS-0101", 2: "DRS-0201", 4: "DRS-0401", 6: "DRS-0601"}
#: STATs per answering device whose reply latency the median is taken of.
LATENCY_READS = 5
#: The PWM of a motion trial (of ±1000): small, but past the drive's dead band.
MOTION_PWM = 80
#: How long one wheel is driven in a trial, s, the command sent again every
#: :data:`MOTION_RESEND_S` (the boards keep the last one; this is not a watchdog).
MOTION_S = 0.3
MOTION_RESEND_S = 0.1
#: A wheel moved when its count changed by more than this, ticks (≈ 1 mm at the rim:
#: ≈ 94.5 ticks a mm; a still wheel's count jitters by a tick or two).
MOVED_TICKS = 100
#: A USB adapter's latency timer at or below this many ms holds replies no longer than
#: the bus's turnaround: the 50 Hz control loop wants it so.
LOW_LATENCY_TIMER_MS = 1
#: The robot's own devices that answer as boards (firmware tag at EEP 0xF1).
_BOARDS = (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE)
_HERKULEX_NECK = int(DeviceId.HERKULEX_NECK)
#: Where the docked byte sits in the tbcore layout (after 5 cells and the current).
_DOCKED_OFFSET = 2 * CELL_COUNT + 2
_WORM_NECK = int(DeviceId.WORM_NECK)


class Status(enum.StrEnum):
    """What a probe found against the assumed profile."""

    CONFIRMED = "confirmed"
    DIFFERS = "differs"
    NOT_FOUND = "not found"


@dataclass(frozen=True, slots=True)
class RawRead:
    """One request and its reply, as they were on the wire.

    Attributes:
        what: What was asked, in words (``"core RAM 0xA0, 18 bytes"``).
        request: The request packet's bytes.
        reply: The reply packet's bytes, or ``None`` when none came.
    """

    what: str
    request: bytes
    reply: bytes | None

    def as_dict(self) -> dict[str, Any]:
        """For JSON: hex bytes (``"FF FF 09 ..."``)."""
        return {
            "what": self.what,
            "request": _hex(self.request),
            "reply": None if self.reply is None else _hex(self.reply),
        }


@dataclass(frozen=True, slots=True)
class Finding:
    """One conclusion of the probe.

    Attributes:
        name: ``devices``, ``usb_adapter``, ``battery``, ``drive_torque``, ``worm_neck``,
            ``ext_servos`` or ``wheel_form``.
        status: Confirmed, differs (``found`` is what the robot speaks) or not found.
        assumed: What the profile assumes (JSON-able).
        found: What the robot showed (JSON-able), or ``None``.
        raw: The requests and replies it rests on.
        detail: One line for people.
        settings: The profile settings this finding measured (confirmed or found
            otherwise): what ``ohmni probe --write`` saves.
    """

    name: str
    status: Status
    assumed: Any
    found: Any
    raw: tuple[RawRead, ...] = ()
    detail: str = ""
    settings: Mapping[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """For JSON."""
        return {
            "name": self.name,
            "status": self.status.value,
            "assumed": self.assumed,
            "found": self.found,
            "raw": [r.as_dict() for r in self.raw],
            "detail": self.detail,
            "settings": dict(self.settings),
        }


@dataclass(frozen=True, slots=True)
class Skipped:
    """A finding the probe did not make, and why (``--allow-motion`` not given, no worm
    neck, not a USB adapter, the ids not scanned)."""

    name: str
    why: str

    def as_dict(self) -> dict[str, Any]:
        """For JSON."""
        return {"name": self.name, "why": self.why}


@dataclass(frozen=True, slots=True)
class Device:
    """One id that answered the scan.

    Attributes:
        sid: Its bus id.
        kind: ``"board"`` (a firmware tag at EEP 0xF1), ``"herkulex"`` (a model at EEP 0)
            or ``"unknown"`` (it answers STAT only).
        firmware: The board's firmware tag, or ``None``.
        model: The HerkuleX model (``"DRS-0101"``...), or ``None``.
        latency_s: Median request-written → reply-parsed time of its STATs, s.
        status_error: Its status error byte at the scan.
        status_detail: Its status detail byte at the scan.
        raw: Its first STAT and the identifying read.
    """

    sid: int
    kind: str
    firmware: str | None
    model: str | None
    latency_s: float | None
    status_error: int
    status_detail: int
    raw: tuple[RawRead, ...] = ()

    @property
    def name(self) -> str:
        """The device map's short name (``left``, ``core``, ``sid13``...)."""
        return device_name(self.sid)

    def as_dict(self) -> dict[str, Any]:
        """For JSON."""
        return {
            "sid": self.sid,
            "name": self.name,
            "kind": self.kind,
            "firmware": self.firmware,
            "model": self.model,
            "latency_ms": None if self.latency_s is None else round(self.latency_s * 1e3, 3),
            "status_error": self.status_error,
            "status_detail": self.status_detail,
        }


@dataclass(frozen=True, slots=True)
class AdapterInfo:
    """The serial port's USB adapter, as the operating system shows it.

    Attributes:
        port: The port as opened.
        usb: Whether it is a USB serial adapter (found under ``/sys/bus/usb-serial``).
        tty: Its kernel name (``ttyUSB0``), when it is one.
        latency_timer_ms: Its latency timer (``latency_timer`` in sysfs), or ``None``
            when it has none or it cannot be read.
        low_latency: The tty's ASYNC_LOW_LATENCY flag (TIOCGSERIAL), or ``None`` when
            it cannot be read.
        usb_id: ``vvvv:pppp``, when known.
        product: The adapter's product string, when known.
        serial_number: The adapter's serial number, when known (left out of a shared
            report unless asked for).
        sysfs_path: The sysfs directory read, when one was.
    """

    port: str
    usb: bool
    tty: str | None = None
    latency_timer_ms: int | None = None
    low_latency: bool | None = None
    usb_id: str | None = None
    product: str | None = None
    serial_number: str | None = None
    sysfs_path: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """For JSON: every field, by name."""
        return dataclasses.asdict(self)


@dataclass(frozen=True, slots=True)
class WheelTrial:
    """One wheel driven in one command form (``ohmni probe --allow-motion``).

    Attributes:
        form: The wheel command's form tried.
        wheel: 0 left, 1 right: the wheel given the PWM (the other got 0).
        pwm: The PWM the board got (board frame, not mirrored).
        before: Both raw counts before.
        after: Both raw counts once the stop was confirmed.
        raw: The count reads and one of the commands sent.
    """

    form: WheelJogForm
    wheel: int
    pwm: int
    before: tuple[int, int]
    after: tuple[int, int]
    raw: tuple[RawRead, ...] = ()

    @property
    def deltas(self) -> tuple[int, int]:
        """Each wheel's count change, ticks (int32 wrap undone)."""
        return (
            unwrap_delta(self.before[0], self.after[0], COUNT_BITS),
            unwrap_delta(self.before[1], self.after[1], COUNT_BITS),
        )

    @property
    def moved(self) -> tuple[bool, bool]:
        """Whether each wheel moved (more than :data:`MOVED_TICKS`)."""
        left, right = self.deltas
        return abs(left) > MOVED_TICKS, abs(right) > MOVED_TICKS

    @property
    def moved_alone(self) -> bool:
        """The driven wheel moved and the other did not."""
        moved = self.moved
        return moved[self.wheel] and not moved[1 - self.wheel]

    def as_dict(self) -> dict[str, Any]:
        """For JSON."""
        delta = self.deltas[self.wheel]
        return {
            "form": self.form.name.lower(),
            "wheel": _WHEELS[self.wheel],
            "pwm": self.pwm,
            "before": list(self.before),
            "after": list(self.after),
            "ticks": list(self.deltas),
            "moved": list(self.moved),
            "sign": _sign_word(delta, self.pwm) if self.moved[self.wheel] else None,
        }


# -- devices ---------------------------------------------------------------------------------


def model_name(data: bytes) -> str | None:
    """The HerkuleX model of an EEP 0..1 read (``(1, 1)`` → ``"DRS-0101"``), or ``None``
    when the two bytes are not a HerkuleX model."""
    if len(data) != 2 or data[1] != 1:
        return None
    return HERKULEX_MODELS.get(data[0])


def firmware_tag(data: bytes) -> str | None:
    """A board's firmware tag (EEP 0xF1, ASCII), or ``None`` when it is empty or not text."""
    text = data.rstrip(b"\x00")
    if not text or any(b < 0x20 or b > 0x7E for b in text):
        return None
    return text.decode("ascii")


def judge_devices(devices: Sequence[Device], scanned: Iterable[int]) -> Finding | Skipped:
    """Every board the robot has (0, 1, 20, a neck at 3 or 4) answered, as what it is."""
    ids = set(scanned)
    wanted = [int(sid) for sid in _BOARDS if sid in ids]
    necks = [sid for sid in (_HERKULEX_NECK, _WORM_NECK) if sid in ids]
    if not wanted and not necks:
        return Skipped("devices", "the scan covered none of the boards (0, 1, 20) nor a neck")
    by_sid = {d.sid: d for d in devices}
    # A neck is a HerkuleX servo at 3 or the worm gear's board at 4.
    assumed = {"boards": wanted, "neck": necks}
    found = [d.sid for d in devices]
    raw = tuple(r for d in devices for r in d.raw[:1])
    missing = [sid for sid in wanted if sid not in by_sid or by_sid[sid].kind != "board"]
    neck_ok = not necks or (
        (_HERKULEX_NECK in by_sid and by_sid[_HERKULEX_NECK].kind == "herkulex")
        or (_WORM_NECK in by_sid and by_sid[_WORM_NECK].kind == "board")
    )
    if not devices:
        return Finding(
            "devices", Status.NOT_FOUND, assumed, [], raw, "no id answered: wrong port or speed?"
        )
    if not missing and neck_ok:
        return Finding("devices", Status.CONFIRMED, assumed, found, raw, _answered(devices))
    problems = [f"{sid} ({device_name(sid)}) did not answer as a board" for sid in missing]
    if not neck_ok:
        problems.append("no neck answered (HerkuleX at 3, worm gear at 4)")
    return Finding("devices", Status.DIFFERS, assumed, found, raw, "; ".join(problems))


def _answered(devices: Sequence[Device]) -> str:
    return f"{len(devices)} answered: " + ", ".join(str(d.sid) for d in devices)


def median_latency(samples: Sequence[float]) -> float | None:
    """The median of the reply latencies, or ``None`` without any."""
    return statistics.median(samples) if samples else None


# -- the USB adapter -------------------------------------------------------------------------


def judge_adapter(adapter: AdapterInfo, usb_latency_ms: int) -> Finding | Skipped:
    """The adapter's latency timer: ``confirmed`` at 1 ms, ``differs`` with what to change
    above it; ``usb_latency_ms`` is the setting the bus waits by."""
    if not adapter.usb:
        return Skipped("usb_adapter", "not a USB serial adapter")
    assumed = {"latency_timer_ms": LOW_LATENCY_TIMER_MS}
    found = {
        "latency_timer_ms": adapter.latency_timer_ms,
        "low_latency": adapter.low_latency,
        "tty": adapter.tty,
        "usb_id": adapter.usb_id,
    }
    timer = adapter.latency_timer_ms
    flag = {True: "set", False: "clear", None: "unknown"}[adapter.low_latency]
    if timer is None:
        return Finding(
            "usb_adapter",
            Status.NOT_FOUND,
            assumed,
            found,
            detail=f"{adapter.tty}: no latency_timer to read (not an FTDI adapter, or sysfs "
            f"is not readable); the low-latency flag is {flag}",
        )
    if timer <= LOW_LATENCY_TIMER_MS:
        detail = f"{adapter.tty}: latency timer {timer} ms, low-latency flag {flag}"
        if usb_latency_ms > timer:
            detail += (
                f"; usb_latency_ms = {usb_latency_ms} may be lowered to {timer} once the "
                "timer is set for good (the udev rule)"
            )
        return Finding("usb_adapter", Status.CONFIRMED, assumed, found, detail=detail)
    sysfs = f"/sys/bus/usb-serial/devices/{adapter.tty}/latency_timer"
    advice = (
        f"{adapter.tty}: the adapter holds replies up to {timer} ms: lower it now with "
        f'`echo 1 | sudo tee {sysfs}`, for good with the udev rule ACTION=="add", '
        'SUBSYSTEM=="usb-serial", DRIVER=="ftdi_sio", ATTR{latency_timer}="1" '
        "(/etc/udev/rules.d/99-ohmni-ftdi.rules), then set usb_latency_ms = 1"
    )
    if usb_latency_ms < timer:
        advice += (
            f"; until then usb_latency_ms = {usb_latency_ms} is below the timer and "
            f"replies will be missed: set usb_latency_ms = {timer}"
        )
    else:
        advice += f"; until then keep usb_latency_ms = {usb_latency_ms}"
    return Finding("usb_adapter", Status.DIFFERS, assumed, found, detail=advice)


# -- the battery -----------------------------------------------------------------------------


def plausible_cells(data: bytes) -> tuple[int, ...] | None:
    """The five cells (mV) when ``data`` starts with five plausible LiFePO4 cells (u16 LE,
    each :data:`CELL_MIN_MV`..:data:`CELL_MAX_MV`, spread at most
    :data:`CELL_SPREAD_MAX_MV`), else ``None``."""
    if len(data) < SEARCH_LENGTH:
        return None
    cells = tuple(int.from_bytes(data[i : i + 2], "little") for i in range(0, SEARCH_LENGTH, 2))
    return cells if cells_plausible(cells) else None


def battery_candidates(reads: Mapping[int, bytes]) -> list[int]:
    """The addresses, lowest first, whose :data:`SEARCH_LENGTH`-byte read holds plausible
    cells (``reads``: address → the bytes read there)."""
    return sorted(addr for addr, data in reads.items() if plausible_cells(data) is not None)


def judge_battery(
    assumed: CoreProfile,
    assumed_read: ReadReply | None,
    *,
    found_addr: int | None = None,
    cells_read: ReadReply | None = None,
    tbcore_read: ReadReply | None = None,
    raw: Sequence[RawRead] = (),
    candidates: Sequence[int] = (),
) -> Finding:
    """The battery block: at the assumed place and layout (confirmed), found elsewhere or
    in another layout by the search (differs), or nowhere (not found).

    Args:
        assumed: The profile's battery block.
        assumed_read: The read of the assumed address and length.
        found_addr: Where the search found plausible cells (``None``: nowhere, or no
            search because the assumed block was plausible).
        cells_read: The :data:`SEARCH_LENGTH`-byte read at ``found_addr``.
        tbcore_read: The 18-byte (tbcore) read at ``found_addr``, if it was answered.
        raw: The reads to show.
        candidates: Every address the search found plausible (noted when several).
    """
    assumed_value = _battery_value(assumed.status_addr, assumed.status_size, assumed.layout)
    status = _decoded(assumed_read, assumed.layout)
    if status is not None:
        return Finding(
            "battery",
            Status.CONFIRMED,
            assumed_value,
            {**assumed_value, **_status_fields(status)},
            tuple(raw),
            f"5 cells {_cells_text(status.cell_mv)} at 0x{assumed.status_addr:02X} "
            f"({assumed.layout.value}, {assumed.status_size} bytes)",
            {
                "battery_addr": assumed.status_addr,
                "battery_length": assumed.status_size,
                "battery_layout": assumed.layout.value,
            },
        )
    if found_addr is None or cells_read is None:
        why = "no core board answered" if assumed_read is None else "no address of 0..255"
        return Finding(
            "battery",
            Status.NOT_FOUND,
            assumed_value,
            None,
            tuple(raw),
            f"{why} holds five LiFePO4 cells ({CELL_MIN_MV}..{CELL_MAX_MV} mV, spread "
            f"≤ {CELL_SPREAD_MAX_MV} mV)",
        )
    cells = plausible_cells(cells_read.data)
    layout, length = BatteryLayout.CELLS, BatteryLayout.CELLS.size
    if tbcore_read is not None and cells is not None:
        tbcore = _decoded(tbcore_read, BatteryLayout.TBCORE)
        if tbcore is not None and all(
            abs(a - b) <= SAME_CELLS_MV for a, b in zip(tbcore.cell_mv, cells, strict=True)
        ):
            layout, length = BatteryLayout.TBCORE, BatteryLayout.TBCORE.size
    read = tbcore_read if layout is BatteryLayout.TBCORE else cells_read
    decoded = _decoded(read, layout)
    found = _battery_value(found_addr, length, layout)
    fields = _status_fields(decoded) if decoded is not None else {}
    same = (found_addr, length, layout) == (
        assumed.status_addr,
        assumed.status_size,
        assumed.layout,
    )
    others = [a for a in candidates if a != found_addr]
    detail = (
        f"5 cells {_cells_text(decoded.cell_mv if decoded else ())} at 0x{found_addr:02X} "
        f"({layout.value}, {length} bytes)"
    )
    if others:
        detail += "; plausible cells also at " + ", ".join(f"0x{a:02X}" for a in others)
    return Finding(
        "battery",
        Status.CONFIRMED if same else Status.DIFFERS,
        assumed_value,
        {**found, **fields},
        tuple(raw),
        detail,
        {"battery_addr": found_addr, "battery_length": length, "battery_layout": layout.value},
    )


def _battery_value(addr: int, length: int, layout: BatteryLayout) -> dict[str, Any]:
    return {"battery_addr": addr, "battery_length": length, "battery_layout": layout.value}


def _decoded(read: ReadReply | None, layout: BatteryLayout) -> TbcoreStatus | None:
    """The block of ``read`` in ``layout`` when it is a plausible one: five plausible
    cells and, in the tbcore layout, a docked byte of 0 or 1."""
    if read is None or len(read.data) < layout.size:
        return None
    if plausible_cells(read.data) is None:
        return None
    if layout is BatteryLayout.TBCORE and read.data[_DOCKED_OFFSET] not in (0, 1):
        return None
    return decode_status(read.data, layout)


def _status_fields(status: TbcoreStatus) -> dict[str, Any]:
    return {
        "cell_mv": list(status.cell_mv),
        "pack_mv": status.pack_mv,
        "charging_current_ma": status.charging_current_ma,
        "docked": status.docked,
        "fet_status": status.fet_status,
        "status": list(status.status),
        "percent": status.percent,
    }


def _cells_text(cells: Sequence[int]) -> str:
    return "/".join(str(mv) for mv in cells) + " mV"


# -- the drive boards' torque register -------------------------------------------------------


def judge_torque(
    profile: DriveProfile,
    reads: Mapping[int, ReadReply | None],
    flags_before: Mapping[int, StatusDetail | None],
    raw: Sequence[RawRead] = (),
) -> Finding:
    """Both drive boards' ``torque_addr`` read as a torque state (0x00, 0x40, 0x60).

    A board that flags the read as outside its registers (EXCEED_REG_RANGE set by this
    read, clear in its STAT just before) has no register there, whatever bytes it sent.
    """
    addr = profile.torque_addr
    assumed = {"drive_torque_addr": addr, "values": sorted(TORQUE_VALUES)}
    found: dict[str, Any] = {}
    problems: list[str] = []
    for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE):
        name = _WHEELS[int(sid)]
        read = reads.get(int(sid))
        if read is None:
            found[name] = None
            problems.append(f"the {name} board did not answer")
            continue
        value = read.data[0] if len(read.data) == 1 else None
        found[name] = value
        if _newly_flagged(read, flags_before.get(int(sid))):
            problems.append(f"the {name} board flagged RAM {addr} as outside its registers")
        elif value not in TORQUE_VALUES:
            shown = "nothing" if value is None else f"0x{value:02X}"
            problems.append(f"the {name} board's RAM {addr} reads {shown}, not a torque state")
    if problems:
        return Finding(
            "drive_torque", Status.NOT_FOUND, assumed, found, tuple(raw), "; ".join(problems)
        )
    names = ", ".join(f"{k} {DriveTorque(v).name.lower()}" for k, v in found.items())
    return Finding(
        "drive_torque",
        Status.CONFIRMED,
        assumed,
        found,
        tuple(raw),
        f"RAM {addr}: {names}",
        {"drive_torque_addr": addr},
    )


def _newly_flagged(read: ReadReply, before: StatusDetail | None) -> bool:
    """This read set EXCEED_REG_RANGE (clear before it): the address is not a register.
    With the flag already set (it is sticky) the flags say nothing."""
    if before is None or before & StatusDetail.EXCEED_REG_RANGE:
        return False
    return bool(read.status_detail & StatusDetail.EXCEED_REG_RANGE)


# -- the worm neck ---------------------------------------------------------------------------


def judge_worm(
    profile: WormProfile,
    target: ReadReply | None,
    feedback: ReadReply | None,
    flags_before: StatusDetail | None,
    raw: Sequence[RawRead] = (),
) -> Finding:
    """The worm neck's target (read first) and feedback registers: a target and a
    position within −127000..120000, flags ≤ 3, neither read flagged as out of range."""
    assumed = {
        "worm_target_addr": profile.target_addr,
        "worm_feedback_addr": profile.feedback_addr,
    }
    found: dict[str, Any] = {"target": None, "position": None, "flags": None}
    problems: list[str] = []
    if target is None:
        problems.append("the target read got no reply")
    elif _newly_flagged(target, flags_before):
        problems.append(f"RAM 0x{profile.target_addr:02X} is outside its registers")
    elif len(target.data) != 4:
        problems.append(f"the target read carried {len(target.data)} bytes, not 4")
    else:
        value = int.from_bytes(target.data, "little", signed=True)
        found["target"] = value
        if not WORM_MIN <= value <= WORM_MAX:
            problems.append(f"target {value} is outside {WORM_MIN}..{WORM_MAX}")
    before = flags_before if target is None else target.status_detail
    if feedback is None:
        problems.append("the feedback read got no reply")
    elif _newly_flagged(feedback, before):
        problems.append(f"RAM 0x{profile.feedback_addr:02X} is outside its registers")
    elif len(feedback.data) != 5:
        problems.append(f"the feedback read carried {len(feedback.data)} bytes, not 5")
    else:
        position = int.from_bytes(feedback.data[:4], "little", signed=True)
        flags = feedback.data[4]
        found["position"], found["flags"] = position, flags
        if not WORM_MIN <= position <= WORM_MAX:
            problems.append(f"position {position} is outside {WORM_MIN}..{WORM_MAX}")
        if flags > WORM_FLAGS_MAX:
            problems.append(f"flags 0x{flags:02X} use more than the two flag bits")
    if problems:
        return Finding(
            "worm_neck", Status.NOT_FOUND, assumed, found, tuple(raw), "; ".join(problems)
        )
    return Finding(
        "worm_neck",
        Status.CONFIRMED,
        assumed,
        found,
        tuple(raw),
        f"target {found['target']}, position {found['position']}, flags {found['flags']}",
        dict(assumed),
    )


# -- the external servos ---------------------------------------------------------------------


def judge_ext_servos(
    assumed: Sequence[int], devices: Sequence[Device], scanned: Iterable[int]
) -> Finding | Skipped:
    """The HerkuleX servos other than the neck at 3, against ``ext_servo_ids``."""
    ids = set(scanned)
    servos = [d.sid for d in devices if d.kind == "herkulex" and d.sid != _HERKULEX_NECK]
    raw = tuple(r for d in devices if d.sid in servos for r in d.raw[1:2])
    unscanned = [sid for sid in assumed if sid not in ids]
    if unscanned and not servos:
        shown = ", ".join(map(str, unscanned))
        return Skipped("ext_servos", f"the scan did not cover the assumed ids {shown}")
    assumed_list = list(assumed)
    if sorted(servos) == sorted(assumed_list):
        return Finding(
            "ext_servos",
            Status.CONFIRMED,
            assumed_list,
            servos,
            raw,
            _servo_text(servos, devices),
            {"ext_servo_ids": list(assumed)},
        )
    settings: dict[str, Any] = {}
    try:
        BusProfile(ext_servo_ids=tuple(servos))
    except InvalidArgumentError as exc:
        note = f"; not a profile: {exc}"
    else:
        settings["ext_servo_ids"] = servos
        note = ""
    if unscanned:
        note += "; ids not scanned: " + ", ".join(map(str, unscanned))
    return Finding(
        "ext_servos",
        Status.DIFFERS,
        assumed_list,
        servos,
        raw,
        _servo_text(servos, devices) + note,
        settings,
    )


def _servo_text(servos: Sequence[int], devices: Sequence[Device]) -> str:
    if not servos:
        return "no external HerkuleX servo answered"
    models = {d.sid: d.model for d in devices}
    return ", ".join(f"{sid} {models.get(sid)}" for sid in servos)


# -- the wheel command -----------------------------------------------------------------------


def judge_wheel_form(profile: DriveProfile, trials: Sequence[WheelTrial]) -> Finding:
    """The form that moved each wheel alone (+PWM → +counts expected in the board frame)."""
    assumed = profile.wheel_form.name.lower()
    forms: list[WheelJogForm] = []
    for form in WheelJogForm:
        tried = [t for t in trials if t.form is form]
        if {t.wheel for t in tried} == {0, 1} and all(t.moved_alone for t in tried):
            forms.append(form)
    raw = tuple(r for t in trials for r in t.raw)
    tried_text = "; ".join(_trial_text(t) for t in trials)
    mirrored = (
        f"right_mirrored cannot be measured by counts (each board counts its own PWM's "
        f"way): kept as assumed ({str(profile.right_mirrored).lower()})"
    )
    per_trial = [t.as_dict() for t in trials]
    if not forms:
        return Finding(
            "wheel_form",
            Status.NOT_FOUND,
            assumed,
            {"form": None, "trials": per_trial},
            raw,
            f"no form moved each wheel alone: {tried_text}; {mirrored}",
        )
    form = profile.wheel_form if profile.wheel_form in forms else forms[0]
    chosen = [t for t in trials if t.form is form]
    signs = {_WHEELS[t.wheel]: _sign_word(t.deltas[t.wheel], t.pwm) for t in chosen}
    found = {
        "form": form.name.lower(),
        **{f"{_WHEELS[t.wheel]}_ticks": t.deltas[t.wheel] for t in chosen},
        **{f"{k}_sign": v for k, v in signs.items()},
        "trials": per_trial,
    }
    detail = f"{form.name} moved each wheel alone: {tried_text}; {mirrored}"
    if len(forms) > 1:
        detail = f"both forms moved the wheels; {detail}"
    return Finding(
        "wheel_form",
        Status.CONFIRMED if form is profile.wheel_form else Status.DIFFERS,
        assumed,
        found,
        raw,
        detail,
        {"wheel_form": form.name.lower()},
    )


def _trial_text(trial: WheelTrial) -> str:
    left, right = trial.deltas
    text = f"{trial.form.name} {_WHEELS[trial.wheel]} {left:+d}/{right:+d} ticks"
    if trial.moved[trial.wheel]:
        text += f" ({_sign_word(trial.deltas[trial.wheel], trial.pwm)})"
    return text


def _sign_word(delta: int, pwm: int) -> str:
    if (delta > 0) == (pwm > 0):
        return "+PWM gives +counts, as expected"
    return "reversed: +PWM gives -counts"


_WHEELS = ("left", "right")


# -- the report ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ProbeReport:
    """Everything one probe found (``ohmni probe``, :func:`ohmni_tb.probe.probe`).

    Attributes:
        port: The port probed.
        assumed: The profile the probe compared against.
        findings: One per thing judged, in the order of the report.
        skipped: What was not judged, and why.
        devices: Every id that answered, lowest first.
        adapter: The serial port's USB adapter.
        scanned: The ids the scan asked.
        elapsed_s: How long the probe took (loop clock).
        motion: Whether the wheels were allowed to turn.
    """

    port: str
    assumed: BusProfile
    findings: tuple[Finding, ...]
    skipped: tuple[Skipped, ...]
    devices: tuple[Device, ...]
    adapter: AdapterInfo
    scanned: tuple[int, ...]
    elapsed_s: float
    motion: bool

    def finding(self, name: str) -> Finding | None:
        """The finding called ``name``, or ``None``."""
        return next((f for f in self.findings if f.name == name), None)

    def measured(self) -> dict[str, Any]:
        """The profile settings measured (confirmed, or found otherwise): what
        ``--write`` saves."""
        out: dict[str, Any] = {}
        for finding in self.findings:
            out.update(finding.settings)
        return {name: out[name] for name in PROFILE_SETTINGS if name in out}

    def found_settings(self) -> dict[str, Any]:
        """The profile the robot speaks, as settings: the assumed one with every measured
        setting in place."""
        return {**_json_settings(self.assumed.settings()), **self.measured()}

    def found_profile(self) -> BusProfile:
        """:meth:`found_settings` as a :class:`~ohmni_tb.protocol.profile.BusProfile`."""
        return BusProfile.from_settings(self.found_settings())

    def differing(self) -> dict[str, tuple[Any, Any]]:
        """Setting → (assumed, found) for every measured setting that differs."""
        assumed = _json_settings(self.assumed.settings())
        return {
            name: (assumed[name], value)
            for name, value in self.measured().items()
            if assumed[name] != value
        }

    def to_json(self) -> dict[str, Any]:
        """The report as one JSON object."""
        return {
            "port": self.port,
            "motion": self.motion,
            "elapsed_s": round(self.elapsed_s, 3),
            "scanned": _ranges(self.scanned),
            "findings": [f.as_dict() for f in self.findings],
            "skipped": [s.as_dict() for s in self.skipped],
            "devices": [d.as_dict() for d in self.devices],
            "adapter": self.adapter.as_dict(),
            "profile": self.found_settings(),
            "measured": list(self.measured()),
            "differs": {
                name: {"assumed": old, "found": new}
                for name, (old, new) in self.differing().items()
            },
        }


def shareable(
    report: Mapping[str, Any], *, serials: bool = False, environment: Mapping[str, Any] = {}
) -> dict[str, Any]:
    """A report (:meth:`ProbeReport.to_json`) to attach to a bug report: the adapter's
    serial number left out unless ``serials``, and ``environment`` (the package version,
    Python, the OS) added under ``"environment"``."""
    shared = dict(report)
    adapter = dict(shared.get("adapter") or {})
    if not serials and adapter.get("serial_number") is not None:
        adapter["serial_number"] = "(left out: --share-serials includes it)"
    shared["adapter"] = adapter
    return {"environment": dict(environment), **shared}


def setting_text(name: str, value: Any) -> str:
    """A setting's value for people: addresses in hex, lists comma-separated."""
    if name in ADDRESS_SETTINGS and isinstance(value, int):
        return f"0x{value:02X}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(str(v) for v in value) + "]"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


def _json_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in settings.items()}


def _ranges(ids: Sequence[int]) -> str:
    """``0..253``, ``0..4,11,20``: the ids scanned, compactly."""
    parts: list[str] = []
    ordered = sorted(set(ids))
    i = 0
    while i < len(ordered):
        j = i
        while j + 1 < len(ordered) and ordered[j + 1] == ordered[j] + 1:
            j += 1
        parts.append(str(ordered[i]) if i == j else f"{ordered[i]}..{ordered[j]}")
        i = j + 1
    return ",".join(parts)


def _hex(data: bytes) -> str:
    return data.hex(" ").upper()
