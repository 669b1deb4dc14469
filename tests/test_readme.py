"""The README's code examples run as written."""

from __future__ import annotations

import re
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _block_after(heading: str) -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index(heading):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_poserconv_example_runs():
    ns: dict = {}
    exec(compile(_block_after("## Using `PoserConv`"), "README.md", "exec"), ns)
    assert ns["out"].x.shape == (3, 32)
    assert ns["out"].edge_pose.shape == (2, 7)
