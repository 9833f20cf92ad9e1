"""Reaching the broker: its address and credentials, the client, and the back-off between
attempts (a module of its own, as reconnecting is a job of its own)."""

from __future__ import annotations

import asyncio
import ipaddress
import random
import ssl
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb._checks import mqtt_address
from ohmni_tb.errors import ConfigError

if TYPE_CHECKING:
    import aiomqtt

    from ohmni_tb.config import RobotConfig

__all__ = [
    "BACKOFF_FIRST_S",
    "BACKOFF_MAX_S",
    "Backoff",
    "Broker",
    "require_client",
]

#: The first wait after a lost or refused connection, s.
BACKOFF_FIRST_S: Final = 0.5
#: The longest wait between two attempts, s: a broker back after a restart is found
#: within this.
BACKOFF_MAX_S: Final = 30.0
#: How long a connection attempt may take (TCP, TLS, CONNACK), s.
_CONNECT_TIMEOUT_S: Final = 10.0
#: Messages paho keeps for QoS 1 in flight at once before it queues them.
_MAX_INFLIGHT: Final = 20


def require_client() -> Any:
    """The ``aiomqtt`` module.

    Raises:
        ConfigError: The mqtt extra is not installed.
    """
    try:
        import aiomqtt  # noqa: PLC0415  # the optional extra
    except ImportError:
        raise ConfigError("MQTT needs the mqtt extra: pip install 'ohmni_tb[mqtt]'") from None
    return aiomqtt


@dataclass(frozen=True, slots=True)
class Broker:
    """Where the broker is and how to log in (``mqtt_*`` settings, or arguments).

    Attributes:
        host: Its host name or address.
        port: Its TCP port.
        tls: Whether the connection is TLS (``mqtts://``).
        username: The user name, or ``None``.
        password: The password, or ``None``.
        ca_file: CA certificates to check the broker's against (``None``: the system's).
        cert_file: A client certificate, or ``None``.
        key_file: Its private key.
        keepalive_s: The MQTT keep-alive, s.
    """

    host: str
    port: int
    tls: bool = False
    username: str | None = None
    password: str | None = None
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    keepalive_s: int = 30

    @classmethod
    def from_url(cls, url: str, **options: Any) -> Broker:
        """The broker at ``url`` (``mqtt://HOST[:PORT]`` or ``mqtts://HOST[:PORT]``).

        Raises:
            ConfigError: Not such a URL; the message names it and what is allowed.
        """
        address = mqtt_address(url)
        if address is None:
            raise ConfigError(
                f"{url!r} is not a broker URL: allowed mqtt://HOST[:PORT] or "
                "mqtts://HOST[:PORT], without a user or path"
            )
        host, port, tls = address
        return cls(host, port, tls, **options)

    @classmethod
    def from_config(cls, config: RobotConfig, url: str | None = None) -> Broker:
        """The broker of ``config`` (``mqtt_url``, or ``url``), with its credentials.

        Raises:
            ConfigError: No broker URL, or not one.
        """
        url = url or config.mqtt_url
        if not url:
            raise ConfigError("no broker: give --mqtt URL, or set mqtt_url (OHMNI_MQTT_URL)")
        password = config.mqtt_password.get_secret_value()
        return cls.from_url(
            url,
            username=config.mqtt_username or None,
            password=password or None,
            ca_file=config.mqtt_ca_file or None,
            cert_file=config.mqtt_cert_file or None,
            key_file=config.mqtt_key_file or None,
            keepalive_s=config.mqtt_keepalive_s,
        )

    @property
    def url(self) -> str:
        """``mqtt://host:port`` (``mqtts`` over TLS)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{'mqtts' if self.tls else 'mqtt'}://{host}:{self.port}"

    @property
    def authenticated(self) -> bool:
        """Whether the broker is told who this is (a user name or a client certificate)."""
        return self.username is not None or self.cert_file is not None

    @property
    def local(self) -> bool:
        """Whether the broker runs on this machine (a loopback address or ``localhost``)."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False

    def client(
        self,
        identifier: str,
        *,
        will: tuple[str, str] | None = None,
        max_queued_incoming: int = 0,
        on_dropped: Callable[[], None] | None = None,
    ) -> aiomqtt.Client:
        """A new MQTT 5 client for this broker (connect it with ``async with``), with a
        retained QoS 1 Last Will ``(topic, payload)`` when given, and a clean start (no
        command sent while it was away is delivered later). It holds at most
        ``max_queued_incoming`` messages unread (0: no limit); each one beyond is dropped,
        and ``on_dropped`` told.

        Raises:
            ConfigError: The mqtt extra is missing, or a TLS file cannot be read.
        """
        mqtt = require_client()
        context = self._tls_context() if self.tls else None
        return mqtt.Client(  # type: ignore[no-any-return]
            self.host,
            self.port,
            identifier=identifier,
            username=self.username,
            password=self.password,
            protocol=mqtt.ProtocolVersion.V5,
            will=None if will is None else mqtt.Will(will[0], will[1], qos=1, retain=True),
            keepalive=self.keepalive_s,
            timeout=_CONNECT_TIMEOUT_S,
            clean_start=True,
            tls_context=context,
            max_inflight_messages=_MAX_INFLIGHT,
            max_queued_incoming_messages=max_queued_incoming,
            queue_type=None if on_dropped is None else _counting_queue(on_dropped),
        )

    def _tls_context(self) -> ssl.SSLContext:
        for name, path in (
            ("mqtt_ca_file", self.ca_file),
            ("mqtt_cert_file", self.cert_file),
            ("mqtt_key_file", self.key_file),
        ):
            if path is not None and not Path(path).is_file():
                raise ConfigError(f"{name}={path!r}: no such file")
        try:
            context = ssl.create_default_context(cafile=self.ca_file)
            if self.cert_file is not None:
                context.load_cert_chain(self.cert_file, self.key_file)
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(f"cannot use the TLS files for {self.url}: {exc}") from exc
        return context


def _counting_queue(on_dropped: Callable[[], None]) -> type[asyncio.Queue[Any]]:
    """The client's queue of unread messages, telling ``on_dropped`` of each it has no room
    for (the client then drops it, and logs a line)."""

    class CountingQueue(asyncio.Queue[Any]):
        def put_nowait(self, item: Any) -> None:
            if self.full():
                on_dropped()
            super().put_nowait(item)

    return CountingQueue


class Backoff:
    """The waits between connection attempts: :data:`BACKOFF_FIRST_S`, doubling up to
    :data:`BACKOFF_MAX_S`, each spread by ±20 % so that a fleet whose broker restarts does
    not come back all at once; :meth:`reset` after a connection that held."""

    def __init__(
        self,
        first_s: float = BACKOFF_FIRST_S,
        max_s: float = BACKOFF_MAX_S,
        rng: random.Random | None = None,
    ) -> None:
        self._first_s = first_s
        self._max_s = max_s
        self._next_s = first_s
        self._rng = rng or random.Random()  # spreading waits, not secrets

    def next_s(self) -> float:
        """The next wait, s."""
        wait = self._next_s
        self._next_s = min(self._max_s, self._next_s * 2)
        return wait * self._rng.uniform(0.8, 1.2)

    def reset(self) -> None:
        """Back to the first wait."""
        self._next_s = self._first_s
