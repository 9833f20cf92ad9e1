"""docs/fleet.md's examples run as written, against a real broker (``mqtt://localhost:1883``
in the page is the test's Mosquitto) with robot ``kitchen`` served: its Python, and its
``ohmni`` commands marked ``needs a broker``."""

from __future__ import annotations

import asyncio
import re
import shlex
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ohmni_tb.cli import app

from ._helpers import served
from .conftest import Mosquitto

PAGE = Path(__file__).resolve().parents[2] / "docs" / "fleet.md"
TEXT = PAGE.read_text(encoding="utf-8")
_SHOWN_URL = "mqtt://localhost:1883"


@pytest.fixture
def kitchen(broker: Mosquitto) -> Iterator[str]:
    """Robot ``kitchen`` served with its bridge, in a thread of its own (the examples run
    their own event loops); the broker's URL."""
    ready = threading.Event()
    stop: asyncio.Event | None = None
    loop: asyncio.AbstractEventLoop | None = None

    async def serve() -> None:
        nonlocal stop, loop
        stop, loop = asyncio.Event(), asyncio.get_running_loop()
        async with served(broker.url, "kitchen"):
            ready.set()
            await stop.wait()

    thread = threading.Thread(target=asyncio.run, args=(serve(),))
    thread.start()
    try:
        assert ready.wait(20), "robot kitchen did not come online"
        yield broker.url
    finally:
        if loop is not None and stop is not None:
            loop.call_soon_threadsafe(stop.set)
        thread.join(20)


def test_the_python_examples_run(kitchen: str, capsys: pytest.CaptureFixture[str]) -> None:
    blocks = re.findall(r"```python\n(.*?)```", TEXT, re.S)
    assert blocks
    for index, code in enumerate(blocks):
        namespace: dict[str, object] = {"__name__": "__main__"}
        exec(
            compile(code.replace(_SHOWN_URL, kitchen), f"fleet.md block {index}", "exec"), namespace
        )  # the docs are ours
    out = capsys.readouterr().out
    assert out.startswith("kitchen True ")


def test_the_commands_that_need_a_broker_run(kitchen: str) -> None:
    """Every ``ohmni`` command the docs mark ``needs a broker`` (but not ``until Ctrl-C``)."""
    shown = [
        line.split(" #")[0]
        for page in sorted(PAGE.parent.glob("*.md"))
        for line in re.findall(r"^ohmni [^\n]*# needs a broker[^\n]*$", page.read_text(), re.M)
        if "until Ctrl-C" not in line
    ]
    assert len(shown) >= 3
    for line in shown:
        argv = shlex.split(line.replace(_SHOWN_URL, kitchen))[1:]
        result = CliRunner().invoke(app, argv, env={"COLUMNS": "120"})
        assert result.exit_code == 0, f"{line}\n{result.output}"
        assert "kitchen" in result.stdout
