"""Large view graphs (1000 and 5000 images): time and peak memory of refining (PoserNet) and
averaging (EIG-SE3) against the number of matched-pair rows.

One graph per size, ``--degree`` neighbours per image on average (72: the density of the paper's
125-image graphs, ~4500 edges) and 5-15 matched detection pairs per edge. Each size runs in a
fresh process so that its peak memory is its own: the peak resident set size of the refine step
and of the averaging step (Linux: the peak is reset before each step), or on CUDA
``torch.cuda.max_memory_allocated``.

    python benchmarks/bench_large.py            # 250 ... 5000 images -> results/large.md
    python benchmarks/bench_large.py --quick    # 250 and 1000 images -> results/quick/large.md
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import time
from pathlib import Path

import torch
from _common import fmt_s, table, write_results


def _reset_peak() -> bool:
    try:  # "5" resets the peak resident set size (Linux >= 4.0)
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def measure(n: int, degree: int, threads: int, device: str, seed: int) -> dict:
    """Build one ``n``-image graph, then refine and average it; times and peak memory."""
    from posernet.graph import GraphBatch
    from posernet.nn import PoserNet
    from posernet.sync import get_backend
    from posernet.testing import random_view_graph

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(seed)
    extra = max(0, n * degree // 2 - (n - 1))
    t0 = time.perf_counter()
    graph = random_view_graph(num_nodes=n, extra_edges=extra, pairs_per_edge=(5, 15),
                              dets_per_node=30, generator=g, name=f"large-{n}")
    batch = GraphBatch.from_graphs([graph]).to(device)
    build = time.perf_counter() - t0
    torch.manual_seed(0)
    model = PoserNet().eval().to(device)
    sync = get_backend("eig_se3")  # unit translations, IRLS; Krylov above 64 images
    cuda = device.startswith("cuda")
    out: dict = {"n": n, "edges": batch.num_edges, "pairs": batch.num_pairs, "build": build}
    for step in ("refine", "average"):
        if cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            base = torch.cuda.memory_allocated()
        else:
            reset = _reset_peak()
            base = _rss_mb() if reset else _peak_mb()
        t0 = time.perf_counter()
        with torch.no_grad():
            if step == "refine":
                refined = model(batch)
            else:
                sync.solve(batch, edge_pose=refined)
        if cuda:
            torch.cuda.synchronize()
        out[step] = time.perf_counter() - t0
        out[step + "_mb"] = ((torch.cuda.max_memory_allocated() - base) / 2**20 if cuda
                             else _peak_mb() - base)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None)
    ap.add_argument("--quick", action="store_true", help="250 and 1000 images")
    ap.add_argument("--degree", type=int, default=72, help="mean neighbours per image")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    sizes = args.sizes or ([250, 1000] if args.quick else [250, 500, 1000, 2000, 5000])
    rows, results = [], []
    ctx = mp.get_context("spawn")
    for n in sizes:
        with ctx.Pool(1) as pool:  # a fresh process: its peak memory is this size's own
            r = pool.apply(measure, (n, args.degree, args.threads, args.device, args.seed))
        results.append(r)
        print(f"{n} images: {r['edges']} edges, {r['pairs']} pairs (built in {r['build']:.1f} s);"
              f" refine {fmt_s(r['refine'])} / {r['refine_mb']:.0f} MB, average "
              f"{fmt_s(r['average'])} / {r['average_mb']:.0f} MB", flush=True)
        mrows = r["pairs"] / 1e6
        rows.append([str(n), str(r["edges"]), str(r["pairs"]), fmt_s(r["refine"]),
                     f"{r['refine'] / mrows:.2f} s", f"{r['refine_mb']:.0f}",
                     f"{r['refine_mb'] / mrows:.0f}", fmt_s(r["average"]),
                     f"{r['average_mb']:.0f}"])
    mem = "peak GPU memory allocated" if args.device.startswith("cuda") else \
        "peak resident memory above the process' memory before the step"
    body = [
        f"One view graph per size, {args.degree} neighbours per image on average (the density "
        "of the paper's 125-image graphs), 5-15 matched detection pairs per edge, 30 "
        "detections per image; untrained default PoserNet (float32, `torch.no_grad()`), then "
        "EIG-SE3 with IRLS on the refined poses (unit translations; block-Krylov eigen-solver "
        f"above 64 images). Memory: {mem}, in MB; each size in a fresh process.",
        "",
        *table(["images", "edges", "matched pairs", "refine", "refine per 1M pairs",
                "refine peak MB", "MB per 1M pairs", "average (EIG-SE3)", "average peak MB"],
               rows),
    ]
    write_results("large", "Large view graphs: refine + average, time and memory", body,
                  args.quick, args.device, args.out)


if __name__ == "__main__":
    main()
