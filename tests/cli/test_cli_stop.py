"""``ohmni stop``: a robot some program left driving stands still, confirmed by its counts.

The robot is ``ohmni sim --pty`` in its own process: its drive boards keep the last wheel
command, as the real ones do, so a program that sends one and closes the port leaves it
driving — until ``ohmni stop``.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from daemon_api._pty_robot import START_S, Simulator
from ohmni_tb.bus import Bus
from ohmni_tb.protocol.drive import wheel_command
from ohmni_tb.transport import open_transport

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs pseudo-terminals")


@pytest.fixture
def sim() -> Iterator[Simulator]:
    simulator = Simulator()
    yield simulator
    simulator.close()


async def _leave_driving(path: str) -> None:
    """Send a wheel command and close the port without a stop."""
    async with Bus(await open_transport(path)) as bus:
        await bus.send(wheel_command(400, 400))


def _ohmni_stop(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ohmni_tb", "stop", *args],
        capture_output=True,
        text=True,
        timeout=START_S,
        check=False,
    )


@pytest.mark.usefixtures("virtual_time")
def test_a_robot_left_driving_stands_still_after_ohmni_stop(sim: Simulator) -> None:
    asyncio.run(_leave_driving(sim.path))
    assert sim.speed_mps() > 0.05  # nobody is connected, and it drives on

    done = _ohmni_stop("--port", sim.path, "--json")

    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["confirmed"] is True
    assert report["port"] == sim.path
    still = sim.pose()
    time.sleep(0.5)
    assert sim.pose() == still


@pytest.mark.usefixtures("virtual_time")
def test_a_port_it_cannot_open_is_one_error_line() -> None:
    done = _ohmni_stop("--port", "/dev/ohmni-no-such-port")
    assert done.returncode == 1
    assert done.stderr.startswith("error: cannot open serial port '/dev/ohmni-no-such-port'")
    assert done.stdout == ""
