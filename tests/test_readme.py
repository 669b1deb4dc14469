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


def test_pyg_example_runs():
    import pytest

    pytest.importorskip("torch_geometric")
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Using `PoserConv`"):text.index("## Scaling out")]
    code = re.findall(r"```python\n(.*?)```", section, re.S)[1]
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    assert ns["poses"].shape[1] == 7
    assert len(ns["graphs_back"]) == 3


def test_reconstruct_example_runs(tmp_path):
    code = _block_after("## From images to camera poses").replace(
        "/tmp/posernet-example", str(tmp_path))
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    assert (tmp_path / "poses.json").is_file()
    assert ns["rec"].graph.num_nodes == 6 and ns["rec"].graph.num_edges > 0


def test_results_sections_quote_the_committed_digests():
    """Each results block of the README (``<!-- results:<scale>:begin -->``) is the runner's own
    digest of the committed run at that scale, verbatim."""
    root = README.parent
    text = README.read_text(encoding="utf-8")
    scales = re.findall(r"<!-- results:(\w+):begin -->", text)
    assert {"paper", "medium"} <= set(scales)
    for scale in scales:
        begin, end = f"<!-- results:{scale}:begin -->", f"<!-- results:{scale}:end -->"
        quoted = text[text.index(begin) + len(begin):text.index(end)].strip()
        digest = (root / "results" / scale / "digest.md").read_text(encoding="utf-8").strip()
        assert quoted == digest, scale
        assert (root / "results" / scale / "summary.md").is_file()
