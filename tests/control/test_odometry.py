"""Odometry: closed-form arcs, lines and spins; properties; batch = streaming."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ohmni_tb.control import Odometry, Pose, WheelNoise, integrate_batch, wrap_angle
from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError

B = 0.330
TOL = 1e-12

increment = st.floats(-0.05, 0.05, allow_nan=False)
steps_strategy = st.lists(st.tuples(increment, increment), min_size=1, max_size=40)
start_pose = st.builds(
    Pose, st.floats(-10.0, 10.0), st.floats(-10.0, 10.0), st.floats(-math.pi, math.pi)
)


def _drive(
    odo: Odometry, linear_mps: float, angular_radps: float, rate_hz: float, duration_s: float
) -> None:
    dt = 1.0 / rate_hz
    d_left = (linear_mps - angular_radps * B / 2) * dt
    d_right = (linear_mps + angular_radps * B / 2) * dt
    for k in range(1, round(duration_s * rate_hz) + 1):
        odo.update(d_left, d_right, k * dt)


def _angle_diff(a: float, b: float) -> float:
    return abs(wrap_angle(a - b))


@pytest.mark.parametrize("rate_hz", [50.0, 5.0, 1.0])
def test_arc_matches_the_closed_form_at_any_rate(rate_hz: float) -> None:
    odo = Odometry(B)
    linear, angular, duration = 0.4, 0.8, 7.0  # radius 0.5 m, 5.6 rad
    _drive(odo, linear, angular, rate_hz, duration)
    radius, heading = linear / angular, angular * duration
    assert odo.pose.x == pytest.approx(radius * math.sin(heading), abs=TOL)
    assert odo.pose.y == pytest.approx(radius * (1.0 - math.cos(heading)), abs=TOL)
    assert odo.pose.yaw == pytest.approx(wrap_angle(heading), abs=TOL)
    assert odo.heading_rad == pytest.approx(heading, abs=TOL)


@pytest.mark.parametrize("rate_hz", [50.0, 5.0])
def test_line_from_any_start_pose(rate_hz: float) -> None:
    odo = Odometry(B)
    odo.reset(x=1.0, y=-2.0, yaw=0.7)
    _drive(odo, -0.6, 0.0, rate_hz, 3.0)
    assert odo.pose.x == pytest.approx(1.0 - 1.8 * math.cos(0.7), abs=TOL)
    assert odo.pose.y == pytest.approx(-2.0 - 1.8 * math.sin(0.7), abs=TOL)
    assert odo.pose.yaw == 0.7


@pytest.mark.parametrize("rate_hz", [50.0, 5.0])
def test_spin_in_place_keeps_the_position_and_counts_turns(rate_hz: float) -> None:
    odo = Odometry(B)
    _drive(odo, 0.0, -2.0, rate_hz, 10.0)  # -20 rad, over three turns
    assert (odo.pose.x, odo.pose.y) == (0.0, 0.0)
    assert odo.heading_rad == pytest.approx(-20.0, abs=TOL)
    assert odo.pose.yaw == pytest.approx(-20.0 + 6.0 * math.pi, abs=TOL)
    assert -math.pi < odo.pose.yaw <= math.pi


@settings(max_examples=60)
@given(start_pose, steps_strategy)
def test_driving_a_path_and_its_reverse_returns_home(
    start: Pose, steps: list[tuple[float, float]]
) -> None:
    odo = Odometry(B)
    odo.reset(start.x, start.y, start.yaw)
    t = 0.0
    for d_left, d_right in [*steps, *[(-dl, -dr) for dl, dr in reversed(steps)]]:
        t += 0.02
        odo.update(d_left, d_right, t)
    assert odo.pose.x == pytest.approx(start.x, abs=1e-9)
    assert odo.pose.y == pytest.approx(start.y, abs=1e-9)
    assert odo.heading_rad == pytest.approx(start.yaw, abs=1e-9)


@settings(max_examples=60)
@given(
    st.floats(-1.0, 1.0),
    st.floats(-1.0, 1.0),
    st.lists(st.floats(0.01, 1.0), min_size=1, max_size=20),
)
def test_result_does_not_depend_on_how_a_motion_is_split(
    d_left: float, d_right: float, weights: list[float]
) -> None:
    whole = Odometry(B)
    whole.update(d_left, d_right, 1.0)
    split = Odometry(B)
    total = math.fsum(weights)
    t = 0.0
    for weight in weights:
        t += weight / total
        split.update(d_left * weight / total, d_right * weight / total, t)
    assert split.pose.x == pytest.approx(whole.pose.x, abs=1e-12)
    assert split.pose.y == pytest.approx(whole.pose.y, abs=1e-12)
    assert split.heading_rad == pytest.approx(whole.heading_rad, abs=1e-12)


def _stream(
    d_left: npt.NDArray[np.float64], d_right: npt.NDArray[np.float64], start: Pose
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    odo = Odometry(B)
    odo.reset(start.x, start.y, start.yaw)
    poses = np.empty((d_left.size, 3))
    headings = np.empty(d_left.size)
    for i, (dl, dr) in enumerate(zip(d_left.tolist(), d_right.tolist(), strict=True)):
        pose = odo.update(dl, dr, (i + 1) * 0.02)
        poses[i] = (pose.x, pose.y, pose.yaw)
        headings[i] = odo.heading_rad
    return poses, headings


@settings(max_examples=60)
@given(start_pose, steps_strategy)
def test_batch_equals_streaming_on_random_paths(
    start: Pose, steps: list[tuple[float, float]]
) -> None:
    d_left = np.array([s[0] for s in steps])
    d_right = np.array([s[1] for s in steps])
    poses, headings = _stream(d_left, d_right, start)
    batch = integrate_batch(d_left, d_right, B, start=start)
    assert batch.shape == (len(steps), 3)
    np.testing.assert_allclose(batch[:, :2], poses[:, :2], rtol=0, atol=TOL)
    unwrapped = integrate_batch(d_left, d_right, B, start=start, wrap_yaw=False)
    np.testing.assert_array_equal(unwrapped[:, 2], headings)
    for got, want in zip(batch[:, 2].tolist(), poses[:, 2].tolist(), strict=True):
        assert _angle_diff(got, want) <= TOL


def test_batch_equals_streaming_on_a_long_log() -> None:
    rng = np.random.default_rng(5)
    n = 20_000  # 400 s at 50 Hz, many turns, straight runs and spins
    v = np.repeat(rng.uniform(-1.0, 1.0, n // 100), 100)
    w = np.repeat(rng.choice([0.0, 0.5, -3.0], n // 100), 100)
    d_left = (v - w * B / 2) * 0.02 + rng.normal(0.0, 1e-4, n)
    d_right = (v + w * B / 2) * 0.02 + rng.normal(0.0, 1e-4, n)
    d_right[:500] = d_left[:500]  # an exactly straight stretch
    poses, _ = _stream(d_left, d_right, Pose(0.5, 0.5, 3.0))
    batch = integrate_batch(d_left, d_right, B, start=Pose(0.5, 0.5, 3.0))
    assert np.max(np.abs(batch[:, :2] - poses[:, :2])) <= TOL
    yaw_error = np.abs(np.angle(np.exp(1j * (batch[:, 2] - poses[:, 2]))))
    assert np.max(yaw_error) <= TOL


def test_batch_rows_are_poses_after_each_increment_without_the_start() -> None:
    out = integrate_batch([0.1, 0.1, 0.0], [0.1, 0.1, 0.0], B, start=Pose(1.0, 0.0, 0.0))
    np.testing.assert_allclose(out, [[1.1, 0.0, 0.0], [1.2, 0.0, 0.0], [1.2, 0.0, 0.0]])
    assert integrate_batch([], [], B).shape == (0, 3)


def test_batch_rejects_bad_input_by_name_and_index() -> None:
    with pytest.raises(InvalidArgumentError, match=r"d_right_m\[2\]=nan"):
        integrate_batch([0.0, 0.0, 0.0], [0.0, 0.0, math.nan], B)
    with pytest.raises(InvalidArgumentError, match="3 increments but d_right_m has 2"):
        integrate_batch([0.0, 0.0, 0.0], [0.0, 0.0], B)
    with pytest.raises(InvalidArgumentError, match="1-D"):
        integrate_batch([[0.0]], [[0.0]], B)
    with pytest.raises(InvalidArgumentError, match=r"wheel_separation_m=0\.0"):
        integrate_batch([0.0], [0.0], 0.0)


@pytest.mark.parametrize(
    ("angle", "wrapped"),
    [
        (math.pi, math.pi),
        (-math.pi, math.pi),
        (3.0 * math.pi, math.pi),
        (-1.5 * math.pi, 0.5 * math.pi),
        (0.1, 0.1),
        (2.0 * math.pi + 0.25, 0.25),
    ],
)
def test_wrap_angle_is_half_open(angle: float, wrapped: float) -> None:
    assert wrap_angle(angle) == pytest.approx(wrapped, abs=1e-15)


def test_twist_is_a_rate_weighted_average_while_the_pose_uses_raw_increments() -> None:
    odo = Odometry(B, twist_window=3)
    assert odo.twist.linear_mps == 0.0
    times = [0.0, 0.018, 0.040, 0.058, 0.080]
    lefts = [0.0, 0.009, 0.012, 0.008, 0.010]
    rights = [0.0, 0.009, 0.014, 0.008, 0.012]
    for t, dl, dr in zip(times, lefts, rights, strict=True):
        odo.update(dl, dr, t)
    # Last three steps: Σds = 0.013 + 0.008 + 0.011 = 0.032 over 0.062 s;
    # Σdθ = (0.002 + 0 + 0.002) / 0.33 over 0.062 s.
    assert odo.twist.linear_mps == pytest.approx(0.032 / 0.062)
    assert odo.twist.angular_radps == pytest.approx(0.004 / B / 0.062)
    raw = integrate_batch(lefts, rights, B)[-1]
    assert (odo.pose.x, odo.pose.y, odo.pose.yaw) == pytest.approx(tuple(raw), abs=TOL)


def test_pose_history_is_interpolated_along_the_arc() -> None:
    odo = Odometry(B)
    odo.update(0.0, 0.0, 0.0)
    linear, angular = 0.4, 0.8
    d_left = (linear - angular * B / 2) * 0.2
    d_right = (linear + angular * B / 2) * 0.2
    for k in range(1, 11):  # 5 Hz, 2 s
        odo.update(d_left, d_right, k * 0.2)
    for t in (0.0, 0.05, 0.37, 1.0, 1.93, 2.0):
        pose = odo.pose_at(t)
        heading = angular * t
        assert pose.x == pytest.approx(0.5 * math.sin(heading), abs=TOL)
        assert pose.y == pytest.approx(0.5 * (1.0 - math.cos(heading)), abs=TOL)
        assert pose.yaw == pytest.approx(heading, abs=TOL)
    with pytest.raises(OutOfRangeError, match=r"t_s=2\.1"):
        odo.pose_at(2.1)
    with pytest.raises(OutOfRangeError, match=r"t_s=-0\.1"):
        odo.pose_at(-0.1)


def test_pose_history_keeps_the_latest_entries_and_restarts_on_reset() -> None:
    odo = Odometry(B, history_size=3)
    for k in range(5):
        odo.update(0.1, 0.1, float(k))
    assert odo.pose_at(2.5).x == pytest.approx(0.35)
    with pytest.raises(OutOfRangeError):
        odo.pose_at(1.5)
    odo.reset(x=5.0, yaw=math.pi / 2)
    assert odo.pose_at(4.0) == Pose(5.0, 0.0, math.pi / 2)
    odo.update(0.1, 0.1, 5.0)
    assert odo.pose_at(4.5).y == pytest.approx(0.05)
    with pytest.raises(OutOfRangeError):
        odo.pose_at(3.9)


def test_reset_keeps_the_clock_and_clears_the_covariance() -> None:
    odo = Odometry(B)
    odo.update(0.0, 0.0, 0.0)
    odo.update(0.01, 0.01, 0.02)
    odo.reset(1.0, 2.0, 4.0)
    assert odo.pose == Pose(1.0, 2.0, 4.0 - 2.0 * math.pi)
    assert odo.heading_rad == 4.0
    assert not odo.covariance.any()
    assert odo.twist.linear_mps == pytest.approx(0.5)
    with pytest.raises(InvalidArgumentError, match=r"t_s=0\.02"):
        odo.update(0.0, 0.0, 0.02)


def test_bad_updates_are_rejected_by_name() -> None:
    odo = Odometry(B)
    with pytest.raises(InvalidArgumentError, match="d_left_m=nan"):
        odo.update(math.nan, 0.0, 0.0)
    with pytest.raises(InvalidArgumentError, match="d_right_m=inf"):
        odo.update(0.0, math.inf, 0.0)
    with pytest.raises(InvalidArgumentError, match="t_s=nan"):
        odo.update(0.0, 0.0, math.nan)
    with pytest.raises(InvalidArgumentError, match="yaw=inf"):
        odo.reset(yaw=math.inf)
    with pytest.raises(InvalidArgumentError, match="twist_window=0"):
        Odometry(B, twist_window=0)
    assert odo.t_s is None


def test_covariance_of_a_straight_line_matches_the_closed_form() -> None:
    k = 1e-4
    odo = Odometry(B, noise=WheelNoise(k, k))
    length, n = 2.0, 2000
    for i in range(n):
        odo.update(length / n, length / n, i * 0.01)
    cov = odo.covariance
    # Each wheel adds k·d per step: var x = ¼(kL + kL), var θ = (kL + kL) / b².
    assert cov[0, 0] == pytest.approx(k * length / 2.0, rel=1e-12)
    assert cov[2, 2] == pytest.approx(2.0 * k * length / B**2, rel=1e-12)
    # Heading noise swings the path: var y → ∫(L - s)² (2k / b²) ds = 2kL³ / (3b²).
    assert cov[1, 1] == pytest.approx(2.0 * k * length**3 / (3.0 * B**2), rel=2e-3)
    assert cov[0, 1] == pytest.approx(0.0, abs=1e-20)
    assert cov[0, 2] == pytest.approx(0.0, abs=1e-20)
    np.testing.assert_array_equal(cov, cov.T)


def test_covariance_rows_are_the_matrix_row_by_row_as_floats() -> None:
    odo = Odometry(B, noise=WheelNoise(1e-4, 2e-4))
    for i in range(50):
        odo.update(0.01 + 0.001 * i, 0.012, 0.02 * i)  # a curve: every term non-zero
    rows = odo.covariance_rows
    assert len(rows) == 9
    assert all(type(v) is float for v in rows)
    assert rows == tuple(odo.covariance.flat)
    assert rows[1] != 0.0
    assert rows[5] != 0.0


def _step(state: npt.NDArray[np.float64], d: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """One exact arc step, written independently: the difference of two circle points."""
    x, y, theta = state
    ds = 0.5 * (d[0] + d[1])
    dtheta = (d[1] - d[0]) / B
    if abs(dtheta) < 1e-9:
        return np.array([x + ds * math.cos(theta), y + ds * math.sin(theta), theta])
    radius = ds / dtheta
    return np.array(
        [
            x + radius * (math.sin(theta + dtheta) - math.sin(theta)),
            y - radius * (math.cos(theta + dtheta) - math.cos(theta)),
            theta + dtheta,
        ]
    )


def test_covariance_on_curves_matches_numerical_jacobians() -> None:
    noise = WheelNoise(2e-4, 1e-4)
    odo = Odometry(B, noise=noise)
    state = np.zeros(3)
    cov = np.zeros((3, 3))
    steps = [(0.05, 0.08), (0.1, -0.1), (0.02, 0.02), (-0.04, 0.09), (0.3, 0.1)]
    eps = 1e-6
    for i, (dl, dr) in enumerate(steps):
        d = np.array([dl, dr])
        f = np.empty((3, 3))
        g = np.empty((3, 2))
        for j in range(3):
            e = np.zeros(3)
            e[j] = eps
            f[:, j] = (_step(state + e, d) - _step(state - e, d)) / (2 * eps)
        for j in range(2):
            e2 = np.zeros(2)
            e2[j] = eps
            g[:, j] = (_step(state, d + e2) - _step(state, d - e2)) / (2 * eps)
        q = np.diag([noise.k_left_m * abs(dl), noise.k_right_m * abs(dr)])
        cov = f @ cov @ f.T + g @ q @ g.T
        state = _step(state, d)
        odo.update(dl, dr, float(i))
    np.testing.assert_allclose(odo.covariance, cov, rtol=1e-6, atol=1e-14)
    assert (odo.pose.x, odo.pose.y) == pytest.approx((state[0], state[1]), abs=TOL)
