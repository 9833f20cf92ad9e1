"""Byte transports and ``open_transport(url)``.

URLs understood:

==================================================  =============================================
``/dev/ttyUSB0``                                    a serial port at 115200 8N1
``serial:///dev/ttyUSB0?baudrate=115200``          the same, options in the query
``memory://``                                       a loopback: what you write, you read
``memory://NAME``                                   one end of a named in-process pipe; the
                                                    second open of NAME gets the other end
                                                    (a third starts a new pair)
``sim://``                                          the simulated robot (:mod:`ohmni_tb.sim`)
``auto``                                            the robot's bus adapter, found by its USB id
                                                    (:mod:`ohmni_tb.transport.ports`)
==================================================  =============================================

More schemes can be added with :func:`register_transport`. A transport that can open its
link again (after a loss, or after handing the port to another program) says so with
:attr:`Transport.can_reopen` and does it in :meth:`Transport.reopen`: serial ports and
the simulated robot do; an in-memory pipe does not.
"""

from __future__ import annotations

import importlib
from collections.abc import Awaitable, Callable
from urllib.parse import SplitResult, parse_qs, urlsplit

from ohmni_tb.errors import ConfigError
from ohmni_tb.transport.base import Transport
from ohmni_tb.transport.memory import (
    Manipulator,
    MemoryTransport,
    corrupt_byte,
    delay,
    drop_bytes,
    split,
)
from ohmni_tb.transport.ports import AUTO_PORT
from ohmni_tb.transport.serial import DEFAULT_BAUDRATE, SerialTransport

__all__ = [
    "DEFAULT_BAUDRATE",
    "Manipulator",
    "MemoryTransport",
    "SerialTransport",
    "Transport",
    "TransportFactory",
    "corrupt_byte",
    "delay",
    "drop_bytes",
    "open_transport",
    "option_bool",
    "option_int",
    "register_transport",
    "registered_schemes",
    "reject_unknown_options",
    "split",
]

#: Opens a transport from a parsed URL and its query options (one value per key).
TransportFactory = Callable[[SplitResult, dict[str, str]], Awaitable[Transport]]

_FACTORIES: dict[str, TransportFactory] = {}
#: Schemes whose module registers its factory when first imported.
_LAZY: dict[str, str] = {"sim": "ohmni_tb.sim.url"}
_MEMORY_ENDS: dict[str, MemoryTransport] = {}


def register_transport(scheme: str, factory: TransportFactory, *, replace: bool = False) -> None:
    """Make ``open_transport`` understand ``scheme://...`` URLs.

    Raises:
        ConfigError: ``scheme`` is taken and ``replace`` is false.
    """
    scheme = scheme.lower()
    if scheme in _FACTORIES and not replace:
        raise ConfigError(f"transport scheme {scheme!r} is already registered")
    _FACTORIES[scheme] = factory


def registered_schemes() -> list[str]:
    """Every scheme ``open_transport`` understands."""
    return sorted(set(_FACTORIES) | set(_LAZY))


async def open_transport(url: str) -> Transport:
    """Open the transport a URL names (see the module docstring).

    Raises:
        ConfigError: The URL or one of its options is invalid; the message says which.
        TransportError: The transport exists but cannot be opened.
        NoBusPortError: ``auto`` found no bus adapter (a :class:`TransportError`).
    """
    if url == AUTO_PORT:
        # Looked for when it opens, and again when it is reopened.
        return await SerialTransport.open(AUTO_PORT)
    if url.startswith("/"):
        url = "serial://" + url
    try:
        parts = urlsplit(url)
    except ValueError as exc:  # an unclosed IPv6 bracket, characters NFKC turns into '/'
        raise ConfigError(f"cannot parse the URL {url!r}: {exc}") from None
    scheme = parts.scheme.lower()
    if not scheme:
        raise ConfigError(
            f"cannot tell what to open from {url!r}: give a device path such as "
            f"/dev/ttyUSB0 or a URL with one of the schemes {registered_schemes()}"
        )
    factory = _FACTORIES.get(scheme)
    if factory is None and scheme in _LAZY:
        importlib.import_module(_LAZY[scheme])
        factory = _FACTORIES.get(scheme)
    if factory is None:
        raise ConfigError(
            f"unknown transport scheme {scheme!r} in {url!r}; known: {registered_schemes()}"
        )
    options: dict[str, str] = {}
    for key, values in parse_qs(parts.query, keep_blank_values=True, strict_parsing=False).items():
        if len(values) != 1:
            raise ConfigError(f"option {key!r} given {len(values)} times in {url!r}")
        options[key] = values[0]
    return await factory(parts, options)


def option_int(options: dict[str, str], key: str, default: int, low: int, high: int) -> int:
    """Pop an integer option, checking its range.

    Raises:
        ConfigError: The value is not an integer in ``low..high``.
    """
    raw = options.pop(key, None)
    if raw is None:
        return default
    try:
        if not raw.isascii():  # int() would read other scripts' digits too
            raise ValueError(raw)
        value = int(raw, 0)
    except ValueError:
        raise ConfigError(f"option {key}={raw!r} is not an integer") from None
    if not low <= value <= high:
        raise ConfigError(f"option {key}={value} is out of range: allowed {low}..{high}")
    return value


def option_bool(options: dict[str, str], key: str, default: bool) -> bool:
    """Pop a boolean option (1/0, true/false, yes/no, on/off).

    Raises:
        ConfigError: The value is not a boolean word.
    """
    raw = options.pop(key, None)
    if raw is None:
        return default
    word = raw.strip().lower()
    if word in {"1", "true", "yes", "on", ""}:
        return True
    if word in {"0", "false", "no", "off"}:
        return False
    raise ConfigError(f"option {key}={raw!r} is not a boolean (use 1/0, true/false)")


def reject_unknown_options(url: SplitResult, options: dict[str, str]) -> None:
    """Raise if any option was not consumed by the factory.

    Raises:
        ConfigError: Names the unknown options.
    """
    if options:
        raise ConfigError(f"unknown option(s) {sorted(options)} for {url.scheme}:// transport")


async def _open_serial(url: SplitResult, options: dict[str, str]) -> Transport:
    port = url.path
    if url.netloc:
        # serial://dev/ttyUSB0 (two slashes) puts "dev" in netloc; accept it.
        port = f"/{url.netloc}{url.path}"
    if not port:
        raise ConfigError("serial:// needs a device path, e.g. serial:///dev/ttyUSB0")
    baudrate = option_int(options, "baudrate", DEFAULT_BAUDRATE, 50, 4_000_000)
    low_latency = option_bool(options, "low_latency", True)
    exclusive = option_bool(options, "exclusive", True)
    reject_unknown_options(url, options)
    return await SerialTransport.open(port, baudrate, low_latency=low_latency, exclusive=exclusive)


async def _open_memory(url: SplitResult, options: dict[str, str]) -> Transport:
    reject_unknown_options(url, options)
    name = url.netloc + url.path
    if not name:
        return MemoryTransport.loopback()
    waiting = _MEMORY_ENDS.pop(name, None)
    if waiting is not None:
        return waiting
    a, b = MemoryTransport.pair(name)
    _MEMORY_ENDS[name] = b
    return a


register_transport("serial", _open_serial)
register_transport("memory", _open_memory)
