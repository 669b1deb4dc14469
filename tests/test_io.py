"""Atomic outputs: complete-or-absent files with the permissions of the process umask."""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import numpy as np
import pytest
import torch

from posernet.io import atomic_path, atomic_write_json, atomic_write_text

SRC = Path(__file__).resolve().parents[1] / "src" / "posernet"


@pytest.fixture(params=[0o022, 0o002, 0o077], ids=["022", "002", "077"])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_atomic_writes_keep_the_umask_permissions(tmp_path, umask):
    from posernet.io import atomic_write_bytes

    want = 0o666 & ~umask
    assert mode(atomic_write_text(tmp_path / "a.txt", "x")) == want
    assert mode(atomic_write_json(tmp_path / "sub" / "b.json", {"a": 1})) == want
    assert mode(atomic_write_bytes(tmp_path / "c.bin", b"\0")) == want
    with atomic_path(tmp_path / "d.png", suffix=".png") as tmp:
        assert tmp.suffix == ".png" and tmp.exists()
        tmp.write_bytes(b"png")
    assert mode(tmp_path / "d.png") == want
    # Replacing a file gives the new file the umask's permissions too.
    target = tmp_path / "a.txt"
    target.chmod(0o600)
    atomic_write_text(target, "y")
    assert mode(target) == want and target.read_text() == "y"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt", "c.bin", "d.png", "sub"]


def test_graphs_tables_and_pngs_keep_the_umask_permissions(tmp_path, umask):
    from posernet.graph import save_graphs
    from posernet.plots import plot_sorted_errors
    from posernet.report import ResultTable, relative_row
    from posernet.testing import random_view_graph

    want = 0o666 & ~umask
    pt = save_graphs(tmp_path / "g.pt", [random_view_graph()])
    md, csv = ResultTable(rows=[relative_row(("KP", "Initial"), [1.0], [2.0])]).write(tmp_path)
    png = plot_sorted_errors(tmp_path / "e.png", {"rot": {"initial": [1.0, 2.0],
                                                          "refined": [0.5, 1.0]}}, window=1)
    for p in (pt, md, csv, png):
        assert mode(p) == want, p.name


def test_rendered_images_keep_the_umask_permissions(tmp_path, umask):
    from posernet.data.render import _write_png

    path = tmp_path / "frame.color.png"
    _write_png(path, np.zeros((4, 4, 3), dtype=np.uint8))
    assert mode(path) == 0o666 & ~umask
    assert [p.name for p in tmp_path.iterdir()] == ["frame.color.png"]


def test_a_failed_write_leaves_neither_target_nor_temporary_file(tmp_path):
    atomic_write_text(tmp_path / "keep.txt", "old")
    with pytest.raises(ValueError):
        atomic_write_json(tmp_path / "keep.txt", {"x": float("nan")})
    with pytest.raises(RuntimeError), atomic_path(tmp_path / "new.bin") as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("interrupted")
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    assert (tmp_path / "keep.txt").read_text() == "old"


def test_nothing_in_src_writes_files_around_posernet_io():
    """Outputs go through posernet.io (atomic, umask permissions): no private temp files (a
    deleted write-test probe aside), and matplotlib / OpenCV / torch write only into a path that
    atomic_path handed out (or into a memory buffer)."""
    offenders = []
    for f in sorted(SRC.rglob("*.py")):
        if f.name == "io.py" and f.parent == SRC:
            continue
        rel = f.relative_to(SRC)
        for line in f.read_text(encoding="utf-8").splitlines():
            if re.search(r"\b(mkstemp|mkdtemp|NamedTemporaryFile)\(", line) and \
                    "write-test" not in line:
                offenders.append(f"{rel}: {line.strip()}")
            for m in re.finditer(r"\b(savefig|imwrite)\(([^,]*?)[,)]", line):
                if m.group(2).strip() not in ("tmp", "str(tmp"):
                    offenders.append(f"{rel}: {line.strip()}")
            for m in re.finditer(r"torch\.save\([^,]+,\s*([\w.]+)", line):
                if m.group(1) not in ("tmp", "buf"):
                    offenders.append(f"{rel}: {line.strip()}")
    assert not offenders, offenders


def test_torch_save_through_atomic_path_roundtrips(tmp_path):
    with atomic_path(tmp_path / "t.pt") as tmp:
        torch.save({"a": torch.ones(2)}, tmp)
    assert torch.equal(torch.load(tmp_path / "t.pt", weights_only=True)["a"], torch.ones(2))
