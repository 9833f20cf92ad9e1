"""Every device of the bus map answers on the simulated line as the reference says.

The requests go through the Bus on ``sim://``, on the virtual clock.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.errors import BusTimeoutError
from ohmni_tb.protocol import (
    BROADCAST_ID,
    Command,
    Memory,
    Packet,
    PacketDecoder,
    ReadReply,
    StatusDetail,
    StatusError,
    StatusReply,
    encode_packet,
)
from ohmni_tb.protocol.core import parse_status, read_status, set_light_ring
from ohmni_tb.protocol.drive import (
    DRIVE_PROFILE,
    DriveProfile,
    DriveTorque,
    WheelJogForm,
    parse_count,
    read_count,
    read_firmware_tag,
    set_torque,
    wheel_command,
)
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.drive import DriveTrain, SimDriveBoard
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport


def _on_sim(url: str, body: Callable[[Bus, SimTransport], Awaitable[None]]) -> None:
    """Run ``body`` with a Bus on the simulated robot ``url``, on the virtual clock."""

    async def main() -> None:
        sim = await open_transport(url)
        assert isinstance(sim, SimTransport)
        async with Bus(sim) as bus:
            await body(bus, sim)

    run_virtual(main())


async def _stat(bus: Bus, sid: int) -> StatusReply:
    reply = await bus.request(Packet(sid, Command.STAT))
    assert reply is not None
    return StatusReply.parse(reply)


async def _tag(bus: Bus, sid: int) -> str:
    reply = ReadReply.parse(await _request(bus, read_firmware_tag(sid)))
    assert reply.memory is Memory.EEP
    assert reply.addr == 0xF1
    return reply.data.decode("ascii")


async def _request(bus: Bus, packet: Packet) -> Packet:
    reply = await bus.request(packet)
    assert reply is not None
    return reply


# -- who answers --------------------------------------------------------------------------


def test_boards_answer_their_firmware_tags() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        assert await _tag(bus, 0) == "sim-drive-1.0"
        assert await _tag(bus, 1) == "sim-drive-1.0"
        assert await _tag(bus, 20) == "sim-core-1.0"
        assert await _tag(bus, 4) == "sim-worm-1.0"

    _on_sim("sim://?neck=worm", body)


@pytest.mark.parametrize(("neck", "model"), [("0101", b"\x01\x01"), ("0201", b"\x02\x01")])
def test_herkulex_neck_reports_its_model(neck: str, model: bytes) -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        reply = await bus.read(3, 0, 2, Memory.EEP)
        assert reply.data == model
        # No worm neck on this robot.
        with pytest.raises(BusTimeoutError, match="sid 4"):
            await bus.read(4, 0xF1, 0, Memory.EEP)

    _on_sim(f"sim://?neck={neck}", body)


def test_the_default_neck_is_a_drs_0101() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        assert (await bus.read(3, 0, 2, Memory.EEP)).data == b"\x01\x01"

    _on_sim("sim://", body)


def test_worm_robot_has_no_herkulex_neck() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        with pytest.raises(BusTimeoutError, match="sid 3"):
            await bus.read(3, 0, 2, Memory.EEP)

    _on_sim("sim://?neck=worm", body)


def test_external_servos_answer_at_11_and_12() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        for sid in (11, 12):
            status = await _stat(bus, sid)
            assert status.sid == sid
            assert (await bus.read(sid, 0, 2, Memory.EEP)).data == b"\x01\x01"
        with pytest.raises(BusTimeoutError, match="sid 13"):
            await _stat(bus, 13)

    _on_sim("sim://", body)


@pytest.mark.parametrize(
    ("ext", "present", "absent"), [("none", (), (11, 12)), ("13", (13,), (11,))]
)
def test_external_servo_ids_follow_the_option(
    ext: str, present: tuple[int, ...], absent: tuple[int, ...]
) -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        for sid in present:
            assert (await _stat(bus, sid)).sid == sid
        for sid in absent:
            with pytest.raises(BusTimeoutError):
                await _stat(bus, sid)

    _on_sim(f"sim://?ext={ext}", body)


@pytest.mark.parametrize("sid", [0, 1, 3, 4, 11, 12, 20])
def test_every_device_answers_stat_with_a_clean_status(sid: int) -> None:
    url = "sim://?neck=worm" if sid == 4 else "sim://"

    async def body(bus: Bus, sim: SimTransport) -> None:
        status = await _stat(bus, sid)
        assert status.cmd == Command.STAT | 0x40
        assert status.status_error == StatusError.NONE

    _on_sim(url, body)


# -- registers of the boards --------------------------------------------------------------


@pytest.mark.parametrize(("sid", "addr"), [(0, 0x99), (1, 0), (20, 0x10), (0, 0xC1)])
def test_an_unknown_register_reads_as_exceed_reg_range(sid: int, addr: int) -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        reply = await bus.read(sid, addr, 2)
        assert reply.data == b"\0\0"
        assert reply.status_detail & StatusDetail.EXCEED_REG_RANGE
        assert reply.status_error & StatusError.INVALID_PACKET
        # The bits stay latched until cleared, as on a HerkuleX servo.
        status = await _stat(bus, sid)
        assert status.status_detail & StatusDetail.EXCEED_REG_RANGE
        await bus.write(sid, 48, b"\0")
        assert (await _stat(bus, sid)).status_detail == StatusDetail.NONE

    _on_sim("sim://", body)


def test_a_read_longer_than_the_register_is_refused() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        reply = await bus.read(0, 59, 5)
        assert reply.status_detail & StatusDetail.EXCEED_REG_RANGE

    _on_sim("sim://", body)


def test_a_read_of_length_zero_returns_the_whole_register() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        assert (await bus.read(0, 59, 0)).data == b"\0\0\0\0"
        assert len((await bus.read(20, 0xA0, 0)).data) == 18

    _on_sim("sim://", body)


def test_drive_board_registers_at_rest() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        for sid in (0, 1):
            assert parse_count(ReadReply.parse(await _request(bus, read_count(sid)))) == 0
            assert (await bus.read(sid, 58, 2)).data == b"\0\0"
            assert (await bus.read(sid, 62, 2)).data == b"\0\0"
            assert (await bus.read(sid, 0x6B, 1)).data == b"\0"
            assert (await bus.read(sid, 52, 1)).data == bytes((DriveTorque.ON,))

    _on_sim("sim://", body)


def test_drive_torque_write_is_read_back_and_free_wheels_do_not_drive() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        await bus.send(set_torque(BROADCAST_ID, DriveTorque.FREE))
        for sid in (0, 1):
            assert (await bus.read(sid, 52, 1)).data == bytes((DriveTorque.FREE,))
        await bus.send(wheel_command(800, 800))
        await asyncio.sleep(0.5)
        assert sim.robot is not None
        assert sim.robot.wheel_speeds_mps() == (0.0, 0.0)
        assert sim.robot.pose.x == 0.0
        # Torque on again: the same command drives.
        await bus.send(set_torque(BROADCAST_ID, DriveTorque.ON))
        await bus.send(wheel_command(800, 800))
        await asyncio.sleep(0.5)
        assert sim.robot.pose.x > 0.1

    _on_sim("sim://", body)


def _drive_train(profile: DriveProfile, packet: Packet, seconds: float = 1.0) -> DriveTrain:
    """Both simulated drive boards on a train built with ``profile``, handed ``packet``
    through the wire's bytes, then run for ``seconds``."""
    train = DriveTrain(profile=profile)
    boards = [SimDriveBoard(0, train), SimDriveBoard(1, train)]
    (received,) = PacketDecoder().feed(encode_packet(packet))
    for board in boards:
        assert board.handle(received, 0.0) is None  # a broadcast: nobody answers
    train.advance(seconds)
    return train


@pytest.mark.parametrize(
    "profile",
    [
        DriveProfile(wheel_form=WheelJogForm.I_JOG),
        DriveProfile(right_mirrored=False),
        DriveProfile(wheel_form=WheelJogForm.I_JOG, right_mirrored=False),
        DRIVE_PROFILE,
    ],
    ids=["I_JOG", "right not mirrored", "both", "default"],
)
def test_a_changed_drive_profile_changes_both_sides(profile: DriveProfile) -> None:
    train = _drive_train(profile, wheel_command(600, 600, profile))
    left_mps, right_mps = train.wheel_speeds_mps()
    assert left_mps > 0.3
    assert right_mps == pytest.approx(left_mps)
    assert train.pose.x > 0.3
    assert train.pose.yaw == pytest.approx(0.0, abs=1e-9)
    # The right board counts mirrored exactly when the profile says so.
    assert train.count(0) > 0
    assert (train.count(1) < 0) is profile.right_mirrored


@pytest.mark.parametrize(
    ("board_profile", "host_profile"),
    [
        (DriveProfile(wheel_form=WheelJogForm.I_JOG), DRIVE_PROFILE),
        (DRIVE_PROFILE, DriveProfile(wheel_form=WheelJogForm.I_JOG)),
    ],
    ids=["boards I_JOG, host S_JOG", "boards S_JOG, host I_JOG"],
)
def test_drive_boards_ignore_a_wheel_command_of_another_form(
    board_profile: DriveProfile, host_profile: DriveProfile
) -> None:
    train = _drive_train(board_profile, wheel_command(600, 600, host_profile))
    assert train.wheel_speeds_mps() == (0.0, 0.0)
    assert train.pose.x == 0.0


def test_a_torque_value_the_board_does_not_know_is_flagged() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        await bus.write(0, 52, b"\x13")
        status = await _stat(bus, 0)
        assert status.status_detail & StatusDetail.EXCEED_REG_RANGE
        assert (await bus.read(0, 52, 1)).data == bytes((DriveTorque.ON,))

    _on_sim("sim://", body)


def test_writes_get_no_reply_under_the_default_ack_policy() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        assert await bus.write(20, 0xC1, b"\x01\x02\x03") is None
        assert sim.line.stats.replies == 0

    _on_sim("sim://", body)


def test_light_ring_is_stored_and_cleared_by_reboot() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        await bus.send(set_light_ring(10, 200, 255))
        assert (await bus.read(20, 0xC1, 3)).data == bytes((10, 200, 255))
        assert sim.robot is not None
        assert bytes(sim.robot.core.light_ring) == bytes((10, 200, 255))
        await bus.send(Packet(20, Command.REBOOT))
        assert (await bus.read(20, 0xC1, 3)).data == b"\0\0\0"

    _on_sim("sim://", body)


def test_a_write_of_the_wrong_size_is_refused_and_flagged() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        await bus.write(20, 0xC1, b"\x01\x02")
        assert (await bus.read(20, 0xC1, 3)).data == b"\0\0\0"
        assert (await _stat(bus, 20)).status_detail & StatusDetail.EXCEED_REG_RANGE

    _on_sim("sim://", body)


def test_a_read_only_register_is_not_written() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        await bus.write(0, 59, (1234).to_bytes(4, "little"))
        assert (await bus.read(0, 59, 4)).data == b"\0\0\0\0"
        assert (await _stat(bus, 0)).status_detail & StatusDetail.EXCEED_REG_RANGE

    _on_sim("sim://", body)


def test_core_status_block_at_start() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        status = parse_status(ReadReply.parse(await _request(bus, read_status())))
        # Five LiFePO4 cells on their plateau, near 3.27 V each at 80 %.
        assert all(3200 <= mv <= 3400 for mv in status.cell_mv)
        assert 16_000 <= status.pack_mv <= 17_000
        assert status.charging_current_ma < 0
        assert not status.docked
        assert status.percent == 80

    _on_sim("sim://", body)


@pytest.mark.parametrize(("soc", "percent"), [(3, 20), (50, 80), (100, 100)])
def test_core_percent_follows_the_state_of_charge_option(soc: int, percent: int) -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        status = parse_status(ReadReply.parse(await _request(bus, read_status())))
        assert status.percent == percent

    _on_sim(f"sim://?soc={soc}", body)


def test_docked_option_starts_on_the_dock() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        status = parse_status(ReadReply.parse(await _request(bus, read_status())))
        assert status.docked
        assert status.status[0] & 0x01

    _on_sim("sim://?docked=1", body)


def test_power_cycle_clears_latched_status_on_every_board() -> None:
    async def body(bus: Bus, sim: SimTransport) -> None:
        for sid in (0, 1, 20, 4):
            await bus.read(sid, 0x01, 1)  # unknown: latches EXCEED_REG_RANGE
            assert (await _stat(bus, sid)).status_error & StatusError.INVALID_PACKET
        sim.line.power_cycle()
        for sid in (0, 1, 20, 4):
            assert (await _stat(bus, sid)).status_error == StatusError.NONE

    _on_sim("sim://?neck=worm", body)
