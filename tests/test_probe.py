"""ohmni_tb.probe as a library: the judges on hand-made replies, the USB adapter on a fake
sysfs tree, the report to share, and a probe cancelled while a wheel turns."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest

from ohmni_tb.probe import (
    Finding,
    ProbeReport,
    Skipped,
    Status,
    probe_port,
    read_adapter,
    shareable,
)
from ohmni_tb.probe.findings import (
    CELL_SPREAD_MAX_MV,
    battery_candidates,
    judge_adapter,
    judge_battery,
    judge_torque,
    plausible_cells,
)
from ohmni_tb.protocol import Command, Memory, PacketDecoder, ReadReply, StatusDetail, StatusError
from ohmni_tb.protocol.core import CORE_PROFILE
from ohmni_tb.protocol.drive import (
    DRIVE_PROFILE,
    DriveProfile,
    WheelJogForm,
    decode_wheel_command,
)
from ohmni_tb.protocol.profile import DEFAULT_PROFILE
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport


def cells(*mv: int) -> bytes:
    return b"".join(v.to_bytes(2, "little") for v in mv)


def reply(sid: int, addr: int, data: bytes, detail: StatusDetail = StatusDetail.NONE) -> ReadReply:
    return ReadReply(sid, Memory.RAM, addr, data, StatusError.NONE, detail)


# -- the battery -----------------------------------------------------------------------------

PACK = cells(3301, 3298, 3305, 3290, 3300)


def test_five_close_lifepo4_cells_are_plausible() -> None:
    assert plausible_cells(PACK) == (3301, 3298, 3305, 3290, 3300)
    assert plausible_cells(PACK + b"\x00" * 8) is not None  # a longer block starts so


@pytest.mark.parametrize(
    "block",
    [
        cells(3301, 3298, 2400, 3290, 3300),  # a cell below 2.5 V
        cells(3301, 3298, 3800, 3290, 3300),  # a cell above 3.7 V
        cells(3000, 3300, 3300, 3300, 3300 + CELL_SPREAD_MAX_MV - 299),  # spread 301 mV
        cells(0, 0, 0, 0, 0),  # an address with nothing (a board answers zeros)
        PACK[:8],  # too short
    ],
    ids=["low cell", "high cell", "spread too wide", "zeros", "short"],
)
def test_cells_out_of_range_or_spread_too_wide_are_not_the_battery(block: bytes) -> None:
    assert plausible_cells(block) is None
    assert battery_candidates({0x10: block, 0xB0: PACK}) == [0xB0]


def test_a_block_found_elsewhere_differs_with_its_address_and_layout() -> None:
    tbcore = PACK + (-1200).to_bytes(2, "little", signed=True) + bytes((0, 2, 0, 0, 0, 0))
    finding = judge_battery(
        CORE_PROFILE,
        reply(20, 0xA0, bytes(18)),
        found_addr=0xB0,
        cells_read=reply(20, 0xB0, PACK),
        tbcore_read=reply(20, 0xB0, tbcore),
    )
    assert finding.status is Status.DIFFERS
    assert finding.settings == {
        "battery_addr": 0xB0,
        "battery_length": 18,
        "battery_layout": "tbcore",
    }
    assert finding.found["charging_current_ma"] == -1200


def test_a_docked_byte_other_than_0_or_1_makes_it_the_cells_layout() -> None:
    tbcore = PACK + bytes((0, 0, 7, 2, 0, 0, 0, 0))
    finding = judge_battery(
        CORE_PROFILE,
        None,
        found_addr=0x40,
        cells_read=reply(20, 0x40, PACK),
        tbcore_read=reply(20, 0x40, tbcore),
    )
    assert finding.settings == {
        "battery_addr": 0x40,
        "battery_length": 10,
        "battery_layout": "cells",
    }


# -- the torque register ---------------------------------------------------------------------


def test_a_read_the_board_flags_as_out_of_range_is_no_torque_register() -> None:
    flagged = reply(0, 52, b"\x00", StatusDetail.EXCEED_REG_RANGE)
    good = reply(1, 52, b"\x60")
    clear = {0: StatusDetail.NONE, 1: StatusDetail.NONE}
    finding = judge_torque(DRIVE_PROFILE, {0: flagged, 1: good}, clear)
    assert finding.status is Status.NOT_FOUND
    assert "left board flagged RAM 52" in finding.detail
    # With the flag already set before (it is sticky) only the value counts.
    sticky = {0: StatusDetail.EXCEED_REG_RANGE, 1: StatusDetail.NONE}
    assert judge_torque(DRIVE_PROFILE, {0: flagged, 1: good}, sticky).status is Status.CONFIRMED
    odd = judge_torque(DRIVE_PROFILE, {0: reply(0, 52, b"\x12"), 1: good}, clear)
    assert odd.status is Status.NOT_FOUND
    assert "reads 0x12, not a torque state" in odd.detail


# -- the USB adapter -------------------------------------------------------------------------


def fake_sysfs(root: Path, timer_ms: int, serial: str = "FT5ABCDE") -> Path:
    """A Linux sysfs tree with one FTDI adapter at ttyUSB0, and the robot's symlink."""
    usb = root / "sys" / "devices" / "pci0000:00" / "usb1" / "1-2" / "1-2.1"
    tty = usb / "1-2.1:1.0" / "ttyUSB0"
    tty.mkdir(parents=True)
    (tty / "latency_timer").write_text(f"{timer_ms}\n")
    (usb / "idVendor").write_text("0403\n")
    (usb / "idProduct").write_text("6015\n")
    (usb / "product").write_text("FT230X Basic UART\n")
    (usb / "serial").write_text(f"{serial}\n")
    devices = root / "sys" / "bus" / "usb-serial" / "devices"
    devices.mkdir(parents=True)
    (devices / "ttyUSB0").symlink_to(tty)
    link = root / "dev" / "usb" / "tty1-2.1"
    link.parent.mkdir(parents=True)
    link.symlink_to(root / "dev" / "ttyUSB0")
    return root / "sys"


def test_a_16_ms_latency_timer_differs_and_says_what_to_change(tmp_path: Path) -> None:
    sysfs = fake_sysfs(tmp_path, 16)
    adapter = read_adapter(str(tmp_path / "dev" / "usb" / "tty1-2.1"), sysfs_root=sysfs)
    assert adapter.usb
    assert (adapter.tty, adapter.latency_timer_ms, adapter.usb_id) == ("ttyUSB0", 16, "0403:6015")
    assert adapter.serial_number == "FT5ABCDE"
    assert adapter.low_latency is None  # not a real tty: tolerated

    finding = judge_adapter(adapter, usb_latency_ms=16)
    assert isinstance(finding, Finding)
    assert finding.status == "differs"
    assert "echo 1 | sudo tee /sys/bus/usb-serial/devices/ttyUSB0/latency_timer" in finding.detail
    assert 'ATTR{latency_timer}="1"' in finding.detail
    assert "set usb_latency_ms = 1" in finding.detail
    assert "until then keep usb_latency_ms = 16" in finding.detail
    # A setting below the timer would miss replies: it says so.
    low = judge_adapter(adapter, usb_latency_ms=1)
    assert isinstance(low, Finding)
    assert "replies will be missed: set usb_latency_ms = 16" in low.detail


def test_a_1_ms_latency_timer_is_confirmed(tmp_path: Path) -> None:
    sysfs = fake_sysfs(tmp_path, 1)
    adapter = read_adapter(str(tmp_path / "dev" / "ttyUSB0"), sysfs_root=sysfs, low_latency=True)
    finding = judge_adapter(adapter, usb_latency_ms=1)
    assert isinstance(finding, Finding)
    assert finding.status == "confirmed"
    assert finding.found == {
        "latency_timer_ms": 1,
        "low_latency": True,
        "tty": "ttyUSB0",
        "usb_id": "0403:6015",
    }


def test_a_port_that_is_no_usb_adapter_is_skipped(tmp_path: Path) -> None:
    sysfs = fake_sysfs(tmp_path, 16)
    adapter = read_adapter(os.devnull, sysfs_root=sysfs)
    assert not adapter.usb
    skipped = judge_adapter(adapter, usb_latency_ms=16)
    assert isinstance(skipped, Skipped)
    assert skipped.why == "not a USB serial adapter"


# -- the report to share ---------------------------------------------------------------------


def test_the_shared_report_leaves_the_serial_number_out_unless_asked(tmp_path: Path) -> None:
    sysfs = fake_sysfs(tmp_path, 16, serial="FT5SECRET")
    adapter = read_adapter(str(tmp_path / "dev" / "ttyUSB0"), sysfs_root=sysfs)
    report = ProbeReport(
        port="/dev/ttyUSB0",
        assumed=DEFAULT_PROFILE,
        findings=(),
        skipped=(),
        devices=(),
        adapter=adapter,
        scanned=(0, 1),
        elapsed_s=0.1,
        motion=False,
    )
    data = report.to_json()
    assert data["adapter"]["serial_number"] == "FT5SECRET"
    shared = shareable(data, environment={"ohmni_tb": "x"})
    assert "FT5SECRET" not in repr(shared)
    assert shared["port"] == "/dev/ttyUSB0"
    assert shared["environment"] == {"ohmni_tb": "x"}
    assert shareable(data, serials=True)["adapter"]["serial_number"] == "FT5SECRET"
    assert data["adapter"]["serial_number"] == "FT5SECRET"  # the report itself is untouched


# -- cancelled while a wheel turns -----------------------------------------------------------


def test_a_probe_cancelled_while_a_wheel_turns_stops_it_in_both_forms() -> None:
    async def main() -> tuple[set[int], tuple[float, float]]:
        transport = await open_transport("sim://")
        assert isinstance(transport, SimTransport)
        sim = transport.robot
        assert sim is not None
        line = transport.line
        write = line.host_write
        decoder = PacketDecoder()
        jogs: list[tuple[int, dict[int, int]]] = []

        def record(data: bytes) -> None:
            for p in decoder.feed(bytes(data)):
                if p.cmd in (Command.S_JOG, Command.I_JOG):
                    form = DriveProfile(wheel_form=WheelJogForm(p.cmd))
                    jogs.append((p.cmd, decode_wheel_command(p, form)))
            write(data)

        setattr(line, "host_write", record)  # noqa: B010 - mypy forbids assigning a method
        task = asyncio.create_task(probe_port(transport, ids=[0, 1], allow_motion=True))
        while not jogs:  # noqa: ASYNC110 - the probe runs on; this only looks at the line
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.15)
        assert max(abs(v) for v in sim.wheel_speeds_mps()) > 0.01  # it turns
        moving = len(jogs)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        after = {cmd for cmd, pwm in jogs[moving:] if set(pwm.values()) == {0}}
        await asyncio.sleep(0.5)
        return after, sim.wheel_speeds_mps()

    stops, speeds = run_virtual(main())
    assert stops == {Command.S_JOG, Command.I_JOG}
    assert speeds == (0.0, 0.0)
