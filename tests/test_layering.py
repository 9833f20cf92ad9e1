"""The sans-IO layers import no asyncio, no serial and no clock.

``protocol/``, ``control/`` and the codec half of ``herkulex/`` must run anywhere and be
testable without a loop or a port (docs/design: "Layers"). Two checks: a fresh interpreter
imports them and reports what they pulled in or asked for, and their source is scanned.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import pytest

import ohmni_tb

#: Top-level modules a sans-IO module must not import.
FORBIDDEN = frozenset({"asyncio", "serial", "serial_asyncio_fast", "time"})
#: Packages that are sans-IO as a whole.
SANS_IO_PACKAGES = (
    "ohmni_tb.protocol",
    "ohmni_tb.control",
    "ohmni_tb.herkulex",
    "ohmni_tb.capture",
)
#: Modules of those packages that are allowed I/O: the herkulex Servo handle drives the Bus.
IO_MODULES = frozenset({"ohmni_tb.herkulex.servo"})
#: Sans-IO modules of packages that also hold I/O: ``ohmni probe``'s judges.
SANS_IO_EXTRA = ("ohmni_tb.probe.findings",)

SRC = Path(ohmni_tb.__file__).parent


def sans_io_modules() -> list[str]:
    """Every module of the sans-IO packages that exists now (packages included)."""
    names: list[str] = []
    for package in SANS_IO_PACKAGES:
        if importlib.util.find_spec(package) is None:
            continue
        path = SRC.joinpath(*package.split(".")[1:])
        if not (path / "__init__.py").exists():
            # A directory without a package yet (work in progress elsewhere).
            continue
        names.append(package)
        names += [f"{package}.{m.name}" for m in pkgutil.iter_modules([str(path)])]
    names += [name for name in SANS_IO_EXTRA if importlib.util.find_spec(name) is not None]
    return [name for name in names if name not in IO_MODULES]


def source_of(module: str) -> Path:
    path = SRC.joinpath(*module.split(".")[1:])
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


MODULES = sans_io_modules()

# Runs in a fresh interpreter: imports the modules and reports (1) which forbidden
# modules ended up loaded and (2) every import statement an ohmni_tb module executed for a
# forbidden module, even one already loaded (`time` is, by the interpreter itself).
_PROBE = """
import builtins, json, sys
forbidden, modules = set(sys.argv[1].split(",")), sys.argv[2].split(",")
asked = []
real_import = builtins.__import__
def spy(name, globals=None, locals=None, fromlist=(), level=0):
    importer = (globals or {}).get("__name__", "")
    if level == 0 and name.split(".")[0] in forbidden and importer.startswith("ohmni_tb"):
        asked.append([importer, name])
    return real_import(name, globals, locals, fromlist, level)
builtins.__import__ = spy
preloaded = {m for m in forbidden if m in sys.modules}
for module in modules:
    __import__(module)
loaded = sorted(m for m in forbidden if m in sys.modules and m not in preloaded)
print(json.dumps({"loaded": loaded, "asked": asked}))
"""


def test_the_sans_io_packages_exist() -> None:
    assert "ohmni_tb.protocol" in MODULES
    assert "ohmni_tb.protocol.framing" in MODULES
    assert "ohmni_tb.protocol.messages" in MODULES


def test_importing_the_sans_io_layers_pulls_in_no_io() -> None:
    result = subprocess.run(
        [sys.executable, "-c", _PROBE, ",".join(sorted(FORBIDDEN)), ",".join(MODULES)],
        capture_output=True,
        text=True,
        check=False,
        timeout=30,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report == {"loaded": [], "asked": []}


def test_the_probe_sees_a_forbidden_import() -> None:
    # The probe must be able to fail: the transport layer does import asyncio and serial.
    result = subprocess.run(
        [sys.executable, "-c", _PROBE, ",".join(sorted(FORBIDDEN)), "ohmni_tb.transport"],
        capture_output=True,
        text=True,
        check=True,
        timeout=30,
    )
    report = json.loads(result.stdout)
    assert {"asyncio", "serial"} <= set(report["loaded"])
    assert ["ohmni_tb.transport.serial", "serial"] in report["asked"]


def forbidden_imports(source: str) -> list[str]:
    found: list[str] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.split(".")[0] in FORBIDDEN]
        elif (
            isinstance(node, ast.ImportFrom)
            and node.level == 0
            and node.module
            and node.module.split(".")[0] in FORBIDDEN
        ):
            found.append(node.module)
    return found


@pytest.mark.parametrize("module", MODULES)
def test_source_has_no_forbidden_import(module: str) -> None:
    # Also catches imports inside functions, which the import probe cannot see.
    assert forbidden_imports(source_of(module).read_text(encoding="utf-8")) == []


@pytest.mark.parametrize(
    "line",
    ["import time", "from time import monotonic", "import asyncio.tasks", "import serial"],
)
def test_the_scan_sees_a_forbidden_import(line: str) -> None:
    assert forbidden_imports(f"def f() -> None:\n    {line}\n") != []


# -- no import circles ---------------------------------------------------------------------


def _module_names() -> dict[str, Path]:
    """Every module of the package by dotted name (packages by their ``__init__``)."""
    found = {}
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The project's modules ``name`` imports anywhere in its source: at the top, in a
    function, or for type checking only — each is an edge of the module graph."""
    edges: set[str] = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            edges.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                edges.add(sub if sub in modules else base)
    return {edge for edge in edges if edge in modules and edge != name}


def test_the_modules_import_each_other_without_circles() -> None:
    modules = _module_names()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    # Depth-first search for a back edge; the circle it closes is the message.
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(name: str) -> list[str] | None:
        state[name] = 1
        path.append(name)
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                return [*path[path.index(target) :], target]
            if target not in state and (circle := visit(target)) is not None:
                return circle
        path.pop()
        state[name] = 2
        return None

    for name in sorted(graph):
        if name not in state:
            circle = visit(name)
            assert circle is None, "an import circle: " + " -> ".join(circle)


# -- imports go down the layers ------------------------------------------------------------

#: The layers, bottom first: a module may import its own layer's and lower layers' modules,
#: never a higher layer's (docs/design "Layers"). The package's own ``__init__`` (the
#: lazy public names) sits with the client: it re-exports the Robot, never the CLI.
LAYERS: tuple[tuple[str, ...], ...] = (
    (
        "ohmni_tb._checks",
        "ohmni_tb.errors",
        "ohmni_tb._version",
        "ohmni_tb._files",
        "ohmni_tb._ratelimit",
    ),
    (
        "ohmni_tb.protocol",
        "ohmni_tb.control",
        "ohmni_tb.herkulex",
        "ohmni_tb.capture",
        "ohmni_tb.transport",
        "ohmni_tb.sim",
        "ohmni_tb.eventloop",
    ),
    ("ohmni_tb.safety", "ohmni_tb.bus", "ohmni_tb.config", "ohmni_tb.config_file"),
    ("ohmni_tb.robot", "ohmni_tb.probe"),
    (
        "ohmni_tb.client",
        "ohmni_tb.daemon",
        "ohmni_tb.foxglove",
        "ohmni_tb.mqtt",
        "ohmni_tb.fleet",
        "ohmni_tb.monitor",
        "ohmni_tb",
    ),
    ("ohmni_tb.cli", "ohmni_tb.__main__"),
)


def layer_of(module: str) -> int:
    """The layer ``module`` belongs to: the one naming it or the package it is in
    (``ohmni_tb`` itself names the package's ``__init__`` only)."""
    for index, prefixes in enumerate(LAYERS):
        for prefix in prefixes:
            inside = prefix != "ohmni_tb" and module.startswith(prefix + ".")
            if module == prefix or inside:
                return index
    raise AssertionError(f"{module} is in no layer: place it in LAYERS")


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    return sorted(
        f"{name} (layer {layer_of(name)}) imports {target} (layer {layer_of(target)})"
        for name, targets in graph.items()
        for target in targets
        if layer_of(target) > layer_of(name)
    )


def test_imports_only_go_down_the_layers() -> None:
    modules = _module_names()
    graph = {name: _imports(name, path, modules) for name, path in modules.items()}
    assert upward_imports(graph) == []


def test_the_layer_rule_sees_an_upward_import() -> None:
    graph = {"ohmni_tb.robot.core": {"ohmni_tb.foxglove.bridge"}, "ohmni_tb.foxglove.bridge": set()}
    assert upward_imports(graph) == [
        "ohmni_tb.robot.core (layer 3) imports ohmni_tb.foxglove.bridge (layer 4)"
    ]
    with pytest.raises(AssertionError, match=r"ohmni_tb\.nowhere is in no layer"):
        layer_of("ohmni_tb.nowhere")
