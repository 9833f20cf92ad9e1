"""``ohmni sim --pty`` in its own process, with the simulated robot's true pose: for the
tests that check the robot stands still after a process that drove it is gone."""

from __future__ import annotations

import os
import re
import select
import subprocess
import sys
import time

#: Starting a process (the interpreter, the Robot, the server) on a loaded machine.
START_S = 30.0
_POSE = re.compile(rb"pose x=(-?[\d.]+) m y=(-?[\d.]+) m")


class Simulator:
    """``ohmni sim --pty``: the device path, and the true pose from its console."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ohmni_tb", "sim", "--pty"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        assert self.proc.stdout is not None
        self.path = read_line(self.proc.stdout.fileno())
        self._console = b""

    def pose(self) -> tuple[float, float]:
        """Where the simulated robot truly is (x, y in metres, to the millimetre)."""
        assert self.proc.stdin is not None
        assert self.proc.stderr is not None
        self.proc.stdin.write(b"status\n")
        self.proc.stdin.flush()
        deadline = time.monotonic() + 5
        while (match := _POSE.search(self._console)) is None:
            ready, _, _ = select.select([self.proc.stderr], [], [], deadline - time.monotonic())
            assert ready, "the simulator did not answer status"
            self._console += os.read(self.proc.stderr.fileno(), 65536)
        self._console = self._console[match.end() :]
        return float(match[1]), float(match[2])

    def speed_mps(self, over_s: float = 0.1) -> float:
        x0, y0 = self.pose()
        started = time.monotonic()
        time.sleep(over_s)
        x1, y1 = self.pose()
        return float(((x1 - x0) ** 2 + (y1 - y0) ** 2) ** 0.5 / (time.monotonic() - started))

    def seconds_to_standstill(self, since: float, give_up_s: float = 8.0) -> float:
        """From ``since`` (a monotonic time) to the first of two poses 0.1 s apart that
        agree to the millimetre; ``inf`` if the robot still moves ``give_up_s`` later."""
        last, last_at = self.pose(), time.monotonic()
        while time.monotonic() - since < give_up_s:
            time.sleep(0.1)
            pose, at = self.pose(), time.monotonic()
            if abs(pose[0] - last[0]) <= 0.001 and abs(pose[1] - last[1]) <= 0.001:
                return last_at - since
            last, last_at = pose, at
        return float("inf")

    def close(self) -> None:
        if self.proc.returncode is None:
            self.proc.kill()
            self.proc.communicate(timeout=START_S)


def read_line(fd: int, timeout_s: float = START_S) -> str:
    line = b""
    deadline = time.monotonic() + timeout_s
    while not line.endswith(b"\n"):
        ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        assert ready, f"no line within {timeout_s} s"
        chunk = os.read(fd, 1)
        assert chunk, "the process ended before its line"
        line += chunk
    return line.decode().strip()
