"""Who may connect to the daemon: the token, and browsers' origins (sans-IO).

On loopback every local program may connect, as to gpsd. Listening anywhere else needs a
token: a random secret kept in a file only its owner can read (``0600``), created on first
use. A client presents it as ``Authorization: Bearer <token>``, or, from a browser (which
cannot set that header on a WebSocket), as one of the WebSocket subprotocols it offers:
``ohmni.token.<the token, base64url>`` beside ``ohmni`` (:data:`WEB_PROTOCOL`, the one the
daemon picks), which keeps it out of URLs, histories and logs; ``?token=<token>`` in the URL
is still taken. It is compared in constant time. Browsers also send ``Origin``: a page from
any site could otherwise open a WebSocket to the daemon from the user's machine, so a
handshake carrying an ``Origin`` is refused unless that origin is allowed.
"""

from __future__ import annotations

import base64
import binascii
import hmac
import os
import secrets
import stat
from pathlib import Path
from typing import Final
from urllib.parse import parse_qs, urlsplit

from ohmni_tb.config import user_config_dir
from ohmni_tb.errors import ConfigError
from ohmni_tb.robot.wire import TOKEN_ENV  # a client's, where it takes the token from

__all__ = [
    "MIN_TOKEN_CHARS",
    "TOKEN_ENV",
    "TOKEN_FILE_NAME",
    "TOKEN_PROTOCOL_PREFIX",
    "WEB_PROTOCOL",
    "check_origin",
    "check_token",
    "default_token_path",
    "load_or_create_token",
    "presented_token",
    "read_token",
]

#: The token file's name in the user's config directory.
TOKEN_FILE_NAME: Final = "daemon-token"
#: Bytes of randomness in a new token (256 bits), shown URL-safe base64 (43 characters).
_TOKEN_BYTES = 32
#: The WebSocket subprotocol a browser offers, and the daemon picks: a browser refuses a
#: handshake that answers none of the subprotocols it offered.
WEB_PROTOCOL: Final = "ohmni"
#: A subprotocol starting with this carries the token, base64url without padding: a
#: browser cannot set ``Authorization`` on a WebSocket, and a URL's query ends up in
#: histories and logs. Never picked, so never sent back.
TOKEN_PROTOCOL_PREFIX: Final = "ohmni.token."
#: A token shorter than this is refused (the daemon, Foxglove control): anyone could
#: guess it.
MIN_TOKEN_CHARS: Final = 16


def default_token_path() -> Path:
    """``$XDG_CONFIG_HOME/ohmni/daemon-token`` (default ``~/.config/ohmni/daemon-token``)."""
    return user_config_dir() / TOKEN_FILE_NAME


def load_or_create_token(path: str | os.PathLike[str] | None = None) -> str:
    """The token in ``path`` (default :func:`default_token_path`), created on first use.

    A new token is written with permissions ``0600`` (the directory ``0700`` when created),
    so only its owner can read it.

    Raises:
        ConfigError: The file can be read by others (group or world permission bits: fix
            with ``chmod 600``), is empty or too short, or cannot be read or written.
    """
    target = Path(path) if path is not None else default_token_path()
    try:
        return read_token(target)
    except FileNotFoundError:
        pass
    token = secrets.token_urlsafe(_TOKEN_BYTES)
    try:
        target.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        # O_EXCL: two daemons starting at once do not overwrite each other's token.
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return read_token(target)
    except OSError as exc:
        raise ConfigError(f"cannot create the daemon token file {target}: {exc.strerror}") from exc
    with os.fdopen(fd, "w", encoding="ascii") as file:
        file.write(token + "\n")
    return token


def read_token(path: str | os.PathLike[str]) -> str:
    """The token in ``path``.

    Raises:
        FileNotFoundError: There is no such file.
        ConfigError: Others can read it, it is too short, or it cannot be read.
    """
    target = Path(path)
    try:
        mode = target.stat().st_mode
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise ConfigError(
                f"the daemon token file {target} is readable by others "
                f"(mode {stat.S_IMODE(mode):04o}): run `chmod 600 {target}`"
            )
        token = target.read_text(encoding="ascii").strip()
    except FileNotFoundError:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the daemon token file {target}: {exc}") from exc
    if len(token) < MIN_TOKEN_CHARS:
        raise ConfigError(
            f"the daemon token in {target} is {len(token)} characters: at least "
            f"{MIN_TOKEN_CHARS} are needed (delete the file and a new one is made)"
        )
    return token


def presented_token(
    path: str, authorization: str | None, protocols: str | None = None
) -> str | None:
    """The token a handshake presents: ``Authorization: Bearer …``, else a subprotocol
    ``ohmni.token.<base64url>`` among ``protocols`` (the ``Sec-WebSocket-Protocol``
    header's value), else ``?token=…``."""
    if authorization is not None:
        scheme, _, value = authorization.partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
    for offered in (protocols or "").split(","):
        name = offered.strip()
        if name.startswith(TOKEN_PROTOCOL_PREFIX):
            return _from_base64url(name[len(TOKEN_PROTOCOL_PREFIX) :])
    values = parse_qs(urlsplit(path).query).get("token")
    return values[0] if values else None


def check_token(presented: str | None, expected: str) -> bool:
    """Whether ``presented`` is the token, compared in constant time."""
    if presented is None:
        return False
    return hmac.compare_digest(presented.encode(), expected.encode())


def check_origin(origin: str | None, allowed: tuple[str, ...]) -> bool:
    """Whether a handshake's ``Origin`` may connect: none (not a browser), or one allowed."""
    return origin is None or origin in allowed


_FROM_URLSAFE = str.maketrans("-_", "+/")


def _from_base64url(text: str) -> str:
    """A token sent base64url (padding optional); a text that is not one is presented as
    itself, and so is refused as a wrong token (never as none)."""
    try:
        standard = text.translate(_FROM_URLSAFE) + "=" * (-len(text) % 4)
        return base64.b64decode(standard, validate=True).decode("utf-8")
    except (binascii.Error, ValueError):
        return text
