"""Time one PoserNet training epoch on a paper-size small-graph training set, and the authors'
batch-1 loop on the same graphs in the same run.

The paper's small-graph training set has 14000 graphs of 8 nodes (~15.5 edges each). Without
``--root`` the graphs are random view graphs of that size (:func:`posernet.testing.
random_view_graph`, ``--pairs`` matched detection pairs per edge); ``--unique`` distinct graphs
are generated and repeated up to ``--graphs`` (the cost of an epoch does not depend on which
graphs repeat). With ``--root`` the ``small/train`` split of a ``posernet-make-data`` dataset is
used (repeated up to ``--graphs`` as well).

Reference: the authors' training loop re-created from the paper and the facts in DESIGN.md
(batch size fixed at 1, plain PyTorch loop, one message-passing block shared by both rounds,
each matched pair's concatenated message through ``Psi_E`` / ``Psi_N``, gradients clipped by
value at 10, Adam): :class:`Batch1Net` / :func:`batch1_epoch` below, written for this benchmark.
It runs on ``--reference-graphs`` graphs of the epoch and is reported per graph and scaled to the
epoch (the cost per step does not depend on which graph it is).

Prints the numbers and writes ``benchmarks/results/train_epoch.md`` atomically::

    python benchmarks/bench_train_epoch.py                 # random paper-size graphs
    python benchmarks/bench_train_epoch.py --quick         # 2800 graphs, reference on 400
    python benchmarks/bench_train_epoch.py --root outputs/data/paper
"""

from __future__ import annotations

import argparse
import time
import warnings

import lightning as L
import torch
from _common import fmt_s, table, write_results
from torch import Tensor, nn
from torch.utils.data import DataLoader

from posernet.graph import GraphBatch, ViewGraph
from posernet.lit import PoserNetModule
from posernet.nn import posernet_loss
from posernet.testing import random_view_graph


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


# --------------------------------------------------------------------------- the batch-1 loop


def mlp(n_in: int, n_out: int, last_act: bool) -> nn.Sequential:
    """Three fully connected layers of 32 units with leaky ReLU (paper, supplementary)."""
    layers: list[nn.Module] = [nn.Linear(n_in, 32), nn.LeakyReLU(), nn.Linear(32, 32),
                               nn.LeakyReLU(), nn.Linear(32, n_out)]
    if last_act:
        layers.append(nn.LeakyReLU())
    return nn.Sequential(*layers)


class Batch1Net(nn.Module):
    """PoserNet as the paper describes it, one graph at a time: node input embedded to 32,
    one message-passing block shared by the ``depth`` rounds; per matched pair ``l`` of edge
    ``(i, j)`` the message input is ``[h_i, h_j, e_ij, bb_i^l, bb_j^l]``; the edge's new pose is
    the mean of ``Psi_E`` over its pairs (regressed directly), a node's new state the mean over
    its neighbours of the mean of ``Psi_N`` over the pairs."""

    def __init__(self, depth: int = 2) -> None:
        super().__init__()
        self.depth = depth
        self.embed = nn.Linear(4, 32)
        self.psi_e = mlp(32 + 32 + 7 + 8, 7, last_act=False)
        self.psi_n = mlp(32 + 32 + 7 + 8, 32, last_act=True)

    def forward(self, g: ViewGraph) -> Tensor:
        h, e = self.embed(g.node_attr), g.edge_pose
        src, dst = g.edge_index
        pe = g.pair_edge
        E, N = e.shape[0], h.shape[0]
        cnt = torch.zeros(E, dtype=h.dtype, device=h.device).index_add_(
            0, pe, torch.ones_like(pe, dtype=h.dtype)).clamp_min(1)[:, None]
        for _ in range(self.depth):
            z = torch.cat((h[src[pe]], h[dst[pe]], e[pe], g.det_box[g.pair_src],
                           g.det_box[g.pair_dst]), dim=-1)
            e = torch.zeros_like(e).index_add_(0, pe, self.psi_e(z)) / cnt
            m = torch.zeros(E, 32, dtype=h.dtype, device=h.device).index_add_(
                0, pe, self.psi_n(z)) / cnt
            ends = torch.cat((src, dst))
            deg = torch.zeros(N, 1, dtype=h.dtype, device=h.device).index_add_(
                0, ends, torch.ones(2 * E, 1, dtype=h.dtype, device=h.device)).clamp_min(1)
            h = torch.zeros_like(m[:N]).index_add_(0, ends, torch.cat((m, m))) / deg
        return e


def batch1_epoch(graphs: list[ViewGraph], threads: int, seed: int, device: str) -> float:
    """Wall time of one optimisation step per graph (the authors' batch size 1), in order."""
    torch.set_num_threads(threads)
    torch.manual_seed(seed)
    model = Batch1Net().to(device)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    graphs = [g.to(device) for g in graphs]
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    for g in graphs:
        loss = posernet_loss(model(g), g.edge_pose_gt, 0.5).loss
        opt.zero_grad()
        loss.backward()
        nn.utils.clip_grad_value_(model.parameters(), 10.0)
        opt.step()
    if device == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graphs", type=int, default=None, help="graphs per epoch (paper: 14000)")
    ap.add_argument("--quick", action="store_true",
                    help="2800 graphs per epoch, reference on 400 graphs")
    ap.add_argument("--reference-graphs", type=int, default=None,
                    help="graphs of the batch-1 reference (default: the whole epoch)")
    ap.add_argument("--unique", type=int, default=1000, help="distinct random graphs")
    ap.add_argument("--pairs", type=int, nargs=2, default=(5, 15),
                    help="min/max matched pairs per edge of the random graphs")
    ap.add_argument("--dets", type=int, default=30, help="detections per image (random graphs)")
    ap.add_argument("--root", default=None, help="dataset directory instead of random graphs")
    ap.add_argument("--estimate", default="kp")
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--threads", type=int, nargs="+", default=[1])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--processes", type=int, nargs="+", default=[1],
                    help="training processes at once, each one epoch (as the experiment "
                         "runner's --jobs, e.g. several sharing one GPU)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    warnings.filterwarnings("ignore")
    n_graphs = args.graphs or (2800 if args.quick else 14000)
    n_ref = args.reference_graphs or (400 if args.quick else n_graphs)

    t0 = time.perf_counter()
    if args.root:
        base = dataset_graphs(args.root, args.estimate)
        source = f"`{args.root}` small/train ({len(base)} graphs, repeated)"
    else:
        base = random_graphs(min(args.unique, n_graphs), tuple(args.pairs), args.dets,
                             args.seed)
        source = (f"random 8-node view graphs ({len(base)} distinct, repeated), "
                  f"{args.pairs[0]}-{args.pairs[1]} matched pairs per edge")
    graphs = [base[i % len(base)] for i in range(n_graphs)]
    build_s = time.perf_counter() - t0
    n_edges = sum(g.num_edges for g in base) / len(base)
    n_pairs = sum(g.num_pairs for g in base) / max(1, sum(g.num_edges for g in base))
    params = PoserNetModule().num_parameters
    print(f"data: {source}; {len(graphs)} graphs, {n_edges:.2f} edges/graph, "
          f"{n_pairs:.2f} pairs/edge (built in {build_s:.1f} s)", flush=True)

    t_ref = batch1_epoch(graphs[:n_ref], args.threads[0], args.seed, args.device)
    ref_epoch = t_ref / n_ref * n_graphs
    print(f"batch-1 reference: {n_ref} steps in {t_ref:.1f} s ({1000 * t_ref / n_ref:.2f} "
          f"ms/graph) -> {ref_epoch:.1f} s per {n_graphs}-graph epoch", flush=True)
    rows = [["authors' loop re-created (batch 1, plain PyTorch)", "1", str(args.threads[0]),
             f"{ref_epoch:.1f}" + ("" if n_ref == n_graphs else f" (from {n_ref} steps)"),
             f"{n_graphs / ref_epoch:.0f}", "1.0x"]]
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
            rows.append([f"posernet Lightning `fit`, batch {args.batch_size}"
                         + (f", {procs} processes" if procs > 1 else ""), str(procs),
                         str(threads), f"{sec:.1f}", f"{procs * len(graphs) / sec:.0f}",
                         f"{ref_epoch * procs / sec:.1f}x"])
            print(f"{args.device} processes={procs} threads={threads}: one epoch each in "
                  f"{sec:.1f} s ({1000 * sec / steps:.1f} ms/step per process)", flush=True)
    torch.set_num_threads(args.threads[0])
    body = [
        f"- data: {source}",
        f"- {len(graphs)} graphs/epoch, {n_edges:.2f} edges/graph, {n_pairs:.2f} matched "
        f"pairs/edge; batch size {args.batch_size} ({steps} steps)",
        f"- model: default PoserNet (depth 2, 3x32 MLPs), {params} parameters; Lightning `fit` "
        "for one epoch (deterministic on the CPU), no validation, no logger/checkpoint",
        f"- reference: the batch-1 loop (see the script) on {n_ref} graphs "
        f"({fmt_s(t_ref / n_ref)} per graph), scaled to the epoch",
        "",
        "Processes: that many training processes at once, each one epoch on the device (the "
        "experiment runner's `--jobs`); epoch: wall time until the last one finished.",
        "",
        *table(["training", "processes", "torch threads", "epoch (s)", "graphs/s in all",
                "vs batch-1 loop"], rows),
    ]
    write_results("train_epoch", f"One PoserNet training epoch ({args.device})", body,
                  args.quick, args.device, args.out)


if __name__ == "__main__":
    main()
