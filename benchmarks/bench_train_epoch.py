"""Time one PoserNet training epoch on a paper-size small-graph training set.

The paper's small-graph training set has 14000 graphs of 8 nodes (~15.5 edges each). Without
``--root`` the graphs are random view graphs of that size (:func:`posernet.testing.
random_view_graph`, ``--pairs`` matched detection pairs per edge); ``--unique`` distinct graphs
are generated and repeated up to ``--graphs`` (the cost of an epoch does not depend on which
graphs repeat). With ``--root`` the ``small/train`` split of a ``posernet-make-data`` dataset is
used (repeated up to ``--graphs`` as well).

Prints the numbers and writes ``benchmarks/results/train_epoch.md`` atomically::

    python benchmarks/bench_train_epoch.py                 # random paper-size graphs
    python benchmarks/bench_train_epoch.py --root outputs/data/paper
"""

from __future__ import annotations

import argparse
import os
import platform
import shlex
import sys
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from posernet.graph import GraphBatch, ViewGraph
from posernet.io import atomic_write_text
from posernet.lit import PoserNetModule
from posernet.testing import random_view_graph

RESULTS = Path(__file__).resolve().parent / "results" / "train_epoch.md"


def random_graphs(n: int, pairs: tuple[int, int], dets: int, seed: int) -> list[ViewGraph]:
    g = torch.Generator().manual_seed(seed)
    # 7 chain edges + 8 or 9 extra distinct pairs: 15.5 edges per 8-node graph on average.
    return [random_view_graph(num_nodes=8, extra_edges=8 + (i % 2), pairs_per_edge=pairs,
                              dets_per_node=dets, generator=g, name=f"bench-{i}")
            for i in range(n)]


def dataset_graphs(root: str, estimate: str) -> list[ViewGraph]:
    from posernet.data.store import open_split

    return [g.with_estimate(estimate) for g in open_split(root, "small", "train")]


def time_epoch(graphs: list[ViewGraph], batch_size: int, threads: int, seed: int,
               device: str = "cpu") -> float:
    torch.set_num_threads(threads)
    warnings.filterwarnings("ignore")
    L.seed_everything(seed, workers=True, verbose=False)
    module = PoserNetModule()
    loader = DataLoader(graphs, batch_size=batch_size, shuffle=True,
                        collate_fn=GraphBatch.from_graphs,
                        generator=torch.Generator().manual_seed(seed))
    trainer = L.Trainer(accelerator="gpu" if device == "cuda" else "cpu", devices=1,
                        max_epochs=1, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False, limit_val_batches=0,
                        num_sanity_val_steps=0,
                        deterministic=True if device == "cpu" else "warn")
    t0 = time.perf_counter()
    trainer.fit(module, loader)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graphs", type=int, default=14000, help="graphs per epoch (paper: 14000)")
    ap.add_argument("--unique", type=int, default=1000, help="distinct random graphs")
    ap.add_argument("--pairs", type=int, nargs=2, default=(5, 15),
                    help="min/max matched pairs per edge of the random graphs")
    ap.add_argument("--dets", type=int, default=30, help="detections per image (random graphs)")
    ap.add_argument("--root", default=None, help="dataset directory instead of random graphs")
    ap.add_argument("--estimate", default="kp")
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, os.cpu_count() or 1])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--processes", type=int, nargs="+", default=[1],
                    help="training processes at once, each one epoch (as the experiment "
                         "runner's --jobs, e.g. several sharing one GPU)")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("--note", default="", help="a line added to the results (e.g. machine load)")
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")

    t0 = time.perf_counter()
    if args.root:
        base = dataset_graphs(args.root, args.estimate)
        source = f"`{args.root}` small/train ({len(base)} graphs, repeated)"
    else:
        base = random_graphs(min(args.unique, args.graphs), tuple(args.pairs), args.dets,
                             args.seed)
        source = (f"random 8-node view graphs ({len(base)} distinct, repeated), "
                  f"{args.pairs[0]}-{args.pairs[1]} matched pairs per edge")
    graphs = [base[i % len(base)] for i in range(args.graphs)]
    build_s = time.perf_counter() - t0
    n_edges = sum(g.num_edges for g in base) / len(base)
    n_pairs = sum(g.num_pairs for g in base) / max(1, sum(g.num_edges for g in base))
    params = PoserNetModule().num_parameters
    print(f"data: {source}; {len(graphs)} graphs, {n_edges:.2f} edges/graph, "
          f"{n_pairs:.2f} pairs/edge (built in {build_s:.1f} s)")
    print(f"PoserNet default model: {params} parameters")

    rows = []
    steps = -(-len(graphs) // args.batch_size)
    for procs in dict.fromkeys(args.processes):
        for threads in dict.fromkeys(args.threads):
            task = (graphs, args.batch_size, threads, args.seed, args.device)
            if procs == 1:
                secs = [time_epoch(*task)]
            else:
                import multiprocessing as mp

                with mp.get_context("spawn").Pool(procs) as pool:
                    secs = pool.starmap(time_epoch, [task] * procs)
            sec = max(secs)  # wall time until the last process finished its epoch
            rows.append((procs, threads, sec, steps))
            print(f"{args.device} processes={procs} threads={threads}: one epoch each in "
                  f"{sec:.1f} s ({1000 * sec / steps:.1f} ms/step per process, "
                  f"{procs * len(graphs) / sec:.0f} graphs/s in all)")

    gpu = (f", GPU {torch.cuda.get_device_name(0)}"
           if args.device == "cuda" and torch.cuda.is_available() else "")
    lines = [
        f"# One PoserNet training epoch ({args.device})",
        "",
        f"- data: {source}",
        f"- {len(graphs)} graphs/epoch, {n_edges:.2f} edges/graph, {n_pairs:.2f} matched "
        f"pairs/edge, batch size {args.batch_size}",
        f"- model: default PoserNet (depth 2, 3x32 MLPs), {params} parameters; Lightning "
        "`fit` for one epoch, no validation, no logger/checkpoint",
        f"- machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"torch {torch.__version__}{gpu}; 1-minute load average before the run: {load:.2f}",
        *([f"- note: {args.note}"] if args.note else []),
        "",
        "Processes: that many training processes at once, each one epoch on the device (the "
        "experiment runner's `--jobs`); epoch: wall time until the last one finished.",
        "",
        "| device | processes | torch threads | epoch (s) | steps | ms/step per process | "
        "graphs/s in all |",
        "|---|---:|---:|---:|---:|---:|---:|",
        *[f"| {args.device} | {p} | {t} | {s:.1f} | {n} | {1000 * s / n:.1f} | "
          f"{p * len(graphs) / s:.0f} |" for p, t, s, n in rows],
        "",
        f"Command: `{shlex.join(['python', 'benchmarks/bench_train_epoch.py', *sys.argv[1:]])}`",
        "",
    ]
    atomic_write_text(args.out, "\n".join(lines))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
