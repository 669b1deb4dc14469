"""The dataset writer both graph generators share (the simulator and the 7-Scenes builder).

Layout::

    ROOT/manifest.json                 written last: its presence means "complete"
    ROOT/.make_data.json               what is being generated (config, seed), for resume
    ROOT/<size>/<split>/<scene>.pt     graphs (``posernet.graph.save_graphs``), atomic
    ROOT/json/<size>.json              optional export in the authors' JSON schema

:func:`prepare_output` makes the folder ready (overwrite / resume rules) and writes the job
file; :func:`save_chunk` writes one chunk file atomically with its statistics and the spec's
hash; :func:`resumed_chunks` keeps the complete chunk files of an interrupted run;
:func:`finish_dataset` writes the manifest, last.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from ..graph import load_graphs, save_graphs
from ..io import atomic_write_json
from .layout import JOB_FILE, MANIFEST, SIZES, SPLITS
from .synthetic.chunks import Chunk
from .synthetic.config import ConfigError
from .synthetic.summary import aggregate_stats, composition_row, error_table

__all__ = [
    "FORMAT",
    "JOB_FILE",
    "MANIFEST",
    "VERSION",
    "DatasetExistsError",
    "GenerationError",
    "check_run_options",
    "export_json",
    "finish_dataset",
    "make_spec",
    "prepare_output",
    "resumed_chunks",
    "save_chunk",
]

FORMAT = "posernet-synthetic-dataset"
VERSION = 1


class DatasetExistsError(FileExistsError):
    """The output directory holds something and neither overwrite nor resume was asked."""


class GenerationError(RuntimeError):
    """Generation failed (e.g. resume with a different config); the message says why."""


def make_spec(name: str, seed: int, config: dict[str, Any], fmt: str = FORMAT,
              version: int = VERSION) -> dict[str, Any]:
    """What a dataset directory is made from (format, name, seed, config) and its hash: chunk
    files of a resumed run are kept only when their stored hash matches."""
    spec = {
        "format": fmt,
        "version": version,
        "preset": name,
        "seed": int(seed),
        "config": config,
    }
    blob = json.dumps(spec, sort_keys=True).encode()
    spec["spec_hash"] = hashlib.sha256(blob).hexdigest()[:16]
    return spec


def _our_files(root: Path) -> list[Path]:
    """Files this generator may have written under ``root`` (never anything else)."""
    out = [root / MANIFEST, root / JOB_FILE]
    for size in SIZES:
        for split in SPLITS:
            d = root / size / split
            if d.is_dir():
                out += [
                    p
                    for p in d.iterdir()
                    if p.suffix == ".pt" or (p.name.startswith(".") and p.suffix == ".tmp")
                ]
    j = root / "json"
    if j.is_dir():
        out += [
            p
            for p in j.iterdir()
            if p.suffix == ".json" or (p.name.startswith(".") and p.suffix == ".tmp")
        ]
    return [p for p in out if p.is_file()]


def _remove_ours(root: Path, temp_only: bool = False) -> None:
    for p in _our_files(root):
        if not temp_only or p.suffix == ".tmp":
            p.unlink()
    for size in SIZES:  # tidy empty folders we made
        for split in SPLITS:
            d = root / size / split
            if d.is_dir() and not any(d.iterdir()):
                d.rmdir()
        if (root / size).is_dir() and not any((root / size).iterdir()):
            (root / size).rmdir()


def _read_json(path: Path) -> dict[str, Any]:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise GenerationError(f"{path}: cannot read ({exc})") from exc


def prepare_output(root: Path, spec: dict[str, Any], overwrite: bool, resume: bool,
             prefix: str = "dataset") -> None:
    """Make ``root`` ready, honouring overwrite / resume; write the job file. ``prefix`` names
    the config in messages (``dataset.small.train: 2 -> 3``)."""
    if root.exists() and not root.is_dir():
        raise DatasetExistsError(f"output path {root} exists and is not a directory")
    if root.is_dir() and any(root.iterdir()):
        if overwrite:
            # manifest first: from this moment the directory no longer looks complete
            (root / MANIFEST).unlink(missing_ok=True)
            _remove_ours(root)
        elif resume:
            job = root / JOB_FILE
            src = job if job.is_file() else root / MANIFEST
            if not src.is_file():
                raise GenerationError(
                    f"cannot resume in {root}: it holds no {JOB_FILE} or {MANIFEST} (not made "
                    f"by posernet-make-data); use another out_dir or overwrite=true"
                )
            old = _read_json(src)
            if old.get("spec_hash") != spec["spec_hash"]:
                diff = _diff(old.get("config", {}), spec["config"], prefix)
                if old.get("seed") != spec["seed"]:
                    diff.insert(0, f"seed {old.get('seed')} -> {spec['seed']}")
                raise GenerationError(
                    f"cannot resume in {root}: it was started with a different configuration "
                    f"({'; '.join(diff[:5]) or 'format changed'}); use overwrite=true"
                )
            (root / MANIFEST).unlink(missing_ok=True)
            _remove_ours(root, temp_only=True)  # temp files of a killed run
        else:
            raise DatasetExistsError(
                f"output directory {root} already exists and is not empty; pass overwrite=true "
                f"to replace the dataset or resume=true to finish an interrupted run"
            )
    root.mkdir(parents=True, exist_ok=True)
    atomic_write_json(root / JOB_FILE, spec)


def _diff(a: Any, b: Any, path: str = "dataset") -> list[str]:
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff(a.get(k), b.get(k), f"{path}.{k}")
        return out
    return [] if a == b else [f"{path}: {a!r} -> {b!r}"]


def _chunk_extra(path: Path) -> dict[str, Any]:
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
        return dict(payload["extra"])
    except Exception as exc:  # corrupt or foreign file
        raise GenerationError(f"{path}: unreadable graph file ({exc}); use overwrite=true") from exc


def save_chunk(root: Path, chunk: Chunk, graphs: list[Any], stats: dict[str, Any],
                spec_hash: str) -> None:
    """Write one chunk's file atomically (graphs + statistics + provenance)."""
    extra = {"stats": stats, "chunk": dataclasses.asdict(chunk), "spec_hash": spec_hash}
    save_graphs(root / chunk.relpath, graphs, extra=extra)


def export_json(root: str | os.PathLike[str]) -> dict[str, str]:
    """Write ``ROOT/json/<size>.json`` in the authors' schema for every size with graphs."""
    from posernet.data.posernet_json import save_posernet_json

    root = Path(root)
    out: dict[str, str] = {}
    for size in SIZES:
        splits: dict[str, list] = {}
        for split in SPLITS:
            d = root / size / split
            if d.is_dir():
                files = sorted(d.glob("*.pt"))
                if files:
                    splits[split] = [g for f in files for g in load_graphs(f)]
        if splits:
            path = save_posernet_json(root / "json" / f"{size}.json", splits)
            out[size] = str(Path(path).relative_to(root))
    return out


# --------------------------------------------------------------------------- public


def check_run_options(seed: Any, workers: Any, overwrite: bool, resume: bool) -> None:
    """Options every generator shares; :class:`ConfigError` naming the bad one."""
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"invalid option seed: must be a non-negative integer, got {seed!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"invalid option workers: must be an integer >= 1, got {workers!r}")
    if overwrite and resume:
        raise ConfigError("invalid options: overwrite=true and resume=true exclude each other")


def resumed_chunks(
    root: Path, chunks: list[Chunk], spec: dict[str, Any], resume: bool
) -> tuple[dict[str, dict[str, Any]], list[Chunk]]:
    """The statistics of the chunk files a resumed run keeps (complete, same spec hash) by
    relpath, and the chunks still to make (in ``chunks`` order)."""
    results: dict[str, dict[str, Any]] = {}
    todo: list[Chunk] = []
    for c in chunks:
        path = root / c.relpath
        if resume and path.is_file():
            extra = _chunk_extra(path)
            if extra.get("spec_hash") != spec["spec_hash"]:
                raise GenerationError(
                    f"{path} was made with a different configuration; use overwrite=true"
                )
            results[c.relpath] = extra["stats"]
        else:
            todo.append(c)
    return results, todo


def finish_dataset(
    root: Path,
    spec: dict[str, Any],
    chunks: list[Chunk],
    results: dict[str, dict[str, Any]],
    export_json_files: bool = False,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write the manifest (``extra`` entries added; json export first when asked), last: the
    dataset is then complete. Returns the manifest."""
    manifest = _manifest(root, spec, chunks, results)
    if extra:
        manifest.update(_json_safe(dict(extra)))
    if export_json_files:
        manifest["json"] = export_json(root)
    atomic_write_json(root / MANIFEST, manifest)  # last: the dataset is now complete
    return manifest


def _manifest(
    root: Path, spec: dict[str, Any], chunks: list[Chunk], results: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    files: dict[str, Any] = {}
    splits: dict[str, dict[str, list[str]]] = {}
    grouped: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for c in chunks:
        st = results[c.relpath]
        files[c.relpath] = {
            "size": c.size,
            "split": c.split,
            "scene": c.scene,
            "graphs": st["graphs"],
            "nodes": st["nodes"],
            "edges": st["edges"],
            "graph_size": c.graph_size,
        }
        splits.setdefault(c.size, {}).setdefault(c.split, []).append(c.scene)
        grouped.setdefault((c.size, c.split), []).append(st)
    composition: dict[str, dict[str, Any]] = {}
    statistics: dict[str, dict[str, Any]] = {}
    for (size, split), sts in grouped.items():
        agg = aggregate_stats(sts)
        composition.setdefault(size, {})[split] = composition_row(agg)
        statistics.setdefault(size, {})[split] = error_table(agg["errors"])
    m = {k: v for k, v in spec.items()}
    m.update(files=files, splits=splits, composition=composition, statistics=statistics)
    return _json_safe(m)


def _json_safe(x: Any) -> Any:
    """NaN/inf -> None so the manifest is strict JSON."""
    if isinstance(x, float):
        return x if x == x and abs(x) != float("inf") else None
    if isinstance(x, Mapping):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_json_safe(v) for v in x]
    return x
