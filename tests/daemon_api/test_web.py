"""The web console's side of the daemon: its page over HTTP on the daemon's own port, the
page's own origin let in (and nothing more), the token as a subprotocol, and ``/auth``.

What the page does in a browser is in tests/web/ (headless Chromium)."""

from __future__ import annotations

import asyncio
import base64
import fnmatch
import json
import re
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import pytest
from websockets.asyncio.client import connect

from ohmni_tb import Robot
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.daemon.web import CONTENT_TYPES, WEB_FOLDER

from ._serving import free_port, start_serving, stop_serving

TOKEN = "x" * 20 + "-a-test-token"
ROOT = Path(__file__).resolve().parents[2]


@dataclass
class Answer:
    status: int
    headers: dict[str, str]
    body: bytes


async def get(url: str, path: str, **headers: str) -> Answer:
    """One HTTP/1.1 request as a browser sends it (``Host`` from the URL unless given)."""
    host, _, port = url.removeprefix("ws://").rpartition(":")
    lines = [f"GET {path} HTTP/1.1", f"Host: {headers.pop('Host', f'{host}:{port}')}"]
    lines += [f"{name.replace('_', '-')}: {value}" for name, value in headers.items()]
    reader, writer = await asyncio.open_connection(host, int(port))
    try:
        writer.write(("\r\n".join(lines) + "\r\n\r\n").encode())
        await writer.drain()
        head = await reader.readuntil(b"\r\n\r\n")
        status_line, *header_lines = head.decode().split("\r\n")
        found = dict(line.split(": ", 1) for line in header_lines if line)
        length = int(found.get("Content-Length", "0"))
        body = await reader.readexactly(length) if length else b""
    finally:
        writer.close()
    return Answer(int(status_line.split()[1]), found, body)


def handshake(origin: str | None = None, **headers: str) -> dict[str, str]:
    """A browser's WebSocket handshake headers."""
    found = {
        "Upgrade": "websocket",
        "Connection": "Upgrade",
        "Sec-WebSocket-Key": base64.b64encode(b"0123456789abcdef").decode(),
        "Sec-WebSocket-Version": "13",
        **headers,
    }
    if origin is not None:
        found["Origin"] = origin
    return found


def token_protocol(token: str) -> str:
    return "ohmni.token." + base64.urlsafe_b64encode(token.encode()).decode().rstrip("=")


# -- the page's files ------------------------------------------------------------------------


async def test_the_page_and_its_files_are_served_with_their_types_and_policy(
    server: RobotServer,
) -> None:
    port = server.url.rpartition(":")[2]
    assert server.web_url == f"http://127.0.0.1:{port}/"
    page = await get(server.url, "/")
    assert page.status == 200
    assert page.headers["Content-Type"] == "text/html; charset=utf-8"
    assert b'<script type="module" src="app.js"></script>' in page.body
    policy = page.headers["Content-Security-Policy"]
    assert "default-src 'self'" in policy
    assert f"connect-src 'self' ws://127.0.0.1:{port} wss://127.0.0.1:{port};" in policy
    assert "frame-ancestors 'none'" in policy
    assert "form-action 'none'" in policy
    assert "unsafe-inline" not in policy
    assert page.headers["X-Content-Type-Options"] == "nosniff"
    assert page.headers["Cache-Control"] == "no-cache"
    for path, kind in [
        ("/app.js", "text/javascript; charset=utf-8"),
        ("/connection.js", "text/javascript; charset=utf-8"),
        ("/style.css", "text/css; charset=utf-8"),
        ("/icon.svg", "image/svg+xml"),
        ("/index.html", "text/html; charset=utf-8"),
    ]:
        answer = await get(server.url, path)
        assert (answer.status, answer.headers["Content-Type"]) == (200, kind), path
        assert answer.body == resources.files("ohmni_tb").joinpath(WEB_FOLDER + path).read_bytes()


async def test_a_file_that_did_not_change_is_not_sent_again(server: RobotServer) -> None:
    first = await get(server.url, "/app.js")
    again = await get(server.url, "/app.js", If_None_Match=first.headers["ETag"])
    assert (again.status, again.body) == (304, b"")
    assert again.headers["ETag"] == first.headers["ETag"]
    other = await get(server.url, "/app.js", If_None_Match='"an-older-one"')
    assert (other.status, other.body) == (200, first.body)


@pytest.mark.parametrize(
    "path",
    [
        "/../web.py",
        "/%2e%2e/web.py",
        "/..%2fserver.py",
        "/../../pyproject.toml",
        "//etc/passwd",
        "/web.py",
        "/app.js/",
        "/APP.JS",
        "/.",
    ],
)
async def test_no_path_reaches_beyond_the_pages_own_files(server: RobotServer, path: str) -> None:
    answer = await get(server.url, path)
    assert answer.status == 404
    assert answer.body.startswith(b"no such page")
    assert answer.headers["X-Content-Type-Options"] == "nosniff"


async def test_without_the_web_console_the_port_serves_no_page(robot: Robot) -> None:
    async with RobotServer(robot, port=0, web=False) as server:
        assert server.web_url is None
        answer = await get(server.url, "/")
        assert answer.status != 200
        assert b"<html" not in answer.body
        # Nor is the page's origin let in.
        own = handshake(f"http://{server.url.removeprefix('ws://')}")
        assert (await get(server.url, "/", **own)).status == 403


# -- the page's origin, the token ------------------------------------------------------------


async def test_the_pages_own_origin_may_connect_and_others_may_not(server: RobotServer) -> None:
    address = server.url.removeprefix("ws://")
    port = address.rpartition(":")[2]
    own = await get(server.url, "/", **handshake(f"http://{address}"))
    assert own.status == 101
    # Reached through a tunnel or another name for loopback: the Host it came to.
    tunnel = await get(server.url, "/", **handshake("http://localhost:9000", Host="localhost:9000"))
    assert tunnel.status == 101
    for origin, host in [
        ("http://evil.example", address),  # another site
        (f"http://127.0.0.1:{int(port) + 1}", address),  # another port of this host
        (f"https://evil.example:{port}", f"evil.example:{port}"),  # DNS rebinding
        (f"http://robot.local:{port}", f"robot.local:{port}"),  # a name: needs the token
        ("null", address),
    ]:
        answer = await get(server.url, "/", **handshake(origin, Host=host))
        assert answer.status == 403, origin
        assert b"is not allowed" in answer.body


async def test_with_a_token_the_page_presents_it_as_a_subprotocol_never_sent_back(
    robot: Robot,
) -> None:
    async with RobotServer(robot, port=0, token=TOKEN) as server:
        address = server.url.removeprefix("ws://")
        port = address.rpartition(":")[2]
        offered = f"ohmni, {token_protocol(TOKEN)}"
        answer = await get(
            server.url, "/", **handshake(f"http://{address}", Sec_WebSocket_Protocol=offered)
        )
        assert answer.status == 101
        assert answer.headers["Sec-WebSocket-Protocol"] == "ohmni"
        assert TOKEN not in json.dumps(answer.headers)
        # With the token, a name is the page's own origin too (a rebinding site has no token).
        named = await get(
            server.url,
            "/",
            **handshake(
                f"http://robot.local:{port}",
                Host=f"robot.local:{port}",
                Sec_WebSocket_Protocol=offered,
            ),
        )
        assert named.status == 101
        for protocols in ["ohmni", f"ohmni, {token_protocol(TOKEN + 'x')}", "ohmni, ohmni.token.!"]:
            refused = await get(
                server.url,
                "/",
                **handshake(f"http://{address}", Sec_WebSocket_Protocol=protocols),
            )
            assert refused.status == 401, protocols
        # A program speaks the protocol the same way.
        async with connect(server.url, subprotocols=["ohmni", token_protocol(TOKEN)]) as ws:  # type: ignore[list-item]  # str subprotocols
            assert ws.subprotocol == "ohmni"
            assert json.loads(await ws.recv())["op"] == "hello"


async def test_auth_tells_the_page_whether_it_needs_the_token(robot: Robot) -> None:
    async with RobotServer(robot, port=0) as open_server:
        assert (await get(open_server.url, "/auth")).status == 204
    async with RobotServer(robot, port=0, token=TOKEN) as server:
        assert (await get(server.url, "/auth")).status == 401
        wrong = await get(server.url, "/auth", Authorization=f"Bearer {TOKEN}x")
        assert wrong.status == 401
        right = await get(server.url, "/auth", Authorization=f"Bearer {TOKEN}")
        assert (right.status, right.body) == (204, b"")


def test_a_daemon_listening_everywhere_shows_an_address_others_reach() -> None:
    from ohmni_tb.daemon.web import page_url

    url = page_url("0.0.0.0", 8766)
    assert url.startswith("http://")
    assert url.endswith(":8766/")
    assert "0.0.0.0" not in url
    assert page_url("::1", 8766) == "http://[::1]:8766/"
    assert page_url("127.0.0.1", 1) == "http://127.0.0.1:1/"


# -- in the package -------------------------------------------------------------------------


def test_every_file_of_the_page_is_in_the_package_data_and_found_installed() -> None:
    folder = resources.files("ohmni_tb").joinpath(WEB_FOLDER)
    names = sorted(entry.name for entry in folder.iterdir() if entry.is_file())
    assert "index.html" in names
    assert {"." + name.rpartition(".")[2] for name in names} <= set(CONTENT_TYPES)
    patterns = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["ohmni_tb"]
    missing = [
        n for n in names if not any(fnmatch.fnmatch(f"{WEB_FOLDER}/{n}", p) for p in patterns)
    ]
    assert missing == [], "not in pyproject's package-data: the wheel would lack them"


def test_the_page_loads_only_its_own_files() -> None:
    folder = resources.files("ohmni_tb").joinpath(WEB_FOLDER)
    names = {entry.name for entry in folder.iterdir()}
    html = folder.joinpath("index.html").read_text()
    referenced = set(re.findall(r'(?:src|href)="([^"]+)"', html))
    for script in (name for name in names if name.endswith(".js")):
        referenced |= set(re.findall(r'from "\./([^"]+)"', folder.joinpath(script).read_text()))
    assert referenced == {
        "icon.svg",
        "style.css",
        "app.js",
        "connection.js",
        "joystick.js",
        "plot.js",
    }
    assert referenced <= names
    for name in names:
        text = folder.joinpath(name).read_text()
        # Nothing from the internet: the robot's network may have none. (An SVG's xmlns
        # names its namespace; nothing is fetched.)
        assert re.findall(r"https?://(?!www\.w3\.org/2000/svg)", text) == [], name


# -- ohmni serve -----------------------------------------------------------------------------


def test_ohmni_serve_prints_the_pages_url_on_its_own_line_and_serves_it() -> None:
    port = free_port()
    proc, url = start_serving("--listen", f"127.0.0.1:{port}")
    try:
        assert url == f"ws://127.0.0.1:{port}"
        assert proc.stdout is not None
        assert proc.stdout.readline().decode().strip() == f"http://127.0.0.1:{port}/"
        answer = asyncio.run(get(url, "/"))
        assert answer.status == 200
        assert b"Ohmni console" in answer.body
    finally:
        stop_serving(proc)


def test_the_token_is_read_from_a_subprotocol_after_the_header() -> None:
    from ohmni_tb.daemon import auth

    offered = f"ohmni, {token_protocol(TOKEN)}"
    assert auth.presented_token("/", None, offered) == TOKEN
    assert auth.presented_token("/", f"Bearer {TOKEN}x", offered) == f"{TOKEN}x"
    assert auth.presented_token(f"/?token={TOKEN}x", None, offered) == TOKEN
    assert auth.presented_token("/", None, "ohmni") is None
    # Not base64url: presented as it is, and so refused as a wrong token, not as none.
    assert auth.presented_token("/", None, "ohmni.token.!!") == "!!"
