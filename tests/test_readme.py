"""The README's code examples run as written, the results quoted in the docs are the committed
digests, the README stays short, and every relative link in the README and docs/ resolves."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
RESULTS_DOC = DOCS / "results.md"


def _section(heading: str, path: Path = README) -> str:
    """The lines from the one starting with ``heading`` to the next heading of the same or a
    higher level (lines inside code blocks are not headings)."""
    level = len(heading) - len(heading.lstrip("#"))
    out: list[str] = []
    fence = False
    for line in path.read_text(encoding="utf-8").splitlines(keepends=True):
        if out and not fence and re.match(rf"#{{1,{level}}} ", line):
            break
        if out or line.startswith(heading):
            out.append(line)
        if line.startswith("```"):
            fence = not fence
    assert out, f"{path.name}: no heading {heading!r}"
    return "".join(out)


def _block_after(heading: str) -> str:
    return re.search(r"```python\n(.*?)```", _section(heading), re.S).group(1)


def test_poserconv_example_runs():
    ns: dict = {}
    exec(compile(_block_after("## Using `PoserConv`"), "README.md", "exec"), ns)
    assert ns["out"].x.shape == (3, 32)
    assert ns["out"].edge_pose.shape == (2, 7)


def test_pyg_example_runs():
    import pytest

    pytest.importorskip("torch_geometric")
    code = re.findall(r"```python\n(.*?)```", _section("## Using `PoserConv`"), re.S)[1]
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    assert ns["poses"].shape[1] == 7
    assert len(ns["graphs_back"]) == 3


def test_pyg_example_trains_the_gcn():
    """The GCN of the PyG example gets node features that are not all zero, so a loss on
    PoserConv's output gives every one of its parameters a non-zero gradient."""
    import pytest

    pytest.importorskip("torch_geometric")
    code = re.findall(r"```python\n(.*?)```", _section("## Using `PoserConv`"), re.S)[1]
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    ns["out"].edge_pose.square().sum().backward()
    for name, p in ns["gcn"].named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_reconstruct_example_runs(tmp_path):
    code = _block_after("## Quick start from Python").replace(
        "/tmp/posernet-example", str(tmp_path))
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    assert (tmp_path / "poses.json").is_file()
    assert ns["rec"].graph.num_nodes == 6 and ns["rec"].graph.num_edges > 0


def test_refine_example_runs(capsys):
    """Loading a checkpoint by name and refining view graphs in plain Python."""
    ns: dict = {}
    exec(compile(_block_after("### Refining view graphs from Python"), "README.md", "exec"), ns)
    graph = ns["graphs"][0]
    assert ns["refined"].shape == (graph.num_edges, 7)
    assert ns["cameras"].shape == (graph.num_nodes, 4, 4)
    printed = capsys.readouterr().out.splitlines()
    assert [ln.split()[0] for ln in printed] == ["initial", "refined"]


def test_results_sections_quote_the_committed_digests():
    """Each results block of docs/results.md (``<!-- results:<scale>:begin -->``) is the
    runner's own digest of the committed run at that scale, verbatim."""
    text = RESULTS_DOC.read_text(encoding="utf-8")
    scales = re.findall(r"<!-- results:(\w+):begin -->", text)
    assert {"paper", "medium"} <= set(scales)
    for scale in scales:
        begin, end = f"<!-- results:{scale}:begin -->", f"<!-- results:{scale}:end -->"
        quoted = text[text.index(begin) + len(begin):text.index(end)].strip()
        digest = (ROOT / "results" / scale / "digest.md").read_text(encoding="utf-8").strip()
        assert quoted == digest, scale
        assert (ROOT / "results" / scale / "summary.md").is_file()


def _relative_links(path: Path) -> list[str]:
    """Targets of the markdown links and images of ``path`` outside code blocks and code spans,
    without http(s)/mailto links, anchors stripped (a bare ``#anchor`` gives nothing)."""
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    text = re.sub(r"`[^`\n]*`", "``", text)
    targets = []
    for target in re.findall(r"\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:, ...
            continue
        target = target.split("#", 1)[0]
        if target:
            targets.append(target)
    return targets


def test_readme_is_short_and_every_relative_link_resolves():
    lines = README.read_text(encoding="utf-8").count("\n")
    assert lines <= 420, f"README.md has {lines} lines; move reference material into docs/"
    pages = [README, *sorted(DOCS.glob("*.md"))]
    assert len(pages) > 1
    missing = [f"{page.relative_to(ROOT)}: {target}" for page in pages
               for target in _relative_links(page)
               if not (page.parent / target).is_file()]
    assert not missing, "links to missing files:\n" + "\n".join(missing)


def test_install_says_how_to_put_the_commands_on_path():
    """``make install`` leaves the ``posernet-*`` commands in ``.venv/bin`` (not on PATH): the
    Install section says to activate the environment or call them there, and every command
    of the README's command table is one that ``make install`` puts there."""
    import tomllib

    install = _section("## Install")
    assert "source .venv/bin/activate" in install
    assert ".venv/bin/posernet-" in install
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))[
        "project"]["scripts"]
    named = set(re.findall(r"^\| `(posernet-[a-z-]+)` \|", _section("## Commands"), re.M))
    assert named and named <= set(scripts), sorted(named - set(scripts))
