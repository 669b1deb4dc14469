import sys

import numpy as np

d = np.load(sys.argv[1])
si = int(sys.argv[2])
e_in, e_raw, e_fin, g, s = d["e_in"], d["e_raw"], d["e_fin"], d["gate"], d["sigma"]


# angle between input and raw rotation
def qang(a, b):
    dot = np.abs((a[:, :4] * b[:, :4]).sum(-1)).clip(0, 1)
    return np.degrees(2 * np.arccos(dot))


dir_ = qang(d["q_in"], d["q_raw"])
for ii, inp in enumerate(["KP", "BB", "GT", "GT+noise"]):
    m = (d["set"] == si) & (e_in < 3) & (d["inp"] == ii)
    dd = e_fin[m] - e_in[m]
    o = np.argsort(-np.abs(dd))
    tot = dd.sum()
    print(
        f"{inp}: n={m.sum()} total change {tot:+.2f} (mean {dd.mean():+.4f}); pos {dd[dd > 0].sum():+.2f} neg {dd[dd < 0].sum():+.2f}"
    )
    for _q in [0, 0.5, 0.9]:
        pass
    # contribution by gate bucket
    for lo, hi in [(0, 0.01), (0.01, 0.05), (0.05, 0.2), (0.2, 0.5), (0.5, 1.01)]:
        b = (g[m, 0] >= lo) & (g[m, 0] < hi)
        if b.sum():
            print(
                f"   gate {lo:.2f}-{hi:.2f}: n={b.sum():5d} change sum {dd[b].sum():+7.2f} mean {dd[b].mean():+.3f}  raw-in ang {np.median(dir_[m][b]):6.2f} e_raw {e_raw[m][b].mean():.2f}"
            )
