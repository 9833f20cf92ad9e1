"""Argument checks shared by the sans-IO modules; every error names the value."""

from __future__ import annotations

import math
import sys
from urllib.parse import urlsplit

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, _brief


def show(value: object) -> str:
    """``repr(value)`` for a one-line message, shortened when long (a huge int)."""
    return _brief(value)


#: The largest finite float: a number beyond it cannot be computed with.
FLOAT_MAX = sys.float_info.max


def finite(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise if it is not a number, NaN or infinite.

    Raises:
        InvalidArgumentError: Not a number (a bool is not one), NaN or infinite.
        OutOfRangeError: An int too large to be a float.
    """
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidArgumentError(f"{name} must be a number, not {type(value).__name__}")
    try:
        number = float(value)
    except OverflowError:
        raise OutOfRangeError(name, value, -FLOAT_MAX, FLOAT_MAX, unit) from None
    if not math.isfinite(number):
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} is not a finite number")
    return number


def number(name: str, value: float, unit: str = "") -> float:
    """:func:`finite`, naming a value of the wrong type itself (``'fast'``), not its type:
    for values that come from a user's message or call rather than from code."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidArgumentError(f"{name} must be a number, not {show(value)}")
    return finite(name, value, unit)


def positive(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is finite and > 0."""
    number = finite(name, value, unit)
    if number <= 0.0:
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} must be > 0")
    return number


def non_negative(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is finite and >= 0."""
    number = finite(name, value, unit)
    if number < 0.0:
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} must be >= 0")
    return number


def positive_or_inf(name: str, value: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is > 0 (``inf`` = no limit)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InvalidArgumentError(f"{name} must be a number, not {type(value).__name__}")
    number = math.inf if value == math.inf else finite(name, value, unit)
    if number <= 0.0:
        suffix = f" {unit}" if unit else ""
        raise InvalidArgumentError(f"{name}={value!r}{suffix} must be > 0 (inf for no limit)")
    return number


def bounded(name: str, value: float, low: float, high: float, unit: str = "") -> float:
    """Return ``value`` as a float, or raise unless it is finite and in ``low..high``.

    Raises:
        InvalidArgumentError: Not a number, NaN or infinite.
        OutOfRangeError: Outside ``low..high``.
    """
    number = finite(name, value, unit)
    if not low <= number <= high:
        raise OutOfRangeError(name, value, low, high, unit)
    return number


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
        raise InvalidArgumentError(f"{name}={_brief(value)} must be an integer >= {low}")
    raise OutOfRangeError(name, value, low, high, unit)


def whole(name: str, value: int) -> int:
    """Return ``value`` if it is an int (not a bool), of any size."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise InvalidArgumentError(
            f"{name} must be an int, not {type(value).__name__} {_brief(value)}"
        )
    return value


def finite_result(
    result: float, name: str, value: float, low: float, high: float, *, unit: str = ""
) -> float:
    """Return ``result`` if it is finite; else ``value`` (of ``name``) was out of ``low..high``.

    For a conversion whose result overflows: the error names the argument and the range
    of arguments whose result is a finite number.
    """
    if not math.isfinite(result):
        raise OutOfRangeError(name, value, low, high, unit)
    return result


def check_seconds(name: str, value: float, low: float, high: float) -> None:
    """Raise unless ``value`` is a finite number of seconds in ``low..high``.

    Raises:
        OutOfRangeError: Names ``name`` and the range.
    """
    if (
        isinstance(value, bool)
        or not isinstance(value, int | float)
        or not math.isfinite(value)
        or not low <= value <= high
    ):
        raise OutOfRangeError(name, value, low, high, "s")


def host_port(text: str, *, default_host: str | None = None) -> tuple[str, int] | None:
    """``HOST:PORT`` (an IPv6 host in brackets) as (host, port), or ``None`` when it is
    not one; with ``default_host``, ``PORT`` or ``:PORT`` alone stands for that host.
    The port is 0..65535."""
    raw_host, sep, port = text.rpartition(":")
    host = raw_host.removeprefix("[").removesuffix("]")
    if default_host is None:
        if not sep or not raw_host:
            return None
    else:
        host = host or default_host
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        return None
    return host, int(port)


#: An MQTT broker's port when its URL names none: plain, and over TLS.
MQTT_PORTS = {"mqtt": 1883, "mqtts": 8883}


def mqtt_address(url: str) -> tuple[str, int, bool] | None:
    """A broker's ``mqtt://HOST[:PORT]`` or ``mqtts://HOST[:PORT]`` URL as (host, port,
    TLS), the port 1883 or 8883 when none is given; ``None`` when it is not one (another
    scheme, no host, a port outside 1..65535, a user, a path other than ``/``, a query)."""
    try:
        parts = urlsplit(url)
        port = parts.port  # a number in 0..65535, or ValueError
    except ValueError:
        return None
    if (
        parts.scheme not in MQTT_PORTS
        or not parts.hostname
        or port == 0
        or "@" in parts.netloc
        or parts.path not in ("", "/")
        or parts.query
        or parts.fragment
    ):
        return None
    return parts.hostname, port or MQTT_PORTS[parts.scheme], parts.scheme == "mqtts"


def ws_address(url: str) -> tuple[str, int] | None:
    """A daemon's ``ws://HOST[:PORT]`` or ``wss://HOST[:PORT]`` URL as (host, port), the
    port 80 or 443 when none is given; ``None`` when it is not one (another scheme, no
    host, a port outside 1..65535, an unclosed ``[`` around an IPv6 host)."""
    try:
        parts = urlsplit(url)
        port = parts.port  # a number in 0..65535, or ValueError
    except ValueError:
        return None
    if parts.scheme not in ("ws", "wss") or not parts.hostname or port == 0:
        return None
    return parts.hostname, port or (443 if parts.scheme == "wss" else 80)
