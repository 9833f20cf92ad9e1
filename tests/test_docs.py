"""Every example in the README and docs/ runs as written (against the simulator).

Python: every ```python block runs on its own, in a fresh namespace, as a reader who
pastes that one block would run it (the blocks of a page in the page's order, so a file an
earlier block wrote is there). The examples in module docstrings listed below run too.

Commands: every ``ohmni …`` command a page shows in a code block — each line of a ```sh
block, each ``$ ohmni …`` line of any other block — runs through the CLI in this process,
on the simulator's virtual time, and must end with exit code 0, or with the code its
comment names (``# exit 2``). The commands of one section of a page (a ``## `` heading) run
in order in one fresh directory, with a config directory of their own (``XDG_CONFIG_HOME``)
and no daemon, as a reader who jumped to that section would run them in a new shell: a
file a command reads is one an earlier command of the section wrote. What is cut off: a
pipe (``| head -3``) and a redirection (``> out.json``, ``< /dev/null``).

A command is shown but not run when it cannot run on ``sim://`` here, and says why:

- its port is a device (``--port /dev/ttyUSB0``, ``/dev/pts/5``, ``serial://…``): it needs
  the robot, or a simulator served on a pty;
- its comment says ``needs a terminal`` (the keyboard teleop, which reads keys);
- its comment says ``needs ohmni serve`` (it talks to a daemon that runs meanwhile, such
  as ``ohmni serve --handoff 60``, or a command without ``--port`` shown going through one);
- its comment says ``until Ctrl-C`` (it serves or streams until stopped: ``ohmni serve``,
  ``ohmni sim --pty``).
- its comment says ``needs a broker`` (an MQTT broker: ``tests/mqtt/test_fleet_docs.py``
  runs those against Mosquitto).

A command written inline in a sentence is not run, only parsed
(:func:`test_doc_commands_parse_as_written`, which also parses every command above).
"""

from __future__ import annotations

import asyncio
import importlib
import os
import re
import shlex
import textwrap
from dataclasses import dataclass
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
#: Pages whose examples need an MQTT broker: ``tests/mqtt/test_fleet_docs.py`` runs them
#: against Mosquitto.
BROKER_PAGES = frozenset({"docs/fleet.md"})


@pytest.mark.parametrize(
    "page", sorted(name for name, blocks in PAGES.items() if blocks and name not in BROKER_PAGES)
)
def test_doc_examples_run(
    page: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    if page not in REAL_TIME_PAGES:
        monkeypatch.setattr(asyncio, "run", run_virtual)
        monkeypatch.setattr(eventloop, "new_event_loop", VirtualClockLoop)
    for i, code in enumerate(PAGES[page]):
        namespace: dict[str, object] = {"__name__": "__main__"}
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


_FENCE = re.compile(r"^```(?P<lang>[\w-]*)\n(?P<body>.*?)^```", re.S | re.M)
#: A device port: the command needs the robot (or a simulator on a pty).
_DEVICE_PORT = re.compile(r"(?:^|\s)(?:/dev/\S+|'?serial://\S+)")
#: What a comment says when its command is shown but not run (module docstring).
NOT_RUN = ("needs a terminal", "needs ohmni serve", "until Ctrl-C", "needs a broker")
_EXIT = re.compile(r"\bexit (?P<code>\d+)\b")
_ASSIGNMENT = re.compile(r"[A-Z_][A-Z0-9_]*=\S*")


@dataclass(frozen=True)
class ShownCommand:
    """One ``ohmni`` command of a page's code blocks, as a reader would type it."""

    page: str
    line: str  #: as written, comment and all
    argv: tuple[str, ...]  #: the words after ``ohmni``, pipe and redirections cut off
    comment: str
    exit_code: int  #: the code its comment names, else 0
    env: tuple[tuple[str, str], ...] = ()  #: ``NAME=value`` before ``ohmni``

    @property
    def why_not_run(self) -> str | None:
        """Why the test does not run it (module docstring), or ``None``."""
        command = shlex.join(self.argv)
        if _DEVICE_PORT.search(command):
            return "needs the robot"
        return next((tag for tag in NOT_RUN if tag in self.comment), None)


def _shown_command(page: str, line: str) -> ShownCommand | None:
    text = line.strip().removeprefix("$ ")
    command, _, comment = text.partition(" #")
    for cut in (" | ", " > ", " < "):
        command = command.split(cut)[0]
    words = shlex.split(command)
    env = {}
    while words and _ASSIGNMENT.fullmatch(words[0]):
        name, _, value = words.pop(0).partition("=")
        env[name] = value
    if words[:1] != ["ohmni"]:
        return None
    code = _EXIT.search(comment)
    exit_code = int(code["code"]) if code else 0
    return ShownCommand(page, line, tuple(words[1:]), comment, exit_code, tuple(env.items()))


def page_commands(path: Path) -> dict[str, list[ShownCommand]]:
    """The ``ohmni`` commands of ``path``'s code blocks by section (``## `` heading; ``""``
    before the first), in the page's order."""
    page = str(path.relative_to(ROOT))
    found: dict[str, list[ShownCommand]] = {}
    intro, *sections = re.split(r"^## ", path.read_text(encoding="utf-8"), flags=re.M)
    for section in ["\n" + intro, *sections]:
        heading, _, body = section.partition("\n")
        for fence in _FENCE.finditer(body):
            for line in fence["body"].splitlines():
                if fence["lang"] != "sh" and not line.startswith("$ "):
                    continue
                shown = _shown_command(page, line)
                if shown is not None:
                    found.setdefault(heading, []).append(shown)
    return found


#: (page, section) → the commands it shows.
COMMAND_SECTIONS = {
    (str(path.relative_to(ROOT)), heading): commands
    for path in DOCS
    for heading, commands in page_commands(path).items()
}
COMMAND_PAGES = {
    page: [c for (p, _), cs in COMMAND_SECTIONS.items() if p == page for c in cs]
    for page, _ in COMMAND_SECTIONS
}


def test_the_shown_commands_are_found_and_classified() -> None:
    # The check must see the commands, or it would pass on none.
    readme = COMMAND_PAGES["README.md"]
    assert any(c.argv[:2] == ("status", "--port") for c in readme)
    shown = _shown_command("x", "$ ohmni neck --raw 700 --port sim://   # exit 1")
    assert shown is not None
    assert shown.argv == ("neck", "--raw", "700", "--port", "sim://")
    assert shown.exit_code == 1
    assert shown.why_not_run is None
    piped = _shown_command("x", "ohmni odom --json --port sim:// | head -3 > x.ndjson")
    assert piped is not None
    assert piped.argv == ("odom", "--json", "--port", "sim://")
    on_robot = _shown_command("x", "ohmni probe --port /dev/ttyUSB0")
    assert on_robot is not None
    assert on_robot.why_not_run == "needs the robot"
    serving = _shown_command("x", "ohmni sim --pty    # prints /dev/pts/5, then until Ctrl-C")
    assert serving is not None
    assert serving.why_not_run == "until Ctrl-C"
    assert _shown_command("x", "setprop ctl.stop tb-node") is None
    with_env = _shown_command("x", "OHMNI_WATCHDOG_S=0.3 ohmni config --changed")
    assert with_env is not None
    assert with_env.env == (("OHMNI_WATCHDOG_S", "0.3"),)


def test_few_commands_are_shown_without_running() -> None:
    commands = [c for cs in COMMAND_PAGES.values() for c in cs]
    # (The commands that need a broker run too, in tests/mqtt/test_fleet_docs.py.)
    run_elsewhere = (None, "needs the robot", "needs a broker")
    marked = [c for c in commands if c.why_not_run not in run_elsewhere]
    assert len(marked) <= len(commands) // 10, [c.line for c in marked]


@pytest.mark.usefixtures("virtual_time")
@pytest.mark.parametrize(
    ("page", "section"),
    [key for key, cs in COMMAND_SECTIONS.items() if any(c.why_not_run is None for c in cs)],
    ids=lambda part: part or "top",
)
def test_doc_commands_run_on_the_simulator(
    page: str, section: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    for name in list(os.environ):
        if name.startswith("OHMNI_") and name != "OHMNI_DAEMON_URL":
            monkeypatch.delenv(name)
    env = {"XDG_CONFIG_HOME": str(tmp_path / "config"), "COLUMNS": "200"}
    runner = CliRunner()
    for shown in COMMAND_SECTIONS[page, section]:
        if shown.why_not_run is not None:
            continue
        result = runner.invoke(app, list(shown.argv), env={**env, **dict(shown.env)})
        assert result.exception is None or isinstance(result.exception, SystemExit), (
            f"{page}: {shown.line}\n{result.output}"
        )
        assert result.exit_code == shown.exit_code, f"{page}: {shown.line}\n{result.output}"


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
