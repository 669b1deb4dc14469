import sys

import torch
from arb import disc, triangles, views
from posernet.experiments.adaptive import make_inputs
from posernet.nn.scatter import scatter_mean
from posernet.pipeline import load_input_graphs
from sets import SETS

from posernet.geometry import quaternion_normalize
from posernet.graph import GraphBatch
from posernet.metrics import relative_pose_errors
from posernet.nn import PoserNet
from posernet.nn.adaptive import EdgeHead, _pair_stats, cycle_features
from posernet.nn.conv import graph_inputs

# usage: feas.py CKPT OUT.pt [--embeddings]; --embeddings adds the last layer's node embeddings
# of both end points (and its edge state) to the features
ckpt, out = sys.argv[1], sys.argv[2]
EMBED = "--embeddings" in sys.argv[3:]
model = PoserNet.from_checkpoint(ckpt).eval()
REC = {}
for conv in model.convs if EMBED else []:
    orig = conv.propagate

    def wrapped(x, edge_index, *a, _o=orig, **k):
        REC["h"], REC["ei"] = x, edge_index
        REC["state"] = a[5] if len(a) > 5 else k.get("edge_state")
        return _o(x, edge_index, *a, **k)

    conv.propagate = wrapped
F, Y = [], []
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
                b = GraphBatch.from_graphs(gs[i : i + 64])
                E = b.edge_pose.shape[0]
                N = b.num_nodes
                ex = model(b, return_extras=True)
                gt = torch.cat([g.edge_pose_gt for g in gs[i : i + 64]]).double()
                pin, raw, fin = b.edge_pose.double(), ex.raw.double(), ex.pose.double()
                cin = cycle_features(b.edge_index, pin, N)
                craw = cycle_features(b.edge_index, raw, N)
                gi = graph_inputs(b)
                st = _pair_stats(
                    gi["pair_edge"], gi["pair_box_src"].double(), gi["pair_box_dst"].double(), E
                )
                hf = EdgeHead.features(pin, raw, cin, craw, st)
                a_, b_, c_ = triangles(b.edge_index, N)
                qi, qf = quaternion_normalize(pin[:, :4]), quaternion_normalize(fin[:, :4])
                d_in, n = disc(views(qi), views(qf), a_, b_, c_, E)
                d_f, _ = disc(views(qf), views(qf), a_, b_, c_, E)
                eb = b.edge_batch
                B = b.num_graphs
                ctx = scatter_mean(
                    torch.stack((cin[:, 0], hf[:, 0], ex.gate[:, 0].double()), -1), eb, 0, B
                )[eb]
                feat = torch.cat(
                    (
                        hf,
                        ex.gate.double(),
                        torch.log(ex.sigma.double()),
                        torch.deg2rad(torch.stack((d_in, d_f), -1)),
                        ctx,
                        (cin[:, :1] / ctx[:, :1].clamp_min(1e-4)).log1p(),
                    ),
                    -1,
                )
                e_in = relative_pose_errors(pin, gt)[0]
                e_fin = relative_pose_errors(fin, gt)[0]
                if EMBED:
                    h = REC["h"].double()
                    ei = REC["ei"]
                    stt = REC["state"]
                    hs = torch.cat((h[ei[0]] + h[ei[1]], (h[ei[0]] - h[ei[1]]).abs()), -1)
                    extra = [hs] + ([stt.double().reshape(E, -1)] if stt is not None else [])
                    feat = torch.cat([feat, *extra], -1)
                F.append(feat.float())
                Y.append(
                    torch.stack(
                        (
                            e_in,
                            e_fin,
                            torch.full((E,), si, dtype=torch.float64),
                            torch.full((E,), ii, dtype=torch.float64),
                        ),
                        -1,
                    )
                )
F, Y = torch.cat(F), torch.cat(Y)
torch.save({"F": F, "Y": Y}, out)
print(F.shape)
