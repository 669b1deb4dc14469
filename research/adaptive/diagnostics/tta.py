"""Does the spread of the shipped model's raw prediction under test-time augmentation (dropped
detection pairs / perturbed neighbour inputs) flag the harmful gate openings, like checkpoint
disagreement does?  Columns as ens.py (st, e_in, e_fin, gate, spread, raw-in, e_mean)."""

import dataclasses
import sys

import torch
from posernet.experiments.adaptive import make_inputs
from posernet.pipeline import load_input_graphs
from sets import SETS

from posernet.data.mixture import perturb_poses
from posernet.geometry import quaternion_angle
from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet
from posernet.nn.adaptive import blend_poses

MODE = sys.argv[1]
K = int(sys.argv[2])
P = float(sys.argv[3])
main = PoserNet.from_checkpoint("src/posernet/checkpoints/posernet_synthetic_kp.ckpt").eval()
gen = torch.Generator().manual_seed(1)


def aug(g):
    if MODE == "drop":
        keep = torch.rand(g.pair_edge.shape[0], generator=gen) >= P
        # every edge keeps at least its first pair
        first = torch.ones_like(keep)
        first[1:] = g.pair_edge[1:] != g.pair_edge[:-1]
        keep |= first
        return dataclasses.replace(
            g, pair_edge=g.pair_edge[keep], pair_src=g.pair_src[keep], pair_dst=g.pair_dst[keep]
        )
    if MODE == "pose":
        rot = torch.rand(g.num_edges, generator=gen, dtype=g.edge_pose.dtype) * P
        return dataclasses.replace(g, edge_pose=perturb_poses(g.edge_pose, rot, 2 * rot, gen))
    raise SystemExit(MODE)


out = []
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
                chunk = gs[i : i + 64]
                b = GraphBatch.from_graphs(chunk)
                gt = torch.cat([g.edge_pose_gt for g in chunk]).double()
                ex = main(b, return_extras=True)
                raws = [
                    main(
                        GraphBatch.from_graphs([aug(g) for g in chunk]), return_extras=True
                    ).raw.double()
                    for _ in range(K)
                ]
                spread = (
                    torch.stack(
                        [quaternion_angle(r[:, :4], ex.raw.double()[:, :4]) for r in raws], -1
                    )
                    .max(-1)
                    .values
                )
                rin = quaternion_angle(ex.raw.double()[:, :4], b.edge_pose.double()[:, :4])
                e_in = relative_pose_errors(b.edge_pose.double(), gt)[0]
                e_fin = relative_pose_errors(ex.pose.double(), gt)[0]
                allr = [ex.raw.double(), *raws]
                q0 = allr[0][:, :4]
                qs = [
                    torch.where(((r[:, :4] * q0).sum(-1, keepdim=True) < 0), -r[:, :4], r[:, :4])
                    for r in allr
                ]
                qm = torch.nn.functional.normalize(sum(qs), dim=-1)
                tm = torch.nn.functional.normalize(sum(r[:, 4:] for r in allr), dim=-1)
                fin_m = blend_poses(b.edge_pose.double(), torch.cat((qm, tm), -1), ex.gate.double())
                e_m = relative_pose_errors(fin_m, gt)[0]
                out.append(
                    torch.stack(
                        (
                            torch.full_like(e_in, si),
                            e_in,
                            e_fin,
                            ex.gate[:, 0].double(),
                            torch.rad2deg(spread),
                            torch.rad2deg(rin),
                            e_m,
                            torch.full_like(e_in, ii),
                        ),
                        -1,
                    )
                )
O = torch.cat(out)
torch.save(O, f"outputs/diag/tta_{MODE}_{P}.pt")
st, e_in, e_fin, g, sp, rin, e_m = O.T[:7]
for name, m in (
    ("<3 & g>0.5", (e_in < 3) & (g > 0.5)),
    ("3-10 & g>0.5", (e_in >= 3) & (e_in < 10) & (g > 0.5)),
    ("10-30 & g>0.5", (e_in >= 10) & (e_in < 30) & (g > 0.5)),
):
    for part, mm in (("harmed", m & (e_fin > e_in)), ("helped", m & (e_fin <= e_in))):
        print(
            f"{name:14s} {part}: n={int(mm.sum()):5d} spread med {sp[mm].median():.2f} raw-in med {rin[mm].median():.2f}  ratio med {(sp[mm] / rin[mm]).median():.3f}"
        )
