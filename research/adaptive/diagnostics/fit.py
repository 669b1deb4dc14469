import sys

import torch

# usage: fit.py FEATURES.pt [all | COLS] [SCALE] (FEATURES.pt written by feas.py)
d = torch.load(sys.argv[1])
F, Y = d["F"], d["Y"].float()
cols = (
    slice(None)
    if len(sys.argv) < 3 or sys.argv[2] == "all"
    else [int(c) for c in sys.argv[2].split(",")]
)
F = F[:, cols]
e_in, e_fin, st = Y[:, 0], Y[:, 1], Y[:, 2].long()
mu, sd = F.mean(0), F.std(0).clamp_min(1e-6)
X = (F - mu) / sd
SC = float(sys.argv[3]) if len(sys.argv) > 3 else 1.0
BINS = [(0, 3), (3, 10), (10, 30), (30, 1e9)]


def fit(tr):
    torch.manual_seed(0)
    net = torch.nn.Sequential(
        torch.nn.Linear(X.shape[1], 32),
        torch.nn.ReLU(),
        torch.nn.Linear(32, 32),
        torch.nn.ReLU(),
        torch.nn.Linear(32, 1),
    )
    opt = torch.optim.Adam(net.parameters(), 3e-3)
    x, a, b = X[tr], e_in[tr], e_fin[tr]
    for _it in range(1500):
        z = net(x)[:, 0]
        lab = (a < b).float()
        w = (b - a).abs() / (a + SC)
        loss = (
            w * torch.nn.functional.binary_cross_entropy_with_logits(z, lab, reduction="none")
        ).sum() / w.sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return net


for test in range(6):
    net = fit(st != test)
    m = st == test
    with torch.no_grad():
        keep = torch.sigmoid(net(X[m])[:, 0]) > 0.5
    e = torch.where(keep, e_in[m], e_fin[m])
    s = f"s{test + 1}: "
    for lo, hi in BINS:
        bm = (e_in[m] >= lo) & (e_in[m] < hi)
        s += f"[{lo}-{hi:g}] {e_in[m][bm].mean():.3f} fin {e_fin[m][bm].mean():.3f} rule {e[bm].mean():.3f} | "
    print(s, f"kept {keep.float().mean():.3f}")
a, b = e_in, e_fin
print(
    "relative loss never keep",
    (b / (a + SC)).mean().item(),
    "oracle",
    (torch.minimum(a, b) / (a + SC)).mean().item(),
)
net = fit(st >= 0)
with torch.no_grad():
    p = torch.sigmoid(net(X)[:, 0])
print(
    "learned",
    ((p * a + (1 - p) * b) / (a + SC)).mean().item(),
    "p quantiles",
    torch.quantile(p, torch.tensor([0.1, 0.5, 0.9, 0.99])).tolist(),
)
