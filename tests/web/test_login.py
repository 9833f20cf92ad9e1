"""The web console of a daemon listening beyond loopback (``ohmni serve --listen
0.0.0.0:PORT``, with its token file), in headless Chromium: without the token the page
asks for it and neither reads nor drives; with it, the page works, and the token stays out
of every URL."""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import pytest
from playwright.sync_api import Page, expect

from .conftest import Served, Tabs, needs_chromium

pytestmark = needs_chromium


@pytest.fixture
def page(tabs: Tabs) -> Page:
    return tabs.open()


def collect(into: list[Any]) -> Callable[[Any], None]:
    """A listener keeping what it is given (Playwright takes Python functions only)."""

    def keep(item: Any) -> None:
        into.append(item)

    return keep


def page_url(guarded: Served) -> str:
    """The address ``ohmni serve`` printed: this machine's, as others reach it (loopback
    on a machine whose printed address cannot be reached from itself: no network)."""
    printed = urlsplit(guarded.page_url)
    assert printed.hostname not in ("0.0.0.0", "127.0.0.1", "localhost")
    try:
        socket.create_connection((printed.hostname, printed.port), timeout=2).close()
    except OSError:
        return f"http://127.0.0.1:{printed.port}/"
    return guarded.page_url


def test_without_the_token_the_page_asks_for_it_and_neither_reads_nor_drives(
    page: Page, guarded: Served
) -> None:
    sockets: list[Any] = []
    page.on("websocket", collect(sockets))
    page.goto(page_url(guarded))
    expect(page.get_by_role("form", name="Token")).to_be_visible()
    expect(page.get_by_role("status", name="Connection")).to_have_text("Needs the daemon's token")
    expect(page.get_by_role("main")).to_be_hidden()
    expect(page.get_by_role("list", name="Cells, V")).to_be_hidden()
    expect(page.get_by_role("button", name="STOP")).to_be_disabled()
    page.keyboard.press("ArrowUp")
    assert sockets == []  # nothing was even tried: no reading, no driving
    # A wrong token is refused, and said so.
    page.get_by_label("Daemon token").fill(f"{guarded.token}x")
    page.get_by_role("button", name="Connect").click()
    expect(page.get_by_role("alert").filter(has_text="not this daemon's token")).to_be_visible()
    expect(page.get_by_role("main")).to_be_hidden()
    assert sockets == []


def test_with_the_token_the_page_works_and_keeps_it_out_of_urls(
    page: Page, guarded: Served
) -> None:
    assert guarded.token is not None
    requested: list[str] = []
    page.on("request", lambda request: requested.append(request.url))  # the URL alone
    sockets: list[Any] = []
    page.on("websocket", collect(sockets))
    page.goto(page_url(guarded))
    page.get_by_label("Daemon token").fill(guarded.token)
    page.get_by_role("button", name="Connect").click()
    expect(page.get_by_role("status", name="Connection")).to_contain_text("Connected")
    cells = page.get_by_role("list", name="Cells, V").get_by_role("listitem")
    expect(cells.first).not_to_contain_text("—")
    page.get_by_role("button", name="Take control").click()
    expect(page.get_by_role("status", name="Control")).to_have_text("You have control")
    assert all(guarded.token not in url for url in [*requested, page.url])
    assert [ws.url for ws in sockets] == [page_url(guarded).replace("http://", "ws://")]
    # Kept for this tab's session: a reload does not ask again ...
    page.reload()
    expect(page.get_by_role("status", name="Connection")).to_contain_text("Connected")
    expect(page.get_by_role("form", name="Token")).to_be_hidden()


def test_the_token_is_kept_for_the_tab_only(tabs: Tabs, guarded: Served) -> None:
    assert guarded.token is not None
    first = tabs.open()
    first.goto(page_url(guarded))
    first.get_by_label("Daemon token").fill(guarded.token)
    first.get_by_role("button", name="Connect").click()
    expect(first.get_by_role("status", name="Connection")).to_contain_text("Connected")
    # ... but another tab asks for it: it was kept in the session's storage alone.
    second = tabs.beside(first)
    second.goto(page_url(guarded))
    expect(second.get_by_role("form", name="Token")).to_be_visible()
    stored = first.evaluate("() => [localStorage.length, document.cookie]")
    assert stored == [0, ""]
