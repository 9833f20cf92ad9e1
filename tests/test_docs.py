"""Every ```python block in the README and docs/ runs as written (against the simulator).

The blocks of one page run in order in one namespace, as a reader pasting them into one
session would.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_BLOCK = re.compile(r"```python\n(.*?)```", re.S)
PAGES = {
    str(path.relative_to(ROOT)): _BLOCK.findall(path.read_text(encoding="utf-8")) for path in DOCS
}


def test_docs_have_examples() -> None:
    with_examples = {name for name, blocks in PAGES.items() if blocks}
    assert {"README.md", "docs/herkulex.md", "docs/protocol.md", "docs/index.md"} <= with_examples


@pytest.mark.parametrize("page", sorted(name for name, blocks in PAGES.items() if blocks))
def test_doc_examples_run(page: str, capsys: pytest.CaptureFixture[str]) -> None:
    namespace: dict[str, object] = {"__name__": "__main__"}
    for i, code in enumerate(PAGES[page]):
        # asyncio.run inside a block is fine: the test itself is synchronous.
        exec(compile(code, f"{page} block {i}", "exec"), namespace)  # the docs are ours
    capsys.readouterr()
