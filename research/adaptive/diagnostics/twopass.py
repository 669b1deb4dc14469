import sys

import torch
from posernet.experiments.adaptive import BINS, make_inputs
from posernet.pipeline import load_input_graphs
from sets import SETS

from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet

model = PoserNet.from_checkpoint(sys.argv[1]).eval()
with torch.no_grad():
    for s, roots in SETS.items():
        graphs = [
            g
            for r in roots
            for g in load_input_graphs(
                f"outputs/data/{r}", split="test", estimate=None, log=lambda *_: None
            )
        ]
        A = {"in": [], "p1": [], "p2": []}
        for _inp, gs in make_inputs(graphs).items():
            for i in range(0, len(gs), 64):
                b = GraphBatch.from_graphs(gs[i : i + 64])
                gt = torch.cat([g.edge_pose_gt for g in gs[i : i + 64]]).double()
                p1 = model(b).to(b.edge_pose.dtype)
                p2 = model(b, edge_pose=p1)
                for k, p in (("in", b.edge_pose), ("p1", p1), ("p2", p2)):
                    A[k].append(relative_pose_errors(p.double(), gt)[0])
        A = {k: torch.cat(v) for k, v in A.items()}
        print(
            s,
            " | ".join(
                f"[{lo:g}-{hi:g}] "
                + " ".join(f"{A[k][(A['in'] >= lo) & (A['in'] < hi)].mean():.3f}" for k in A)
                for lo, hi in BINS
            ),
        )
