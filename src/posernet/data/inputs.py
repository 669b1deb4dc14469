"""The view graphs a command refines or evaluates, from a graph file, a folder of them, or a
dataset folder (``manifest.json``: one split of one size), checked on the way in."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

from ..graph import GraphValidationError, ViewGraph, load_graphs

__all__ = ["ESTIMATES", "load_input_graphs"]

#: the initial estimates ``estimate`` may pick: keypoint and box-centre 5-point, the free
#: keypoint 5-point (authors' ``.json``), ground truth
ESTIMATES = ("kp", "bb", "free", "gt")


def load_input_graphs(path: str | os.PathLike[str], split: str = "test",
                      estimate: str | None = "kp", strict: bool = True, size: str = "small",
                      log: Callable[[str], None] | None = None) -> list[ViewGraph]:
    """Graphs from a posernet ``.pt`` file, a folder of them, a dataset root or an authors' JSON.

    * ``.json``: the ``split`` list of an authors'-format file (``strict`` applies).
    * a dataset root made by ``posernet-make-data`` (it has ``manifest.json``): the graphs of
      ``split`` (``train``/``val``/``test``) and ``size`` (``small``, ``large`` or ``all``);
      the choice is reported through ``log``.
    * any other folder: every ``.pt`` under it, which must all belong to one split (by each
      graph's ``meta["split"]``, else by a ``train``/``val``/``test`` folder in its path):
      a folder mixing splits without a manifest is refused, naming the folder.
    * a ``.pt`` file: its graphs.

    ``estimate`` picks the initial poses to refine (``kp``/``bb``/...; ``None`` keeps the
    stored ``edge_pose``). Ground truth is optional everywhere. ``log`` (e.g. ``print``)
    receives one line saying what was selected from a dataset root.
    """
    path = Path(path)
    if path.suffix.lower() == ".json":
        from .posernet_json import load_posernet_json

        return load_posernet_json(path, split=split, estimate=estimate or "feature_5pt",
                                  strict=strict)
    if path.is_dir():
        if (path / "manifest.json").is_file():
            loaded = _load_dataset_root(path, split, size, log)
        else:
            files = sorted(path.rglob("*.pt"))
            if not files:
                raise FileNotFoundError(f"no graph files (*.pt) under {path}")
            loaded = [(f, load_graphs(f)) for f in files]
            _refuse_mixed_splits(path, loaded)
    elif path.is_file():
        loaded = [(path, load_graphs(path))]
    else:
        raise FileNotFoundError(f"input graph file not found: {path}")
    graphs: list[ViewGraph] = []
    for f, file_graphs in loaded:
        for g in file_graphs:
            if estimate is not None:
                if estimate not in g.estimates:
                    raise GraphValidationError(
                        f"{f}: graph {g.name!r} has no initial estimate {estimate!r} "
                        f"(available: {sorted(g.estimates)}); use estimate=null for its "
                        "stored edge_pose")
                g = g.with_estimate(estimate)
            graphs.append(g)
    if not graphs:
        raise GraphValidationError(f"{path}: no graphs")
    return graphs


def _load_dataset_root(root: Path, split: str, size: str,
                       log: Callable[[str], None] | None) -> list[tuple[Path, list[ViewGraph]]]:
    """``(file, graphs)`` of one split and size (or all sizes) of a posernet-make-data root."""
    from .store import SIZES, SPLITS, DatasetError, available_scenes, read_manifest

    if split not in SPLITS:
        raise DatasetError(f"{root}: is a dataset root; split must be one of {list(SPLITS)}, "
                           f"got {split!r}")
    if size != "all" and size not in SIZES:
        raise DatasetError(f"{root}: is a dataset root; size must be one of "
                           f"{[*SIZES, 'all']}, got {size!r}")
    read_manifest(root)
    sizes = list(SIZES) if size == "all" else [size]
    loaded: list[tuple[Path, list[ViewGraph]]] = []
    counts: dict[str, int] = {}
    for sz in sizes:
        for scene in available_scenes(root, sz, split):
            f = root / sz / split / f"{scene}.pt"
            if not f.is_file():
                raise DatasetError(f"{f}: listed in the manifest but missing")
            loaded.append((f, load_graphs(f)))
            counts[sz] = counts.get(sz, 0) + len(loaded[-1][1])
    if not loaded:
        raise DatasetError(f"{root}: the dataset has no {'/'.join(sizes)} {split} graphs "
                           "(choose another split= or size=)")
    if log is not None:
        what = ", ".join(f"{n} {sz}" for sz, n in counts.items())
        log(f"{root}: dataset root; using split={split} size={size}: {what} {split} graphs "
            f"from {len(loaded)} file(s)")
    return loaded


def _refuse_mixed_splits(folder: Path, loaded: Sequence[tuple[Path, list[ViewGraph]]]) -> None:
    """Raise when the ``.pt`` files under ``folder`` (no manifest) hold more than one split."""
    from .store import SPLITS

    by_split: dict[str, list[Path]] = {}
    for f, graphs in loaded:
        named = {str(g.meta["split"]) for g in graphs if g.meta.get("split")}
        if not named:  # no split in the graphs: take it from the folders below ``folder``
            named = {p for p in f.relative_to(folder).parts[:-1] if p in SPLITS}
        for sp in named:
            by_split.setdefault(sp, []).append(f)
    if len(by_split) > 1:
        desc = "; ".join(f"{sp}: {len(fs)} file(s), e.g. {fs[0].relative_to(folder)}"
                         for sp, fs in sorted(by_split.items()))
        raise GraphValidationError(
            f"{folder}: its .pt files mix splits ({desc}) and it has no manifest.json; point "
            "input= at one split's folder (e.g. <dataset>/small/test) or at a dataset root made "
            "by posernet-make-data (then split= and size= choose)")
