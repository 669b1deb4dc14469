"""Per-edge dump (input, raw prediction, gate, sigma, final) of one model on selection sets."""

import sys

import numpy as np
import torch
from posernet.experiments.adaptive import make_inputs
from posernet.pipeline import load_input_graphs
from sets import SETS

from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet

ckpt, out = sys.argv[1], sys.argv[2]
if len(sys.argv) > 3:
    SETS = {n: [n] for n in sys.argv[3].split(",")}
model = PoserNet.from_checkpoint(ckpt).eval()
rec = {
    k: []
    for k in (
        "set",
        "inp",
        "graph",
        "e_in",
        "t_in",
        "e_raw",
        "t_raw",
        "e_fin",
        "t_fin",
        "gate",
        "sigma",
        "q_in",
        "q_raw",
        "gt",
    )
}
gid = 0
with torch.no_grad():
    for si, (_s, roots) in enumerate(SETS.items()):
        graphs = [
            g
            for r in roots
            for g in load_input_graphs(
                f"outputs/data/{r}", split="test", estimate=None, log=lambda *_: None
            )
        ]
        for ii, (_inp, gs) in enumerate(make_inputs(graphs).items()):
            for i in range(0, len(gs), 64):
                ch = gs[i : i + 64]
                b = GraphBatch.from_graphs(ch)
                ex = model(b, return_extras=True)
                gt = torch.cat([g.edge_pose_gt for g in ch]).double()
                for key, p in (("in", b.edge_pose), ("raw", ex.raw), ("fin", ex.pose)):
                    r, t = relative_pose_errors(p.double(), gt)
                    rec["e_" + key].append(r)
                    rec["t_" + key].append(t)
                rec["gate"].append(ex.gate.double())
                rec["sigma"].append(torch.rad2deg(ex.sigma.double()))
                rec["q_in"].append(b.edge_pose.double())
                rec["q_raw"].append(ex.raw.double())
                rec["gt"].append(gt)
                E = b.edge_pose.shape[0]
                rec["set"].append(torch.full((E,), si))
                rec["inp"].append(torch.full((E,), ii))
                rec["graph"].append(b.edge_batch + gid + i)
        gid += len(graphs) * 0 + 100000 * (si + 1)
np.savez(out, **{k: torch.cat(v).numpy() for k, v in rec.items()}, sets=np.array(list(SETS)))
print("saved", out)
