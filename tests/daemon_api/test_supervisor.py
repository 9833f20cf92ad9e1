"""``ohmni serve`` as a supervisor: a killed daemon does not leave the robot driving.

The robot is ``ohmni sim --pty`` in its own process — the simulated drive boards keep
their last command, as the real ones do — and its console's ``status`` gives the true
pose. A client drives at 0.5 m/s through ``ohmni serve --port PTY``; then the worker (the
supervisor's child) or the supervisor itself is killed with SIGKILL, and the simulated
robot must stand still soon after. These tests run processes in real time: their waits
are seconds, with margins for a loaded machine.
"""

from __future__ import annotations

import asyncio
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from daemon_api._pty_robot import START_S, Simulator, read_line
from ohmni_tb.client import RobotClient
from ohmni_tb.errors import OhmniError, TransportError

pytestmark = pytest.mark.skipif(
    sys.platform != "linux", reason="reads the processes' parents from /proc"
)

#: From the kill to a robot standing still: 1 s, and as much again for a loaded machine.
#: Without the supervisor the robot drives on for as long as anyone watches.
STANDSTILL_WITHIN_S = 2.0


class Driver:
    """A client that takes the lease and drives at 0.5 m/s, 10 commands a second, until
    its connection ends or it is told to stop."""

    def __init__(self, url: str) -> None:
        self._url = url
        self._done = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._drive()), daemon=True)
        self._thread.start()

    async def _drive(self) -> None:
        try:
            async with RobotClient.connect(self._url) as client, client.lease():
                while not self._done.is_set():
                    client.drive(0.5, 0.0)
                    await asyncio.sleep(0.1)
        except OhmniError:
            pass  # the daemon killed under it: the end of driving

    def close(self) -> None:
        self._done.set()
        self._thread.join(10)


def children(pid: int) -> list[int]:
    """The processes whose parent is ``pid``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue  # ended meanwhile
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def wait_until(condition: object, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if callable(condition) and condition():
            return True
        time.sleep(0.05)
    return False


class Daemon:
    """``ohmni serve --port PTY --listen 127.0.0.1:0`` and the addresses it printed: its
    own, and its web console's page."""

    def __init__(self, port: str, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ohmni_tb", "serve", "--port", port, *args],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        assert self.proc.stdout is not None
        try:
            self.url = read_line(self.proc.stdout.fileno())
            self.page = read_line(self.proc.stdout.fileno())
        except BaseException:
            self.proc.kill()
            self.proc.communicate()
            raise

    def worker(self) -> int:
        found = children(self.proc.pid)
        assert len(found) == 1, f"the robot runs in one child process, not in {found}"
        return found[0]

    def more_stdout(self) -> bytes:
        """What it printed on stdout after the address, so far."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        ready, _, _ = select.select([fd], [], [], 0)
        return os.read(fd, 65536) if ready else b""

    def finish(self, signum: int = signal.SIGTERM) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(signum)
        try:
            _, err = self.proc.communicate(timeout=START_S)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.communicate()
        return self.proc.returncode, err.decode(errors="replace")


@pytest.fixture
def sim() -> Iterator[Simulator]:
    simulator = Simulator()
    yield simulator
    simulator.close()


def _drive_until_moving(sim: Simulator, url: str) -> Driver:
    driver = Driver(url)
    assert wait_until(lambda: sim.speed_mps() > 0.2, START_S), "the client never drove"
    return driver


async def _reads_robot_state(url: str) -> bool:
    try:
        async with RobotClient.connect(url) as client:
            return client.latest("robot_state") is not None
    except TransportError:
        return False  # nothing listens there (yet)


def test_a_killed_worker_ends_in_stopped_wheels_and_a_new_worker(sim: Simulator) -> None:
    daemon = Daemon(sim.path, "--listen", "127.0.0.1:0")
    driver = None
    try:
        worker = daemon.worker()
        driver = _drive_until_moving(sim, daemon.url)
        os.kill(worker, signal.SIGKILL)
        killed = time.monotonic()
        assert sim.seconds_to_standstill(killed) < STANDSTILL_WITHIN_S
        still = sim.pose()
        time.sleep(0.5)
        assert sim.pose() == still  # stopped, not paused
        # A new worker serves at the same address (port 0 chose it the first time).
        assert wait_until(lambda: children(daemon.proc.pid) not in ([], [worker]), START_S)
        assert wait_until(lambda: asyncio.run(_reads_robot_state(daemon.url)), START_S)
        assert daemon.more_stdout() == b""  # the addresses were printed once
    finally:
        if driver is not None:
            driver.close()
        code, log = daemon.finish()
    assert code == 0, log
    assert f"the worker (pid {worker}) was killed by SIGKILL: the wheels are stopped" in log
    assert "worker restarted" in log


def test_a_hung_worker_is_killed_and_ends_in_stopped_wheels(sim: Simulator) -> None:
    """A worker whose event loop is stuck (here: stopped with SIGSTOP) cannot run its
    watchdog: the supervisor misses its heartbeat, kills it and stops the wheels."""
    daemon = Daemon(sim.path, "--listen", "127.0.0.1:0")
    driver = None
    try:
        worker = daemon.worker()
        driver = _drive_until_moving(sim, daemon.url)
        os.kill(worker, signal.SIGSTOP)
        hung = time.monotonic()
        # HUNG_S (1 s) without a heartbeat, then the stop: as after a death.
        assert sim.seconds_to_standstill(hung) < 1.0 + STANDSTILL_WITHIN_S
        assert wait_until(lambda: not alive(worker), START_S)
    finally:
        if driver is not None:
            driver.close()
        code, log = daemon.finish()
    assert code == 0, log
    assert f"the worker (pid {worker}) has not run for" in log
    assert f"the worker (pid {worker}) was killed by SIGKILL: the wheels are stopped" in log


def test_a_killed_supervisor_ends_in_stopped_wheels(sim: Simulator) -> None:
    daemon = Daemon(sim.path, "--listen", "127.0.0.1:0")
    driver = None
    try:
        workers = children(daemon.proc.pid)
        driver = _drive_until_moving(sim, daemon.url)
        daemon.proc.kill()
        killed = time.monotonic()
        assert sim.seconds_to_standstill(killed) < STANDSTILL_WITHIN_S
        # The worker closed by itself: nothing holds the port any more.
        assert workers
        assert wait_until(lambda: not any(alive(pid) for pid in workers), START_S)
    finally:
        if driver is not None:
            driver.close()
        daemon.finish()


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_requested_stop_that_shuts_down_cleanly_exits_0(signum: int) -> None:
    daemon = Daemon("sim://", "--listen", "127.0.0.1:0")
    workers = children(daemon.proc.pid)
    code, log = daemon.finish(signum)
    assert code == 0, log  # not 128 + N: a service manager's stop is not a failure
    assert not any(alive(pid) for pid in workers)


def test_a_worker_that_keeps_dying_is_given_up_on(sim: Simulator) -> None:
    daemon = Daemon(sim.path, "--listen", "127.0.0.1:0")
    try:
        worker = daemon.worker()
        sim.close()  # the port is gone: no new worker can open it
        os.kill(worker, signal.SIGKILL)
        daemon.proc.wait(timeout=50)
    finally:
        code, log = daemon.finish()
    assert code == 1, log
    assert "the wheels may still be moving" in log  # the port it could not open
    assert "not restarted again" in log
    assert "Traceback" not in log
