"""Every ```python block in the README and docs/ runs as written (against the simulator).

The blocks of one page run in order in one namespace, as a reader pasting them into one
session would. The examples in module docstrings listed below run too.
"""

from __future__ import annotations

import asyncio
import importlib
import re
import shlex
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from ohmni_tb import eventloop
from ohmni_tb.cli import app
from ohmni_tb.protocol import BROADCAST_ID, PacketDecoder
from ohmni_tb.sim.clock import VirtualClockLoop, run_virtual

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_BLOCK = re.compile(r"```python\n(.*?)```", re.S)
PAGES = {
    str(path.relative_to(ROOT)): _BLOCK.findall(path.read_text(encoding="utf-8")) for path in DOCS
}


def test_docs_have_examples() -> None:
    with_examples = {name for name, blocks in PAGES.items() if blocks}
    assert {"README.md", "docs/herkulex.md", "docs/protocol.md", "docs/index.md"} <= with_examples


#: Pages whose examples serve the robot to other programs (the daemon, the Foxglove app's
#: threads): they keep real time. The others run on the simulator's virtual time.
REAL_TIME_PAGES = frozenset({"docs/daemon.md", "docs/foxglove.md"})


@pytest.mark.parametrize("page", sorted(name for name, blocks in PAGES.items() if blocks))
def test_doc_examples_run(
    page: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    if page not in REAL_TIME_PAGES:
        monkeypatch.setattr(asyncio, "run", run_virtual)
        monkeypatch.setattr(eventloop, "new_event_loop", VirtualClockLoop)
    namespace: dict[str, object] = {"__name__": "__main__"}
    for i, code in enumerate(PAGES[page]):
        # asyncio.run inside a block is fine: the test itself is synchronous.
        exec(compile(code, f"{page} block {i}", "exec"), namespace)  # the docs are ours
    capsys.readouterr()


#: Modules whose docstring's first ``::`` block is an example a reader would paste.
DOCSTRING_EXAMPLES = ["ohmni_tb.herkulex", "ohmni_tb.herkulex.servo", "ohmni_tb.probe"]


def docstring_example(module: str) -> str:
    """The indented block after the first ``::`` of ``module``'s docstring."""
    doc = importlib.import_module(module).__doc__ or ""
    _, marker, rest = doc.partition("::\n")
    assert marker, f"{module} has no :: example"
    lines: list[str] = []
    for line in rest.splitlines():
        if line.strip() and not line.startswith(" "):
            break
        lines.append(line)
    return textwrap.dedent("\n".join(lines)).strip() + "\n"


def test_docstring_example_extraction_stops_at_the_text() -> None:
    code = docstring_example("ohmni_tb.herkulex")
    assert code.startswith("from ohmni_tb.herkulex import")
    assert "Whether a request" not in code


@pytest.mark.parametrize("module", DOCSTRING_EXAMPLES)
def test_docstring_examples_run(module: str, capsys: pytest.CaptureFixture[str]) -> None:
    namespace: dict[str, object] = {"__name__": "__main__"}
    exec(compile(docstring_example(module), f"{module} docstring", "exec"), namespace)  # ours
    assert capsys.readouterr().out


_SH_BLOCK = re.compile(r"```sh\n(.*?)```", re.S)
_INLINE = re.compile(r"`(ohmni [^`]*)`")
#: Marks of a synopsis rather than a command: options in brackets, alternatives, "…".
_PLACEHOLDER = re.compile(r"[\[\]|<>…]|\.\.\.|\b[A-Z]{2,}\b")


def shell_commands() -> list[tuple[str, str]]:
    """Every ``ohmni …`` command a page shows in a sh block or inline, as written."""
    found: list[tuple[str, str]] = []
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        lines = [ln for block in _SH_BLOCK.findall(text) for ln in block.splitlines()]
        lines += _INLINE.findall(text)
        for line in lines:
            command = line.split(" #")[0].split(" > ")[0].strip()
            if command.startswith("ohmni ") and not _PLACEHOLDER.search(command):
                found.append((str(path.relative_to(ROOT)), command))
    return found


def test_docs_show_commands_with_a_port() -> None:
    assert any("--port" in command for _, command in shell_commands())


@pytest.mark.parametrize(("page", "command"), shell_commands())
def test_doc_commands_parse_as_written(page: str, command: str) -> None:
    # --help after the words: the CLI parses every option and argument's place, then stops
    # before opening a port. An option given to the wrong command fails here.
    result = CliRunner().invoke(app, [*shlex.split(command)[1:], "--help"])
    assert result.exit_code == 0, f"{page}: {command}\n{result.output}"


_WORKED_EXAMPLE = re.compile(r"^(?P<label>\S.*?)\s{2,}(?P<hex>FF FF(?: [0-9A-F]{2})+)$", re.M)


def test_protocol_worked_examples_name_the_sid_they_carry() -> None:
    text = (ROOT / "docs" / "protocol.md").read_text(encoding="utf-8")
    examples = _WORKED_EXAMPLE.findall(text)
    assert len(examples) >= 4
    for label, wire_hex in examples:
        (packet,) = PacketDecoder().feed(bytes.fromhex(wire_hex))
        if "broadcast" in label:
            assert packet.sid == BROADCAST_ID, label
        named = re.search(r"\bsid (?:0x)?([0-9A-F]{2})\b", label)
        if named:
            assert packet.sid == int(named.group(1), 16), label


_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(ROOT)))
def test_docs_point_only_at_files_that_exist(path: Path) -> None:
    text = path.read_text(encoding="utf-8")
    # The project's notes outside the repository are not shipped with it.
    assert "../shared" not in text
    for target in _LINK.findall(text):
        if "://" not in target and not target.startswith("mailto:"):
            assert (path.parent / target).exists(), f"{path.name}: {target}"
