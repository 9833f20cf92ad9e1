"""What the status and robot-command tests share: running ``ohmni``, watching the ports
the Robot opens, and ``ohmni sim --pty`` in a subprocess."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app, common
from ohmni_tb.sim.robot import SimRobot
from ohmni_tb.transport import Transport, open_transport

runner = CliRunner()
#: Wide enough that rich wraps nothing a test looks for.
WIDE = {"COLUMNS": "200"}


@dataclass
class Result:
    code: int
    out: str  # stdout and stderr
    stdout: str


def invoke(*args: str, env: dict[str, str] | None = None) -> Result:
    result = runner.invoke(app, list(args), env={**WIDE, **(env or {})})
    assert result.exception is None or isinstance(result.exception, SystemExit), (
        result.output,
        result.exception,
    )
    return Result(result.exit_code, result.output, result.stdout)


def words(text: str) -> str:
    """The output with rich's boxes and line wrapping undone."""
    return " ".join(text.replace("│", " ").split())


@dataclass
class Opened:
    """Every port the commands opened (the Robot's and the raw bus's)."""

    urls: list[str] = field(default_factory=list)
    sims: list[SimRobot] = field(default_factory=list)
    transports: list[Transport] = field(default_factory=list)


def spy_on_ports(
    monkeypatch: pytest.MonkeyPatch, setup: Callable[[SimRobot], None] | None = None
) -> Opened:
    """Record what the CLI opens; ``setup`` prepares each simulated robot before use."""
    opened = Opened()

    async def spy(url: str) -> Transport:
        transport = await open_transport(url)
        opened.urls.append(url)
        opened.transports.append(transport)
        sim: Any = getattr(transport, "robot", None)
        if isinstance(sim, SimRobot):
            opened.sims.append(sim)
            if setup is not None:
                setup(sim)
        return transport

    monkeypatch.setattr("ohmni_tb.robot.core.open_transport", spy)
    monkeypatch.setattr(common, "open_transport", spy)
    return opened


def can_open_pty() -> bool:
    if not hasattr(os, "openpty"):
        return False
    try:
        master, slave = os.openpty()
    except OSError:
        return False
    os.close(master)
    os.close(slave)
    return True


needs_pty = pytest.mark.skipif(not can_open_pty(), reason="needs pseudo-terminals")
_START_TIMEOUT_S = 30.0


@contextmanager
def sim_on_pty(*args: str) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """``ohmni sim --pty`` in a subprocess: its device path and the process (stdin a
    pipe for operator commands); stopped with SIGINT afterwards."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "ohmni_tb", "sim", "--pty", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        assert proc.stdout is not None
        fd = proc.stdout.fileno()
        deadline = time.monotonic() + _START_TIMEOUT_S
        line = b""
        while not line.endswith(b"\n"):
            ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            assert ready, "ohmni sim --pty printed no device path"
            chunk = os.read(fd, 1)
            assert chunk, "ohmni sim --pty ended early"
            line += chunk
        yield line.decode().strip(), proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        for stream in (proc.stdin, proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()


def operator(proc: subprocess.Popen[bytes], command: str) -> None:
    """Type a command on the simulator's stdin; return once it has answered ``ok``."""
    assert proc.stdin is not None
    assert proc.stderr is not None
    proc.stdin.write(command.encode() + b"\n")
    proc.stdin.flush()
    fd = proc.stderr.fileno()
    deadline = time.monotonic() + _START_TIMEOUT_S
    said = b""
    while not said.endswith(b"ok\n"):
        ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
        assert ready, f"the simulator did not answer {command!r}: {said!r}"
        chunk = os.read(fd, 4096)
        assert chunk, f"the simulator ended: {said!r}"
        said += chunk
