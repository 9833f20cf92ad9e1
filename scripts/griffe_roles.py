"""A griffe extension for the docs site (mkdocs.yml): the docstrings' Sphinx habits in
Markdown.

The code's docstrings name other objects the way Sphinx does (``:class:`~ohmni_tb.x.Y```,
``:meth:`open```) and introduce an example with ``::``. mkdocstrings renders Markdown, so
here each role becomes the object's name in code, linked to its page where the site
documents it (an *optional* cross-reference: a name the site does not document stays
plain code and fails nothing), and a ``::`` before an indented block becomes ``:``.
"""

from __future__ import annotations

import re
from html import escape
from typing import Any

from griffe import Extension, Object

_ROLE = re.compile(r":(?:class|meth|func|mod|attr|data|exc|obj|const):`(?P<target>[^`]+)`")
_LITERAL = re.compile(r"::\n(?=\n[ \t]+\S)")


def _link(obj: Object, target: str) -> str:
    titled = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^<>]+)>", target)
    if titled:
        shown, target = titled["title"], titled["target"]
    else:
        shown = target
    if target.startswith("~"):
        target = target[1:]
        shown = target.rsplit(".", 1)[-1]
    target = target.rstrip("()")
    if not target.startswith("ohmni_tb."):
        # Relative, as Sphinx resolves it: a member of this object's class, else a name in
        # its module.
        scope = obj if obj.is_class else obj.parent
        if scope is not None and scope.is_class and "." not in target:
            target = f"{scope.path}.{target}"
        else:
            target = f"{obj.module.path}.{target}"
    return f'<autoref identifier="{escape(target)}" optional><code>{escape(shown)}</code></autoref>'


def markdown(obj: Object, text: str) -> str:
    """``text`` with Sphinx roles as optional cross-references and ``::`` as ``:``."""
    text = _ROLE.sub(lambda m: _link(obj, m["target"]), text)
    return _LITERAL.sub(":\n", text)


class SphinxRoles(Extension):
    """Rewrites every docstring griffe loads (see the module docstring)."""

    def on_instance(self, *, obj: Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown(obj, obj.docstring.value)
