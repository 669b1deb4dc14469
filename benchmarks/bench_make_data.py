"""Generation time of a synthetic dataset preset (``posernet.data.synthetic``).

Generates the preset (optionally a fraction of its graph counts) once per worker count, prints
wall time and throughput, extrapolates a fraction to the full preset, times the simulator's
stages on one scene, and writes ``benchmarks/results/make_data.md`` atomically.

    python benchmarks/bench_make_data.py --preset tiny --workers 1 2
    python benchmarks/bench_make_data.py --preset paper --fraction 0.1 --workers 2
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from posernet.data.layout import SIZES, SPLITS
from posernet.data.synthetic import SceneWorld, generate_dataset, load_preset
from posernet.data.synthetic.config import DatasetOptions, options_from_dict
from posernet.io import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results" / "make_data.md"


def scaled(opts: DatasetOptions, fraction: float, small_only: bool = False) -> DatasetOptions:
    """Small-graph counts times ``fraction`` (at least 1 where non-zero); large graphs kept
    (or dropped with ``small_only``)."""
    d = opts.to_dict()
    for split in SPLITS:
        n = d["small"][split]
        d["small"][split] = max(1, round(n * fraction)) if n else 0
        if small_only:
            d["large"][split] = 0
    return options_from_dict(d)


def count_graphs(opts: DatasetOptions) -> dict[str, int]:
    return {
        size: sum(getattr(getattr(opts, size), s) for s in SPLITS) * len(opts.scenes_for(size))
        for size in SIZES
    }


def stage_times(opts: DatasetOptions, scene: str, n: int = 30) -> dict[str, float]:
    """Milliseconds per simulated image and per evaluated image pair (one process)."""
    import cv2

    cv2.setNumThreads(1)
    world = SceneWorld(opts, scene, seed=123)
    frames = world.pools["train"].frames
    rng = np.random.default_rng(0)
    pick = rng.choice(frames, size=min(n, frames.size), replace=False)
    t0 = time.perf_counter()
    for f in pick:
        world.frame(int(f))
    t_frame = (time.perf_counter() - t0) / len(pick) * 1e3
    pairs = [(int(pick[i]), int(pick[i + 1])) for i in range(len(pick) - 1)]
    # nearby frames too, so that some pairs reach the 5-point stage
    pairs += [(int(f), int(f) + 2) for f in pick if int(f) + 2 < world.num_frames]
    t0 = time.perf_counter()
    edges = sum(world.pair(a, b).status != "unmatched" for a, b in pairs)
    t_pair = (time.perf_counter() - t0) / len(pairs) * 1e3
    return {"frame_ms": t_frame, "pair_ms": t_pair, "pairs": len(pairs), "matched": edges}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny")
    ap.add_argument(
        "--fraction",
        type=float,
        default=1.0,
        help="scale the small-graph counts (large graphs are kept)",
    )
    ap.add_argument("--small-only", action="store_true", help="skip the large graphs")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="scratch directory (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the generated datasets")
    ap.add_argument("--no-write", action="store_true", help="do not write the results table")
    args = ap.parse_args()

    base = load_preset(args.preset)
    opts = scaled(base, args.fraction, args.small_only)
    if args.small_only:
        base = scaled(base, 1.0, True)
    scratch = Path(args.out or tempfile.mkdtemp(prefix="bench_make_data_"))
    rows = []
    for w in args.workers:
        out = scratch / f"{args.preset}_w{w}"
        if out.exists():
            shutil.rmtree(out)
        t0 = time.perf_counter()
        m = generate_dataset(opts, out, seed=args.seed, workers=w, progress=False, echo=None)
        wall = time.perf_counter() - t0
        graphs = sum(f["graphs"] for f in m["files"].values())
        edges = sum(f["edges"] for f in m["files"].values())
        st = m["statistics"].get("small", {}).get("test") or {}
        rows.append(
            {
                "workers": w,
                "wall": wall,
                "graphs": graphs,
                "edges": edges,
                "kp": st.get("kp"),
                "bb": st.get("bb"),
            }
        )
        print(
            f"{args.preset} x{args.fraction:g} workers={w}: {wall:.1f} s, {graphs} graphs, "
            f"{edges} edges, {graphs / wall:.2f} graphs/s, {edges / wall:.0f} edges/s"
        )
        if not args.keep:
            shutil.rmtree(out, ignore_errors=True)
    stages = stage_times(opts, opts.scenes[0])
    print(
        f"stages ({opts.scenes[0]}, 1 process): {stages['frame_ms']:.1f} ms per image, "
        f"{stages['pair_ms']:.1f} ms per image pair ({stages['matched']}/{stages['pairs']} "
        f"pairs matched and went through both 5-point estimates)"
    )

    full = count_graphs(base)
    part = count_graphs(opts)
    lines = [
        "# Synthetic dataset generation time",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} CPU cores visible, "
        f"{platform.python_implementation()} {platform.python_version()}. "
        f"Command: `python benchmarks/bench_make_data.py --preset {args.preset} "
        f"--fraction {args.fraction:g} --workers {' '.join(map(str, args.workers))}"
        f"{' --small-only' if args.small_only else ''}`. Wall times depend on what else runs "
        f"on the machine (load average at the start: {os.getloadavg()[0]:.1f}).",
        "",
        f"Preset `{args.preset}`: {full['small']} small + {full['large']} large graphs in full; "
        f"this run: {part['small']} small + {part['large']} large.",
        "",
        "| workers | wall (s) | graphs | edges | graphs/s | KP eta rot/tdir | BB eta rot/tdir |"
        " full preset, extrapolated (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def eta(t: dict | None) -> str:
        if not t:
            return "-"
        return f"{t['rot']['median']:.1f} / {t['tdir']['median']:.1f}"

    for r in rows:
        # linear in the small-graph count; large graphs (kept in full) do not scale
        if args.fraction == 1.0:
            est = f"{r['wall']:.0f}"
        elif args.small_only:
            est = f"{r['wall'] / args.fraction:.0f} (wall / fraction)"
        else:
            est = "- (use --small-only)"
        lines.append(
            f"| {r['workers']} | {r['wall']:.1f} | {r['graphs']} | {r['edges']} | "
            f"{r['graphs'] / r['wall']:.2f} | {eta(r['kp'])} | {eta(r['bb'])} | {est} |"
        )
    lines += [
        "",
        f"Stages on `{opts.scenes[0]}` (one process): {stages['frame_ms']:.1f} ms per simulated "
        f"image, {stages['pair_ms']:.1f} ms per evaluated image pair "
        f"({stages['matched']} of {stages['pairs']} pairs matched >= 5 boxes and ran both "
        f"5-point estimates).",
        "",
    ]
    text = "\n".join(lines)
    if not args.no_write:
        atomic_write_text(RESULTS, text)
        print(f"wrote {RESULTS}")
    if not args.out and not args.keep:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
