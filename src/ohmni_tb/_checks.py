"""Argument checks shared by the sans-IO modules; every error names the value."""

from __future__ import annotations

import math

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError


def finite(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise if it is not a number, NaN or infinite."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidArgumentError(f"{name} must be a number, not {type(value).__name__}")
    if not math.isfinite(value):
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} is not a finite number")
    return float(value)


def positive(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is finite and > 0."""
    finite(name, value, unit)
    if value <= 0.0:
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} must be > 0")
    return float(value)


def non_negative(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is finite and >= 0."""
    finite(name, value, unit)
    if value < 0.0:
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} must be >= 0")
    return float(value)


def positive_or_inf(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is > 0 (``inf`` = no limit)."""
    if math.isnan(value) or value <= 0.0:
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} must be > 0 (inf for no limit)")
    return float(value)


def integer(name: str, value: int, low: int, high: int | None = None, unit: str = "") -> int:
    """Return ``value``, or raise unless it is an int (not a bool) in ``low..high``."""
    if (
        isinstance(value, int)
        and not isinstance(value, bool)
        and value >= low
        and (high is None or value <= high)
    ):
        return value
    if high is None:
        raise InvalidArgumentError(f"{name}={value!r} must be an integer >= {low}")
    raise OutOfRangeError(name, value, low, high, unit)
