"""Prototype: per-edge arbitration between input and refined rotation by consistency with the
refined neighbours' two-edge paths."""

import sys

import torch
from posernet.experiments.adaptive import BINS, make_inputs
from posernet.nn.scatter import scatter_count, scatter_mean
from posernet.pipeline import load_input_graphs
from sets import SETS

from posernet.geometry import quaternion_conjugate, quaternion_multiply, quaternion_normalize
from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet


def triangles(edge_index, N):
    E = edge_index.shape[1]
    dev = edge_index.device
    src = torch.cat((edge_index[0], edge_index[1]))
    dst = torch.cat((edge_index[1], edge_index[0]))
    V = 2 * E
    order = torch.argsort(src, stable=True)
    deg = scatter_count(src, N)
    start = torch.cumsum(deg, 0) - deg
    n_next = deg[dst]
    a = torch.repeat_interleave(torch.arange(V, device=dev), n_next)
    first = torch.repeat_interleave(torch.cumsum(n_next, 0) - n_next, n_next)
    b = order[start[dst[a]] + torch.arange(a.numel(), device=dev) - first]
    i, j = src[a], dst[b]
    keep = i != j
    a, b, i, j = a[keep], b[keep], i[keep], j[keep]
    key = src * N + dst
    sk, ko = torch.sort(key)
    want = i * N + j
    pos = torch.searchsorted(sk, want).clamp_max(V - 1)
    found = sk[pos] == want
    return a[found], b[found], ko[pos][found]


def views(q):
    return torch.cat((q, quaternion_conjugate(q)))


def disc(qc_views, qpath_views, a, b, c, E):
    path = quaternion_multiply(qpath_views[b], qpath_views[a])
    d = quaternion_multiply(quaternion_conjugate(qc_views[c]), path)
    ang = torch.rad2deg(2.0 * torch.atan2(d[:, 1:].norm(dim=-1), d[:, 0].abs()))
    e = c % E
    return scatter_mean(ang[:, None], e, 0, E)[:, 0], scatter_count(e, E)


if __name__ == "__main__":  # feas.py / feas2.py import the helpers above
    ckpt = sys.argv[1]
    if len(sys.argv) > 2:
        SETS = {n: [n] for n in sys.argv[2].split(",")}
    MARGINS = [0.0, 0.5, 1.0, 2.0]
    model = PoserNet.from_checkpoint(ckpt).eval()
    with torch.no_grad():
        for s, roots in SETS.items():
            graphs = [
                g
                for r in roots
                for g in load_input_graphs(
                    f"outputs/data/{r}", split="test", estimate=None, log=lambda *_: None
                )
            ]
            acc = {k: [] for k in ["e_in", "e_fin", "inp", "ntri"] + [f"arb{m}" for m in MARGINS]}
            for ii, (_inp, gs) in enumerate(make_inputs(graphs).items()):
                for i in range(0, len(gs), 64):
                    b = GraphBatch.from_graphs(gs[i : i + 64])
                    E = b.edge_pose.shape[0]
                    ex = model(b, return_extras=True)
                    gt = torch.cat([g.edge_pose_gt for g in gs[i : i + 64]]).double()
                    q_in = quaternion_normalize(b.edge_pose[:, :4].double())
                    q_f = quaternion_normalize(ex.pose[:, :4].double())
                    a_, b_, c_ = triangles(b.edge_index, b.num_nodes)
                    d_in, n = disc(views(q_in), views(q_f), a_, b_, c_, E)
                    d_f, _ = disc(views(q_f), views(q_f), a_, b_, c_, E)
                    e_in = relative_pose_errors(b.edge_pose.double(), gt)[0]
                    acc["e_in"].append(e_in)
                    acc["inp"].append(torch.full((E,), ii))
                    acc["ntri"].append(n)
                    acc["e_fin"].append(relative_pose_errors(ex.pose.double(), gt)[0])
                    for m in MARGINS:
                        keep = (n > 0) & (d_in + m < d_f)
                        p = torch.where(
                            keep[:, None],
                            torch.cat((b.edge_pose[:, :4].double(), ex.pose[:, 4:].double()), 1),
                            ex.pose.double(),
                        )
                        acc[f"arb{m}"].append(relative_pose_errors(p, gt)[0])
            A = {k: torch.cat(v).numpy() for k, v in acc.items()}
            line = f"{s}: "
            for lo, hi in BINS:
                sel = (A["e_in"] >= lo) & (A["e_in"] < hi)
                line += (
                    f"[{lo:g}-{hi:g}] in {A['e_in'][sel].mean():.3f} fin {A['e_fin'][sel].mean():.3f} "
                    + " ".join(f"a{m}:{A[f'arb{m}'][sel].mean():.3f}" for m in MARGINS)
                    + " | "
                )
            print(line, f"no-tri share {(A['ntri'] == 0).mean():.3f}", flush=True)
            sel = A["e_in"] < 3
            for nm, c in (("no-tri", A["ntri"] == 0), ("tri", A["ntri"] > 0)):
                m = sel & c
                print(
                    f"   <3 {nm}: n={m.sum()} change sum {(A['e_fin'][m] - A['e_in'][m]).sum():+.2f}  arb1 {(A['arb1.0'][m] - A['e_in'][m]).sum():+.2f}"
                )
