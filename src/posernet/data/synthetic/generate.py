"""Simulate a synthetic dataset into a dataset folder (layout, resume and manifest:
:mod:`posernet.data.writer`).

Chunks (one file each) are split into parts of consecutive graphs that run in worker processes
(spawn-safe); each graph is seeded from ``(seed, scene, split, size, index)``, so the files are
bit-identical for any number of workers and any split.
An interrupted run leaves only complete files (atomic rename) and no manifest; ``resume``
keeps the complete files and makes the rest.
"""

from __future__ import annotations

import io
import multiprocessing as mp
import os
import queue as queue_mod
import signal
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from ..writer import (
    check_run_options,
    finish_dataset,
    make_spec,
    prepare_output,
    resumed_chunks,
    save_chunk,
)
from .chunks import Chunk, merge_stats, plan_chunks, simulate_chunk, split_chunk
from .config import ConfigError, DatasetOptions, resolve_options
from .summary import format_summary

__all__ = ["generate_dataset", "plan_parts"]


# --------------------------------------------------------------------------- helpers


def _spec(opts: DatasetOptions, seed: int) -> dict[str, Any]:
    return make_spec(opts.name, seed, opts.to_dict())


# --------------------------------------------------------------------------- workers

_QUEUE: Any = None


def _init_worker(q: Any) -> None:
    global _QUEUE
    _QUEUE = q
    import cv2

    cv2.setNumThreads(1)  # one process per core; OpenCV threads would oversubscribe
    torch.set_num_threads(1)


def _report(k: int) -> None:
    if _QUEUE is not None:
        _QUEUE.put(k)


def _simulate_part(options: dict[str, Any], chunk: Chunk, seed: int, graphs_range: range) -> bytes:
    """Worker task: the graphs ``graphs_range`` of ``chunk`` and their statistics, serialised.

    One ``torch.save`` blob: a pool result holding the tensors themselves would share each
    through its own file descriptor and run out of them for thousands of graphs.
    """
    from .config import options_from_dict

    out = simulate_chunk(options_from_dict(options), chunk, seed, progress=_report,
                         graphs_range=graphs_range)
    buf = io.BytesIO()
    torch.save(out, buf)
    return buf.getvalue()


def _unpack_part(blob: bytes) -> tuple[list[Any], dict[str, Any]]:
    # our own worker's output (ViewGraph objects), hence weights_only=False
    return torch.load(io.BytesIO(blob), map_location="cpu", weights_only=False)


def plan_parts(todo: list[Chunk], workers: int) -> list[tuple[Chunk, range]]:
    """Split chunks into parts so ``workers`` processes stay busy until the end.

    A chunk is one file (one scene, split and size) and can hold thousands of graphs; with more
    workers than big chunks the rest would idle. Parts aim at a quarter of a worker's share of
    the total cost; biggest parts come first for load balance.
    """
    if workers <= 1:
        return [(c, range(c.count)) for c in todo]
    target = sum(c.cost for c in todo) / (4 * workers)
    parts = [(c, r) for c in todo
             for r in split_chunk(c, -(-c.cost // target) if target > 0 else 1)]
    parts.sort(key=lambda p: -len(p[1]) * p[0].cost / p[0].count)
    return parts


def _run_all(
    todo: list[Chunk],
    opts: DatasetOptions,
    seed: int,
    root: Path,
    spec_hash: str,
    workers: int,
    progress: bool,
) -> dict[str, dict[str, Any]]:
    from tqdm.auto import tqdm

    total = sum(c.count for c in todo)
    bar = tqdm(
        total=total,
        unit="graph",
        desc="make-data",
        disable=not progress or not total,
        dynamic_ncols=True,
    )
    results: dict[str, dict[str, Any]] = {}
    parts = plan_parts(todo, workers)
    # parts of each chunk, by start index, until the chunk is complete and written
    done: dict[str, dict[int, tuple[list[Any], dict[str, Any]]]] = {c.relpath: {} for c in todo}
    expected = {c.relpath: sum(1 for pc, _ in parts if pc.relpath == c.relpath) for c in todo}

    def finish(chunk: Chunk, rng: range, out: tuple[list[Any], dict[str, Any]]) -> None:
        got = done[chunk.relpath]
        got[rng.start] = out
        if len(got) == expected[chunk.relpath]:
            ordered = [got[k] for k in sorted(got)]
            graphs = [g for gs, _ in ordered for g in gs]
            stats = merge_stats([st for _, st in ordered])
            save_chunk(root, chunk, graphs, stats, spec_hash)
            results[chunk.relpath] = stats
            del done[chunk.relpath]

    opts_dict = opts.to_dict()
    try:
        if workers <= 1 or len(parts) <= 1:
            import cv2

            threads = cv2.getNumThreads()
            cv2.setNumThreads(1)
            try:
                for c, rng in parts:
                    finish(c, rng, simulate_chunk(opts, c, seed, progress=bar.update,
                                                  graphs_range=rng))
            finally:
                cv2.setNumThreads(threads)
            return results
        ctx = mp.get_context("spawn")
        q = ctx.Queue()
        # Ctrl-C reaches the whole process group: workers start with SIGINT ignored (inherited)
        # so that only this process stops, terminates the pool and keeps the complete files
        main = threading.current_thread() is threading.main_thread()
        sigint = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
        try:
            pool = ctx.Pool(
                processes=min(workers, len(parts)), initializer=_init_worker, initargs=(q,)
            )
        finally:
            if main:
                signal.signal(signal.SIGINT, sigint)
        with pool:
            pending = [(c, rng, pool.apply_async(_simulate_part, (opts_dict, c, seed, rng)))
                       for c, rng in parts]
            while pending:
                try:
                    bar.update(q.get(timeout=0.2))
                except queue_mod.Empty:
                    pass
                still = []
                for c, rng, r in pending:
                    if r.ready():
                        finish(c, rng, _unpack_part(r.get()))  # re-raises a worker's error
                    else:
                        still.append((c, rng, r))
                pending = still
            while True:  # progress ticks still queued
                try:
                    bar.update(q.get_nowait())
                except queue_mod.Empty:
                    break
        return results
    finally:
        bar.close()


def generate_dataset(
    options: DatasetOptions | str | Mapping[str, Any],
    out_dir: str | os.PathLike[str],
    *,
    seed: int = 0,
    workers: int = 2,
    overwrite: bool = False,
    resume: bool = False,
    export_json_files: bool = False,
    progress: bool = True,
    echo: Callable[[str], None] | None = print,
) -> dict[str, Any]:
    """Generate a dataset directory (see the module docstring); returns the manifest.

    ``options``: preset name (``paper``, ``easy``, ``demo``, ``tiny``), a mapping or
    :class:`DatasetOptions`. ``echo`` receives the summary (``None``: silent).
    """
    opts = resolve_options(options)
    check_run_options(seed, workers, overwrite, resume)
    chunks = plan_chunks(opts)
    if not chunks:
        raise ConfigError(
            "invalid dataset options: every graph count (dataset.small.* and "
            "dataset.large.*) is 0, nothing to generate"
        )
    root = Path(out_dir)
    spec = _spec(opts, seed)
    prepare_output(root, spec, overwrite, resume)

    t0 = time.perf_counter()
    results, todo = resumed_chunks(root, chunks, spec, resume)
    todo.sort(key=lambda c: -c.cost)  # biggest first: better load balance
    results.update(_run_all(todo, opts, seed, root, spec["spec_hash"], workers, progress))
    elapsed = time.perf_counter() - t0

    manifest = finish_dataset(root, spec, chunks, results, export_json_files)
    if echo is not None:
        shown = dict(manifest, root=str(root))
        echo(format_summary(shown))
        echo(
            f"generated {sum(c.count for c in todo)} graphs in {elapsed:.1f} s "
            f"({len(todo)} of {len(chunks)} files, workers={workers})"
        )
    return manifest


