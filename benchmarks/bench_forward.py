"""PoserNet forward pass on the paper's test set size: 7000 graphs batched, fast vs literal path.

Both paths run in this process on the same batch with the same weights (the shipped
checkpoint): the fast path (``PoserConv(fused=True)``, the default) and the literal one
(``fused=False``: every matched pair runs both MLPs on its concatenated message, the code before
the fused path). Reported: best-of-``--repeat`` wall time, graphs/s, the ratio, the largest output
difference between the paths, and the top operators of the fast path (what bounds it).

    python benchmarks/bench_forward.py                 # 7000 graphs -> results/forward.md
    python benchmarks/bench_forward.py --quick         # 1400 graphs -> results/quick/forward.md
    python benchmarks/bench_forward.py --device cuda
    git worktree add /tmp/before <commit>              # the code to compare with, then:
    python benchmarks/bench_forward.py --baseline /tmp/before/src

``--baseline SRC`` also times the fast path of an older checkout (its ``src`` folder) on the same
batch and weights, in a subprocess of this run that imports ``posernet`` from there, once before
and once after this checkout's runs (the best of both: a shared machine's load changes), row
"before", with the largest output difference.
"""

from __future__ import annotations

import argparse
import copy
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import torch
from _common import baseline_label, best_of, fmt_s, paper_batch, table, write_results

from posernet.checkpoints import CheckpointError
from posernet.nn import PoserConv, PoserNet

# the paper's architecture (depth 2, 3x32 MLPs): the checkpoint shipped before the
# input-adaptive one, kept in the package for exactly such comparisons
SHIPPED = "src/posernet/checkpoints/posernet_synthetic_kp_v1.ckpt"


def load_model() -> PoserNet:
    path = Path(__file__).resolve().parents[1] / SHIPPED
    try:
        return PoserNet.from_checkpoint(path)
    except CheckpointError:  # an installed package without the checkpoint: random weights
        torch.manual_seed(0)
        return PoserNet().eval()


def literal(model: PoserNet) -> PoserNet:
    ref = copy.deepcopy(model)
    for m in ref.modules():
        if isinstance(m, PoserConv):
            m.fused = False
    return ref


def profile_rows(fn, n: int = 8) -> list[list[str]]:
    from torch.profiler import profile

    with profile() as prof:
        fn()
    events = sorted(prof.key_averages(), key=lambda e: -e.self_cpu_time_total)
    total = sum(e.self_cpu_time_total for e in events) or 1.0
    return [[e.key, f"{100 * e.self_cpu_time_total / total:.1f} %", str(e.count)]
            for e in events[:n]]


def run_baseline(args: argparse.Namespace, n: int, repeat: int) -> dict:
    """The fast path of the checkout whose ``src`` is ``args.baseline``, on the same batch
    (a subprocess of this script in ``--worker`` mode): ``{time, times, out}``."""
    src = str(Path(args.baseline).resolve())
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [src] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    with tempfile.TemporaryDirectory() as tmp:
        out = str(Path(tmp) / "baseline.pt")
        subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", out,
                        "--graphs", str(n), "--repeat", str(repeat), "--threads",
                        str(args.threads), "--device", args.device], env=env, check=True)
        return torch.load(out)


def worker(args: argparse.Namespace, n: int, repeat: int) -> None:
    """``--baseline``'s subprocess: time the fast path of the ``posernet`` on the path."""
    batch = paper_batch(n).to(args.device)
    model = load_model().to(args.device)
    with torch.no_grad():
        out = model(batch)
        t, times = best_of(lambda: model(batch), repeat, args.device)
    torch.save({"time": t, "times": times, "out": out.cpu()}, args.worker)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--graphs", type=int, default=None, help="graphs in the batch (7000)")
    ap.add_argument("--quick", action="store_true", help="1400 graphs, fewer repeats")
    ap.add_argument("--repeat", type=int, default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action="store_true", help="also time torch.compile(model)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--baseline", default=None, metavar="SRC",
                    help="the src folder of an older checkout: time its fast path too")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # internal: --baseline
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    n = args.graphs or (1400 if args.quick else 7000)
    repeat = args.repeat or (2 if args.quick else 3)
    dev = args.device
    if args.worker:
        worker(args, n, repeat)
        return
    base = run_baseline(args, n, repeat) if args.baseline else None

    batch = paper_batch(n).to(dev)
    model = load_model().to(dev)
    ref = literal(model)
    print(f"{n} graphs: {batch.num_edges} edges, {batch.num_pairs} matched pairs", flush=True)
    with torch.no_grad():
        fast_out = model(batch)
        ref_out = ref(batch)
        diff = float((fast_out - ref_out).abs().max())
        t_fast, all_fast = best_of(lambda: model(batch), repeat, dev)
        print(f"fast path: {fmt_s(t_fast)} {[round(t, 3) for t in all_fast]}", flush=True)
        if base is not None:  # once more after this checkout's runs: the best of both
            again = run_baseline(args, n, repeat)
            if again["time"] < base["time"]:
                base = {**again, "times": base["times"] + again["times"]}
            else:
                base = {**base, "times": base["times"] + again["times"]}
        t_ref, all_ref = best_of(lambda: ref(batch), max(1, repeat - 1), dev)
        print(f"literal path: {fmt_s(t_ref)} {[round(t, 3) for t in all_ref]}", flush=True)
        rows = [["literal path (`fused=False`, before the fused path)", fmt_s(t_ref),
                 f"{n / t_ref:.0f}", "1.0x"],
                ["fast path (default)", fmt_s(t_fast), f"{n / t_fast:.0f}",
                 f"{t_ref / t_fast:.1f}x"]]
        if base is not None:
            name = baseline_label(args.baseline)
            base_diff = float((fast_out.cpu() - base["out"]).abs().max())
            print(f"fast path of {name}: {fmt_s(base['time'])} "
                  f"{[round(t, 3) for t in base['times']]}", flush=True)
            rows.insert(1, [f"fast path of {name} (`--baseline`)", fmt_s(base["time"]),
                            f"{n / base['time']:.0f}", f"{t_ref / base['time']:.1f}x"])
        if args.compile:
            compiled = torch.compile(model)
            t_c, _ = best_of(lambda: compiled(batch), repeat, dev, warmup=2)
            rows.append(["fast path, `torch.compile`", fmt_s(t_c), f"{n / t_c:.0f}",
                         f"{t_ref / t_c:.1f}x"])
        prof = profile_rows(lambda: model(batch)) if dev == "cpu" else []
    body = [
        f"Input: {n} random 8-image view graphs of the paper's test-graph size, one batch: "
        f"{batch.num_edges} edges, {batch.num_pairs} matched detection pairs "
        f"({batch.num_pairs / batch.num_edges:.1f} per edge); the paper-architecture checkpoint "
        f"posernet_synthetic_kp_v1.ckpt (depth 2, "
        "3x32 MLPs), float32, `torch.no_grad()`. Best of "
        f"{repeat} runs (literal path: best of {max(1, repeat - 1)}), both paths in this "
        "process on the same batch.",
        "",
        *table(["path", "forward", "graphs/s", "speed-up"], rows),
        "",
        f"Largest output difference between the paths: {diff:.1e} (float32 round-off).",
    ]
    if base is not None:
        body += ["", f"Fast path before ({baseline_label(args.baseline)}, a subprocess of this "
                 f"run, same batch and weights) / now: {base['time'] / t_fast:.2f}x; largest "
                 f"output difference {base_diff:.1e}."]
    if prof:
        body += ["", "Where the fast path's time goes (torch profiler, self CPU time):", "",
                 *table(["operator", "share", "calls"], prof)]
    write_results("forward", "PoserNet forward, paper-size test set, batched", body, args.quick,
                  dev, args.out)


if __name__ == "__main__":
    main()
