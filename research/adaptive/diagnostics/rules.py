import sys

import torch

O = torch.load(sys.argv[1])
st, e_in, e_fin, g, sp, rin, e_m = O.T[:7]
B = [(0, 3), (3, 10), (10, 30), (30, 1e9)]
rules = {"none": e_fin, "ensmean-raw": e_m}
for t in (1.5, 2, 3):
    for c in (6, 10, 15):
        rules[f"t{t}c{c}"] = torch.where((sp > t) & (rin < c), e_in, e_fin)
        rules[f"mean+t{t}c{c}"] = torch.where((sp > t) & (rin < c), e_in, e_m)
for t, e in rules.items():
    line = f"{t:14s}: "
    for s in range(6):
        m = st == s
        line += (
            f"s{s + 1} "
            + "/".join(
                f"{e[m & (e_in >= lo) & (e_in < hi)].mean() - e_in[m & (e_in >= lo) & (e_in < hi)].mean():+.3f}"
                for lo, hi in B
            )
            + "  "
        )
    print(line)
