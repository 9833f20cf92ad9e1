"""The scripts in examples/ run against the simulator and say what they promise."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from ohmni_tb.sim.clock import run_virtual

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def load(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ("script", "args", "expected"),
    [
        ("read_sensors.py", [], ["left firmware 'sim-drive-1.0'", "battery: 16.", "80 %"]),
        ("neck_nod.py", ["--times", "1"], ["neck: DRS_0101, at 512", "at 400", "at 560"]),
    ],
)
def test_example_script_runs(script: str, args: list[str], expected: list[str]) -> None:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    for text in expected:
        assert text in result.stdout


def test_odometry_example_tracks_the_ground_truth(capsys: pytest.CaptureFixture[str]) -> None:
    drive = load("drive_and_odometry").drive
    assert run_virtual(drive("sim://", 300, 450, 1.5)) == 0
    out = capsys.readouterr().out
    odometry = re.search(r"odometry:\s+x=(\S+) m\s+y=(\S+) m\s+yaw=(\S+) rad", out)
    truth = re.search(r"ground truth: x=(\S+) m\s+y=(\S+) m\s+yaw=(\S+) rad", out)
    assert odometry is not None
    assert truth is not None
    est = [float(v) for v in odometry.groups()]
    real = [float(v) for v in truth.groups()]
    assert real[0] > 0.3  # it drove forward
    assert real[2] > 0.3  # and turned left (right wheel faster)
    # Sampling the two wheels 4 ms apart is the only error source: a few millimetres.
    assert est[0] == pytest.approx(real[0], abs=0.01)
    assert est[1] == pytest.approx(real[1], abs=0.01)
    assert est[2] == pytest.approx(real[2], abs=0.01)


def test_odometry_example_refuses_a_real_robot_without_consent() -> None:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "drive_and_odometry.py"), "--port", "/dev/ttyUSB9"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 2
    assert "--i-am-clear-of-obstacles" in result.stderr


def test_square_example_closes_the_square(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    square = load("square")
    png = tmp_path / "square.png"
    assert run_virtual(square.run("sim://", png=png)) == 0
    out = capsys.readouterr().out
    drift = re.search(r"final error \(odometry vs truth\): (\S+) cm, (\S+)°", out)
    closure = re.search(r"back at the start \(truth\): (\S+) cm, (\S+)° away", out)
    assert drift is not None, out
    assert closure is not None, out
    assert float(drift.group(1)) < 2.0
    assert float(drift.group(2)) < 1.0
    assert float(closure.group(1)) < 2.0
    assert float(closure.group(2)) < 1.0
    # Four legs, each ending about a metre from the last corner.
    legs = re.findall(r"leg \d: odometry x=(\S+) m\s+y=(\S+) m", out)
    corners = [(round(float(x)), round(float(y))) for x, y in legs]
    assert corners == [(1, 0), (1, 1), (0, 1), (0, 0)]
    if importlib.util.find_spec("matplotlib") is None:
        assert "plot skipped: matplotlib is not installed" in out
        assert not png.exists()
    else:
        assert f"plot: {png}" in out
        assert png.read_bytes().startswith(b"\x89PNG")


def test_square_example_refuses_a_real_robot_without_consent() -> None:
    result = subprocess.run(
        [sys.executable, str(EXAMPLES / "square.py"), "--port", "/dev/ttyUSB9"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert result.returncode == 2
    assert "--yes" in result.stderr


def test_one_script_drives_its_own_robot_or_the_daemons() -> None:
    from daemon_api._serving import free_port, start_serving, stop_serving

    script = str(EXAMPLES / "embedded_or_daemon.py")
    alone = subprocess.run(
        [sys.executable, script], capture_output=True, text=True, timeout=60, check=False
    )
    assert alone.returncode == 0, alone.stderr
    assert "through its own Robot on sim://" in alone.stdout
    proc, url = start_serving("--listen", f"127.0.0.1:{free_port()}")
    try:
        shared = subprocess.run(
            [sys.executable, script, "--daemon", url],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    finally:
        stop_serving(proc)
    assert shared.returncode == 0, shared.stderr
    for run in (alone, shared):
        metres = float(re.search(r"drove (\d+\.\d+) m", run.stdout).group(1))  # type: ignore[union-attr]  # asserted by the run
        assert 0.2 < metres < 0.35, run.stdout
    assert f"through the daemon at {url}" in shared.stdout
