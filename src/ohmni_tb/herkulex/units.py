"""Raw HerkuleX counts to physical units and back (sans-IO, pure functions).

DRS-0101 and DRS-0201 alike:

* position: 0.325 ° a count, 512 = the mechanical centre. A per-servo zero offset (in raw
  counts, like tb_control's ``set_servo_zero_offset``) moves where 0 ° is:
  ``angle_deg = (pos_raw - 512 - zero_offset_raw) * 0.325``;
* speed: one count of differential position (RAM 62) = 29.09 °/s;
* voltage: 0.074 V a count (RAM 54, and the min/max voltage settings);
* playtime: ticks of 11.2 ms, 0..254 (0..2.8448 s). Seconds go to the *nearest* tick
  (:func:`playtime_ticks_from_s`: 2.84 s is 253.57 ticks, sent as 254 = 2.8448 s), and
  every caller — ``neck.move``, ``ohmni neck``, ``ohmni servo move``, the daemon and
  Foxglove — takes the same range, 0..2.8448 s (:func:`check_playtime_s`).

Temperature (RAM 55) is a non-linear raw ADC value whose full table is not available, so
no conversion is offered: compare it with the servo's own max-temperature register.

Every function refuses NaN and infinity; conversions towards raw refuse results outside
the allowed raw range instead of clamping or wrapping them.
"""

from __future__ import annotations

import math
from typing import Final

from ohmni_tb._checks import FLOAT_MAX as _FLOAT_MAX
from ohmni_tb._checks import finite, finite_result, integer, show
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

__all__ = [
    "CENTRE_RAW",
    "DEG_PER_COUNT",
    "DEG_S_PER_DIFF",
    "MAX_PLAYTIME_S",
    "MAX_PLAYTIME_TICKS",
    "MAX_VOLTAGE_V",
    "POSITION_MAX_RAW",
    "TICK_S",
    "VOLT_PER_COUNT",
    "angle_deg_from_raw",
    "angle_rad_from_raw",
    "check_playtime_s",
    "check_playtime_ticks",
    "check_zero_offset_raw",
    "playtime_s_from_ticks",
    "playtime_sent_s",
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
#: How far outside 0..1023 ``min_raw`` and ``max_raw`` may reach (a range that never binds).
_RAW_LIMIT_SPAN: Final = 1 << 20
#: The longest playtime, 254 ticks.
MAX_PLAYTIME_S: Final = round(MAX_PLAYTIME_TICKS * TICK_S, 6)
#: The largest voltage the voltage registers hold (0xFF counts).
MAX_VOLTAGE_V: Final = round(0xFF * VOLT_PER_COUNT, 6)


def angle_deg_from_raw(pos_raw: float, *, zero_offset_raw: int = 0) -> float:
    """Convert a raw position (RAM 58, or a JOG value) to degrees.

    Args:
        pos_raw: The raw position.
        zero_offset_raw: The raw offset of this servo's 0 ° from the centre (512).

    Raises:
        InvalidArgumentError: ``pos_raw`` is not a number, NaN or infinite, or
            ``zero_offset_raw`` is not an int.
        OutOfRangeError: ``zero_offset_raw`` is outside −512..511.
    """
    # A register's position and an offset in range (a servo's feedback) pass without a
    # call; anything else (a float, a huge int) goes the full way and gets its error.
    if (
        type(pos_raw) is int
        and -0x10000 <= pos_raw <= 0xFFFF
        and type(zero_offset_raw) is int
        and -CENTRE_RAW <= zero_offset_raw <= POSITION_MAX_RAW - CENTRE_RAW
    ):
        return (pos_raw - CENTRE_RAW - zero_offset_raw) * DEG_PER_COUNT
    raw = finite("pos_raw", pos_raw)
    offset = check_zero_offset_raw(zero_offset_raw)
    return (raw - CENTRE_RAW - offset) * DEG_PER_COUNT


def check_zero_offset_raw(zero_offset_raw: int) -> int:
    """Return ``zero_offset_raw`` if it puts 0 ° on a real position (0..1023).

    Raises:
        InvalidArgumentError: Not an int.
        OutOfRangeError: Outside −512..511.
    """
    return integer(
        "zero_offset_raw", zero_offset_raw, -CENTRE_RAW, POSITION_MAX_RAW - CENTRE_RAW, "count"
    )


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
        zero_offset_raw: The raw offset of this servo's 0 ° from the centre (−512..511).
        min_raw: The smallest raw position allowed (the servo's min position, or the
            range of the joint, like the neck's 280).
        max_raw: The largest raw position allowed.

    Raises:
        InvalidArgumentError: ``angle_deg`` is not a number, NaN or infinite, or a
            keyword is not an int, or ``min_raw > max_raw``.
        OutOfRangeError: The angle lies outside ``min_raw..max_raw``; the error gives
            the allowed range in degrees.
    """
    return _pos_raw(
        "angle_deg",
        angle_deg,
        "deg",
        deg_per_unit=1.0,
        zero_offset_raw=zero_offset_raw,
        min_raw=min_raw,
        max_raw=max_raw,
    )


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
        InvalidArgumentError: ``angle_rad`` is not a number, NaN or infinite.
        OutOfRangeError: The angle lies outside ``min_raw..max_raw`` (given in rad).
    """
    return _pos_raw(
        "angle_rad",
        angle_rad,
        "rad",
        deg_per_unit=math.degrees(1.0),
        zero_offset_raw=zero_offset_raw,
        min_raw=min_raw,
        max_raw=max_raw,
    )


def speed_dps_from_raw(diff_raw: int) -> float:
    """Convert a differential position (RAM 62, signed) to degrees per second.

    Raises:
        InvalidArgumentError: ``diff_raw`` is not a number, NaN or infinite.
        OutOfRangeError: The speed would not be a finite number.
    """
    raw = finite("diff_raw", diff_raw)
    limit = _FLOAT_MAX / DEG_S_PER_DIFF
    return finite_result(raw * DEG_S_PER_DIFF, "diff_raw", diff_raw, -limit, limit)


def speed_rad_s_from_raw(diff_raw: int) -> float:
    """Convert a differential position (RAM 62, signed) to radians per second."""
    return math.radians(speed_dps_from_raw(diff_raw))


def voltage_v_from_raw(voltage_raw: int) -> float:
    """Convert a voltage register value (RAM 54, EEP 12/13) to volts.

    Raises:
        InvalidArgumentError: ``voltage_raw`` is not a number, NaN or infinite.
    """
    if type(voltage_raw) is int and 0 <= voltage_raw <= 0xFFFF:  # a register's value
        return voltage_raw * VOLT_PER_COUNT
    return finite("voltage_raw", voltage_raw) * VOLT_PER_COUNT


def voltage_raw_from_v(voltage_v: float) -> int:
    """Convert volts to the nearest voltage register value (for the min/max settings).

    Raises:
        InvalidArgumentError: ``voltage_v`` is not a number, NaN or infinite.
        OutOfRangeError: The value does not fit the register's byte (0..18.87 V).
    """
    volts = finite("voltage_v", voltage_v, "V")
    counts = volts / VOLT_PER_COUNT
    # Compared before rounding: round() of a huge float is a huge int, of inf an error.
    if not -0.5 <= counts <= 0xFF + 0.5 or not 0 <= round(counts) <= 0xFF:
        raise OutOfRangeError("voltage_v", voltage_v, 0.0, MAX_VOLTAGE_V, "V")
    return round(counts)


def check_playtime_s(playtime_s: float) -> float:
    """Return ``playtime_s`` as a float if it is a playtime a HerkuleX servo takes.

    The one range of every playtime in seconds: 0..2.8448 s (254 ticks of 11.2 ms,
    tb_control's ``playtime`` 1 = 11.2 ms … 254 = 2.844 s), both ends included. A longer
    one is refused, never clamped to 254 ticks nor wrapped to 8 bits.

    Raises:
        InvalidArgumentError: ``playtime_s`` is not a number (a bool is not one), NaN
            or infinite.
        OutOfRangeError: Negative, or longer than 2.8448 s.
    """
    if isinstance(playtime_s, bool) or not isinstance(playtime_s, int | float):
        raise InvalidArgumentError(
            f"playtime_s must be a number of seconds, not {type(playtime_s).__name__} "
            f"{show(playtime_s)}"
        )
    if isinstance(playtime_s, float) and not math.isfinite(playtime_s):
        raise InvalidArgumentError(
            f"playtime_s={playtime_s!r} is not a finite number: allowed 0.0..{MAX_PLAYTIME_S} s"
        )
    # An int too large for a float compares exactly.
    if not 0.0 <= playtime_s <= MAX_PLAYTIME_S:
        raise OutOfRangeError("playtime_s", playtime_s, 0.0, MAX_PLAYTIME_S, "s")
    return float(playtime_s)


def playtime_ticks_from_s(playtime_s: float) -> int:
    """Convert a playtime in seconds to the nearest whole number of 11.2 ms ticks.

    The one conversion of every caller: 2.84 s is 253.57 ticks, sent as 254; 0.5 s is
    44.6, sent as 45. The seconds actually sent are :func:`playtime_s_from_ticks` of the
    result, or :func:`playtime_sent_s` in one call.

    Raises:
        InvalidArgumentError: ``playtime_s`` is not a number, NaN or infinite.
        OutOfRangeError: The playtime is outside 0..2.8448 s (:func:`check_playtime_s`).
    """
    ticks = round(check_playtime_s(playtime_s) / TICK_S)
    # 2.8448 / 0.0112 is 254 within float noise; the range check makes it at most 254.
    return min(ticks, MAX_PLAYTIME_TICKS)


def playtime_s_from_ticks(playtime_ticks: int) -> float:
    """Convert a playtime in ticks (0..254) to seconds.

    Raises:
        InvalidArgumentError: ``playtime_ticks`` is not an int.
        OutOfRangeError: ``playtime_ticks`` is outside 0..254.
    """
    check_playtime_ticks(playtime_ticks)
    # Rounded to the 0.1 ms the ticks are made of, so 254 ticks print as 2.8448 s.
    return round(playtime_ticks * TICK_S, 6)


def playtime_sent_s(playtime_s: float) -> float:
    """The playtime actually sent for ``playtime_s``: rounded to whole 11.2 ms ticks.

    ``playtime_sent_s(2.84)`` is 2.8448 (254 ticks), ``playtime_sent_s(0.5)`` 0.504
    (45 ticks); show this, not the request, when telling a user what was sent.

    Raises:
        InvalidArgumentError: ``playtime_s`` is not a number, NaN or infinite.
        OutOfRangeError: As :func:`playtime_ticks_from_s`.
    """
    return playtime_s_from_ticks(playtime_ticks_from_s(playtime_s))


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


def _pos_raw(
    name: str,
    angle: float,
    unit: str,
    *,
    deg_per_unit: float,
    zero_offset_raw: int,
    min_raw: int,
    max_raw: int,
) -> int:
    """The nearest raw position of ``angle`` (in ``unit``), checked against the range."""
    value = finite(name, angle, unit)
    offset = check_zero_offset_raw(zero_offset_raw)
    # Wider than a position can be, so a caller may switch the range check off.
    low_raw = integer("min_raw", min_raw, -_RAW_LIMIT_SPAN, _RAW_LIMIT_SPAN, "count")
    high_raw = integer("max_raw", max_raw, -_RAW_LIMIT_SPAN, _RAW_LIMIT_SPAN, "count")
    if low_raw > high_raw:
        raise InvalidArgumentError(f"min_raw={low_raw} is above max_raw={high_raw}")
    # Counts from 0 deg; a huge angle overflows to inf, which the range check refuses
    # before round() could fail on it.
    counts = value * deg_per_unit / DEG_PER_COUNT
    centre = CENTRE_RAW + offset
    if low_raw - 0.5 <= counts + centre <= high_raw + 0.5:
        pos_raw = round(counts) + centre
        if low_raw <= pos_raw <= high_raw:
            return pos_raw
    low = (low_raw - centre) * DEG_PER_COUNT / deg_per_unit
    high = (high_raw - centre) * DEG_PER_COUNT / deg_per_unit
    raise OutOfRangeError(name, angle, round(low, 6), round(high, 6), unit)
