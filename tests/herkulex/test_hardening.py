"""Issue 9: extreme arguments give a one-line OhmniError naming the parameter and its range."""

from __future__ import annotations

import asyncio
import math

import pytest

from ohmni_tb.errors import InvalidArgumentError, OhmniError, OutOfRangeError
from ohmni_tb.herkulex import units
from ohmni_tb.herkulex.servo import Servo
from ohmni_tb.protocol import Packet
from ohmni_tb.protocol.devices import NECK_RAW_RANGE, DeviceId


class Carrier:
    """Records what a Servo sends; never answers."""

    def __init__(self) -> None:
        self.sent: list[Packet] = []

    async def request(self, packet: Packet, **_: object) -> Packet | None:
        self.sent.append(packet)
        return None

    async def send(self, packet: Packet) -> None:
        self.sent.append(packet)

    def ack_policy(self, sid: int) -> int:
        return 1

    def set_ack_policy(self, sid: int, policy: int) -> None:
        return None


@pytest.mark.parametrize(
    ("convert", "value", "name"),
    [
        (units.playtime_ticks_from_s, 1e308, "playtime_s"),
        (units.pos_raw_from_deg, 1e308, "angle_deg"),
        (units.pos_raw_from_deg, -1e308, "angle_deg"),
        (units.pos_raw_from_rad, 1e308, "angle_rad"),
        (units.pos_raw_from_rad, -1e308, "angle_rad"),
        (units.voltage_raw_from_v, 1e308, "voltage_v"),
        (units.voltage_raw_from_v, -1e308, "voltage_v"),
    ],
)
def test_huge_values_are_out_of_range_not_overflow(
    convert: object, value: float, name: str
) -> None:
    with pytest.raises(OutOfRangeError) as info:
        convert(value)  # type: ignore[operator]  # a table of converters
    assert info.value.name == name
    assert math.isfinite(info.value.low)
    assert math.isfinite(info.value.high)
    assert "nan" not in str(info.value)


def test_the_range_of_a_huge_angle_is_given_in_its_own_unit() -> None:
    with pytest.raises(OutOfRangeError) as info:
        units.pos_raw_from_rad(1e308)
    assert (info.value.name, info.value.unit) == ("angle_rad", "rad")
    assert info.value.high == pytest.approx(math.radians((1023 - 512) * 0.325), abs=1e-6)


def test_a_nan_zero_offset_is_named_not_reported_as_a_nan_range() -> None:
    with pytest.raises(InvalidArgumentError, match="zero_offset_raw") as info:
        units.pos_raw_from_deg(0.0, zero_offset_raw=math.nan)  # type: ignore[arg-type]  # a caller's mistake
    assert "nan..nan" not in str(info.value)


def test_negative_playtimes_are_refused_even_when_they_round_to_zero() -> None:
    for seconds in (-0.001, -1.0, -1e308):
        with pytest.raises(OutOfRangeError, match=r"playtime_s=.* allowed 0\.0\.\.2\.8448 s"):
            units.playtime_ticks_from_s(seconds)
    assert units.playtime_ticks_from_s(-0.0) == 0


def test_the_playtime_sent_is_reportable() -> None:
    assert units.playtime_ticks_from_s(2.84) == 254
    assert units.playtime_sent_s(2.84) == 2.8448
    assert units.playtime_s_from_ticks(254) == 2.8448
    assert units.playtime_sent_s(0.5) == 0.504


def test_move_to_with_a_string_angle_is_an_ohmni_error() -> None:
    async def main() -> None:
        servo = Servo(Carrier(), 11)
        with pytest.raises(InvalidArgumentError, match="angle_rad must be a number"):
            await servo.move_to(angle_rad="1")  # type: ignore[arg-type]  # a caller's mistake

    asyncio.run(main())


def test_a_nan_angle_names_angle_rad_and_the_servos_range() -> None:
    servo = Servo(Carrier(), DeviceId.HERKULEX_NECK)
    with pytest.raises(InvalidArgumentError, match="angle_rad=nan"):
        servo.target(angle_rad=math.nan)
    with pytest.raises(OutOfRangeError) as info:
        servo.target(angle_rad=1e308)
    assert (info.value.name, info.value.unit) == ("angle_rad", "rad")
    assert info.value.low == pytest.approx(math.radians((280 - 512) * 0.325), abs=1e-6)
    assert info.value.high == pytest.approx(math.radians((650 - 512) * 0.325), abs=1e-6)


def test_the_neck_is_held_to_its_safe_range_by_default() -> None:
    carrier = Carrier()
    neck = Servo(carrier, DeviceId.HERKULEX_NECK)
    assert (neck.min_raw, neck.max_raw) == NECK_RAW_RANGE == (280, 650)

    async def main() -> None:
        with pytest.raises(OutOfRangeError, match=r"allowed 280\.\.650"):
            await neck.move_to(1000)

    asyncio.run(main())
    assert carrier.sent == []
    # Another id keeps the servo's factory range; explicit limits still override.
    assert (Servo(carrier, 11).min_raw, Servo(carrier, 11).max_raw) == (21, 1002)
    wide = Servo(carrier, DeviceId.HERKULEX_NECK, min_raw=21, max_raw=1002)
    assert wide.target(1000).value == 1000


@pytest.mark.parametrize(
    "kwargs",
    [
        {"min_raw": "1"},
        {"max_raw": 1.5},
        {"zero_offset_raw": math.nan},
        {"zero_offset_raw": 10**400},
        {"min_raw": 10**5000},
    ],
)
def test_bad_servo_limits_are_one_line_ohmni_errors(kwargs: dict[str, object]) -> None:
    with pytest.raises(OhmniError) as info:
        Servo(Carrier(), 11, **kwargs)  # type: ignore[arg-type]  # a caller's mistake
    assert "\n" not in str(info.value)
