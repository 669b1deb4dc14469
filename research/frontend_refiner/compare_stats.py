"""Side-by-side statistics of front-end graph datasets (rendered vs real): what the refiner sees.

Per dataset (``posernet-make-data`` folders, the split given): graphs, boxes per image, matched
box pairs per edge, edges per node, focal lengths, and the per-edge initial KP / BB errors
(median rotation and translation-direction error; share of KP edges over 10 degrees).
Usage: ``compare_stats.py SPLIT NAME=DIR [NAME=DIR ...]``; prints a markdown table.
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from posernet.data.store import open_split
from posernet.metrics import relative_pose_errors


def stats(root: str, split: str) -> dict[str, float]:
    graphs = open_split(root, "small", split, None)
    boxes, pairs, epn, focal, err = [], [], [], [], {"kp": [], "bb": []}
    for g in graphs:
        n = int(g.node_attr.shape[0])
        boxes += torch.bincount(g.det_node, minlength=n).tolist()
        pairs += torch.bincount(g.pair_edge, minlength=g.num_edges).tolist()
        epn.append(2 * g.num_edges / n)
        focal += g.K[:, 0, 0].tolist()
        for est in ("kp", "bb"):
            rot, tdir = relative_pose_errors(g.with_estimate(est).edge_pose.double(),
                                             g.edge_pose_gt.double())
            err[est].append(torch.stack([rot, tdir], 1))
    kp, bb = torch.cat(err["kp"]).numpy(), torch.cat(err["bb"]).numpy()
    return {"graphs": len(graphs), "edges": len(kp), "boxes/img": float(np.mean(boxes)),
            "pairs/edge": float(np.mean(pairs)), "edges/node": float(np.mean(epn)),
            "focal": f"{min(focal):.0f}-{max(focal):.0f}",
            "KP rot": float(np.median(kp[:, 0])), "KP tdir": float(np.median(kp[:, 1])),
            "KP >10°": float((kp[:, 0] > 10).mean() * 100),
            "BB rot": float(np.median(bb[:, 0])), "BB tdir": float(np.median(bb[:, 1]))}


def main(argv: list[str]) -> None:
    split, sets = argv[0], [a.split("=", 1) for a in argv[1:]]
    rows = [(name, stats(root, split)) for name, root in sets]
    cols = list(rows[0][1])
    print("| set | " + " | ".join(cols) + " |")
    print("|---|" + "---:|" * len(cols))
    for name, r in rows:
        cells = [f"{v:.1f}" if isinstance(v, float) else str(v) for v in r.values()]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main(sys.argv[1:])
