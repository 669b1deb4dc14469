"""Do the edge's own matched box centres tell a good input from a poor raw prediction?"""

import torch
from posernet.experiments.adaptive import make_inputs
from posernet.pipeline import load_input_graphs
from sets import SETS

from posernet.geometry import quaternion_to_rotation_matrix
from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet

model = PoserNet.from_checkpoint("src/posernet/checkpoints/posernet_synthetic_kp.ckpt").eval()


def rays(b, det, node):
    box = b.det_box[det].double()
    W, H = b.image_size[node, 0].double(), b.image_size[node, 1].double()
    px = torch.stack(((box[:, 0] + 1) * W / 2, (box[:, 1] + 1) * H / 2, torch.ones_like(W)), -1)
    r = torch.linalg.solve(b.K[node].double(), px[..., None])[..., 0]
    return r / r[:, 2:]


def residuals(pose, b, xi, xj, pe):
    R = quaternion_to_rotation_matrix(pose[pe, :4])
    t = torch.nn.functional.normalize(pose[pe, 4:], dim=-1)
    Rx = (R @ xi[..., None])[..., 0]
    rot = torch.rad2deg(
        torch.arccos(torch.nn.functional.cosine_similarity(Rx, xj, dim=-1).clamp(-1, 1))
    )
    tx = torch.zeros(t.shape[0], 3, 3, dtype=t.dtype)
    tx[:, 0, 1], tx[:, 0, 2], tx[:, 1, 0], tx[:, 1, 2], tx[:, 2, 0], tx[:, 2, 1] = (
        -t[:, 2],
        t[:, 1],
        t[:, 2],
        -t[:, 0],
        -t[:, 1],
        t[:, 0],
    )
    E = tx @ R
    Ex = (E @ xi[..., None])[..., 0]
    Etx = (E.transpose(1, 2) @ xj[..., None])[..., 0]
    num = (xj * Ex).sum(-1)
    samp = num.abs() / (Ex[:, :2].pow(2).sum(-1) + Etx[:, :2].pow(2).sum(-1)).sqrt().clamp_min(
        1e-12
    )
    return rot, samp


rows = []
with torch.no_grad():
    for si, (_s, roots) in enumerate(SETS.items()):
        graphs = [
            g
            for r in roots
            for g in load_input_graphs(
                f"outputs/data/{r}", split="test", estimate=None, log=lambda *_: None
            )
        ]
        for _ii, (_inp, gs) in enumerate(make_inputs(graphs).items()):
            for i in range(0, len(gs), 64):
                b = GraphBatch.from_graphs(gs[i : i + 64])
                E = b.edge_pose.shape[0]
                gt = torch.cat([g.edge_pose_gt for g in gs[i : i + 64]]).double()
                ex = model(b, return_extras=True)
                pe = b.pair_edge
                ni, nj = b.edge_index[0, pe], b.edge_index[1, pe]
                xi, xj = rays(b, b.pair_src, ni), rays(b, b.pair_dst, nj)
                feats = []
                for pose in (b.edge_pose.double(), ex.raw.double()):
                    rot, samp = residuals(pose, b, xi, xj, pe)
                    cnt = (
                        torch.zeros(E, dtype=torch.float64)
                        .index_add_(0, pe, torch.ones_like(rot))
                        .clamp_min(1)
                    )
                    feats += [
                        torch.zeros(E, dtype=torch.float64).index_add_(0, pe, rot) / cnt,
                        torch.zeros(E, dtype=torch.float64).index_add_(0, pe, samp.clamp_max(1.0))
                        / cnt,
                    ]
                e_in = relative_pose_errors(b.edge_pose.double(), gt)[0]
                e_fin = relative_pose_errors(ex.pose.double(), gt)[0]
                rows.append(
                    torch.stack(
                        [torch.full_like(e_in, si), e_in, e_fin, ex.gate[:, 0].double(), *feats], -1
                    )
                )
O = torch.cat(rows)
torch.save(O, "outputs/diag/epi.pt")
st, e_in, e_fin, g, rot_in, samp_in, rot_raw, samp_raw = O.T
for name, m in (
    ("<3 & g>0.5", (e_in < 3) & (g > 0.5)),
    ("3-10 & g>0.5", (e_in >= 3) & (e_in < 10) & (g > 0.5)),
    ("10-30 & g>0.5", (e_in >= 10) & (e_in < 30) & (g > 0.5)),
):
    for part, mm in (("harmed", m & (e_fin > e_in)), ("helped", m & (e_fin <= e_in))):
        print(
            f"{name:14s} {part}: n={int(mm.sum()):5d} rot-transfer in-raw med {(rot_in - rot_raw)[mm].median():+.3f}  sampson in-raw med {(samp_in - samp_raw)[mm].median():+.5f}  share in<raw(sampson) {((samp_in < samp_raw)[mm]).double().mean():.2f}"
        )
