import sys

import numpy as np

d = np.load(sys.argv[1])
sets = list(d["sets"])
INP = ["KP", "BB", "GT", "GT+noise"]
e_in, e_raw, e_fin, g, s = d["e_in"], d["e_raw"], d["e_fin"], d["gate"], d["sigma"]
print("sigma cols: 0 out_rot 1 out_dir 2 in_rot 3 in_dir")
for si, name in enumerate(sets):
    m = (d["set"] == si) & (e_in < 3)
    print(
        f"{name}: <3 all n={m.sum()} in {e_in[m].mean():.4f} fin {e_fin[m].mean():.4f} d {e_fin[m].mean() - e_in[m].mean():+.4f}"
    )
    for ii, inp in enumerate(INP):
        mm = m & (d["inp"] == ii)
        if mm.sum() == 0:
            continue
        print(
            f"   {inp:9s} n={mm.sum():5d} in {e_in[mm].mean():.3f} raw {e_raw[mm].mean():.3f} fin {e_fin[mm].mean():.3f}"
            f"  gate med {np.median(g[mm, 0]):.3f} mean {g[mm, 0].mean():.3f} p90 {np.quantile(g[mm, 0], 0.9):.3f}"
            f"  sig_in {np.median(s[mm, 2]):.2f} sig_out {np.median(s[mm, 0]):.2f}"
        )
