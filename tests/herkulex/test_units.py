"""Raw counts to degrees, radians, volts, speed and seconds, and back."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError
from ohmni_tb.herkulex import units


def test_position_centre_and_scale() -> None:
    assert units.angle_deg_from_raw(512) == 0.0
    assert units.angle_deg_from_raw(612) == pytest.approx(32.5)
    assert units.angle_deg_from_raw(0) == pytest.approx(-166.4)
    assert units.angle_rad_from_raw(512 + 100) == pytest.approx(math.radians(32.5))


def test_zero_offset_moves_zero_degrees() -> None:
    # The neck's level position is not the servo's centre: offset +20 counts.
    assert units.angle_deg_from_raw(532, zero_offset_raw=20) == 0.0
    assert units.pos_raw_from_deg(0.0, zero_offset_raw=20) == 532
    assert units.pos_raw_from_deg(-6.5, zero_offset_raw=-20) == 472


def test_degrees_outside_the_range_are_refused_in_degrees() -> None:
    with pytest.raises(OutOfRangeError) as info:
        units.pos_raw_from_deg(50.0, min_raw=280, max_raw=650)
    assert info.value.unit == "deg"
    assert info.value.low == pytest.approx((280 - 512) * 0.325)
    assert info.value.high == pytest.approx((650 - 512) * 0.325)
    with pytest.raises(OutOfRangeError) as rad_info:
        units.pos_raw_from_rad(math.pi)
    assert rad_info.value.unit == "rad"
    assert rad_info.value.high == pytest.approx(math.radians((1023 - 512) * 0.325))


@given(st.integers(0, 1023), st.integers(-100, 100))
def test_raw_degree_round_trip(pos_raw: int, offset: int) -> None:
    angle = units.angle_deg_from_raw(pos_raw, zero_offset_raw=offset)
    assert units.pos_raw_from_deg(angle, zero_offset_raw=offset, max_raw=2000, min_raw=-1000) == (
        pos_raw
    )
    angle_rad = units.angle_rad_from_raw(pos_raw, zero_offset_raw=offset)
    assert (
        units.pos_raw_from_rad(angle_rad, zero_offset_raw=offset, max_raw=2000, min_raw=-1000)
        == pos_raw
    )


def test_voltage() -> None:
    assert units.voltage_v_from_raw(0x5B) == pytest.approx(6.734, abs=1e-3)
    assert units.voltage_raw_from_v(10.0) == 135
    assert units.voltage_raw_from_v(units.voltage_v_from_raw(0x89)) == 0x89
    with pytest.raises(OutOfRangeError):
        units.voltage_raw_from_v(19.0)
    with pytest.raises(OutOfRangeError):
        units.voltage_raw_from_v(-1.0)


def test_speed_is_signed() -> None:
    assert units.speed_dps_from_raw(1) == pytest.approx(29.09)
    assert units.speed_dps_from_raw(-2) == pytest.approx(-58.18)
    assert units.speed_rad_s_from_raw(1) == pytest.approx(math.radians(29.09))


def test_playtime() -> None:
    assert units.playtime_s_from_ticks(60) == pytest.approx(0.672)
    assert units.playtime_s_from_ticks(254) == pytest.approx(2.8448)
    assert units.playtime_ticks_from_s(0.0) == 0
    assert units.playtime_ticks_from_s(0.0056) == 0  # half a tick rounds to even
    assert units.playtime_ticks_from_s(1.0) == 89
    with pytest.raises(OutOfRangeError) as info:
        units.playtime_ticks_from_s(-0.1)
    assert (info.value.low, info.value.high, info.value.unit) == (0.0, 2.8448, "s")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    "convert",
    [
        units.angle_deg_from_raw,
        units.angle_rad_from_raw,
        units.pos_raw_from_deg,
        units.pos_raw_from_rad,
        units.speed_dps_from_raw,
        units.voltage_v_from_raw,
        units.voltage_raw_from_v,
        units.playtime_ticks_from_s,
    ],
    ids=lambda f: f.__name__,
)
def test_nan_and_inf_are_refused(convert: object, bad: float) -> None:
    with pytest.raises(InvalidArgumentError, match="finite"):
        convert(bad)  # type: ignore[operator]


def test_one_playtime_range_and_one_rounding() -> None:
    # 0..2.8448 s (254 ticks), both ends included; seconds go to the nearest tick.
    assert units.check_playtime_s(2.8448) == 2.8448
    assert units.playtime_ticks_from_s(2.8448) == 254
    assert units.playtime_ticks_from_s(2.84) == 254  # 253.57 ticks: the nearest is 254
    assert units.playtime_ticks_from_s(2.8336) == 253
    assert units.playtime_ticks_from_s(0) == 0
    for seconds in (2.8449, 2.85, 2.86, 10**400):
        with pytest.raises(OutOfRangeError, match=r"allowed 0\.0\.\.2\.8448 s"):
            units.playtime_ticks_from_s(seconds)
    with pytest.raises(
        InvalidArgumentError, match=r"not a finite number: allowed 0\.0\.\.2\.8448 s"
    ):
        units.playtime_ticks_from_s(math.nan)
    with pytest.raises(InvalidArgumentError, match="playtime_s must be a number"):
        units.check_playtime_s(True)
