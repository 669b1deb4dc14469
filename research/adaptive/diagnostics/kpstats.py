"""Do RANSAC support statistics of the KP estimate (keypoints, inliers, inlier spread) tell
good KP inputs from bad ones, beyond what the shipped model's own input-error scale knows?"""

import json
import sys

import numpy as np
import torch
from posernet.pipeline import load_input_graphs

import posernet.data.synthetic.world as W
from posernet.data.synthetic.config import options_from_dict
from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet

REC = []
orig = W.five_point


def fp(p1, p2, K, thr, *a, **k):
    res = orig(p1, p2, K, thr, *a, **k)
    n = p1.shape[0]
    ninl = 0
    spread = 0.0
    med = np.nan
    if res is not None:
        R, t = res
        tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
        Ki = np.linalg.inv(K)
        F = Ki.T @ tx @ R @ Ki
        x1 = np.c_[p1, np.ones(n)]
        x2 = np.c_[p2, np.ones(n)]
        Fx1 = x1 @ F.T
        Ftx2 = x2 @ F
        num = np.sum(x2 * Fx1, 1) ** 2
        den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
        d = np.sqrt(num / np.maximum(den, 1e-12))
        inl = d < thr
        ninl = int(inl.sum())
        med = float(np.median(d[inl])) if ninl else np.nan
        if ninl > 2:
            spread = float(np.sqrt(np.linalg.det(np.cov(p1[inl].T)) + 1e-9))
    REC.append((n, ninl, spread, med))
    return res


W.five_point = fp
model = PoserNet.from_checkpoint("src/posernet/checkpoints/posernet_synthetic_kp.ckpt").eval()
rows = []
for si, roots in enumerate(sys.argv[1:]):
    for root in roots.split(","):
        man = json.load(open(f"outputs/data/{root}/manifest.json"))
        opts = options_from_dict(man["config"])
        graphs = load_input_graphs(
            f"outputs/data/{root}", split="test", estimate=None, log=lambda *_: None
        )[:150]
        worlds = {}
        for g in graphs:
            sc = g.meta["scene"]
            if sc not in worlds:
                worlds[sc] = W.SceneWorld(opts, sc, int(g.meta["seed"]))
            w = worlds[sc]
            fr = [int(x) for x in g.meta["frames"].split(",")]
            feats = []
            for s, d in g.edge_index.T.tolist():
                a, b = sorted((fr[s], fr[d]))
                REC.clear()
                w._pairs.pop((a, b), None)
                w.pair(a, b)
                feats.append(REC[0])
            g = g.with_estimate("kp")
            with torch.no_grad():
                ex = model(GraphBatch.from_graphs([g]), return_extras=True)
            gt = g.edge_pose_gt.double()
            e_in = relative_pose_errors(g.edge_pose.double(), gt)[0]
            e_fin = relative_pose_errors(ex.pose.double(), gt)[0]
            f = torch.tensor(feats, dtype=torch.float64)
            rows.append(
                torch.cat(
                    (
                        torch.full((len(e_in), 1), float(si)),
                        e_in[:, None],
                        e_fin[:, None],
                        ex.gate[:, :1].double(),
                        torch.rad2deg(ex.sigma.double()),
                        f,
                    ),
                    1,
                )
            )
O = torch.cat(rows)
torch.save(O, "outputs/diag/kpstats.pt")
print(O.shape)
