"""Who may control the robot through a Foxglove server: the clients that proved the token.

The Foxglove WebSocket protocol has no authentication, and foxglove-sdk's server tells
its listener nothing of a connection but a client id: not the peer, not the handshake's
``Origin``. A web page the user visits could open a WebSocket to the server on loopback
as well as the app can, so a client is never trusted for being local. Every client may
watch; a client drives (Teleop Twists), sets parameters and calls services only after
calling :data:`UNLOCK_SERVICE` with the token (``{"token": "..."}``), and only that
client id is unlocked. The SDK numbers clients from one counter and never reuses an id,
so a closed client's unlock cannot pass to a new connection.

:class:`ControlGate` is that rule without I/O: it compares the token in constant time,
keeps the unlocked ids and counts what it refused.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from typing import Any, Final

from ohmni_tb.daemon.auth import MIN_TOKEN_CHARS, check_token
from ohmni_tb.errors import ConfigError, InvalidArgumentError, StateError

__all__ = [
    "LOCKED_MESSAGE",
    "LOCKED_STATUS_ID",
    "UNLOCK_SCHEMAS",
    "UNLOCK_SERVICE",
    "AccessStats",
    "ControlGate",
]

#: The service a client calls with the token to unlock control for itself.
UNLOCK_SERVICE: Final = "/tb_control/unlock"
#: Its (request, response) JSON Schemas, as the app's Service Call panel shows them.
UNLOCK_SCHEMAS: Final[tuple[dict[str, Any], dict[str, Any]]] = (
    {
        "type": "object",
        "properties": {"token": {"type": "string"}},
        "required": ["token"],
        "additionalProperties": False,
    },
    {
        "type": "object",
        "properties": {"unlocked": {"type": "boolean"}},
        "additionalProperties": False,
    },
)
#: The id of the status message telling a locked client why its Twists move nothing: the
#: app replaces a status of the same id instead of piling them up.
LOCKED_STATUS_ID: Final = "tb_control/locked"
#: That status message (the SDK sends a status to every client: it names no client).
LOCKED_MESSAGE: Final = (
    f"a client's Twists are ignored: control is locked until that client calls "
    f'{UNLOCK_SERVICE} with the token ({{"token": "..."}})'
)
#: Locked clients remembered as already told; beyond, the memory starts again (a client
#: that opens connection after connection is told once more, never more often).
_MAX_TOLD = 1024
#: A request longer than this is not read (a token is 43 characters).
_MAX_REQUEST_BYTES = 4096


@dataclass(frozen=True, slots=True)
class AccessStats:
    """What the gate decided.

    Attributes:
        unlocked: Clients that unlocked control with the token.
        refused_unlocks: Unlock calls with a wrong or missing token.
        ignored_twists: Twists from clients that had not unlocked control.
        refused_changes: Parameter changes and service calls refused for the same reason.
    """

    unlocked: int
    refused_unlocks: int
    ignored_twists: int
    refused_changes: int


class ControlGate:
    """The token's check and the unlocked client ids (module docstring). Thread-safe: the
    SDK calls its listener and service handlers from its own threads.

    Args:
        token: The secret a client presents to :data:`UNLOCK_SERVICE`.

    Raises:
        ConfigError: The token is shorter than 16 characters.
    """

    def __init__(self, token: str) -> None:
        if len(token) < MIN_TOKEN_CHARS:
            raise ConfigError(
                f"a control token of {len(token)} characters is too easy to guess: at least "
                f"{MIN_TOKEN_CHARS} (ohmni_tb.daemon.auth.load_or_create_token makes one)"
            )
        self._token = token
        self._lock = threading.Lock()
        self._unlocked: set[int] = set()
        self._told: set[int] = set()
        self._refused_unlocks = 0
        self._ignored_twists = 0
        self._refused_changes = 0

    def unlock(self, client_id: int, request: bytes) -> bytes:
        """Answer an unlock call: ``{"token": "..."}`` in, ``{"unlocked": true}`` out.

        Raises:
            InvalidArgumentError: Not a JSON object with a string ``token``.
            StateError: The wrong token (the client stays locked).
        """
        token = _presented(request)
        if not check_token(token, self._token):
            with self._lock:
                self._refused_unlocks += 1
            raise StateError(f"{UNLOCK_SERVICE}: wrong token: control stays locked")
        with self._lock:
            self._unlocked.add(client_id)
            self._told.discard(client_id)
        return json.dumps({"unlocked": True}).encode()

    def allows(self, client_id: int) -> bool:
        """Whether this client unlocked control."""
        return client_id in self._unlocked

    def ignore_twist(self, client_id: int) -> bool:
        """Count a locked client's Twist; whether the client is to be told (its first)."""
        with self._lock:
            self._ignored_twists += 1
            if client_id in self._told:
                return False
            if len(self._told) >= _MAX_TOLD:
                self._told.clear()
            self._told.add(client_id)
            return True

    def refuse_change(self, what: str) -> StateError:
        """Count a locked client's parameter change or service call; the error to tell it."""
        with self._lock:
            self._refused_changes += 1
        return StateError(
            f"{what}: control is locked for this client: call {UNLOCK_SERVICE} with the "
            'token first ({"token": "..."})'
        )

    def stats(self) -> AccessStats:
        """The counts so far."""
        with self._lock:
            return AccessStats(
                len(self._unlocked),
                self._refused_unlocks,
                self._ignored_twists,
                self._refused_changes,
            )


def _presented(request: bytes) -> str:
    if len(request) > _MAX_REQUEST_BYTES:
        raise InvalidArgumentError(
            f"{UNLOCK_SERVICE}: a request of {len(request)} bytes is not a token "
            f"(at most {_MAX_REQUEST_BYTES})"
        )
    try:
        args = json.loads(request or b"{}")
    except ValueError as exc:
        raise InvalidArgumentError(f"{UNLOCK_SERVICE}: the request is not JSON: {exc}") from exc
    if not isinstance(args, dict) or set(args) != {"token"} or not isinstance(args["token"], str):
        raise InvalidArgumentError(f'{UNLOCK_SERVICE} takes {{"token": "..."}}, nothing else')
    token: str = args["token"]
    return token
