"""The web console on a loopback daemon (``ohmni serve --port sim://``), in headless
Chromium: what it shows, and that it drives the robot only as it should.

What the robot did comes from the test's own client of the daemon (the simulated boards'
wheel counts, the Robot's state), never from the page."""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from typing import Any

import pytest
from playwright.sync_api import Page, expect

from .conftest import Peer, Served, Tabs, needs_chromium, until

pytestmark = needs_chromium

#: The page's top speed when it opens (within the simulator's 1 m/s).
START_LINEAR_MPS = 0.4


@pytest.fixture
def peer(daemon: Served) -> Iterator[Peer]:
    """The test's own client; afterwards the robot is left as found: no emergency stop,
    no lease held, standing still."""
    opened = daemon.peer()
    yield opened
    opened.call("acquire", steal=True)
    opened.call("clear_estop")
    opened.call("stop")
    opened.call("release")
    until(opened.still, 3.0)
    opened.close()


@pytest.fixture
def page(tabs: Tabs, daemon: Served, peer: Peer) -> Page:
    opened = tabs.open(viewport={"width": 1280, "height": 900})
    opened.goto(daemon.page_url)
    expect(opened.get_by_role("status", name="Connection")).to_contain_text("Connected")
    return opened


def take_control(page: Page) -> None:
    page.get_by_role("button", name="Take control").click()
    expect(page.get_by_role("status", name="Control")).to_have_text("You have control")


class Stick:
    """The joystick, held with the mouse (pointer events, as a finger's)."""

    def __init__(self, page: Page) -> None:
        self.page = page
        self.element = page.get_by_role("application", name="Drive joystick")

    def hold(self, right: float = 0.0, up: float = 1.0) -> None:
        box = self.element.bounding_box()
        assert box is not None
        x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
        radius = box["width"] / 2
        self.page.mouse.move(x, y)
        self.page.mouse.down()
        self.page.mouse.move(x + right * radius, y - up * radius, steps=4)

    def let_go(self) -> None:
        self.page.mouse.up()


def page_stop_s(peer: Peer) -> float:
    """Within this the page's own stop has zeroed the command: half the watchdog's time
    (it takes a few hundredths of a second), so the watchdog, which acts only after
    ``watchdog_s`` without a command, cannot pass for it."""
    return float(peer.hello["motion"]["watchdog_s"]) / 2


def requested_mps(peer: Peer) -> float:
    """The drive command the Robot follows now, as given (0 after a stop)."""
    return float(peer.latest("wheel_odom")["requested_linear_mps"])


def test_the_page_shows_the_robots_status(page: Page, peer: Peer) -> None:
    cells = page.get_by_role("list", name="Cells, V").get_by_role("listitem")
    expect(cells).to_have_count(5)
    expect(cells.first).not_to_contain_text("—")
    truth = peer.latest("tbcore_status")["cell_v"]
    assert len(truth) == 5
    shown = [float(text.split()[1]) for text in cells.all_inner_texts()]
    assert shown == pytest.approx(truth, abs=0.01)
    pack = page.get_by_label("Pack voltage").inner_text()
    assert float(pack.removesuffix(" V")) == pytest.approx(sum(truth), abs=0.05)
    expect(page.get_by_label("Robot link")).to_have_text("connected")
    expect(page.get_by_label("Faults")).to_have_text("none")
    neck = peer.latest("servo_neck")["position_raw"]
    shown_neck = int(page.get_by_label("Neck", exact=True).inner_text().split()[0])
    assert shown_neck == pytest.approx(neck, abs=3)
    expect(page.get_by_role("status", name="Control")).to_have_text("Nobody has control")
    expect(page.get_by_role("button", name="STOP")).to_be_enabled()
    # The command source row appears only where the daemon's Robot tells one.
    assert ("active_source" in peer.latest("robot_state")) == page.get_by_label(
        "Command source"
    ).is_visible()


def test_the_plots_update_at_10_hz_or_more(tabs: Tabs, daemon: Served, peer: Peer) -> None:
    page = tabs.open()
    odometry: list[float] = []

    def frames(ws: Any) -> None:
        def seen(payload: str | bytes) -> None:
            message = json.loads(payload)
            samples = message["samples"] if message["op"] == "batch" else [message]
            odometry.extend(time.monotonic() for s in samples if s.get("topic") == "wheel_odom")

        ws.on("framereceived", seen)

    page.on("websocket", frames)
    page.goto(daemon.page_url)
    caption = page.get_by_label("Odometry updates")
    until(lambda: caption.inner_text().endswith("Hz") and int(caption.inner_text()[:-3]) >= 10)
    assert int(page.get_by_label("Wheel speed updates").inner_text()[:-3]) >= 10
    start = len(odometry)
    page.wait_for_timeout(1000)  # the browser's events are seen meanwhile
    assert len(odometry) - start >= 10
    # The plots are drawn: not a blank canvas of their size.
    for plot in ("Wheel speeds, commanded and measured", "Odometry path"):
        drawn = page.get_by_role("img", name=plot).evaluate(
            """(canvas) => { const blank = document.createElement("canvas");
                             blank.width = canvas.width; blank.height = canvas.height;
                             return canvas.toDataURL() !== blank.toDataURL(); }"""
        )
        assert drawn, plot


def test_holding_the_joystick_forward_drives_and_letting_go_stops(page: Page, peer: Peer) -> None:
    take_control(page)
    before = peer.rolled_m()
    stick = Stick(page)
    stick.hold(up=1.0)
    time.sleep(1.0)
    assert requested_mps(peer) == pytest.approx(START_LINEAR_MPS)
    after = peer.rolled_m()
    assert after[0] - before[0] > 0.1
    assert after[1] - before[1] > 0.1
    stick.let_go()
    released = time.monotonic()
    until(lambda: requested_mps(peer) == 0.0, 2.0)
    assert time.monotonic() - released < page_stop_s(peer)
    # Standing still within the watchdog's time and the braking ramp from that speed.
    ramp_s = START_LINEAR_MPS / peer.call("config")["linear_decel_mps2"]
    until(peer.still, 2.0)
    assert time.monotonic() - released < peer.hello["motion"]["watchdog_s"] + ramp_s
    expect(page.get_by_label("Command", exact=True)).to_have_text("stopped")


def test_the_keys_drive_and_space_stops(page: Page, peer: Peer) -> None:
    take_control(page)
    page.get_by_role("application", name="Drive joystick").focus()
    before = peer.rolled_m()
    page.keyboard.down("ArrowUp")
    until(lambda: requested_mps(peer) > 0, 2.0)
    time.sleep(0.5)
    assert peer.rolled_m()[0] > before[0] + 0.02
    page.keyboard.press("Space")
    pressed = time.monotonic()
    until(lambda: requested_mps(peer) == 0.0, 2.0)
    assert time.monotonic() - pressed < page_stop_s(peer)
    page.keyboard.up("ArrowUp")
    # W A S D too: D turns right (clockwise, negative yaw rate).
    page.keyboard.down("d")
    until(lambda: peer.latest("wheel_odom")["requested_angular_radps"] < 0, 2.0)
    page.keyboard.up("d")
    until(lambda: peer.latest("wheel_odom")["requested_angular_radps"] == 0.0, 2.0)


@pytest.mark.parametrize("leaving", ["blur", "hidden"])
def test_losing_focus_or_visibility_stops(page: Page, peer: Peer, leaving: str) -> None:
    take_control(page)
    stick = Stick(page)
    stick.hold(up=0.8)
    until(lambda: requested_mps(peer) > 0, 2.0)
    if leaving == "blur":
        page.evaluate("window.dispatchEvent(new Event('blur'))")
    else:
        page.evaluate(
            """() => { Object.defineProperty(document, "visibilityState",
                                             { value: "hidden", configurable: true });
                       document.dispatchEvent(new Event("visibilitychange")); }"""
        )
    left = time.monotonic()
    until(lambda: requested_mps(peer) == 0.0, 2.0)
    assert time.monotonic() - left < page_stop_s(peer)
    stick.let_go()


def test_the_stop_button_latches_the_emergency_stop(page: Page, peer: Peer) -> None:
    # Anyone may stop the robot: no lease needed.
    page.get_by_role("button", name="STOP").click()
    until(lambda: peer.latest("robot_state")["estopped"], 3.0)
    expect(page.get_by_text("Emergency stop latched.")).to_be_visible()
    take_control(page)
    joystick = page.get_by_role("application", name="Drive joystick")
    expect(joystick).to_have_attribute("aria-disabled", "true")
    page.get_by_role("button", name="Clear emergency stop").click()
    until(lambda: not peer.latest("robot_state")["estopped"], 3.0)
    expect(page.get_by_text("Emergency stop latched.")).to_be_hidden()
    expect(joystick).to_have_attribute("aria-disabled", "false")


def test_while_another_client_drives_the_page_says_so_and_cannot_drive(
    page: Page, peer: Peer
) -> None:
    peer.call("acquire")
    control = page.get_by_role("status", name="Control")
    expect(control).to_have_text(f"{peer.peer} has control")
    expect(page.get_by_role("button", name="Take control")).to_be_hidden()
    expect(page.get_by_role("button", name="Take over")).to_be_visible()
    joystick = page.get_by_role("application", name="Drive joystick")
    expect(joystick).to_have_attribute("aria-disabled", "true")
    before = peer.rolled_m()
    stick = Stick(page)
    stick.hold(up=1.0)
    joystick.focus()
    page.keyboard.down("ArrowUp")
    time.sleep(0.6)
    page.keyboard.up("ArrowUp")
    stick.let_go()
    assert requested_mps(peer) == 0.0
    assert peer.rolled_m() == pytest.approx(before, abs=1e-3)
    expect(page.get_by_role("button", name="Neck up")).to_be_disabled()
    # An operator may take over, after saying so; the other client is told.
    page.once("dialog", lambda dialog: dialog.accept())
    page.get_by_role("button", name="Take over").click()
    expect(control).to_have_text("You have control")
    lease = peer.call("lease")
    assert lease["holder"] != peer.peer
    assert lease["you"] is False


def test_leaving_the_page_gives_the_lease_back(tabs: Tabs, daemon: Served, peer: Peer) -> None:
    page = tabs.open()
    page.goto(daemon.page_url)
    take_control(page)
    holder = until(lambda: peer.call("lease")["holder"], 2.0)
    assert holder != peer.peer
    page.close()
    until(lambda: peer.call("lease")["holder"] is None, 3.0)


def test_the_neck_moves_within_its_range(page: Page, peer: Peer) -> None:
    take_control(page)
    config = peer.call("config")
    slider = page.get_by_label("Neck position")
    expect(slider).to_be_enabled()
    assert slider.get_attribute("min") == str(config["neck_min_raw"])
    assert slider.get_attribute("max") == str(config["neck_max_raw"])
    page.get_by_role("button", name="Level the neck").click()
    level = 512 + config["neck_zero_offset_raw"]
    until(lambda: abs(peer.latest("servo_neck")["position_raw"] - level) <= 3, 3.0)
    page.get_by_role("button", name="Neck up").click()
    step = (config["neck_max_raw"] - config["neck_min_raw"]) / 8
    until(lambda: abs(peer.latest("servo_neck")["position_raw"] - (level + step)) <= 3, 3.0)
    for _ in range(10):  # beyond the top: held at the range's end
        page.get_by_role("button", name="Neck up").click()
    until(lambda: abs(peer.latest("servo_neck")["position_raw"] - config["neck_max_raw"]) <= 3, 4.0)


def test_the_top_speed_is_shown_and_set_within_the_robots_limit(page: Page, peer: Peer) -> None:
    limit = peer.hello["motion"]["max_linear_mps"]
    speed = page.get_by_label("Top speed")
    assert float(speed.get_attribute("max") or "nan") == pytest.approx(limit)
    expect(page.get_by_text(f"The robot's limit: {limit:.2f} m/s")).to_be_visible()
    speed.fill("0.2")
    take_control(page)
    stick = Stick(page)
    stick.hold(up=1.0)  # full forward
    until(lambda: requested_mps(peer) == pytest.approx(0.2), 2.0)
    seen = [requested_mps(peer) for _ in range(10)]
    assert max(seen) == pytest.approx(0.2)
    stick.let_go()
    until(lambda: requested_mps(peer) == 0.0, 2.0)


def test_a_lease_taken_while_the_page_drives_ends_its_commands(
    tabs: Tabs, daemon: Served, peer: Peer
) -> None:
    page = tabs.open()
    # The page's frames in the order the browser saw them: its drive commands, and the
    # lease message telling it the lease went to another client.
    frames: list[str] = []

    def watch(ws: Any) -> None:
        def sent(payload: str | bytes) -> None:
            if '"method":"drive"' in str(payload):
                frames.append("drive")

        def received(payload: str | bytes) -> None:
            if '"op":"lease"' in str(payload) and '"you":false' in str(payload):
                frames.append("lease lost")

        ws.on("framesent", sent)
        ws.on("framereceived", received)

    page.on("websocket", watch)
    page.goto(daemon.page_url)
    take_control(page)
    stick = Stick(page)
    stick.hold(up=1.0)
    until(lambda: requested_mps(peer) > 0, 2.0)
    peer.call("acquire", steal=True)  # an operator takes over
    expect(page.get_by_role("status", name="Control")).to_have_text(f"{peer.peer} has control")
    page.wait_for_timeout(500)  # the finger still on the joystick
    assert "lease lost" in frames
    after = frames[frames.index("lease lost") + 1 :]
    # At most one already on its way as the message came in; none after it was read.
    assert after.count("drive") <= 1, after
    assert requested_mps(peer) == 0.0
    expect(page.get_by_role("application", name="Drive joystick")).to_have_attribute(
        "aria-disabled", "true"
    )
    stick.let_go()


def test_a_person_at_the_robot_overrides_the_page_and_the_page_says_so(
    page: Page, peer: Peer
) -> None:
    # The page holds the remote source's lease; a program on the robot's own computer
    # takes the local one and keeps commanding standstill. The page's joystick moves
    # nothing while that source is live, and the page shows who drives.
    take_control(page)
    peer.call("acquire", source="local")
    try:
        peer.call("drive", linear_mps=0.0, angular_radps=0.0)
        expect(page.locator("#v-source")).to_have_text("local")
        before = peer.rolled_m()
        stick = Stick(page)
        stick.hold(up=1.0)
        for _ in range(5):  # the local source stays live: a command every 0.15 s
            peer.call("drive", linear_mps=0.0, angular_radps=0.0)
            time.sleep(0.15)
        stick.let_go()
        assert requested_mps(peer) == 0.0
        assert peer.rolled_m() == pytest.approx(before, abs=1e-3)
        # Its refusal, in the daemon's words.
        expect(page.locator("#notice")).to_contain_text("source 'local', of higher priority")
        # The page still holds its own lease: it drives again once the local source lapses.
        expect(page.get_by_role("status", name="Control")).to_have_text("You have control")
    finally:
        peer.call("release", source="local")
