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


def test_results_section_quotes_the_committed_digest():
    """The README's results are the runner's own digest of the committed run, verbatim."""
    root = README.parent
    text = README.read_text(encoding="utf-8")
    begin, end = "<!-- results:medium:begin -->", "<!-- results:medium:end -->"
    quoted = text[text.index(begin) + len(begin):text.index(end)].strip()
    digest = (root / "results" / "medium" / "digest.md").read_text(encoding="utf-8").strip()
    assert quoted == digest
    assert (root / "results" / "medium" / "summary.md").is_file()
