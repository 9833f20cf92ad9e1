"""Fixtures for every test: leak checks, the in-memory line, and opt-in hardware tests.

Hardware-in-the-loop tests carry ``@pytest.mark.hardware`` and run only when a port is
given (``pytest --ohmni-port=/dev/ttyUSB0``); they get the port from the ``ohmni_port``
fixture. Everything else runs against fakes and the simulator.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from hypothesis import settings

from ohmni_tb import eventloop
from ohmni_tb.sim.clock import VirtualClockLoop
from ohmni_tb.transport import MemoryTransport

# CI (CI=true) replays the same examples every run, so a landing is never decided by a
# newly drawn example; developers' runs keep drawing new ones and find new bugs.
settings.register_profile("ci", derandomize=True)
if os.environ.get("CI"):
    settings.load_profile("ci")

# pytest-xdist's workers start with COLUMNS/LINES set to 80x24, and rich fixes a console's
# width when it is created with COLUMNS set: the CLI's console, created at import, would then
# ignore the width each CliRunner call asks for. The tests set the width per call instead.
for _name in ("COLUMNS", "LINES"):
    os.environ.pop(_name, None)

_PORT_OPTION = "--ohmni-port"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        _PORT_OPTION,
        action="store",
        default=None,
        metavar="PATH",
        help="serial port of a real Ohmni robot; enables tests marked 'hardware'",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption(_PORT_OPTION):
        return
    skip = pytest.mark.skip(reason=f"needs a robot: pass {_PORT_OPTION}=/dev/ttyUSB0")
    for item in items:
        if item.get_closest_marker("hardware") is not None:
            item.add_marker(skip)


@pytest.fixture
def ohmni_port(request: pytest.FixtureRequest) -> str:
    """The serial port given with ``--ohmni-port`` (the test is skipped without one)."""
    port: str | None = request.config.getoption(_PORT_OPTION)
    if not port:
        pytest.skip(f"needs a robot: pass {_PORT_OPTION}=/dev/ttyUSB0")
    return port


@pytest.fixture(autouse=True)
def _no_leaked_tasks(request: pytest.FixtureRequest) -> None:
    """Fail an async test that leaves a task it created still running."""
    if request.node.get_closest_marker("asyncio") is not None:
        request.getfixturevalue("_task_leak_check")


@pytest.fixture
async def _task_leak_check(request: pytest.FixtureRequest) -> AsyncIterator[None]:
    # Set up before, and so torn down after, every other fixture of the test: tasks
    # that a fixture starts and stops are not leaks.
    before = asyncio.all_tasks()
    yield
    # One pass of the loop lets a task that was cancelled but not awaited finish.
    await asyncio.sleep(0)
    leaked = asyncio.all_tasks() - before - {asyncio.current_task()}
    if not leaked:
        return
    for task in leaked:
        task.cancel()
    await asyncio.wait(leaked)
    names = sorted(task.get_name() for task in leaked)
    pytest.fail(f"{request.node.nodeid} left {len(leaked)} task(s) running: {names}")


@pytest.fixture
async def memory_pair() -> AsyncIterator[tuple[MemoryTransport, MemoryTransport]]:
    """A connected (host, device) in-memory pipe, both ends closed after the test."""
    host, device = MemoryTransport.pair("test")
    yield host, device
    await host.aclose()
    await device.aclose()


@pytest.fixture
def hermetic(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No OHMNI_* variable, an empty XDG config dir, and an empty working directory (its
    path): the settings of the machine running the tests do not reach the test."""
    for name in list(os.environ):
        if name.upper().startswith("OHMNI_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    return work


@pytest.fixture
def virtual_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """Commands run in the test's process (``ohmni ...`` through typer's
    CliRunner, :func:`ohmni_tb.run`) go on the simulator's virtual clock
    (:mod:`ohmni_tb.sim.clock`): their waits take no wall time, and what they time is
    exact. For commands on ``sim://`` only: a pseudo-terminal, a subprocess or a thread
    keeps real time, so a test that has one does not ask for this."""
    monkeypatch.setattr(eventloop, "new_event_loop", VirtualClockLoop)


@pytest.fixture(autouse=True)
def _no_daemon_unless_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    """The commands go through ``ohmni serve`` when one answers on this machine: not in
    tests (a developer's own daemon must not answer them), except where a test sets
    ``OHMNI_DAEMON_URL`` to the daemon it started."""
    monkeypatch.setenv("OHMNI_DAEMON_URL", "off")
