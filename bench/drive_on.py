"""Can anything make the robot drive on? Each way, tried from outside and measured.

Every scenario runs the programs a user runs — ``ohmni sim --pty`` (the simulated robot on
a pseudo-terminal, in a process of its own) and ``ohmni serve`` on it — and attacks them
only through the public CLI and WebSocket protocols. Each scenario has a moment by which
the robot must be stopping (the watchdog plus the braking ramp after a driver goes
silent, 1 s after the driving process dies, at once for a client that may not drive); the
simulator's true pose, asked on its console, gives how far the robot moved after that
moment. A pass is under 1 cm::

    python bench/drive_on.py              # every scenario once
    python bench/drive_on.py --runs 3     # each three times (the worst is printed)
    python bench/drive_on.py --only kill-worker

docs/safety.md's table has its figures.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import re
import select
import signal
import struct
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from websockets.asyncio.client import ClientConnection

#: A pass: the robot moved less than this after the moment it had to be stopping.
LIMIT_M = 0.01
#: The Robot's defaults that set the moments: the watchdog and the braking ramp from the
#: driving speed used here (0.5 m/s at linear_decel_mps2 = 1 m/s²).
WATCHDOG_S = 0.5
SPEED_MPS = 0.5
RAMP_S = SPEED_MPS / 1.0
#: How long the robot is watched after the moment.
WATCH_S = 2.0
#: A driver's command period (a teleop's 20 Hz).
COMMAND_PERIOD_S = 0.05
#: Latency allowance between a process's event and the robot's (pipes, the pty, the
#: simulator's own tick): added to each moment.
MARGIN_S = 0.1

_POSE = re.compile(r"pose x=(-?[\d.]+) m y=(-?[\d.]+) m yaw=(-?[\d.]+) rad")


class Console:
    """A child process's line-by-line stdout and stderr, read without blocking."""

    def __init__(self, proc: subprocess.Popen[bytes]) -> None:
        self.proc = proc
        self._buffers: dict[int, bytes] = {}

    def line(self, stream: str, timeout_s: float, match: str = "") -> str:
        """The next line of ``stream`` (``stdout``/``stderr``) holding ``match``."""
        pipe = getattr(self.proc, stream)
        fd = pipe.fileno()
        deadline = time.monotonic() + timeout_s
        while True:
            buffer = self._buffers.get(fd, b"")
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                self._buffers[fd] = buffer
                text = line.decode(errors="replace")
                if match in text:
                    return text
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"no line with {match!r} on {stream} in {timeout_s} s")
            ready, _, _ = select.select([fd], [], [], left)
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:
                    raise EOFError(f"{stream} ended: {self.proc.args!r}")
                self._buffers[fd] = self._buffers.get(fd, b"") + chunk


class Sim:
    """``ohmni sim --pty``: the simulated robot, and its true pose from its console."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ohmni_tb", "sim", "--pty"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        self.console = Console(self.proc)
        self.path = self.console.line("stdout", 30).strip()

    def pose(self) -> tuple[float, float, float]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(b"status\n")
        self.proc.stdin.flush()
        found = _POSE.search(self.console.line("stderr", 10, "pose x="))
        assert found is not None
        x, y, yaw = (float(value) for value in found.groups())
        return x, y, yaw

    def close(self) -> None:
        _end(self.proc)


class Serve:
    """``ohmni serve --port PTY ARGS``: its ws:// URL, and the Foxglove URL if asked."""

    def __init__(self, port: str, *args: str) -> None:
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "ohmni_tb",
                "serve",
                "--port",
                port,
                "--listen",
                "127.0.0.1:0",
                *args,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,  # a kill of the group takes the worker too, at the end
        )
        self.console = Console(self.proc)
        self.url = self.console.line("stdout", 60).strip()
        self.foxglove = self.console.line("stdout", 30).strip() if "--foxglove" in args else None

    def worker(self) -> int:
        """The pid of the process that runs the Robot (the supervisor's child)."""
        children = Path(f"/proc/{self.proc.pid}/task/{self.proc.pid}/children")
        pids = [int(pid) for pid in children.read_text().split()]
        if len(pids) != 1:
            raise RuntimeError(f"ohmni serve has {len(pids)} children, expected its worker")
        return pids[0]

    def close(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGTERM)
        _end(self.proc)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)


def _end(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.communicate(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


#: A driver in a process of its own: takes the lease, drives at SPEED_MPS at 20 Hz, prints
#: ``driving`` after its first second and the monotonic time of each later command.
_DRIVER = textwrap.dedent(
    """
    import asyncio, sys, time
    from ohmni_tb.client import RobotClient

    async def main(url, token):
        async with RobotClient.connect(url, token=token or None) as client:
            await client.acquire()
            started = time.monotonic()
            said = False
            while True:
                client.drive({speed}, 0.0)
                if not said and time.monotonic() - started > 1.0:
                    print("driving", flush=True)
                    said = True
                print(time.monotonic(), flush=True)
                await asyncio.sleep({period})

    asyncio.run(main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else ""))
    """
).format(speed=SPEED_MPS, period=COMMAND_PERIOD_S)


class Driver:
    """The driving client's process."""

    def __init__(self, url: str, token: str = "") -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _DRIVER, url, token],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        self.console = Console(self.proc)
        self.console.line("stdout", 30, "driving")

    def close(self) -> None:
        with contextlib.suppress(ProcessLookupError):
            self.proc.send_signal(signal.SIGCONT)
        _end(self.proc)


@dataclass
class Outcome:
    deadline: str
    moved: tuple[float, float]  # after the deadline (m), and the standstill (s)
    note: str = ""
    must_move: bool = False  # a control case: the harness must see the robot move

    @property
    def moved_m(self) -> float:
        return self.moved[0]

    @property
    def passed(self) -> bool:
        return self.moved_m > 0.1 if self.must_move else self.moved_m < LIMIT_M


def _speed(sim: Sim) -> float:
    """The robot's true speed over half a second, m/s (a scenario's driver is live)."""
    x0, y0, _ = sim.pose()
    time.sleep(0.5)
    x1, y1, _ = sim.pose()
    return math.hypot(x1 - x0, y1 - y0) / 0.5


def _moved(sim: Sim, event_s: float, must_stop_s: float) -> tuple[float, float]:
    """Watch the robot from ``event_s`` (monotonic, now or just past) to ``must_stop_s`` +
    WATCH_S: how far it went after ``must_stop_s``, and how long after ``event_s`` it
    stood still for good (a pose within 1 mm of the last one from then on)."""
    track: list[tuple[float, tuple[float, float, float]]] = []
    while True:
        now = time.monotonic()
        track.append((now, sim.pose()))
        if now > must_stop_s + WATCH_S:
            break
        time.sleep(0.05)

    def travel(a: tuple[float, float, float], b: tuple[float, float, float]) -> float:
        # A turn on the spot moves each wheel by half the track times the angle.
        return max(math.hypot(b[0] - a[0], b[1] - a[1]), abs(b[2] - a[2]) * 0.165)

    final = track[-1][1]
    at_deadline = next(pose for t, pose in track if t >= must_stop_s)
    still_from = track[-1][0]
    for t, pose in reversed(track):
        if travel(pose, final) > 0.001:
            break
        still_from = t
    return travel(at_deadline, final), max(0.0, still_from - event_s)


def _silent_driver(freeze: bool, readers: int = 0) -> Callable[[Sim], Outcome]:
    def run(sim: Sim) -> Outcome:
        serve = Serve(sim.path)
        flood: subprocess.Popen[bytes] | None = None
        driver = Driver(serve.url)
        try:
            note = ""
            if readers:
                flood = subprocess.Popen(
                    [
                        sys.executable,
                        str(Path(__file__).with_name("_daemon_clients.py")),
                        serve.url,
                        "flood",
                        str(readers),
                    ],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=subprocess.PIPE,
                )
                Console(flood).line("stdout", 60, "ready")
                time.sleep(1.0)
            note = f"driving at {_speed(sim):.2f} m/s before"
            driver.proc.send_signal(signal.SIGSTOP if freeze else signal.SIGKILL)
            event = time.monotonic()
            if freeze:  # the watchdog stops it
                deadline = f"last command + watchdog {WATCHDOG_S:g} s + ramp {RAMP_S:g} s"
                moved = _moved(sim, event, event + WATCHDOG_S + RAMP_S + MARGIN_S)
            else:  # its connection closes: the lease changes hands, which stops it
                deadline = f"kill + ramp {RAMP_S:g} s"
                moved = _moved(sim, event, event + RAMP_S + MARGIN_S)
            return Outcome(deadline, moved, note)
        finally:
            driver.close()
            if flood is not None:
                _end(flood)
            serve.close()

    return run


def _kill(which: str) -> Callable[[Sim], Outcome]:
    def run(sim: Sim) -> Outcome:
        from ohmni_tb.daemon.supervisor import HUNG_S  # noqa: PLC0415

        serve = Serve(sim.path)
        driver = Driver(serve.url)
        try:
            pid = serve.proc.pid if which == "serve" else serve.worker()
            note = f"driving at {_speed(sim):.2f} m/s before"
            if which == "hung":
                os.kill(pid, signal.SIGSTOP)
                deadline, after_s = f"SIGSTOP + {HUNG_S:g} s (no heartbeat) + 1 s", HUNG_S + 1.0
            else:
                os.kill(pid, signal.SIGKILL)
                deadline, after_s = "kill -9 + 1 s", 1.0
            event = time.monotonic()
            moved = _moved(sim, event, event + after_s)
            return Outcome(deadline, moved, note)
        finally:
            driver.close()
            serve.close()

    return run


class _Foxglove:
    """The least of a Foxglove client: advertise a Twist channel and publish on it."""

    SUBPROTOCOL = "foxglove.sdk.v1"

    @staticmethod
    async def drive(
        url: str, *, origin: str | None, seconds: float, token: str | None = None
    ) -> None:
        from websockets.asyncio.client import connect  # noqa: PLC0415
        from websockets.typing import Origin, Subprotocol  # noqa: PLC0415

        async with connect(
            url,
            subprotocols=[Subprotocol(_Foxglove.SUBPROTOCOL)],
            origin=None if origin is None else Origin(origin),
        ) as ws:
            if token is not None:
                await _Foxglove.unlock(ws, token)
            channel = {
                "id": 1,
                "topic": "/tb_cmd_vel",
                "encoding": "json",
                "schemaName": "geometry_msgs/Twist",
            }
            await ws.send(json.dumps({"op": "advertise", "channels": [channel]}))
            twist = {
                "linear": {"x": SPEED_MPS, "y": 0, "z": 0},
                "angular": {"x": 0, "y": 0, "z": 0},
            }
            frame = struct.pack("<BI", 1, 1) + json.dumps(twist).encode()
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                await ws.send(frame)
                await asyncio.sleep(COMMAND_PERIOD_S)

    @staticmethod
    async def unlock(ws: ClientConnection, token: str) -> None:
        """Call ``/tb_control/unlock`` with ``token`` (JSON), as the app's Service panel does."""
        from ohmni_tb.foxglove.access import UNLOCK_SERVICE  # noqa: PLC0415

        service_id = None
        while service_id is None:
            message = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(message, str):
                parsed = json.loads(message)
                if parsed.get("op") == "advertiseServices":
                    for service in parsed["services"]:
                        if service["name"] == UNLOCK_SERVICE:
                            service_id = service["id"]
        encoding = b"json"
        request = json.dumps({"token": token}).encode()
        await ws.send(struct.pack("<BIII", 2, service_id, 1, len(encoding)) + encoding + request)
        while True:  # the answer: binary op 3 (a response) or a JSON failure
            message = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(message, bytes) and message[0] == 3:
                return
            if isinstance(message, str) and json.loads(message).get("op") == "serviceCallFailure":
                raise RuntimeError(f"unlock refused: {message}")


def _foxglove(origin: str | None, token: bool, unlock: bool = False) -> Callable[[Sim], Outcome]:
    def run(sim: Sim) -> Outcome:
        from websockets.exceptions import InvalidHandshake  # noqa: PLC0415

        args = ["--foxglove", "0", "--foxglove-control"]
        tmp = None
        if token:
            tmp = tempfile.TemporaryDirectory()
            args += ["--token-file", str(Path(tmp.name) / "token")]
        serve = Serve(sim.path, *args)
        try:
            assert serve.foxglove is not None
            key = (Path(tmp.name) / "token").read_text().strip() if tmp and unlock else None
            drive = _Foxglove.drive(serve.foxglove, origin=origin, seconds=WATCH_S, token=key)
            x0, y0, yaw0 = sim.pose()
            note = ""
            try:
                asyncio.run(drive)
            except (OSError, InvalidHandshake) as exc:  # it may not even watch
                note = f"refused: {exc}"
            time.sleep(0.5)
            x1, y1, yaw1 = sim.pose()
            moved = max(math.hypot(x1 - x0, y1 - y0), abs(yaw1 - yaw0) * 0.165)
            if unlock:  # the control case: the same Twists, from a client that may drive
                return Outcome("(it may drive: it must move)", (moved, math.nan), note, True)
            return Outcome(
                "its first Twist (it may not drive)",
                (moved, 0.0 if moved < LIMIT_M else math.inf),
                note or f"Twists at {1 / COMMAND_PERIOD_S:g} Hz for {WATCH_S:g} s",
            )
        finally:
            serve.close()
            if tmp is not None:
                tmp.cleanup()

    return run


def _slow_tick(sim: Sim) -> Outcome:
    serve = Serve(sim.path)
    try:
        note = asyncio.run(_set_slowest(serve.url))
        driver = Driver(serve.url)
        try:
            note += f"; driving at {_speed(sim):.2f} m/s before"
            driver.proc.send_signal(signal.SIGSTOP)
            last = time.monotonic()
            moved = _moved(sim, last, last + WATCHDOG_S + RAMP_S + MARGIN_S)
        finally:
            driver.close()
        return Outcome(f"last command + watchdog {WATCHDOG_S:g} s + ramp", moved, note)
    finally:
        serve.close()


async def _set_slowest(url: str) -> str:
    from ohmni_tb.client import RobotClient  # noqa: PLC0415
    from ohmni_tb.control.defaults import CONTROL_HZ_RANGE  # noqa: PLC0415
    from ohmni_tb.errors import OhmniError  # noqa: PLC0415

    async with RobotClient.connect(url) as client:
        await client.acquire()
        try:
            client.set_rate("wheel_encoder", 0.1)
            await client.confirm()
            refused = "0.1 Hz accepted"
        except OhmniError as exc:
            refused = f"0.1 Hz refused ({exc})"
        client.set_rate("wheel_encoder", CONTROL_HZ_RANGE[0])
        await client.confirm()
        await client.release()
    return f"{refused}; ran at {CONTROL_HZ_RANGE[0]:g} Hz"


SCENARIOS: dict[str, tuple[str, Callable[[Sim], Outcome]]] = {
    "slow-tick": (
        "the driver asks the slowest control tick, drives, goes silent",
        _slow_tick,
    ),
    "driver-frozen": ("the lease holder is frozen (SIGSTOP) mid-drive", _silent_driver(True)),
    "driver-killed": ("the lease holder is killed mid-drive", _silent_driver(False)),
    "flood": (
        "200 readers flood the daemon; the lease holder is frozen",
        _silent_driver(True, readers=200),
    ),
    "kill-worker": ("kill -9 of the process that runs the Robot", _kill("worker")),
    "kill-serve": ("kill -9 of `ohmni serve` (the supervisor)", _kill("serve")),
    "worker-hung": ("the process that runs the Robot hangs (SIGSTOP)", _kill("hung")),
    "foxglove-page": (
        "a web page (Origin: https://evil.example) sends Teleop Twists",
        _foxglove("https://evil.example", token=False),
    ),
    "foxglove-token": (
        "a Foxglove client that has not unlocked, on a daemon with a token",
        _foxglove(None, token=True),
    ),
    "foxglove-unlocked": (
        "the same client after /tb_control/unlock with the token (the harness sees motion)",
        _foxglove(None, token=True, unlock=True),
    ),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--only", choices=sorted(SCENARIOS), action="append")
    options = parser.parse_args()
    names = options.only or list(SCENARIOS)
    print(
        f"{'scenario':<15} {'must stop by':<48} {'moved after (cm)':>17} "
        f"{'still after (s)':>16}  verdict"
    )
    failed = 0
    for name in names:
        what, run = SCENARIOS[name]
        worst: Outcome | None = None
        for _ in range(options.runs):
            sim = Sim()
            try:
                outcome = run(sim)
            finally:
                sim.close()
            if worst is None or not outcome.passed or outcome.moved_m > worst.moved_m:
                worst = outcome
        assert worst is not None
        verdict = "pass" if worst.passed else "FAIL"
        failed += verdict != "pass"
        print(
            f"{name:<15} {worst.deadline:<48} {worst.moved_m * 100:>17.2f} "
            f"{worst.moved[1]:>16.2f}  {verdict}"
        )
        print(f"{'':<15} {what}{'; ' + worst.note if worst.note else ''}")
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
