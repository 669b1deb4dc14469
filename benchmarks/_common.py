"""Shared helpers of the benchmark scripts: paper-size inputs, timing, the machine description
and the results tables (written atomically to ``benchmarks/results/``; ``--quick`` runs to
``benchmarks/results/quick/`` so they never overwrite the committed full tables)."""

from __future__ import annotations

import datetime as _dt
import os
import platform
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from posernet.graph import GraphBatch, ViewGraph
from posernet.io import atomic_write_text
from posernet.report import cpu_model
from posernet.testing import random_view_graph

RESULTS = Path(__file__).resolve().parent / "results"

# The paper's small test graphs: 7000 graphs of 8 images; the `paper` preset of the simulator
# gives ~19 edges per graph and ~10 matched detection pairs per edge (~134k edges, ~1.3M pairs).
PAPER_TEST_GRAPHS = 7000
PAPER_EXTRA_EDGES = 12  # 7 chain edges + 12 = 19 edges per 8-node graph
PAPER_PAIRS = (5, 15)  # matched pairs per edge, uniform: 10 on average
PAPER_DETS = 30  # detections per image


def paper_graphs(n: int, unique: int = 500, seed: int = 0,
                 dtype: torch.dtype = torch.float32) -> list[ViewGraph]:
    """``n`` random 8-node view graphs of the paper's test-graph size (``unique`` distinct ones,
    repeated: the cost of a batch does not depend on which graphs repeat)."""
    g = torch.Generator().manual_seed(seed)
    base = [random_view_graph(num_nodes=8, extra_edges=PAPER_EXTRA_EDGES,
                              pairs_per_edge=PAPER_PAIRS, dets_per_node=PAPER_DETS, generator=g,
                              dtype=dtype, name=f"paper-{i}")
            for i in range(min(n, unique))]
    return [base[i % len(base)] for i in range(n)]


def paper_batch(n: int, seed: int = 0, dtype: torch.dtype = torch.float32) -> GraphBatch:
    return GraphBatch.from_graphs(paper_graphs(n, seed=seed, dtype=dtype))


def sync(device: str | torch.device) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def best_of(fn: Callable[[], object], repeat: int, device: str | torch.device = "cpu",
            warmup: int = 1) -> tuple[float, list[float]]:
    """Best wall time (s) of ``repeat`` calls after ``warmup`` calls, and all the times. The
    best of a few is the least disturbed by the other jobs of a shared machine."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return min(times), times


def machine(device: str = "cpu") -> list[str]:
    """Lines describing where and how the numbers were taken."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    cpu = cpu_model()
    gpu = ""
    if torch.device(device).type == "cuda" and torch.cuda.is_available():
        gpu = f", GPU {torch.cuda.get_device_name(0)}"
    return [
        f"- date: {_dt.datetime.now().astimezone().isoformat(timespec='seconds')}",
        f"- machine: {cpu}, {os.cpu_count()} CPU core(s){gpu}; device: {device}",
        f"- versions: python {platform.python_version()}, torch {torch.__version__}",
        f"- torch threads: {torch.get_num_threads()}; load average (1/5/15 min) at the end: "
        + " / ".join(f"{x:.2f}" for x in load),
    ]


def command() -> str:
    return shlex.join(["python", f"benchmarks/{Path(sys.argv[0]).name}", *sys.argv[1:]])


def table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return out


def write_results(name: str, title: str, body: Sequence[str], quick: bool, device: str,
                  out: str | None = None) -> Path:
    """Print the table and write it (with machine, versions, date, threads, load and the exact
    command) to ``results/<name>.md`` (``results/quick/<name>.md`` for ``--quick``)."""
    path = Path(out) if out else (RESULTS / "quick" if quick else RESULTS) / f"{name}.md"
    text = "\n".join([f"# {title}" + (" (quick mode)" if quick else ""), "",
                      *machine(device), f"- command: `{command()}`", "", *body, ""])
    print("\n" + text)
    atomic_write_text(path, text)
    print(f"written: {path}")
    return path


def fmt_s(x: float) -> str:
    return f"{x * 1000:.1f} ms" if x < 1 else f"{x:.2f} s"


def baseline_label(src: str) -> str:
    """``commit`` of the checkout holding ``src`` (or the folder's name): how ``--baseline``
    runs are labelled."""
    import subprocess

    folder = Path(src).resolve().parent
    try:
        top, commit = subprocess.run(
            ["git", "-C", src, "rev-parse", "--show-toplevel", "--short", "HEAD"],
            capture_output=True, text=True, check=True).stdout.split()
    except (OSError, ValueError, subprocess.CalledProcessError):
        return folder.name
    # a copied src inside another checkout is not that checkout's commit
    return f"commit {commit}" if Path(top).resolve() == folder else folder.name
