"""Odometry benchmark: accuracy against closed-form arcs, batch and streaming speed.

Run with ``.venv/bin/python bench/odometry.py``. It prints:

1. Position error against the closed-form circle for exact arc integration (what
   ``ohmni_tb.control`` does), RK2 (midpoint heading, ROS diff_drive_controller's small-turn
   path) and Euler (start heading), at the same dt, side by side.
2. ``integrate_batch`` throughput in samples/s (target >= 1,000,000).
3. ``Odometry.update`` cost per step, and how far batch and streaming disagree.
"""

from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from ohmni_tb.control import Odometry, integrate_batch

FloatArray = npt.NDArray[np.float64]
SEPARATION_M = 0.330
BATCH_SAMPLES = 1_000_000
STREAM_SAMPLES = 100_000
REPEATS = 5


def main() -> None:
    """Print every figure with the machine it ran on."""
    print(_machine())
    print()
    _accuracy()
    print()
    _batch_throughput()
    print()
    _streaming_cost()


def _machine() -> str:
    model = "unknown"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return (
        f"machine: {model}, nproc {cpus}; Python {platform.python_version()}, "
        f"numpy {np.__version__}"
    )


def _euler(d_left: FloatArray, d_right: FloatArray, separation_m: float) -> FloatArray:
    """Forward Euler: each step moves along the heading at its start."""
    ds = 0.5 * (d_left + d_right)
    dtheta = (d_right - d_left) / separation_m
    theta = np.cumsum(dtheta)
    start = theta - dtheta
    return np.column_stack((np.cumsum(ds * np.cos(start)), np.cumsum(ds * np.sin(start)), theta))


def _rk2(d_left: FloatArray, d_right: FloatArray, separation_m: float) -> FloatArray:
    """Second-order Runge-Kutta: each step moves along the mid-step heading."""
    ds = 0.5 * (d_left + d_right)
    dtheta = (d_right - d_left) / separation_m
    theta = np.cumsum(dtheta)
    mid = theta - 0.5 * dtheta
    return np.column_stack((np.cumsum(ds * np.cos(mid)), np.cumsum(ds * np.sin(mid)), theta))


Integrator = Callable[[FloatArray, FloatArray, float], FloatArray]
METHODS: tuple[tuple[str, Integrator], ...] = (
    ("exact", integrate_batch),
    ("RK2", _rk2),
    ("Euler", _euler),
)


def _accuracy() -> None:
    # (linear m/s, angular rad/s, seconds): a gentle arc, a tight turn, a fast spin-drive.
    cases = ((0.5, 0.5, 20.0), (0.3, 2.0, 20.0), (1.0, 2.0, 20.0))
    print("1. position error vs the closed-form circle (max over the run, metres)")
    header = f"{'v m/s':>6} {'w rad/s':>8} {'rate':>6} {'dt s':>6}"
    header += "".join(f" {name:>10}" for name, _ in METHODS)
    print(header)
    for linear, angular, duration_s in cases:
        for rate_hz in (50.0, 5.0):
            dt = 1.0 / rate_hz
            n = round(duration_s * rate_hz)
            d_left = np.full(n, (linear - angular * SEPARATION_M / 2) * dt)
            d_right = np.full(n, (linear + angular * SEPARATION_M / 2) * dt)
            t = dt * np.arange(1, n + 1)
            radius = linear / angular
            truth_x = radius * np.sin(angular * t)
            truth_y = radius * (1.0 - np.cos(angular * t))
            row = f"{linear:>6.2f} {angular:>8.2f} {rate_hz:>4.0f}Hz {dt:>6.2f}"
            for _, method in METHODS:
                poses = method(d_left, d_right, SEPARATION_M)
                error = np.hypot(poses[:, 0] - truth_x, poses[:, 1] - truth_y).max()
                row += f" {error:>10.2e}"
            print(row)


def _best_of(run: Callable[[], object], repeats: int = REPEATS) -> float:
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return best


def _random_log(n: int, seed: int) -> tuple[FloatArray, FloatArray]:
    rng = np.random.default_rng(seed)
    speed = np.repeat(rng.uniform(-1.0, 1.0, n // 50 + 1), 50)[:n]
    turn = np.repeat(rng.uniform(-2.0, 2.0, n // 50 + 1), 50)[:n]
    d_left = (speed - turn * SEPARATION_M / 2) * 0.02
    d_right = (speed + turn * SEPARATION_M / 2) * 0.02
    return d_left, d_right


def _batch_throughput() -> None:
    d_left, d_right = _random_log(BATCH_SAMPLES, seed=1)
    integrate_batch(d_left, d_right, SEPARATION_M)  # warm up
    seconds = _best_of(lambda: integrate_batch(d_left, d_right, SEPARATION_M))
    print("2. integrate_batch throughput (best of 5)")
    print(f"{'samples':>10} {'seconds':>9} {'samples/s':>12} {'target':>12}")
    rate = BATCH_SAMPLES / seconds
    verdict = "met" if rate >= 1e6 else "MISSED"
    print(f"{BATCH_SAMPLES:>10,} {seconds:>9.4f} {rate:>12,.0f} {'>= 1,000,000':>12} {verdict}")


def _streaming_cost() -> None:
    d_left, d_right = _random_log(STREAM_SAMPLES, seed=2)
    lefts = d_left.tolist()
    rights = d_right.tolist()
    times = (0.02 * np.arange(1, STREAM_SAMPLES + 1)).tolist()
    poses = np.empty((STREAM_SAMPLES, 2))

    def run() -> None:
        odo = Odometry(SEPARATION_M)
        update = odo.update
        for i, (dl, dr, t) in enumerate(zip(lefts, rights, times, strict=True)):
            pose = update(dl, dr, t)
            poses[i, 0] = pose.x
            poses[i, 1] = pose.y

    seconds = _best_of(run, repeats=3)
    batch = integrate_batch(d_left, d_right, SEPARATION_M)
    disagreement = float(np.abs(batch[:, :2] - poses).max())
    print("3. Odometry.update, streaming (pose, covariance, twist window, history; best of 3)")
    print(f"{'steps':>10} {'us/step':>9} {'steps/s':>12} {'max |batch - stream| m':>24}")
    print(
        f"{STREAM_SAMPLES:>10,} {seconds / STREAM_SAMPLES * 1e6:>9.2f} "
        f"{STREAM_SAMPLES / seconds:>12,.0f} {disagreement:>24.1e}"
    )
    print(f"   at 50 Hz one step is {seconds / STREAM_SAMPLES * 50 * 100:.4f} % of one core")


if __name__ == "__main__":
    main()
