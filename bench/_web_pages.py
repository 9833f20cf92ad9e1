"""N pages of the web console open in headless Chromium, for ``bench/daemon.py --only web``.

``python bench/_web_pages.py URL N``: opens ``URL`` (the daemon's page) in N pages of one
headless Chromium (the distribution's: ``apt-get install chromium``), waits until every
page says it is connected and its plots update, prints ``{"event": "ready"}``, and keeps
them open (drawing, as a person watching them would have them) until a line ``quit`` on
stdin; then prints ``{"event": "done", "updates_hz": [...]}``: each page's own figure of
its plots' updates a second, read just before closing.
"""

from __future__ import annotations

import json
import shutil
import sys

from ohmni_tb.daemon.web import HEADLESS_CHROMIUM_ARGS

#: A laptop's window: every plot on screen (a page draws what it shows).
WIDTH, HEIGHT = 1280, 860


def main() -> int:
    url, count = sys.argv[1], int(sys.argv[2])
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("needs Chromium: apt-get install chromium")
    from playwright.sync_api import expect, sync_playwright  # noqa: PLC0415  # the test extra

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=chromium, args=list(HEADLESS_CHROMIUM_ARGS)
        )
        pages = []
        for _ in range(count):
            # A context each: every page is a browser tab of its own, as five people's.
            context = browser.new_context(viewport={"width": WIDTH, "height": HEIGHT})
            page = context.new_page()
            page.goto(url)
            pages.append(page)
        for page in pages:
            expect(page.get_by_role("status", name="Connection")).to_contain_text("Connected")
            expect(page.get_by_label("Odometry updates")).to_have_text("20 Hz", timeout=10_000)
        print(json.dumps({"event": "ready"}), flush=True)
        while (line := sys.stdin.readline()) and line.strip() != "quit":
            pass
        rates = [int(page.get_by_label("Odometry updates").inner_text()[:-3]) for page in pages]
        browser.close()
    print(json.dumps({"event": "done", "updates_hz": rates}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
