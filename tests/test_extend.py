"""docs/extend.md's examples: a custom editor, scheduler and density strategy, each plugged
into a whole edit through the public API, run as the page shows them."""

import re
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "extend.md"


def _blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", PAGE.read_text(), flags=re.S)


def test_the_page_has_a_setup_and_three_examples_of_at_most_30_lines():
    blocks = _blocks()
    assert len(blocks) == 4
    # each example's own definitions (the plug-in), without the lines that run and check it
    for block in blocks[1:]:
        definition = block.split("\n\n\n")[0]
        assert len(definition.strip().splitlines()) <= 30, definition


def test_the_examples_run_as_written():
    namespace: dict = {}
    for block in _blocks():
        exec(compile(block, str(PAGE), "exec"), namespace)  # noqa: S102 - our own page
