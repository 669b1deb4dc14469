"""Rotation + translation averaging (the default backend) on one sequence's view graph of
256 to 1024 cameras: the sparse position solve of large components beside the dense one.

Each graph is what ``posernet-reconstruct pairs.mode=sequential`` builds from a video: every
camera paired with its next 5, plus one loop closure per 4 cameras between random far-apart
cameras; relative rotations 3 deg off at most, directions a little noisy. The backend runs
four times on each graph in one process:

* without edge weights: as shipped (components over
  ``posernet.sync.translation.SPARSE_MIN_NODES`` cameras test parallel rigidity, solve their
  position systems with scipy's sparse solvers and find rotations by Lanczos on the shifted
  inverse), and with every component on the dense batched eigen- and LU solves and plain
  block Krylov (the earlier code path), whose time grows as n^3;
* with the per-edge weights ``posernet-reconstruct`` passes (translation weight 0 on 2 % of
  the edges, rotation-only pairs): as shipped, and with ``solver=dense``, the eigen-solver
  every weighted problem took before (a ``3n x 3n`` ``eigh`` per IRLS round).

    python benchmarks/bench_averaging.py                 # 256, 512, 1024 cameras
    python benchmarks/bench_averaging.py --quick         # 256 and 512

Writes ``benchmarks/results/averaging.md`` (``--quick``: ``results/quick/averaging.md``).
"""

from __future__ import annotations

import argparse
import time

import torch
from _common import fmt_s, table, write_results


def sequence_edges(n: int, window: int = 5, seed: int = 0) -> torch.Tensor:
    """``[2, E]`` edges of an ``n``-frame sequence: each frame with its next ``window``, plus
    ``n // 4`` loop closures between frames more than ``window`` apart."""
    src = torch.cat([torch.arange(n - k) for k in range(1, window + 1)])
    dst = torch.cat([torch.arange(k, n) for k in range(1, window + 1)])
    g = torch.Generator().manual_seed(seed)
    a, b = torch.randint(0, n, (2, n // 4), generator=g)
    lo, hi = torch.minimum(a, b), torch.maximum(a, b)
    far = hi - lo > window
    return torch.stack((torch.cat((src, lo[far])), torch.cat((dst, hi[far]))))


def run(n: int, threads: int, seed: int) -> dict:
    import posernet.sync.translation as rt
    from posernet.sync import get_backend
    from posernet.testing import random_view_graph

    torch.set_num_threads(threads)
    graph = random_view_graph(num_nodes=n, pairs_per_edge=(1, 2), dets_per_node=4,
                              rot_noise_deg=3.0, trans_noise=0.05, dtype=torch.float64,
                              generator=torch.Generator().manual_seed(seed),
                              edge_index=sequence_edges(n, seed=seed), name=f"sequence-{n}")
    shipped = rt.SPARSE_MIN_NODES
    out: dict = {"n": n, "edges": graph.num_edges}
    for label, limit in (("sparse", shipped), ("dense", 10**9)):
        rt.SPARSE_MIN_NODES = limit
        try:
            t0 = time.perf_counter()
            poses = get_backend("rotation_translation").solve(graph)
            out[label] = time.perf_counter() - t0
        finally:
            rt.SPARSE_MIN_NODES = shipped
        out[label + "_poses"] = poses
    out["diff"] = float((out["sparse_poses"] - out["dense_poses"]).abs().max())
    w = torch.ones(graph.num_edges, 2, dtype=torch.float64)
    w[torch.randperm(graph.num_edges, generator=torch.Generator().manual_seed(seed))
      [:graph.num_edges // 50], 1] = 0.0
    for label, solver in (("weighted", "auto"), ("weighted_dense", "dense")):
        t0 = time.perf_counter()
        poses = get_backend("rotation_translation", solver=solver).solve(graph, edge_weight=w)
        out[label] = time.perf_counter() - t0
        out[label + "_poses"] = poses
    out["wdiff"] = float((out["weighted_poses"] - out["weighted_dense_poses"]).abs().max())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None)
    ap.add_argument("--quick", action="store_true", help="256 and 512 cameras")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    sizes = args.sizes or ([256, 512] if args.quick else [256, 512, 1024])
    rows = []
    for n in sizes:
        r = run(n, args.threads, args.seed)
        print(f"{n} cameras, {r['edges']} edges: sparse {fmt_s(r['sparse'])}, dense "
              f"{fmt_s(r['dense'])} ({r['dense'] / r['sparse']:.1f}x), largest pose "
              f"difference {r['diff']:.1e}; weighted {fmt_s(r['weighted'])}, weighted with "
              f"solver=dense {fmt_s(r['weighted_dense'])} "
              f"({r['weighted_dense'] / r['weighted']:.1f}x), difference {r['wdiff']:.1e}",
              flush=True)
        rows.append([str(n), str(r["edges"]), fmt_s(r["sparse"]), fmt_s(r["dense"]),
                     f"{r['dense'] / r['sparse']:.1f}x", f"{r['diff']:.1e}",
                     fmt_s(r["weighted"]), fmt_s(r["weighted_dense"]),
                     f"{r['weighted_dense'] / r['weighted']:.1f}x", f"{r['wdiff']:.1e}"])
    body = [
        "One sequence view graph per size (each camera with its next 5, one loop closure per 4 "
        "cameras), relative rotations up to 3 deg off; `rotation_translation` with its "
        "defaults (robust rotations, BATA positions from triangle-weighted directions), as "
        "shipped (sparse rigidity test, position solves and shifted-inverse Lanczos above "
        "`posernet.sync.translation.SPARSE_MIN_NODES` cameras) and with the dense batched "
        "eigen- and LU solves and plain block Krylov everywhere; then with "
        "`posernet-reconstruct`'s per-edge weights (translation weight 0 on 2 % of the "
        "edges) as shipped and with `solver=dense` (the eigen-solver weighted problems took "
        f"before); in one process, {args.threads} torch thread(s). Difference: largest "
        "absolute difference between two runs' world-to-camera matrices.",
        "",
        *table(["cameras", "edges", "sparse (shipped)", "dense", "dense / sparse",
                "difference", "weighted (shipped)", "weighted, solver=dense",
                "dense / shipped", "difference"], rows),
    ]
    write_results("averaging", "Rotation + translation averaging of long sequences", body,
                  args.quick, "cpu", args.out)


if __name__ == "__main__":
    main()
