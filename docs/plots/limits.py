"""The plots of docs/control.md's limits section, made by the code they show.

Run from the repository: ``python docs/plots/limits.py`` (or ``… limits.py OUT_DIR``; the
default is ``docs/img``). It writes, each from the real limiter (``ohmni_tb.control``):

- ``limits-accel-brake.svg``: speeding up at the acceleration limit, braking at the
  braking limit, forward and backward alike;
- ``limits-reversal.svg``: a Robot on ``sim://`` in virtual time reversing: what was asked,
  the command after the limits, and what the simulated wheels did;
- ``limits-jerk.svg``: the same drive without and with a jerk limit, speed and
  acceleration; and a stop, which the jerk limit does not hold back;
- ``limits-saturation.svg``: the path of a turn too fast for the outer wheel, both wheels
  scaled (the circle kept) against one wheel clipped (another circle).

The SVG is written by hand (axes, polylines, labels), so nothing beyond the package is
needed. ``tests/test_limit_plots.py`` runs this into a temporary directory and checks that
the committed files are what it makes.
"""

from __future__ import annotations

import asyncio
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ohmni_tb.control import (
    AccelLimits,
    DiffDrive,
    Twist,
    TwistLimiter,
    WheelSpeeds,
    integrate_batch,
    saturate_wheel_speeds,
)
from ohmni_tb.robot import LocalRobot
from ohmni_tb.sim.clock import run_virtual

#: Where the plots go by default: docs/img next to this directory.
DEFAULT_OUT = Path(__file__).resolve().parent.parent / "img"
#: The control tick (``wheel_hz`` 50).
DT_S = 0.02
#: Default limits (RobotConfig): linear up 0.5 m/s², braking 1 m/s².
LINEAR = AccelLimits(0.5, 1.0)

Point = tuple[float, float]

# -- a small SVG chart ---------------------------------------------------------------------

WIDTH = 640
PANEL_HEIGHT = 250
TITLE_HEIGHT = 30
MARGIN_LEFT = 62
MARGIN_RIGHT = 16
MARGIN_TOP = 14
MARGIN_BOTTOM = 42
FONT = "font-family='sans-serif' font-size='12'"
BLUE, ORANGE, GREEN, RED, GREY = "#1f77b4", "#e07b00", "#2a9d3a", "#c62828", "#888888"


@dataclass
class Series:
    """One line: its legend label, points, colour and dash pattern."""

    label: str
    points: list[Point]
    color: str
    dash: str = ""
    in_legend: bool = True


@dataclass
class Panel:
    """One chart: axes, their labels and ranges, and the lines."""

    x_label: str
    y_label: str
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    series: list[Series] = field(default_factory=list)
    #: Where the legend goes: in the top or bottom right corner, or below the axes.
    legend: Literal["top", "bottom", "below"] = "top"
    #: Widen the x range so a metre is as long across as up (a path drawn true).
    equal_aspect: bool = False


def ticks(low: float, high: float) -> list[float]:
    """Round tick values across ``low..high``: steps of 1, 2 or 5 × 10^k, about five."""
    raw = (high - low) / 5
    power = 10 ** math.floor(math.log10(raw))
    step = next(m * power for m in (1, 2, 5, 10) if m * power >= raw)
    first = math.ceil(low / step - 1e-9)
    return [round(i * step, 10) for i in range(first, math.floor(high / step + 1e-9) + 1)]


def number(value: float) -> str:
    """A tick label: ``0.5``, ``-1``, ``0``."""
    text = f"{value:.4g}"
    return "0" if text == "-0" else text


def render(title: str, panels: Sequence[Panel], *, height: int = PANEL_HEIGHT) -> str:
    """The SVG text of ``panels`` stacked under ``title``."""
    total = TITLE_HEIGHT + height * len(panels)
    out = [
        f"<svg xmlns='http://www.w3.org/2000/svg' width='{WIDTH}' height='{total}' "
        f"viewBox='0 0 {WIDTH} {total}'>",
        f"<rect width='{WIDTH}' height='{total}' fill='white'/>",
        f"<text x='{WIDTH / 2:.0f}' y='20' text-anchor='middle' font-family='sans-serif' "
        "font-size='14' "
        f"font-weight='bold'>{escape(title)}</text>",
    ]
    for index, panel in enumerate(panels):
        out += render_panel(panel, TITLE_HEIGHT + index * height, height)
    out.append("</svg>")
    return "\n".join(out) + "\n"


def render_panel(panel: Panel, top: float, height: float) -> list[str]:
    """One panel's axes, grid, lines and legend."""
    left, right = MARGIN_LEFT, WIDTH - MARGIN_RIGHT
    legend = [series for series in panel.series if series.in_legend]
    row = 17
    below = row * len(legend) + 12 if panel.legend == "below" else 0
    upper, lower = top + MARGIN_TOP, top + height - MARGIN_BOTTOM - below
    (x0, x1), (y0, y1) = panel.x_range, panel.y_range
    if panel.equal_aspect:
        half = (y1 - y0) * (right - left) / (lower - upper) / 2
        x0, x1 = (x0 + x1) / 2 - half, (x0 + x1) / 2 + half

    def px(x: float) -> float:
        return left + (x - x0) / (x1 - x0) * (right - left)

    def py(y: float) -> float:
        return lower - (y - y0) / (y1 - y0) * (lower - upper)

    out = []
    for x in ticks(x0, x1):
        out.append(
            f"<line x1='{px(x):.1f}' y1='{upper:.1f}' x2='{px(x):.1f}' y2='{lower:.1f}' "
            "stroke='#e4e4e4'/>"
        )
        out.append(
            f"<text x='{px(x):.1f}' y='{lower + 15:.1f}' text-anchor='middle' {FONT}>"
            f"{number(x)}</text>"
        )
    for y in ticks(y0, y1):
        color = "#9e9e9e" if y == 0 else "#e4e4e4"
        out.append(
            f"<line x1='{left}' y1='{py(y):.1f}' x2='{right}' y2='{py(y):.1f}' stroke='{color}'/>"
        )
        out.append(
            f"<text x='{left - 6}' y='{py(y) + 4:.1f}' text-anchor='end' {FONT}>{number(y)}</text>"
        )
    out.append(
        f"<rect x='{left}' y='{upper:.1f}' width='{right - left}' height='{lower - upper:.1f}' "
        "fill='none' stroke='#444444'/>"
    )
    out.append(
        f"<text x='{(left + right) / 2:.1f}' y='{lower + 33:.1f}' text-anchor='middle' "
        f"{FONT}>{escape(panel.x_label)}</text>"
    )
    middle = (upper + lower) / 2
    out.append(
        f"<text x='14' y='{middle:.1f}' text-anchor='middle' {FONT} "
        f"transform='rotate(-90 14 {middle:.1f})'>{escape(panel.y_label)}</text>"
    )
    for series in panel.series:
        points = " ".join(f"{px(x):.1f},{py(y):.1f}" for x, y in series.points)
        dash = f" stroke-dasharray='{series.dash}'" if series.dash else ""
        out.append(
            f"<polyline points='{points}' fill='none' stroke='{series.color}' "
            f"stroke-width='2'{dash}/>"
        )
    legend_top = {
        "top": upper + 6,
        "bottom": lower - 8 - row * len(legend),
        "below": lower + MARGIN_BOTTOM - 4,
    }[panel.legend]
    width = 32 + 7 * max(len(series.label) for series in legend)
    out.append(
        f"<rect x='{right - width - 8}' y='{legend_top:.1f}' width='{width}' "
        f"height='{row * len(legend) + 4}' fill='white' fill-opacity='0.9' "
        "stroke='#cccccc'/>"
    )
    for i, series in enumerate(legend):
        y = legend_top + 13 + i * row
        dash = f" stroke-dasharray='{series.dash}'" if series.dash else ""
        out.append(
            f"<line x1='{right - width - 2}' y1='{y - 4:.1f}' x2='{right - width + 18}' "
            f"y2='{y - 4:.1f}' stroke='{series.color}' stroke-width='2'{dash}/>"
        )
        out.append(
            f"<text x='{right - width + 24}' y='{y:.1f}' {FONT}>{escape(series.label)}</text>"
        )
    return out


def escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


# -- the plots -------------------------------------------------------------------------------


def run_limiter(
    limiter: TwistLimiter, schedule: Sequence[tuple[float, float, bool]]
) -> tuple[list[Point], list[Point], list[Point]]:
    """Step ``limiter``'s linear axis through ``schedule`` ((seconds, target, jerk-limited)
    in turn): the requested, limited and acceleration profiles against time."""
    requested: list[Point] = []
    speeds: list[Point] = [(0.0, limiter.current.linear_mps)]
    accels: list[Point] = [(0.0, 0.0)]
    t = 0.0
    for seconds, target, jerk_limited in schedule:
        requested += [(t, target), (t + seconds, target)]
        for _ in range(round(seconds / DT_S)):
            before = limiter.current.linear_mps
            after = limiter.step(Twist(target, 0.0), DT_S, jerk_limited=jerk_limited).linear_mps
            t += DT_S
            speeds.append((t, after))
            accels.append((t, (after - before) / DT_S))
    return requested, speeds, accels


def accel_brake() -> str:
    forward = run_limiter(TwistLimiter(LINEAR), [(1.5, 0.5, True), (1.0, 0.0, True)])
    backward = run_limiter(TwistLimiter(LINEAR), [(1.5, -0.5, True), (1.0, 0.0, True)])
    panel = Panel(
        "time (s)",
        "linear speed (m/s)",
        (0.0, 2.5),
        (-0.6, 1.0),
        [
            Series("asked", forward[0], GREY, "5 4"),
            Series("asked", backward[0], GREY, "5 4", in_legend=False),
            Series("forward: up 0.5 m/s², braking 1 m/s²", forward[1], BLUE),
            Series("backward: the same limits", backward[1], ORANGE),
        ],
    )
    return render("Speeding up and braking, forward and backward (the defaults)", [panel])


async def drive_reversal() -> tuple[list[Point], list[Point], list[Point]]:
    """+0.4 m/s, then -0.4 m/s from 2 s, on ``sim://``: asked, commanded, measured."""
    async with LocalRobot.open("sim://", linear_accel_mps2=0.25, linear_decel_mps2=1.0) as robot:
        odom = robot.subscribe("wheel_odom", maxlen=1000)
        loop = asyncio.get_running_loop()
        start = loop.time()
        for until_s, speed in ((2.0, 0.4), (4.5, -0.4)):
            while loop.time() < start + until_s:
                robot.drive(speed, 0.0)
                await asyncio.sleep(0.1)
        robot.stop()
        commanded: list[Point] = []
        measured: list[Point] = []
        while (sample := odom.get_nowait()) is not None:
            t = sample.stamp_s - start
            commanded.append((t, sample.commanded_linear_mps))
            measured.append((t, sample.linear_mps))
    asked = [(0.0, 0.4), (2.0, 0.4), (2.0, -0.4), (4.5, -0.4)]
    return asked, commanded, measured


def reversal() -> str:
    asked, commanded, measured = run_virtual(drive_reversal())
    panel = Panel(
        "time (s)",
        "linear speed (m/s)",
        (0.0, 4.5),
        (-0.5, 0.6),
        [
            Series("drive() asked", asked, GREY, "5 4"),
            Series("command after the limits", commanded, BLUE),
            Series("simulated wheels", measured, ORANGE),
        ],
    )
    return render(
        "Reversing on sim://: brake to zero at 1 m/s², then back up at 0.25 m/s²", [panel]
    )


def jerk() -> str:
    smooth = AccelLimits(0.5, 1.0, 2.0)
    drive = [(1.8, 0.5, True), (1.5, 0.0, True)]
    _, plain_v, plain_a = run_limiter(TwistLimiter(LINEAR), drive)
    _, smooth_v, smooth_a = run_limiter(TwistLimiter(smooth), drive)
    _, stop_v, stop_a = run_limiter(TwistLimiter(smooth), [(1.8, 0.5, True), (1.5, 0.0, False)])
    # The stop's own part: from the last step before it.
    stop_v, stop_a = stop_v[89:], stop_a[89:]
    speed = Panel(
        "time (s)",
        "linear speed (m/s)",
        (0.0, 3.3),
        (0.0, 0.8),
        [
            Series("no jerk limit", plain_v, BLUE),
            Series("jerk 2 m/s³: drive(0.5), then drive(0)", smooth_v, ORANGE),
            Series("jerk 2 m/s³: drive(0.5), then stop()", stop_v, GREEN, "6 3"),
        ],
    )
    accel = Panel(
        "time (s)",
        "acceleration (m/s²)",
        (0.0, 3.3),
        (-1.2, 1.0),
        [
            Series("no jerk limit", plain_a, BLUE),
            Series("jerk 2 m/s³", smooth_a, ORANGE),
            Series("stop(): not held back", stop_a, GREEN, "6 3"),
        ],
    )
    return render(
        "A jerk limit of 2 m/s³: S-curves for drive commands, not for a stop", [speed, accel]
    )


def saturation() -> str:
    drive = DiffDrive()
    asked = drive.wheel_speeds(Twist(0.8, 2.4))
    scaled = saturate_wheel_speeds(asked, 1.0)
    clipped = WheelSpeeds(min(asked.left_mps, 1.0), min(asked.right_mps, 1.0))
    seconds = 2.5

    def path(wheels: WheelSpeeds) -> list[Point]:
        steps = round(seconds / DT_S)
        poses = integrate_batch(
            [wheels.left_mps * DT_S] * steps,
            [wheels.right_mps * DT_S] * steps,
            drive.wheel_separation_m,
        )
        return [(0.0, 0.0)] + [(float(row[0]), float(row[1])) for row in poses]

    def radius(wheels: WheelSpeeds) -> str:
        twist = drive.twist(wheels)
        return f"{twist.linear_mps / twist.angular_radps:.2f} m"

    panel = Panel(
        "x (m)",
        "y (m)",
        (-0.1, 0.1),
        (-0.05, 0.85),
        [
            Series(
                f"asked: {asked.left_mps:.2f} / {asked.right_mps:.2f} m/s, r {radius(asked)}",
                path(asked),
                GREY,
                "5 4",
            ),
            Series(
                f"scaled: {scaled.left_mps:.2f} / {scaled.right_mps:.2f} m/s, r {radius(scaled)}",
                path(scaled),
                BLUE,
            ),
            Series(
                f"one clipped: {clipped.left_mps:.2f} / {clipped.right_mps:.2f} m/s, "
                f"r {radius(clipped)}",
                path(clipped),
                RED,
                "2 3",
            ),
        ],
        legend="below",
        equal_aspect=True,
    )
    return render(
        f"{seconds:g} s of a turn the outer wheel cannot make (max_wheel_mps 1)",
        [panel],
        height=480,
    )


PLOTS: dict[str, Callable[[], str]] = {
    "limits-accel-brake.svg": accel_brake,
    "limits-reversal.svg": reversal,
    "limits-jerk.svg": jerk,
    "limits-saturation.svg": saturation,
}


def write_all(out_dir: Path) -> list[Path]:
    """Write every plot into ``out_dir``; the paths written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name, make in PLOTS.items():
        path = out_dir / name
        path.write_text(make(), encoding="utf-8")
        written.append(path)
    return written


def main(argv: Sequence[str]) -> int:
    out_dir = Path(argv[1]) if len(argv) > 1 else DEFAULT_OUT
    for path in write_all(out_dir):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
