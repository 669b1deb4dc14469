"""CPU beside GPU on one machine: the network's forward, EIG-SE3, rotation averaging and one
training epoch at the paper's size.

Workloads (each timed on the CPU and on CUDA in this process, on the same inputs):

* PoserNet forward of 7000 paper-size test graphs in one batch (8 images, ~15.5 edges and
  5-15 matched detection pairs per edge, float32, the paper-architecture checkpoint);
* EIG-SE3 (``eig_se3``, IRLS) and rotation averaging (``rotation_translation``: spectral
  rotation IRLS, geodesic refinement, then positions from directions) on the same 7000
  graphs, batched;
* one training epoch of 14000 such graphs (the paper's small-graph training set), batch 32,
  Lightning ``fit`` as ``bench_train_epoch.py`` times it.

Besides the times: the largest GPU-CPU difference of each output (forward: the edge poses;
averaging: gauge-free absolute poses), so speed is not bought with other answers. Without
CUDA the script says so and fills the CPU column only (its table goes to ``gpu_cpu_only.md``,
never to ``gpu.md``)::

    python benchmarks/bench_gpu.py                 # on a GPU machine -> results/gpu.md
    python benchmarks/bench_gpu.py --quick         # 300 graphs, 700-graph epoch
                                                   # -> results/quick/gpu.md
"""

from __future__ import annotations

import argparse
import os
import time
import warnings
from collections.abc import Callable
from typing import Any

import torch
from _common import RESULTS, best_of, fmt_s, table, write_results
from bench_forward import load_model
from bench_sync import gauge_free_diff
from bench_train_epoch import random_graphs, time_epoch

from posernet.graph import GraphBatch
from posernet.sync import get_backend

PAIRS = (5, 15)  # matched pairs per edge, as bench_train_epoch's default
DETS = 30


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graphs", type=int, default=None,
                    help="test graphs for forward and averaging (7000)")
    ap.add_argument("--train-graphs", type=int, default=None,
                    help="graphs of the training epoch (14000; 0 skips it)")
    ap.add_argument("--unique", type=int, default=1000, help="distinct random graphs")
    ap.add_argument("--batch-size", type=int, default=32, help="training batch size")
    ap.add_argument("--repeat", type=int, default=None, help="best of this many runs")
    ap.add_argument("--threads", type=int, nargs="+", default=None,
                    help="torch threads of the CPU columns, one column each (default: 1, and "
                         "every core where there are more than 2)")
    ap.add_argument("--quick", action="store_true",
                    help="300 graphs, a 700-graph epoch, one run each")
    ap.add_argument("--out", default=None)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.threads is None:
        cores = os.cpu_count() or 1
        args.threads = [1, cores] if cores > 2 else [1]
    return args


def columns(threads: list[int]) -> list[tuple[str, str, int]]:
    """``(key, device, torch threads)`` of every column: the CPU ones, then CUDA's."""
    cols = [(f"cpu{t}", "cpu", t) for t in dict.fromkeys(threads)]
    if torch.cuda.is_available():
        cols.append(("cuda", "cuda", threads[0]))
    return cols


def _forward(batch: GraphBatch, device: str) -> Callable[[], torch.Tensor]:
    model = load_model().to(device).eval()
    b = batch.to(device)

    def run() -> torch.Tensor:
        with torch.no_grad():
            return model(b)

    return run


def _averaging(name: str, batch: GraphBatch, device: str) -> Callable[[], torch.Tensor]:
    backend = get_backend(name)
    b = batch.to(device)
    return lambda: backend.solve(b)


def measure(workloads: dict[str, Callable[[GraphBatch, str], Callable[[], torch.Tensor]]],
            batch: GraphBatch, repeat: int, threads: list[int]) -> list[dict[str, Any]]:
    """Best-of-``repeat`` time of every workload in every column, and the largest difference
    between the GPU's output and the first CPU column's."""
    rows = []
    for label, make in workloads.items():
        row: dict[str, Any] = {"label": label}
        outs: dict[str, torch.Tensor] = {}
        for key, dev, t in columns(threads):
            torch.set_num_threads(t)
            run = make(batch, dev)

            def keep(run: Callable[[], torch.Tensor] = run, key: str = key,
                     outs: dict[str, torch.Tensor] = outs) -> None:
                outs[key] = run()  # the last run's output is compared

            row[key], _ = best_of(keep, repeat, dev)
            outs[key] = outs[key].detach().cpu()
            print(f"{label}, {key}: {fmt_s(row[key])}", flush=True)
        if "cuda" in outs:
            a, c = outs["cuda"], outs[f"cpu{threads[0]}"]
            row["diff"] = (gauge_free_diff(a, c, batch) if a.ndim == 3
                           else float((a.double() - c.double()).abs().max()))
        rows.append(row)
    return rows


def main() -> None:
    args = parse_args()
    warnings.filterwarnings("ignore")
    cuda = torch.cuda.is_available()
    if not cuda:
        print("NOTE: CUDA is not available here: only the CPU column is measured. The GPU "
              "table needs a machine with CUDA (the same command there).", flush=True)
    n = args.graphs or (300 if args.quick else 7000)
    n_train = args.train_graphs if args.train_graphs is not None else \
        (700 if args.quick else 14000)
    repeat = args.repeat or (1 if args.quick else 3)
    t0 = time.perf_counter()
    base = random_graphs(min(args.unique, max(n, n_train)), PAIRS, DETS, args.seed)
    batch = GraphBatch.from_graphs([base[i % len(base)] for i in range(n)])
    print(f"{n} graphs: {batch.num_edges} edges ({batch.num_edges / n:.2f} per graph), "
          f"{batch.num_pairs} matched pairs (built in {time.perf_counter() - t0:.1f} s)",
          flush=True)
    workloads = {
        "PoserNet forward": _forward,
        "EIG-SE3 (`eig_se3`, IRLS)": lambda b, d: _averaging("eig_se3", b, d),
        "rotation averaging (`rotation_translation`)":
            lambda b, d: _averaging("rotation_translation", b, d),
    }
    rows = measure(workloads, batch, repeat, args.threads)
    if n_train:
        graphs = [base[i % len(base)] for i in range(n_train)]
        row: dict[str, Any] = {"label": f"one training epoch, {n_train} graphs, batch "
                                        f"{args.batch_size}"}
        for key, dev, t in columns(args.threads):
            row[key] = time_epoch(graphs, args.batch_size, t, args.seed, dev)
            print(f"{row['label']}, {key}: {fmt_s(row[key])}", flush=True)
        rows.append(row)
    torch.set_num_threads(args.threads[0])
    peak = torch.cuda.max_memory_allocated() / 2**20 if cuda else None
    cols = columns(args.threads)
    cpu_keys = [k for k, d, _ in cols if d == "cpu"]

    def speed_up(r: dict[str, Any]) -> str:
        return f"{min(r[k] for k in cpu_keys) / r['cuda']:.1f}x" if "cuda" in r else "-"

    header = ["workload", *[f"CPU, {t} thread{'s' * (t > 1)}" for _, d, t in cols
                            if d == "cpu"], "GPU", "GPU speed-up (vs the fastest CPU)",
              "max GPU-CPU difference"]
    body = [
        f"Input: {n} random 8-image view graphs of the paper's size ({batch.num_edges / n:.2f} "
        f"edges per graph, {PAIRS[0]}-{PAIRS[1]} matched detection pairs per edge, "
        f"{min(args.unique, n)} distinct ones repeated), one batch; forward in "
        "float32 with the paper-architecture checkpoint, averaging in float64 with each "
        "backend's defaults (EIG-SE3: unit relative translations; rotation_translation: "
        "scale-free positions). Training: Lightning `fit` of the default PoserNet for one "
        "epoch (deterministic on the CPU, `warn` on the GPU), no validation. Best of "
        f"{repeat} run(s) after one warm-up (training: one run).",
        "",
    ]
    if not cuda:
        body += ["**No CUDA on this machine: the GPU column is empty.** Run the same command "
                 "on a GPU machine for the comparison.", ""]
    body += table(header, [[r["label"], *[fmt_s(r[k]) for k in cpu_keys],
                            fmt_s(r["cuda"]) if "cuda" in r else "-", speed_up(r),
                            f"{r['diff']:.1e}" if "diff" in r else "-"] for r in rows])
    if peak is not None:
        body += ["", f"Peak GPU memory allocated by torch: {peak:.0f} MiB."]
    body += ["", f"Differences: GPU against the {args.threads[0]}-thread CPU run; forward, "
             "the largest edge-pose entry (float32 round-off); averaging, the largest entry "
             "of the gauge-free poses `M_i M_first^-1`."]
    name = "gpu" if cuda else "gpu_cpu_only"
    out = args.out or str((RESULTS / "quick" if args.quick else RESULTS) / f"{name}.md")
    write_results(name, "CPU beside GPU: forward, motion averaging, training"
                  + ("" if cuda else " (no CUDA: CPU only)"), body, args.quick,
                  "cuda" if cuda else "cpu", out)


if __name__ == "__main__":
    main()
