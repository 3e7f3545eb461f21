"""A griffe extension for the API reference: Sphinx roles in the docstrings as code spans.

jaxedit's docstrings cross-reference with Sphinx roles (``:func:`run_edit```,
``:class:`~jaxedit.train.TrainConfig```), which Markdown would show literally. This rewrites
each role to a code span of its target (the last component for a ``~`` target), leaving the
docstrings themselves as they are.
"""

from __future__ import annotations

import re

import griffe

ROLE = re.compile(r":(?:py:)?(?:mod|func|class|meth|attr|data|exc|obj|const|ref|doc):`([^`]+)`")


def _target(match: re.Match) -> str:
    text = match.group(1)
    if "<" in text and text.endswith(">"):  # :role:`title <target>`
        text = text[: text.index("<")].strip()
    if text.startswith("~"):
        text = text[1:].rsplit(".", 1)[-1]
    return f"``{text}``"


class SphinxRoles(griffe.Extension):
    """Rewrite ``:role:`target``` to ````target```` in every docstring."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None and ":" in obj.docstring.value:
            obj.docstring.value = ROLE.sub(_target, obj.docstring.value)
