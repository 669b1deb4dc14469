"""Scale: ``posernet-reconstruct`` on 16, 64 and 256 rendered images with each pair-selection
mode, wall time and peak memory per stage, accuracy against ground truth.

Each run is one ``posernet-reconstruct`` subprocess (``cache=false``: nothing reused) on a
rendered 7-Scenes-layout sequence (``posernet.data.render``, 640x480, ground-truth poses),
with ``pairs.mode`` set to ``exhaustive`` (only up to ``--exhaustive-max`` images: it matches
N(N-1)/2 pairs), ``sequential`` or ``retrieval``. Per run the table gives the pairs matched,
cameras placed and the largest component, the median absolute rotation / position errors on
it, the wall time and peak memory of the process, and per stage (from the run's
``summary.json``: images = proposals and features, pairs = matching and two-view verification,
BA = tracks, triangulation and bundle adjustment) its wall time and the peak memory at its
end; then, per size, each mode's errors relative to exhaustive where exhaustive ran, and the
time per image (roughly constant when time grows linearly).

    python benchmarks/bench_scale.py                       # 16, 64, 256 images, 2 threads
    python benchmarks/bench_scale.py --quick               # 8 and 16 images at 320x240
    python benchmarks/bench_scale.py --sizes 1000 --modes retrieval   # a GPU machine

Writes ``benchmarks/results/scale.md`` and ``scale.json`` (``--quick``: under
``benchmarks/results/quick/``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import bench_real as br  # noqa: E402  (benchmarks/ on the path first)

MODES = ("exhaustive", "sequential", "retrieval")
STAGES = ("images", "pair_selection", "pairs", "graph", "averaging", "bundle_adjustment")
HEADER = ["images", "pairs mode", "pairs", "placed", "largest", "abs. rot (deg)",
          "abs. pos (GT units)", "wall (s)", "s / image", "peak mem (MB)",
          "images (s)", "selection (s)", "pairs (s)", "averaging (s)", "BA (s)", "note"]


def stage_row(summary: dict[str, Any]) -> dict[str, dict[str, float]]:
    """The ``stages`` record of a run's ``summary.json`` (empty when absent)."""
    return dict(summary.get("stages") or {})


def run(size: int, mode: str, work: Path, threads: int, timeout: float, quick: bool,
        scene: str) -> dict[str, Any]:
    """One reconstruction of ``size`` rendered frames with ``pairs.mode=mode``."""
    w, h = (320, 240) if quick else (640, 480)
    s = br.rendered_set(work / "render", scene, size, w, h)
    s.name = f"{scene}-{size}"
    method = br.Method(mode, "posernet", [f"pairs.mode={mode}", "cache=false"])
    row = br.run_method(s, method, work, threads, timeout)
    row.update(size=size, mode=mode)
    summary = work / "runs" / s.name / mode / "out" / "summary.json"
    if summary.is_file():
        data = json.loads(summary.read_text(encoding="utf-8"))
        row["stages"] = stage_row(data)
        row["pairs"] = (data.get("pair_selection") or {}).get("n_pairs")
        row["pair_components"] = (data.get("pair_selection") or {}).get("components")
    return row


def _f(v: Any, fmt: str = "{:.2f}") -> str:
    return br._cell(v, fmt)


def table_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    out = []
    for r in rows:
        st = r.get("stages") or {}

        def sec(name: str, st: dict = st) -> str:
            return _f((st.get(name) or {}).get("seconds"), "{:.1f}")

        per = r["wall_s"] / r["size"] if r.get("wall_s") == r.get("wall_s") else float("nan")
        out.append([str(r["size"]), r["mode"], _f(r.get("pairs"), "{}"),
                    f"{_f(r.get('placed'), '{}')} / {r['size']}", _f(r.get("largest"), "{}"),
                    _f(r.get("rot_deg")), _f(r.get("pos"), "{:.3f}"),
                    _f(r.get("wall_s"), "{:.1f}"), _f(per, "{:.2f}"),
                    _f(r.get("peak_mb"), "{:.0f}"), sec("images"), sec("pair_selection"),
                    sec("pairs"), sec("averaging"), sec("bundle_adjustment"),
                    r.get("note", "")])
    return out


def relative_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    """Per size and mode: errors and wall time relative to exhaustive at that size."""
    out = []
    ref = {r["size"]: r for r in rows if r["mode"] == "exhaustive" and not r.get("note")}
    for r in rows:
        e = ref.get(r["size"])
        if e is None or r["mode"] == "exhaustive" or r.get("note"):
            continue

        def ratio(k: str, r: dict = r, e: dict = e) -> str:
            a, b = r.get(k), e.get(k)
            return _f(a / b if a is not None and b else float("nan"), "{:.2f}")

        out.append([str(r["size"]), r["mode"], ratio("pairs"), ratio("rot_deg"),
                    ratio("pos"), ratio("wall_s")])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=None,
                    help="images per run (default 16 64 256; --quick: 8 16)")
    ap.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    ap.add_argument("--exhaustive-max", type=int, default=64,
                    help="largest size run with pairs.mode=exhaustive")
    ap.add_argument("--threads", type=int, default=2, help="workers and threads per run")
    ap.add_argument("--scene", default="chess", help="preset of the rendered scene")
    ap.add_argument("--timeout", type=float, default=1800, help="seconds per run")
    ap.add_argument("--work", default=None, help="renders and run outputs (default: temp)")
    ap.add_argument("--quick", action="store_true", help="8 and 16 images at 320x240")
    ap.add_argument("--out", default=None, help="results table (default results/scale.md)")
    args = ap.parse_args(argv)
    sizes = args.sizes or ([8, 16] if args.quick else [16, 64, 256])
    if min(sizes) < 2:
        raise SystemExit("bench_scale: --sizes must be >= 2")
    work = Path(args.work or Path(tempfile.gettempdir()) / "posernet-bench-scale")
    work.mkdir(parents=True, exist_ok=True)
    compiled = br.compile_bytecode()
    rows = []
    for n in sizes:
        for mode in args.modes:
            if mode == "exhaustive" and n > args.exhaustive_max:
                continue
            rows.append(run(n, mode, work, args.threads, args.timeout, args.quick, args.scene))

    from _common import command, table, write_results

    from posernet.io import atomic_write_json

    body = [
        f"- packages: {', '.join(f'{k} {v}' for k, v in br.versions().items() if k != 'python')}",
        f"- scene: rendered `{args.scene}` sequence ({'320x240' if args.quick else '640x480'}, "
        f"ground-truth poses); {args.threads} worker thread(s) per run; `cache=false`; other "
        "options at their defaults (SIFT, verification, rotation+translation averaging, BA); "
        f"{compiled}",
        "- errors on the largest component: abs. rot after the best global rotation, abs. pos "
        "after a similarity on the camera centres (medians). Stage times from the run's "
        "summary.json (images: features; pairs: matching + verification; BA: tracks, "
        "triangulation, bundle adjustment); wall time and peak memory of the whole process",
        "",
        *table(HEADER, table_rows(rows)),
        "",
        "Relative to exhaustive at the same size (ratios; < 1 is fewer / better / faster):",
        "",
        *table(["images", "pairs mode", "pairs", "abs. rot", "abs. pos", "wall"],
               relative_rows(rows)),
    ]
    md = write_results("scale", "posernet-reconstruct from 16 to 256 images", body,
                       args.quick, "cpu", args.out)
    report = {"command": command(), "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
              "machine": {"cores": os.cpu_count(), "threads_per_run": args.threads},
              "versions": br.versions(), "arguments": vars(args), "rows": rows}
    path = atomic_write_json(md.with_suffix(".json"), br._jsonable(report))
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
