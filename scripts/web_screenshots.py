"""The web console's screenshots in docs/: ``python scripts/web_screenshots.py``.

Starts ``ohmni serve --port sim://`` on a free loopback port, opens its page in headless
Chromium (the distribution's: ``apt-get install chromium``; Playwright drives it, with no
browser download of its own), takes control, drives a curve with the on-screen joystick
and tilts the neck, then writes ``docs/web-desktop.png`` (1280 × 860) and
``docs/web-phone.png`` (390 × 844, as a phone shows it, at twice the pixels).
"""

from __future__ import annotations

import argparse
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from ohmni_tb.daemon.web import HEADLESS_CHROMIUM_ARGS

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


def read_line(proc: subprocess.Popen[bytes], timeout_s: float = 30.0) -> str:
    assert proc.stdout is not None
    line = b""
    deadline = time.monotonic() + timeout_s
    while not line.endswith(b"\n"):
        ready, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
        chunk = os.read(proc.stdout.fileno(), 1) if ready else b""
        if not chunk:
            raise SystemExit("ohmni serve did not print its addresses")
        line += chunk
    return line.decode().strip()


def drive(page: Any, seconds: float, right: float, up: float) -> None:
    """Hold the joystick at (``right``, ``up``), fractions of its radius."""
    box = page.get_by_role("application", name="Drive joystick").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    radius = box["width"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + right * radius, y - up * radius, steps=5)
    page.wait_for_timeout(seconds * 1000)
    page.mouse.up()


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs", help="where (docs/)")
    args = parser.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("needs Chromium: apt-get install chromium")
    from playwright.sync_api import sync_playwright  # noqa: PLC0415  # the test extra

    proc = subprocess.Popen(
        [
            *(sys.executable, "-m", "ohmni_tb", "serve", "--port", "sim://"),
            *("--listen", f"127.0.0.1:{free_port()}"),
        ],
        stdout=subprocess.PIPE,
    )
    try:
        read_line(proc)
        url = read_line(proc)
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=chromium, args=list(HEADLESS_CHROMIUM_ARGS)
            )
            desktop = browser.new_page(viewport={"width": 1280, "height": 860})
            desktop.goto(url)
            desktop.get_by_role("button", name="Take control").click()
            desktop.get_by_role("button", name="Neck up").click()
            desktop.get_by_label("Neck", exact=True).filter(has_text="558 raw").wait_for()
            drive(desktop, 2.5, right=0.0, up=0.9)
            drive(desktop, 3.0, right=0.45, up=0.9)
            drive(desktop, 1.5, right=-0.2, up=0.6)
            desktop.wait_for_timeout(1200)
            desktop.screenshot(path=args.out / "web-desktop.png")
            desktop.close()  # gives the lease back
            phone = browser.new_page(
                viewport={"width": 390, "height": 844},
                device_scale_factor=2,
                is_mobile=True,
                has_touch=True,
            )
            phone.goto(url)
            phone.get_by_role("button", name="Take control").click()
            phone.wait_for_timeout(1500)
            phone.screenshot(path=args.out / "web-phone.png")
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(20)
    print(f"wrote {args.out / 'web-desktop.png'} and {args.out / 'web-phone.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
