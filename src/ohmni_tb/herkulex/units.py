"""Raw HerkuleX counts to physical units and back (sans-IO, pure functions).

DRS-0101 and DRS-0201 alike:

* position: 0.325 ° a count, 512 = the mechanical centre. A per-servo zero offset (in raw
  counts, like tb_control's ``set_servo_zero_offset``) moves where 0 ° is:
  ``angle_deg = (pos_raw - 512 - zero_offset_raw) * 0.325``;
* speed: one count of differential position (RAM 62) = 29.09 °/s;
* voltage: 0.074 V a count (RAM 54, and the min/max voltage settings);
* playtime: ticks of 11.2 ms, 0..254.

Temperature (RAM 55) is a non-linear raw ADC value whose full table is not available, so
no conversion is offered: compare it with the servo's own max-temperature register.

Every function refuses NaN and infinity; conversions towards raw refuse results outside
the allowed raw range instead of clamping or wrapping them.
"""

from __future__ import annotations

import math
from typing import Final

from ohmni_tb._checks import finite
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

__all__ = [
    "CENTRE_RAW",
    "DEG_PER_COUNT",
    "DEG_S_PER_DIFF",
    "MAX_PLAYTIME_S",
    "MAX_PLAYTIME_TICKS",
    "POSITION_MAX_RAW",
    "TICK_S",
    "VOLT_PER_COUNT",
    "angle_deg_from_raw",
    "angle_rad_from_raw",
    "check_playtime_ticks",
    "playtime_s_from_ticks",
    "playtime_ticks_from_s",
    "pos_raw_from_deg",
    "pos_raw_from_rad",
    "speed_dps_from_raw",
    "speed_rad_s_from_raw",
    "voltage_raw_from_v",
    "voltage_v_from_raw",
]

#: Degrees per position count (0.02778 belongs to the DRS-0402/0602, not these models).
DEG_PER_COUNT: Final = 0.325
#: The raw position of the mechanical centre.
CENTRE_RAW: Final = 512
#: Positions are 10-bit.
POSITION_MAX_RAW: Final = 1023
#: Degrees per second for one count of differential position (RAM 62).
DEG_S_PER_DIFF: Final = 29.09
#: Volts per count of the voltage registers.
VOLT_PER_COUNT: Final = 0.074
#: One playtime tick (and the servo's control period).
TICK_S: Final = 0.0112
#: The playtime byte's largest legal value; 255 is outside the manual's range.
MAX_PLAYTIME_TICKS: Final = 254
MAX_PLAYTIME_S: Final = MAX_PLAYTIME_TICKS * TICK_S


def angle_deg_from_raw(pos_raw: float, *, zero_offset_raw: int = 0) -> float:
    """Convert a raw position (RAM 58, or a JOG value) to degrees.

    Args:
        pos_raw: The raw position.
        zero_offset_raw: The raw offset of this servo's 0 ° from the centre (512).

    Raises:
        InvalidArgumentError: ``pos_raw`` is NaN or infinite.
    """
    finite("pos_raw", pos_raw)
    return (pos_raw - CENTRE_RAW - zero_offset_raw) * DEG_PER_COUNT


def pos_raw_from_deg(
    angle_deg: float,
    *,
    zero_offset_raw: int = 0,
    min_raw: int = 0,
    max_raw: int = POSITION_MAX_RAW,
) -> int:
    """Convert degrees to the nearest raw position.

    Args:
        angle_deg: The angle, 0 ° being ``512 + zero_offset_raw``.
        zero_offset_raw: The raw offset of this servo's 0 ° from the centre.
        min_raw: The smallest raw position allowed (the servo's min position, or the
            range of the joint, like the neck's 280).
        max_raw: The largest raw position allowed.

    Raises:
        InvalidArgumentError: ``angle_deg`` is NaN or infinite.
        OutOfRangeError: The angle lies outside ``min_raw..max_raw``; the error gives
            the allowed range in degrees.
    """
    finite("angle_deg", angle_deg)
    pos_raw = round(angle_deg / DEG_PER_COUNT) + CENTRE_RAW + zero_offset_raw
    if not min_raw <= pos_raw <= max_raw:
        low = angle_deg_from_raw(min_raw, zero_offset_raw=zero_offset_raw)
        high = angle_deg_from_raw(max_raw, zero_offset_raw=zero_offset_raw)
        raise OutOfRangeError("angle_deg", angle_deg, low, high, "deg")
    return pos_raw


def angle_rad_from_raw(pos_raw: float, *, zero_offset_raw: int = 0) -> float:
    """Convert a raw position to radians; see :func:`angle_deg_from_raw`."""
    return math.radians(angle_deg_from_raw(pos_raw, zero_offset_raw=zero_offset_raw))


def pos_raw_from_rad(
    angle_rad: float,
    *,
    zero_offset_raw: int = 0,
    min_raw: int = 0,
    max_raw: int = POSITION_MAX_RAW,
) -> int:
    """Convert radians to the nearest raw position; see :func:`pos_raw_from_deg`.

    Raises:
        InvalidArgumentError: ``angle_rad`` is NaN or infinite.
        OutOfRangeError: The angle lies outside ``min_raw..max_raw`` (given in rad).
    """
    finite("angle_rad", angle_rad)
    try:
        return pos_raw_from_deg(
            math.degrees(angle_rad),
            zero_offset_raw=zero_offset_raw,
            min_raw=min_raw,
            max_raw=max_raw,
        )
    except OutOfRangeError as exc:
        raise OutOfRangeError(
            "angle_rad", angle_rad, math.radians(exc.low), math.radians(exc.high), "rad"
        ) from None


def speed_dps_from_raw(diff_raw: int) -> float:
    """Convert a differential position (RAM 62, signed) to degrees per second."""
    finite("diff_raw", diff_raw)
    return diff_raw * DEG_S_PER_DIFF


def speed_rad_s_from_raw(diff_raw: int) -> float:
    """Convert a differential position (RAM 62, signed) to radians per second."""
    return math.radians(speed_dps_from_raw(diff_raw))


def voltage_v_from_raw(voltage_raw: int) -> float:
    """Convert a voltage register value (RAM 54, EEP 12/13) to volts."""
    finite("voltage_raw", voltage_raw)
    return voltage_raw * VOLT_PER_COUNT


def voltage_raw_from_v(voltage_v: float) -> int:
    """Convert volts to the nearest voltage register value (for the min/max settings).

    Raises:
        InvalidArgumentError: ``voltage_v`` is NaN or infinite.
        OutOfRangeError: The value does not fit the register's byte (0..18.87 V).
    """
    finite("voltage_v", voltage_v)
    voltage_raw = round(voltage_v / VOLT_PER_COUNT)
    if not 0 <= voltage_raw <= 0xFF:
        raise OutOfRangeError("voltage_v", voltage_v, 0.0, 0xFF * VOLT_PER_COUNT, "V")
    return voltage_raw


def playtime_ticks_from_s(playtime_s: float) -> int:
    """Convert a playtime in seconds to the nearest whole number of 11.2 ms ticks.

    Raises:
        InvalidArgumentError: ``playtime_s`` is NaN or infinite.
        OutOfRangeError: The playtime rounds outside 0..254 ticks (0..2.8448 s); it is
            never wrapped to 8 bits nor clamped.
    """
    finite("playtime_s", playtime_s)
    ticks = round(playtime_s / TICK_S)
    if not 0 <= ticks <= MAX_PLAYTIME_TICKS:
        raise OutOfRangeError("playtime_s", playtime_s, 0.0, MAX_PLAYTIME_S, "s")
    return ticks


def playtime_s_from_ticks(playtime_ticks: int) -> float:
    """Convert a playtime in ticks (0..254) to seconds.

    Raises:
        InvalidArgumentError: ``playtime_ticks`` is not an int.
        OutOfRangeError: ``playtime_ticks`` is outside 0..254.
    """
    check_playtime_ticks(playtime_ticks)
    return playtime_ticks * TICK_S


def check_playtime_ticks(playtime_ticks: int) -> int:
    """Return ``playtime_ticks`` if it is a legal playtime byte.

    Raises:
        InvalidArgumentError: ``playtime_ticks`` is not an int (seconds given as a float).
        OutOfRangeError: ``playtime_ticks`` is outside 0..254 (255, or milliseconds).
    """
    if isinstance(playtime_ticks, bool) or not isinstance(playtime_ticks, int):
        raise InvalidArgumentError(
            f"playtime_ticks must be an int number of 11.2 ms ticks, not "
            f"{type(playtime_ticks).__name__} {playtime_ticks!r}; convert seconds with "
            f"playtime_ticks_from_s()"
        )
    if not 0 <= playtime_ticks <= MAX_PLAYTIME_TICKS:
        raise OutOfRangeError("playtime_ticks", playtime_ticks, 0, MAX_PLAYTIME_TICKS, "ticks")
    return playtime_ticks
