"""The web console: ``ohmni serve`` serves its page over HTTP on its own port.

A browser opens ``http://HOST:PORT/`` (the daemon's port: 8766 by default) and gets a page
of plain HTML, CSS and JavaScript modules shipped in the package (``ohmni_tb/web/``: no
build step, nothing fetched from elsewhere). The page then opens a WebSocket to the same
address and speaks the daemon's own protocol (:mod:`ohmni_tb.robot.wire`), under the
daemon's own rules: a token beyond loopback, one lease holder drives.

Each request arrives as a WebSocket handshake would (websockets' ``process_request``): a
request without ``Upgrade: websocket`` for one of the page's paths is answered here, and
every other one goes on to the daemon's checks as before. What is answered:

* The page's files, from memory (read once, when the server is made): only the names in
  the folder, so no path reaches the file system (``/../``, ``%2e%2e`` are 404); each
  with its type, ``Cache-Control: no-cache`` and an ``ETag`` (a browser asks again each
  time, and gets 304 when the package did not change), and a Content-Security-Policy
  that lets the page load and connect to its own origin only.
* ``/auth``: 204 when no token is needed or the one presented (``Authorization: Bearer``)
  is right, else 401. The page asks it before connecting, to tell "needs the token" from
  "cannot reach the daemon": a refused WebSocket handshake shows a browser nothing.

Browsers send ``Origin`` with a WebSocket handshake, and the daemon refuses origins not
allowed (``--allow-origin``). The page's own origin is allowed (:meth:`WebConsole.own_origin`):
the ``Origin`` is ``http://`` (or ``https://``) and the ``Host`` the browser connected to,
and the host is an IP address or ``localhost`` — or the daemon has a token. A name that is
not (``robot.local``) is refused on a daemon without a token: a web site could make its
own name resolve to the robot's address (DNS rebinding) and be that origin.
"""

from __future__ import annotations

import contextlib
import hashlib
import ipaddress
import logging
import re
import socket
from dataclasses import dataclass
from importlib import resources
from typing import TYPE_CHECKING, Final
from urllib.parse import urlsplit

from ohmni_tb.daemon.auth import check_token, presented_token

if TYPE_CHECKING:
    from websockets.asyncio.server import ServerConnection
    from websockets.http11 import Request, Response

__all__ = [
    "AUTH_PATH",
    "CONTENT_TYPES",
    "HEADLESS_CHROMIUM_ARGS",
    "WEB_FOLDER",
    "WebConsole",
    "page_url",
]

_log = logging.getLogger("ohmni_tb.daemon")

#: Chromium's arguments to open the console headless on a closed network (the tests, the
#: screenshots, the benchmark): nothing of its own reaching out (updates, sync, QUIC
#: probes), no sandbox (CI runs as root).
HEADLESS_CHROMIUM_ARGS: tuple[str, ...] = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)

#: The package folder with the page's files (``ohmni_tb/web``).
WEB_FOLDER: Final = "web"
#: Where the page asks whether it needs the token, or whether the one it has is right.
AUTH_PATH: Final = "/auth"
#: The files' types by suffix: a file of another kind in the folder is not served.
CONTENT_TYPES: Final = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".webmanifest": "application/manifest+json",
}
#: A ``Host`` header as a browser sends it: a name or an IPv4 address, or an IPv6 one in
#: brackets, and a port. Anything else is not written into the policy.
_HOST = re.compile(r"^(?:[A-Za-z0-9.-]+|\[[0-9A-Fa-f:.]+\])(?::[0-9]{1,5})?$")
#: The headers of every answer: the page loads and connects to its own origin only, is
#: never framed, sends no referrer, and its types are not second-guessed.
_SECURITY_HEADERS: Final = (
    ("X-Content-Type-Options", "nosniff"),
    ("Referrer-Policy", "no-referrer"),
    ("X-Frame-Options", "DENY"),
    ("Cross-Origin-Opener-Policy", "same-origin"),
    ("Cross-Origin-Resource-Policy", "same-origin"),
)
#: The policy; ``{ws}`` is the page's own WebSocket origin (older Safari does not count
#: ``ws:`` as ``'self'``). No inline script or style; forms go nowhere (the login form is
#: handled by the page: a form sent as a GET would put the token in the URL).
_POLICY = (
    "default-src 'self'; connect-src 'self'{ws}; img-src 'self'; object-src 'none'; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
#: A public address to route toward (TEST-NET-1, RFC 5737): connecting a UDP socket to it
#: sends nothing, and tells the address this host would use (:func:`page_url`).
_ROUTE_PROBE = ("192.0.2.1", 9)


@dataclass(frozen=True, slots=True)
class _File:
    body: bytes
    content_type: str
    etag: str


class WebConsole:
    """The page's files and its ``/auth``, answered in the daemon's handshake hook.

    Args:
        token: The daemon's token, or ``None`` when it has none (loopback, no
            ``--token-file``).

    Raises:
        FileNotFoundError: The package has no page (``ohmni_tb/web/index.html``).
    """

    def __init__(self, token: str | None) -> None:
        self._token = token
        self._files = _load_files()
        if "/index.html" not in self._files:
            raise FileNotFoundError("the web console's index.html is missing from the package")
        self._files["/"] = self._files["/index.html"]

    @property
    def paths(self) -> tuple[str, ...]:
        """The paths it answers (``/``, ``/index.html``, ``/app.js`` …; and ``/auth``)."""
        return (*sorted(self._files), AUTH_PATH)

    def respond(self, connection: ServerConnection, request: Request) -> Response | None:
        """The answer to a plain HTTP request for the page, or ``None`` for a WebSocket
        handshake (the daemon's checks take it)."""
        if (_header(request, "Upgrade") or "").lower() == "websocket":
            return None
        path = urlsplit(request.path).path
        if path == AUTH_PATH:
            return self._auth(connection, request)
        found = self._files.get(path)
        if found is None:
            return _response(connection, 404, f"no such page: {path[:100]}\n", request)
        if found.etag in _etags(_header(request, "If-None-Match")):
            response = _response(connection, 304, "", request)
            response.headers["ETag"] = found.etag
            response.headers["Cache-Control"] = "no-cache"
            return response
        response = _response(connection, 200, "", request)
        response.body = found.body
        headers_out = response.headers
        del headers_out["Content-Length"], headers_out["Content-Type"]
        headers_out["Content-Length"] = str(len(found.body))
        headers_out["Content-Type"] = found.content_type
        headers_out["ETag"] = found.etag
        headers_out["Cache-Control"] = "no-cache"
        return response

    def own_origin(self, request: Request) -> bool:
        """Whether a handshake's ``Origin`` is the page's own: ``http://`` or
        ``https://`` and the ``Host`` it came to, which is an IP address or ``localhost``
        unless the daemon has a token (module docstring)."""
        origin = _header(request, "Origin")
        host = _header(request, "Host")
        if origin is None or host is None or not _HOST.match(host):
            return False
        if origin.lower() not in (f"http://{host}".lower(), f"https://{host}".lower()):
            return False
        return self._token is not None or _not_a_dns_name(host)

    def _auth(self, connection: ServerConnection, request: Request) -> Response:
        if self._token is None:
            return _response(connection, 204, "", request)
        given = presented_token("", _header(request, "Authorization"))
        if check_token(given, self._token):
            return _response(connection, 204, "", request)
        if given is not None:
            address = connection.remote_address
            peer = f"{address[0]}:{address[1]}" if isinstance(address, tuple) else str(address)
            _log.warning(
                "client %s: refused: a wrong token (the web console's %s)", peer, AUTH_PATH
            )
        return _response(connection, 401, "this daemon needs its token\n", request)


def page_url(host: str, port: int) -> str:
    """The page's address for a daemon listening on ``host``:``port``: a wildcard address
    (``0.0.0.0``, ``::``) is shown as the address other machines reach this one at (the
    one its default route leaves from), else as this host's name."""
    if host in ("0.0.0.0", "", "::"):
        host = _reachable_address() or socket.gethostname()
    shown = f"[{host}]" if ":" in host else host
    return f"http://{shown}:{port}/"


def _reachable_address() -> str | None:
    with contextlib.suppress(OSError), socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.connect(_ROUTE_PROBE)  # UDP: nothing is sent
        address: str = sock.getsockname()[0]
        return None if address.startswith("0.") else address
    return None


def _load_files() -> dict[str, _File]:
    """Every file of the folder whose type is known, by its path (``/app.js``)."""
    files: dict[str, _File] = {}
    folder = resources.files("ohmni_tb").joinpath(WEB_FOLDER)
    for entry in folder.iterdir():
        suffix = "." + entry.name.rpartition(".")[2]
        content_type = CONTENT_TYPES.get(suffix)
        if content_type is None or not entry.is_file():
            continue
        body = entry.read_bytes()
        etag = '"' + hashlib.sha256(body).hexdigest()[:20] + '"'
        files["/" + entry.name] = _File(body, content_type, etag)
    return files


def _response(connection: ServerConnection, status: int, text: str, request: Request) -> Response:
    """websockets' plain answer (it closes the connection after it), with the page's
    security headers."""
    response = connection.respond(status, text)
    headers = response.headers
    for name, value in _SECURITY_HEADERS:
        headers[name] = value
    host = _header(request, "Host")
    ws = f" ws://{host} wss://{host}" if host is not None and _HOST.match(host) else ""
    headers["Content-Security-Policy"] = _POLICY.format(ws=ws)
    if status in {204, 304}:
        response.body = b""
        del headers["Content-Type"], headers["Content-Length"]
    return response


def _header(request: Request, name: str) -> str | None:
    """A request header's first value (a repeated one is no error here)."""
    values = request.headers.get_all(name)
    return values[0] if values else None


def _etags(header: str | None) -> set[str]:
    return {tag.strip().removeprefix("W/") for tag in (header or "").split(",") if tag.strip()}


def _not_a_dns_name(host: str) -> bool:
    """Whether the host part of a ``Host`` header is ``localhost`` or an IP address: no
    DNS answer chose where it leads."""
    name = host.rpartition(":")[0] if not host.endswith("]") and ":" in host else host
    name = name.strip("[]")
    if name.lower() == "localhost":
        return True
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True
