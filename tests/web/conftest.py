"""The web console in a real browser: the distribution's Chromium, headless, driven by
Playwright's Python package (never its own browser download: ``executable_path``).

``ohmni serve --port sim://`` runs in its own process on a free port, as a user starts it;
the page is opened at the URL it printed. What the robot did is read by the test's own
client of the daemon (:class:`Peer`: the daemon's protocol, as docs/daemon.md shows it),
from the simulated boards' wheel counts — never from the page. One browser serves every
test of a module; each test has a page of its own, in a fresh context (its own session
storage)."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
from websockets.sync.client import ClientConnection, connect

from daemon_api._pty_robot import START_S, read_line
from daemon_api._serving import free_port, stop_serving
from ohmni_tb.daemon.web import HEADLESS_CHROMIUM_ARGS

if TYPE_CHECKING:
    from playwright.sync_api import Page

#: Debian's and Ubuntu's package; ``.ci/run`` installs it when missing.
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: Skips a browser test only when there is no Chromium to run it in.
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="needs Chromium: apt-get install chromium (.ci/run installs it)",
)


def until(condition: Callable[[], Any], timeout_s: float = 5.0, every_s: float = 0.02) -> Any:
    """Poll ``condition()`` until it is truthy; its value. Fails after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout_s} s: {condition}")
        time.sleep(every_s)


class Peer:
    """Another client of the daemon, beside the page: the test's own eyes on the robot."""

    def __init__(self, url: str, token: str | None = None) -> None:
        headers = {"Authorization": f"Bearer {token}"} if token else None
        self._stack = contextlib.ExitStack()
        self.ws: ClientConnection = self._stack.enter_context(
            connect(url, additional_headers=headers)
        )
        self.hello: dict[str, Any] = json.loads(self.ws.recv(timeout=10))
        self.peer: str = self.hello["peer"]
        self._next_id = 0

    def call(self, method: str, **args: Any) -> Any:
        """The ``result``'s data; an ``error`` fails the test."""
        self._next_id += 1
        ident = self._next_id
        self.ws.send(json.dumps({"op": "call", "id": ident, "method": method, "args": args}))
        while True:
            message = json.loads(self.ws.recv(timeout=10))
            if message.get("id") != ident:
                continue  # a lease message for every client
            assert message["op"] == "result", message
            return message["data"]

    def latest(self, topic: str) -> dict[str, Any]:
        sample: dict[str, Any] = self.call("latest", topic=topic)
        assert sample is not None, f"no {topic} sample yet"
        return sample

    def rolled_m(self) -> tuple[float, float]:
        """How far each wheel rolled since the Robot opened (its boards' counts)."""
        wheels = self.latest("wheel_encoder")
        return wheels["left_m"], wheels["right_m"]

    def still(self) -> bool:
        wheels = self.latest("wheel_encoder")
        return bool(abs(wheels["left_mps"]) < 0.01 and abs(wheels["right_mps"]) < 0.01)

    def close(self) -> None:
        """Idempotent."""
        self._stack.close()


@dataclass
class Served:
    """``ohmni serve`` in its own process: its address, its page's, its token."""

    proc: subprocess.Popen[bytes]
    url: str
    page_url: str
    token: str | None = None
    peers: list[Peer] = field(default_factory=list)

    def peer(self) -> Peer:
        opened = Peer(self.url, self.token)
        self.peers.append(opened)
        return opened

    def close(self) -> str:
        for peer in self.peers:
            peer.close()
        return stop_serving(self.proc)


def serve(*args: str, env: dict[str, str] | None = None) -> Served:
    """``ohmni serve --port sim:// ARGS``: the two addresses it printed."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "serve", "--port", "sim://", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
    )
    assert proc.stdout is not None
    try:
        url = read_line(proc.stdout.fileno(), START_S)
        page_url = read_line(proc.stdout.fileno(), START_S)
    except BaseException:
        proc.kill()
        _, err = proc.communicate()
        raise AssertionError(f"ohmni serve did not start: {err.decode()}") from None
    return Served(proc, url, page_url)


def token_protocol(token: str) -> str:
    return "ohmni.token." + base64.urlsafe_b64encode(token.encode()).decode().rstrip("=")


@pytest.fixture(scope="module")
def daemon() -> Iterator[Served]:
    """A loopback daemon, as ``ohmni serve --port sim://`` starts by default."""
    served = serve("--listen", f"127.0.0.1:{free_port()}")
    yield served
    served.close()


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """A daemon listening beyond loopback (every address): it needs its token."""
    home = tmp_path_factory.mktemp("config")
    env = {**os.environ, "XDG_CONFIG_HOME": str(home)}
    served = serve("--listen", f"0.0.0.0:{free_port()}", env=env)
    token_file = Path(home, "ohmni", "daemon-token")
    served.token = token_file.read_text().strip()
    port = served.url.rpartition(":")[2]
    served.url = f"ws://127.0.0.1:{port}"  # the test's own client, from this machine
    yield served
    served.close()


class Tabs:
    """A test's browser tabs, each in a fresh context (its own session storage) unless
    opened beside another; closed after the test, which fails if a page's script raised
    (an uncaught exception: the page would be broken for its user)."""

    def __init__(self, browser: Any) -> None:
        self._browser = browser
        self._contexts: list[Any] = []
        self.errors: list[str] = []

    def open(self, **options: Any) -> Page:
        context = self._browser.new_context(**options)
        self._contexts.append(context)
        return self._watched(context.new_page())

    def beside(self, page: Page) -> Page:
        """Another tab of the same browser window (the same context)."""
        return self._watched(page.context.new_page())

    def _watched(self, page: Page) -> Page:
        page.on("pageerror", self._raised)
        return page

    def _raised(self, error: Any) -> None:
        self.errors.append(str(error))

    def close(self) -> None:
        for context in self._contexts:
            context.close()


@pytest.fixture
def tabs(browser: Any) -> Iterator[Tabs]:
    opened = Tabs(browser)
    yield opened
    opened.close()
    assert opened.errors == [], "the page's script raised"


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One Chromium for a module's tests. Not for a whole session: while Playwright's
    synchronous API is in use, its event loop counts as running in this thread, and the
    async tests of another module (pytest-asyncio) could not start theirs."""
    if CHROMIUM is None:
        pytest.skip("needs Chromium: apt-get install chromium (.ci/run installs it)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(
            executable_path=CHROMIUM, args=list(HEADLESS_CHROMIUM_ARGS)
        )
        yield launched
        launched.close()
