"""docs/control.md's plots of the limits are what the code makes today.

``docs/plots/limits.py`` runs the real limiter (and a Robot on ``sim://`` in virtual time)
and writes the SVG files docs/control.md shows; run again into a temporary directory, it
must write the committed files exactly. When the limiter changes on purpose, run
``python docs/plots/limits.py`` and commit the new plots.
"""

from __future__ import annotations

import importlib.util
import sys
import xml.etree.ElementTree as ET
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "docs" / "plots" / "limits.py"
IMAGES = ROOT / "docs" / "img"


def load_script() -> ModuleType:
    """docs/plots/limits.py (not a package, and not on the path when testing)."""
    spec = importlib.util.spec_from_file_location("limits_plots", SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[spec.name]
    return module


def test_the_committed_plots_are_what_the_code_makes(tmp_path: Path) -> None:
    written: list[Path] = load_script().write_all(tmp_path)
    assert [path.name for path in written] == [
        "limits-accel-brake.svg",
        "limits-reversal.svg",
        "limits-jerk.svg",
        "limits-saturation.svg",
    ]
    stale = [
        path.name
        for path in written
        if not (IMAGES / path.name).exists()
        or (IMAGES / path.name).read_text(encoding="utf-8") != path.read_text(encoding="utf-8")
    ]
    assert not stale, f"regenerate with `python docs/plots/limits.py`: {stale}"
    page = (ROOT / "docs" / "control.md").read_text(encoding="utf-8")
    for path in written:
        root = ET.parse(path).getroot()  # well-formed, so a browser draws it
        assert root.tag == "{http://www.w3.org/2000/svg}svg"
        assert f"](img/{path.name})" in page, f"docs/control.md does not show {path.name}"
