"""The bus profile is configuration: one value the settings, the simulator, the monitor
and the Robot take (``ohmni_tb.protocol.profile``)."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from ohmni_tb.bus import Bus
from ohmni_tb.config import RobotConfig
from ohmni_tb.errors import BusTimeoutError, ConfigError, InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import stat
from ohmni_tb.monitor import BusMonitor
from ohmni_tb.protocol import encode_packet, read_request
from ohmni_tb.protocol.core import BatteryLayout, CoreProfile, decode_status, read_status
from ohmni_tb.protocol.drive import DriveProfile, WheelJogForm, wheel_command
from ohmni_tb.protocol.profile import DEFAULT_PROFILE, PROFILE_SETTINGS, BusProfile
from ohmni_tb.sim.clock import run_virtual
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import open_transport

VARIANT = {"wheel_form": "i_jog", "battery_addr": "0xB0", "ext_servo_ids": "13,14"}


# -- the value ------------------------------------------------------------------------------


def test_the_default_profile_is_the_assumed_one() -> None:
    settings = DEFAULT_PROFILE.settings()
    assert list(settings) == list(PROFILE_SETTINGS)
    assert settings == {
        "wheel_form": "s_jog",
        "right_mirrored": True,
        "drive_torque_addr": 52,
        "battery_addr": 0xA0,
        "battery_length": 18,
        "battery_layout": "tbcore",
        "worm_target_addr": 0x70,
        "worm_feedback_addr": 0x74,
        "ext_servo_ids": (11, 12),
    }
    assert BusProfile.from_settings(settings) == DEFAULT_PROFILE


def test_settings_as_a_url_or_the_environment_give_them() -> None:
    profile = BusProfile.from_settings(
        {**VARIANT, "right_mirrored": "0", "battery_layout": "CELLS", "battery_length": "10"}
    )
    assert profile.drive.wheel_form is WheelJogForm.I_JOG
    assert profile.drive.right_mirrored is False
    assert profile.core == CoreProfile(status_addr=0xB0, status_size=10, layout=BatteryLayout.CELLS)
    assert profile.ext_servo_ids == (13, 14)
    assert profile.replace(ext_servo_ids="none").ext_servo_ids == ()
    assert profile.as_json()["ext_servo_ids"] == [13, 14]


@pytest.mark.parametrize(
    ("settings", "error", "says"),
    [
        (
            {"battery_addr": "0x100"},
            OutOfRangeError,
            "battery_addr=256 is out of range: allowed 0..255",
        ),
        (
            {"battery_length": 12},
            OutOfRangeError,
            "battery_length=12 is out of range: allowed 18..",
        ),
        ({"battery_layout": "cells", "battery_length": 9}, OutOfRangeError, "battery_length=9"),
        ({"worm_feedback_addr": -1}, OutOfRangeError, "worm_feedback_addr=-1"),
        ({"drive_torque_addr": 999}, OutOfRangeError, "drive_torque_addr=999"),
        (
            {"wheel_form": "jog"},
            InvalidArgumentError,
            "wheel_form='jog' is not one of s_jog, i_jog",
        ),
        ({"battery_layout": "x"}, InvalidArgumentError, "battery_layout='x' is not one of"),
        ({"right_mirrored": "maybe"}, InvalidArgumentError, "right_mirrored='maybe' is not a bool"),
        ({"battery_addr": "A0"}, InvalidArgumentError, "battery_addr='A0' is not an integer"),
        ({"ext_servo_ids": "13,20"}, InvalidArgumentError, "id 20 is the core board's"),
        ({"ext_servo_ids": "13,13"}, InvalidArgumentError, "repeats id 13"),
        ({"ext_servo_ids": "11,12,13"}, InvalidArgumentError, "at most 2"),
        ({"torque": 52}, InvalidArgumentError, "unknown profile setting(s) torque"),
    ],
)
def test_a_bad_setting_is_named_with_what_is_allowed(
    settings: dict[str, object], error: type[Exception], says: str
) -> None:
    with pytest.raises(error) as caught:
        BusProfile.from_settings(settings)
    assert says in str(caught.value)


def test_a_cells_block_decodes_the_cells_alone() -> None:
    data = (3300).to_bytes(2, "little") * 5
    status = decode_status(data, BatteryLayout.CELLS)
    assert status.cell_mv == (3300,) * 5
    assert (status.docked, status.charging_current_ma) == (False, 0)
    with pytest.raises(Exception, match="takes 18 bytes, got 10"):
        decode_status(data, BatteryLayout.TBCORE)


# -- the settings -------------------------------------------------------------------------


def test_the_environment_sets_the_profile_in_hex_or_decimal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("OHMNI_BATTERY_ADDR", "0xB0")
    monkeypatch.setenv("OHMNI_WHEEL_FORM", "i_jog")
    monkeypatch.setenv("OHMNI_EXT_SERVO_IDS", "13,14")
    monkeypatch.setenv("OHMNI_WORM_FEEDBACK_ADDR", "120")
    profile = RobotConfig().profile()
    assert profile.core.status_addr == 0xB0
    assert profile.drive.wheel_form is WheelJogForm.I_JOG
    assert profile.ext_servo_ids == (13, 14)
    assert profile.worm.feedback_addr == 120


def test_a_config_file_sets_the_profile(tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text(
        'wheel_form = "i_jog"\nbattery_addr = 0xB0\nbattery_layout = "cells"\n'
        "battery_length = 10\next_servo_ids = [13, 14]\n"
    )
    profile = RobotConfig.load(path).profile()
    assert profile == BusProfile.from_settings(
        {**VARIANT, "battery_layout": "cells", "battery_length": 10}
    )


def test_a_block_shorter_than_its_layout_is_refused_with_the_file_named(tmp_path: Path) -> None:
    path = tmp_path / "ohmni.toml"
    path.write_text("battery_length = 10\n")
    with pytest.raises(ConfigError) as caught:
        RobotConfig.load(path)
    assert "battery_length=10 is shorter than the tbcore layout's 18 bytes" in str(caught.value)


def test_the_addresses_are_checked_like_every_setting() -> None:
    with pytest.raises(ConfigError, match=r"battery_addr=300 is out of range: allowed 0\.\.255"):
        RobotConfig(battery_addr=300)
    with pytest.raises(ConfigError, match="wheel_form='S-JOG' is not a choice"):
        RobotConfig(wheel_form="S-JOG")  # type: ignore[arg-type]  # what a user may type


# -- the simulator plays any profile ------------------------------------------------------


async def _sim(query: str) -> tuple[Bus, SimTransport]:
    transport = await open_transport(f"sim://?{query}")
    assert isinstance(transport, SimTransport)
    bus = Bus(transport)
    bus.start()
    return bus, transport


def test_the_simulated_battery_block_sits_where_its_url_says() -> None:
    async def main() -> tuple[tuple[int, ...], bytes]:
        bus, _ = await _sim("battery_addr=0xB0")
        try:
            moved = await bus.query(read_status(CoreProfile(status_addr=0xB0)))
            assumed = await bus.query(read_status())
        finally:
            await bus.aclose()
        return decode_status(moved.data).cell_mv, assumed.data

    cells, at_assumed = run_virtual(main())
    assert all(3000 <= mv <= 3500 for mv in cells)
    assert at_assumed == bytes(18)  # nothing there: the board answers zeros, flagged


def test_the_simulated_boards_take_only_their_urls_wheel_form() -> None:
    async def travel(query: str, form: WheelJogForm) -> float:
        bus, transport = await _sim(query)
        assert transport.robot is not None
        try:
            profile = DriveProfile(wheel_form=form)
            for _ in range(10):
                await bus.send(wheel_command(300, 300, profile))
                await asyncio.sleep(0.05)
            await bus.send(wheel_command(0, 0, profile))
            await asyncio.sleep(0.3)
            return transport.robot.pose.x
        finally:
            await bus.aclose()

    assert run_virtual(travel("wheel_form=i_jog", WheelJogForm.S_JOG)) == 0.0
    assert run_virtual(travel("wheel_form=i_jog", WheelJogForm.I_JOG)) > 0.05
    assert run_virtual(travel("", WheelJogForm.I_JOG)) == 0.0


def test_the_simulated_external_servos_take_the_urls_ids() -> None:
    async def answers(query: str) -> dict[int, bool]:
        bus, _ = await _sim(query)
        found = {}
        try:
            for sid in (11, 12, 13, 14):
                try:
                    await bus.request(stat(sid))
                    found[sid] = True
                except BusTimeoutError:
                    found[sid] = False
        finally:
            await bus.aclose()
        return found

    assert run_virtual(answers("ext_servos=13,14")) == {11: False, 12: False, 13: True, 14: True}
    assert run_virtual(answers("ext=13")) == {11: False, 12: False, 13: True, 14: False}


@pytest.mark.parametrize(
    ("query", "says"),
    [
        ("wheel_form=x_jog", "wheel_form='x_jog' is not one of s_jog, i_jog"),
        ("battery_addr=0x1FF", "battery_addr=511 is out of range: allowed 0..255"),
        ("battery_layout=cells&battery_length=2", "battery_length=2 is out of range"),
    ],
)
def test_a_bad_profile_option_of_a_sim_url_is_named(query: str, says: str) -> None:
    async def main() -> None:
        await open_transport(f"sim://?{query}")

    with pytest.raises(ConfigError) as caught:
        run_virtual(main())
    assert says in str(caught.value)


# -- the monitor reads as the profile says ------------------------------------------------


def test_the_monitor_decodes_the_battery_block_where_the_profile_puts_it() -> None:
    async def traffic() -> bytes:
        bus, _transport = await _sim("battery_addr=0xB0")
        written = bytearray()
        try:
            request = read_status(CoreProfile(status_addr=0xB0))
            reply = await bus.request(request)
            assert reply is not None
            written += encode_packet(request) + encode_packet(reply)
        finally:
            await bus.aclose()
        return bytes(written)

    data = run_virtual(traffic())
    profile = BusProfile.from_settings({"battery_addr": 0xB0})
    moved = [event.text for event in BusMonitor(profile).feed(data)]
    assumed = [event.text for event in BusMonitor().feed(data)]
    assert "status (assumed)" in moved[0]
    assert "cells 3" in moved[1]
    assert "RAM[176]" in assumed[0]
    assert "cells" not in assumed[1]


def test_the_monitor_decodes_a_wheel_command_in_either_form() -> None:
    for form in WheelJogForm:
        packet = wheel_command(300, 300, DriveProfile(wheel_form=form))
        (event,) = BusMonitor().feed(encode_packet(packet))
        assert event.text == f"{form.name} wheels: left pwm +300, right pwm -300 (board frame)"


def test_a_read_request_builder_takes_the_profile() -> None:
    assert read_status(
        CoreProfile(status_addr=0xB0, status_size=10, layout=BatteryLayout.CELLS)
    ) == (read_request(20, 0xB0, 10))
