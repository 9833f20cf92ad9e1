"""The probe's reads (and, when allowed, its wheel trials) on a :class:`~ohmni_tb.bus.Bus`.

:func:`probe` asks the bus and hands the replies to the judges of
:mod:`ohmni_tb.probe.findings`; :func:`probe_port` opens a port for it and closes it again,
with stops in both wheel-command forms last when the wheels were allowed to turn.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Iterable, Sequence
from pathlib import Path

from ohmni_tb.bus import DEFAULT_TIMEOUT_S, Bus, ReplyPacket
from ohmni_tb.errors import (
    BusTimeoutError,
    DeviceUnavailableError,
    MalformedReplyError,
    OhmniError,
    OutOfRangeError,
)
from ohmni_tb.herkulex.commands import model_read, stat
from ohmni_tb.probe.adapter import SYSFS_ROOT, read_adapter
from ohmni_tb.probe.findings import (
    LATENCY_READS,
    MOTION_PWM,
    MOTION_RESEND_S,
    MOTION_S,
    SEARCH_LENGTH,
    AdapterInfo,
    Device,
    Finding,
    ProbeReport,
    RawRead,
    Skipped,
    Status,
    WheelTrial,
    battery_candidates,
    firmware_tag,
    judge_adapter,
    judge_battery,
    judge_devices,
    judge_ext_servos,
    judge_torque,
    judge_wheel_form,
    judge_worm,
    median_latency,
    model_name,
)
from ohmni_tb.protocol import Packet, ReadReply, StatusDetail, StatusReply, encode_packet
from ohmni_tb.protocol.core import BatteryLayout
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.drive import (
    PWM_LIMIT,
    DriveProfile,
    WheelJogForm,
    parse_count,
    read_count,
    read_firmware_tag,
    wheel_command,
)
from ohmni_tb.protocol.messages import read_request
from ohmni_tb.protocol.profile import DEFAULT_PROFILE, BusProfile
from ohmni_tb.protocol.worm_neck import read_feedback
from ohmni_tb.safety import stop_wheels
from ohmni_tb.transport import SerialTransport, Transport, open_transport

__all__ = [
    "ALL_IDS",
    "DEFAULT_USB_LATENCY_MS",
    "MAX_PWM",
    "MIN_PWM",
    "probe",
    "probe_port",
    "wheel_stops",
]

#: Every id a device may have (0xFE is broadcast).
ALL_IDS = range(0xFE)
#: The adapter latency the bus assumes unless told (RobotConfig.usb_latency_ms).
DEFAULT_USB_LATENCY_MS = 16
#: The PWM a wheel trial may use: past the dead band, far from full speed.
MIN_PWM, MAX_PWM = 20, 300
_BOARD_IDS = frozenset(
    int(d) for d in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE, DeviceId.CORE, DeviceId.WORM_NECK)
)
_DRIVES = (int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE))
_CORE = int(DeviceId.CORE)
_WORM = int(DeviceId.WORM_NECK)
#: Core-board RAM addresses the battery search reads.
_ADDRESSES = range(0x100)


def wheel_stops() -> tuple[Packet, Packet]:
    """The zero wheel command in both forms (S_JOG, I_JOG): a board stops whichever it
    takes."""
    return (
        wheel_command(0, 0, DriveProfile(wheel_form=WheelJogForm.S_JOG)),
        wheel_command(0, 0, DriveProfile(wheel_form=WheelJogForm.I_JOG)),
    )


async def probe(
    bus: Bus,
    *,
    profile: BusProfile = DEFAULT_PROFILE,
    ids: Iterable[int] = ALL_IDS,
    allow_motion: bool = False,
    pwm: int = MOTION_PWM,
    adapter: AdapterInfo | None = None,
    usb_latency_ms: int = DEFAULT_USB_LATENCY_MS,
    port: str = "",
) -> ProbeReport:
    """Find what the robot on ``bus`` speaks, against ``profile``.

    Read-only unless ``allow_motion``: STAT to every id of ``ids`` (a silent id costs one
    bus timeout), each answering one's firmware tag or HerkuleX model, the battery block
    (searched over the core board's RAM when it is not where assumed), the drive boards'
    torque register, the worm neck's registers. With ``allow_motion`` each wheel is then
    driven alone at ``pwm`` for 0.3 s in each wheel-command form, stopped in both forms
    and the stop confirmed by the counts (:func:`~ohmni_tb.safety.stop_wheels`) before
    the next; an error or a cancellation meanwhile sends the stops in both forms first.

    Args:
        bus: A started bus on the robot's port.
        profile: The profile to compare against (the settings').
        ids: The ids to scan, 0..253.
        allow_motion: Let the wheels turn to find the wheel command's form.
        pwm: The trial PWM, 20..300 of 1000.
        adapter: The port's USB adapter (:func:`~ohmni_tb.probe.adapter.read_adapter`).
        usb_latency_ms: The ``usb_latency_ms`` setting, for the adapter's advice.
        port: The port's name for the report.

    Raises:
        OutOfRangeError: An id or ``pwm`` is out of range; nothing was sent.
        StopNotConfirmedError: A trial's stop was not confirmed: the wheels may still be
            moving (stops in both forms were sent).
        TransportError: The link failed.
    """
    scanned = tuple(sorted(set(ids)))
    for sid in scanned:
        if isinstance(sid, bool) or not isinstance(sid, int) or not 0 <= sid < 0xFE:
            raise OutOfRangeError("id", sid, 0, 0xFD)
    if isinstance(pwm, bool) or not isinstance(pwm, int) or not MIN_PWM <= pwm <= MAX_PWM:
        raise OutOfRangeError("pwm", pwm, MIN_PWM, MAX_PWM, f"of {PWM_LIMIT}")
    loop = asyncio.get_running_loop()
    started = loop.time()
    reader = _Reader(bus)
    devices, flags = await _scan(reader, scanned)
    present = {d.sid for d in devices}
    results: list[Finding | Skipped] = [judge_devices(devices, scanned)]
    results.append(judge_adapter(adapter or AdapterInfo(port=port, usb=False), usb_latency_ms))
    results.append(await _battery(reader, profile, present, scanned))
    results.append(await _torque(reader, profile.drive, flags, present, scanned))
    results.append(await _worm(reader, profile, flags, present, scanned))
    results.append(judge_ext_servos(profile.ext_servo_ids, devices, scanned))
    if not allow_motion:
        results.append(Skipped("wheel_form", "the wheels turn to find it: pass --allow-motion"))
    elif not set(_DRIVES) <= present:
        results.append(Skipped("wheel_form", "both drive boards (0, 1) must answer"))
    else:
        trials = await _wheel_trials(bus, pwm)
        results.append(judge_wheel_form(profile.drive, trials))
    return ProbeReport(
        port=port,
        assumed=profile,
        findings=tuple(r for r in results if isinstance(r, Finding)),
        skipped=tuple(r for r in results if isinstance(r, Skipped)),
        devices=tuple(devices),
        adapter=adapter or AdapterInfo(port=port, usb=False),
        scanned=scanned,
        elapsed_s=loop.time() - started,
        motion=allow_motion,
    )


async def probe_port(
    port: str | Transport,
    *,
    profile: BusProfile = DEFAULT_PROFILE,
    ids: Iterable[int] = ALL_IDS,
    allow_motion: bool = False,
    pwm: int = MOTION_PWM,
    bus_timeout_s: float = DEFAULT_TIMEOUT_S,
    usb_latency_ms: int = DEFAULT_USB_LATENCY_MS,
    sysfs_root: Path = SYSFS_ROOT,
    port_name: str | None = None,
) -> ProbeReport:
    """Open ``port`` (a URL, or a transport already open), :func:`probe` it, close it.

    With ``allow_motion`` the port's last packets are the wheel stops in both forms,
    written even when the probe fails or is cancelled. Arguments as :func:`probe`;
    ``bus_timeout_s`` is the reply timeout (RobotConfig.bus_timeout_s()), ``sysfs_root``
    where the USB adapter is looked up, ``port_name`` the port's name in the report (by
    default the URL, or the transport's device path).

    Raises:
        TransportError: The port cannot be opened, or the link failed.
        StopNotConfirmedError: A trial's stop was not confirmed.
    """
    transport = await open_transport(port) if isinstance(port, str) else port
    name = port_name or (
        port if isinstance(port, str) else str(getattr(transport, "port", repr(transport)))
    )
    bus = Bus(transport, timeout_s=bus_timeout_s)
    bus.start()
    final: Sequence[Packet] = wheel_stops() if allow_motion else ()
    try:
        adapter = (
            read_adapter(transport.port, sysfs_root=sysfs_root)
            if isinstance(transport, SerialTransport)
            else AdapterInfo(port=name, usb=False)
        )
        return await probe(
            bus,
            profile=profile,
            ids=ids,
            allow_motion=allow_motion,
            pwm=pwm,
            adapter=adapter,
            usb_latency_ms=usb_latency_ms,
            port=name,
        )
    finally:
        await bus.aclose(final=final)


# -- the reads -------------------------------------------------------------------------------


class _Reader:
    """Requests that may go unanswered, each kept as a :class:`RawRead`."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus

    async def ask(
        self, packet: Packet, what: str, *, retries: int | None = None
    ) -> tuple[ReplyPacket | None, RawRead]:
        try:
            reply = await self.bus.request(packet, expect_reply=True, retries=retries)
        except (BusTimeoutError, DeviceUnavailableError):
            reply = None
        wire = None if reply is None else encode_packet(reply)
        return reply, RawRead(what, encode_packet(packet), wire)

    async def read(
        self, packet: Packet, what: str, *, retries: int | None = None
    ) -> tuple[ReadReply | None, RawRead]:
        reply, raw = await self.ask(packet, what, retries=retries)
        if reply is None:
            return None, raw
        try:
            return ReadReply.parse(reply), raw
        except MalformedReplyError:
            return None, raw


async def _scan(
    reader: _Reader, ids: Sequence[int]
) -> tuple[list[Device], dict[int, StatusDetail]]:
    """Every id that answers STAT, identified; and each one's detail flags at the scan."""
    devices: list[Device] = []
    flags: dict[int, StatusDetail] = {}
    for sid in ids:
        # No retries: a silent id costs one timeout, and most ids are silent.
        reply, raw = await reader.ask(stat(sid), f"{sid} STAT", retries=0)
        if reply is None:
            continue
        try:
            status = StatusReply.parse(reply)
        except MalformedReplyError:
            continue
        flags[sid] = status.status_detail
        latencies = [reply.received_at - reply.sent_at]
        for _ in range(LATENCY_READS - 1):
            again, _raw = await reader.ask(stat(sid), f"{sid} STAT", retries=0)
            if again is not None:
                latencies.append(again.received_at - again.sent_at)
        kind, firmware, model, ident = await _identify(reader, sid)
        devices.append(
            Device(
                sid=sid,
                kind=kind,
                firmware=firmware,
                model=model,
                latency_s=median_latency(latencies),
                status_error=int(status.status_error),
                status_detail=int(status.status_detail),
                raw=(raw, *ident),
            )
        )
    return devices, flags


async def _identify(
    reader: _Reader, sid: int
) -> tuple[str, str | None, str | None, tuple[RawRead, ...]]:
    """A board (its firmware tag) or a HerkuleX servo (its model). The robot's boards are
    asked for their tag first and the rest for a model first, so neither is sent a read
    outside its registers when it is what its id says (a HerkuleX servo blinks its alarm
    LED at one)."""
    order = ("tag", "model") if sid in _BOARD_IDS else ("model", "tag")
    raws: list[RawRead] = []
    for step in order:
        if step == "tag":
            read, raw = await reader.read(read_firmware_tag(sid), f"{sid} EEP 0xF1 (firmware tag)")
            raws.append(raw)
            tag = None if read is None else firmware_tag(read.data)
            if tag is not None:
                return "board", tag, None, tuple(raws)
        else:
            read, raw = await reader.read(model_read(sid), f"{sid} EEP 0, 2 bytes (model)")
            raws.append(raw)
            model = None if read is None else model_name(read.data)
            if model is not None:
                return "herkulex", None, model, tuple(raws)
    return "unknown", None, None, tuple(raws)


async def _battery(
    reader: _Reader, profile: BusProfile, present: set[int], scanned: Sequence[int]
) -> Finding | Skipped:
    core = profile.core
    if _CORE not in scanned:
        return Skipped("battery", "the scan did not cover the core board (20)")
    if _CORE not in present:
        return judge_battery(core, None)
    assumed_read, assumed_raw = await reader.read(
        read_request(_CORE, core.status_addr, core.status_size),
        f"20 RAM 0x{core.status_addr:02X}, {core.status_size} bytes (assumed block)",
    )
    first = judge_battery(core, assumed_read, raw=[assumed_raw])
    if first.status is Status.CONFIRMED:
        return first
    found: dict[int, ReadReply] = {}
    raws: dict[int, RawRead] = {}
    for addr in _ADDRESSES:
        # No retries: an address the board does not answer is no battery block.
        read, raw = await reader.read(
            read_request(_CORE, addr, SEARCH_LENGTH),
            f"20 RAM 0x{addr:02X}, {SEARCH_LENGTH} bytes",
            retries=0,
        )
        if read is not None:
            found[addr] = read
            raws[addr] = raw
    candidates = battery_candidates({addr: read.data for addr, read in found.items()})
    if not candidates:
        return judge_battery(core, assumed_read, raw=[assumed_raw])
    addr = candidates[0]
    size = BatteryLayout.TBCORE.size
    tbcore, tbcore_raw = await reader.read(
        read_request(_CORE, addr, size), f"20 RAM 0x{addr:02X}, {size} bytes (tbcore layout?)"
    )
    return judge_battery(
        core,
        assumed_read,
        found_addr=addr,
        cells_read=found[addr],
        tbcore_read=tbcore,
        raw=[raws[addr], tbcore_raw, assumed_raw],
        candidates=candidates,
    )


async def _torque(
    reader: _Reader,
    drive: DriveProfile,
    flags: dict[int, StatusDetail],
    present: set[int],
    scanned: Sequence[int],
) -> Finding | Skipped:
    if not set(_DRIVES) <= set(scanned):
        return Skipped("drive_torque", "the scan did not cover both drive boards (0, 1)")
    reads: dict[int, ReadReply | None] = {}
    raws: list[RawRead] = []
    for sid in _DRIVES:
        if sid not in present:
            reads[sid] = None
            continue
        read, raw = await reader.read(
            read_request(sid, drive.torque_addr, 1), f"{sid} RAM {drive.torque_addr}, 1 byte"
        )
        reads[sid] = read
        raws.append(raw)
    before: dict[int, StatusDetail | None] = {sid: flags.get(sid) for sid in _DRIVES}
    return judge_torque(drive, reads, before, raws)


async def _worm(
    reader: _Reader,
    profile: BusProfile,
    flags: dict[int, StatusDetail],
    present: set[int],
    scanned: Sequence[int],
) -> Finding | Skipped:
    if _WORM not in present:
        why = "no worm neck answered at 4" if _WORM in scanned else "the scan did not cover 4"
        return Skipped("worm_neck", why)
    worm = profile.worm
    # The target first: the feedback read is then judged by the flags the target read left.
    target, target_raw = await reader.read(
        read_request(_WORM, worm.target_addr, 4), f"4 RAM 0x{worm.target_addr:02X}, 4 bytes"
    )
    feedback, feedback_raw = await reader.read(
        read_feedback(worm), f"4 RAM 0x{worm.feedback_addr:02X}, 5 bytes"
    )
    return judge_worm(worm, target, feedback, flags.get(_WORM), [target_raw, feedback_raw])


# -- the wheel trials ------------------------------------------------------------------------


async def _wheel_trials(bus: Bus, pwm: int) -> list[WheelTrial]:
    """Each wheel alone, in each form; every trial ends in a confirmed stop."""
    trials: list[WheelTrial] = []
    try:
        for form in WheelJogForm:
            # The board frame: no mirroring, so the PWM is what the board gets.
            board = DriveProfile(wheel_form=form, right_mirrored=False)
            trials += [await _trial(bus, board, wheel, pwm) for wheel in (0, 1)]
    except BaseException:
        # An error, a stop not confirmed, Ctrl-C: the boards get the stop in both forms
        # before anything else (send_now is shielded once called).
        for packet in wheel_stops():
            with contextlib.suppress(OhmniError):
                await bus.send_now(packet)
        raise
    return trials


async def _trial(bus: Bus, board: DriveProfile, wheel: int, pwm: int) -> WheelTrial:
    loop = asyncio.get_running_loop()
    before, before_raw = await _counts(bus, "before")
    left, right = (pwm, 0) if wheel == 0 else (0, pwm)
    command = wheel_command(left, right, board)
    start = loop.time()
    sends = round(MOTION_S / MOTION_RESEND_S)
    for k in range(sends):
        await asyncio.sleep(max(0.0, start + k * MOTION_RESEND_S - loop.time()))
        await bus.send(command)
    await asyncio.sleep(max(0.0, start + MOTION_S - loop.time()))
    for packet in wheel_stops():
        await bus.send_now(packet)
    # Confirmed by the counts, repeating the stop in the form just tried.
    await stop_wheels(bus, profile=board)
    after, after_raw = await _counts(bus, "after")
    name = ("left", "right")[wheel]
    sent = RawRead(
        f"{board.wheel_form.name} PWM {pwm} to the {name} board ({sends} times)",
        encode_packet(command),
        None,
    )
    return WheelTrial(
        form=board.wheel_form,
        wheel=wheel,
        pwm=pwm,
        before=before,
        after=after,
        raw=(*before_raw, sent, *after_raw),
    )


async def _counts(bus: Bus, when: str) -> tuple[tuple[int, int], tuple[RawRead, RawRead]]:
    """Both raw wheel counts (a missing reply raises: the trial stops)."""
    counts: list[int] = []
    raws: list[RawRead] = []
    for sid in _DRIVES:
        request = read_count(sid)
        reply = await bus.request(request, expect_reply=True)
        assert reply is not None  # expect_reply: a reply, or BusTimeoutError
        counts.append(parse_count(ReadReply.parse(reply)))
        raws.append(RawRead(f"{sid} count {when}", encode_packet(request), encode_packet(reply)))
    return (counts[0], counts[1]), (raws[0], raws[1])
