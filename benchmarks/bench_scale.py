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

Beside posernet, at each size, COLMAP's global mapper (GLOMAP, ``pycolmap.global_mapping``,
run by bench_real's COLMAP worker in its own process) on the same rendered images with the
same fixed intrinsics, SIFT, the same threads and sequential matching (overlap 10, quadratic
overlap); one table per size puts it side by side with posernet's ``pairs.mode=sequential``
run: wall time and its ratio, CPU time, peak memory, pairs, cameras placed, errors after the
same alignment, and the stage times each side reports (posernet's summary.json; COLMAP's
feature extraction, matching + verification and mapper as the worker times them).
``--no-colmap`` leaves it out; without pycolmap (a benchmark-only extra, ``pip install
pycolmap==4.2.1``) it is left out with a note.

    python benchmarks/bench_scale.py                       # 16, 64, 256 images, 2 threads
    python benchmarks/bench_scale.py --quick               # 8 and 16 images at 320x240
    python benchmarks/bench_scale.py --sizes 1000 --modes retrieval   # a GPU machine
    python benchmarks/bench_scale.py --sizes 256 1024 --modes sequential \
        --out benchmarks/results/scale_colmap.md      # posernet and COLMAP, sequential

Writes ``benchmarks/results/scale.md`` and ``scale.json`` (``--quick``: under
``benchmarks/results/quick/``).
"""

from __future__ import annotations

import argparse
import json
import math
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
COLMAP = "colmap-global"  # COLMAP's global mapper (GLOMAP), beside posernet at every size
COLMAP_MATCHING = "sequential"  # ... compared with posernet's run of the same pairs mode
STAGES = ("images", "pair_selection", "pairs", "graph", "averaging", "bundle_adjustment")
HEADER = ["images", "pairs mode", "pairs", "placed", "largest", "abs. rot (deg)",
          "abs. pos (GT units)", "wall (s)", "s / image", "peak mem (MB)",
          "images (s)", "selection (s)", "pairs (s)", "averaging (s)", "BA (s)", "note"]


def stage_row(summary: dict[str, Any]) -> dict[str, dict[str, float]]:
    """The ``stages`` record of a run's ``summary.json`` (empty when absent)."""
    return dict(summary.get("stages") or {})


def _load() -> float:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def _scene_set(size: int, work: Path, quick: bool, scene: str) -> br.ImageSet:
    w, h = (320, 240) if quick else (640, 480)
    s = br.rendered_set(work / "render", scene, size, w, h)
    s.name = f"{scene}-{size}"
    return s


def run(size: int, mode: str, work: Path, threads: int, timeout: float, quick: bool,
        scene: str) -> dict[str, Any]:
    """One reconstruction of ``size`` rendered frames with ``pairs.mode=mode``."""
    s = _scene_set(size, work, quick, scene)
    method = br.Method(mode, "posernet", [f"pairs.mode={mode}", "cache=false"])
    load = _load()
    row = br.run_method(s, method, work, threads, timeout)
    row.update(size=size, mode=mode, load_start=load)
    summary = work / "runs" / s.name / mode / "out" / "summary.json"
    if summary.is_file():
        data = json.loads(summary.read_text(encoding="utf-8"))
        row["stages"] = stage_row(data)
        row["pairs"] = (data.get("pair_selection") or {}).get("n_pairs")
        row["pair_components"] = (data.get("pair_selection") or {}).get("components")
        row["verified"] = data.get("edges")
    return row


def run_colmap(size: int, work: Path, threads: int, timeout: float, quick: bool,
               scene: str, seed: int = 0) -> dict[str, Any]:
    """COLMAP's global mapper on the same ``size`` rendered frames (bench_real's worker: SIFT
    with the set's intrinsics fixed, sequential matching, ``threads`` threads)."""
    s = _scene_set(size, work, quick, scene)
    load = _load()
    row = br.run_method(s, br.Method(COLMAP, COLMAP), work, threads, timeout, seed,
                        colmap_matching=COLMAP_MATCHING)
    row.update(size=size, mode=COLMAP_MATCHING, load_start=load)
    inside = row.get("seconds_inside")
    if isinstance(inside, dict):  # the worker's own timing of its steps
        row["stages"] = {k: {"seconds": v} for k, v in inside.items()}
    pairs = row.get("colmap_pairs") or {}
    row["pairs"], row["verified"] = pairs.get("matched"), pairs.get("verified")
    return row


def _f(v: Any, fmt: str = "{:.2f}") -> str:
    return br._cell(v, fmt)


def _is_posernet(r: dict[str, Any]) -> bool:
    return r.get("kind", "posernet") == "posernet"


def table_rows(rows: list[dict[str, Any]]) -> list[list[str]]:
    """The posernet table: one line per run (COLMAP rows are in :func:`compare_rows`)."""
    out = []
    for r in rows:
        if not _is_posernet(r):
            continue
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
    rows = [r for r in rows if _is_posernet(r)]
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


# posernet's stages (summary.json) and COLMAP's steps (the worker's timing) per line of the
# side-by-side table; None: that side has no such step of its own (it is inside another)
POSERNET_STEPS = {"features": ("images",), "matching": ("pair_selection", "pairs"),
                  "averaging": ("graph", "averaging"), "ba": ("bundle_adjustment",),
                  "check": ("self_check",),
                  "mapper": ("graph", "averaging", "bundle_adjustment", "self_check")}
COLMAP_STEPS = {"features": ("features",), "matching": ("matching",), "averaging": None,
                "ba": None, "check": None, "mapper": ("mapping",)}
COMPARE_HEADER = ["", "posernet", "COLMAP global", "posernet / COLMAP"]


def _seconds(r: dict[str, Any] | None, names: tuple[str, ...] | None) -> float | None:
    """Summed seconds of the stages ``names`` of run ``r`` (``None``: not reported)."""
    if r is None or names is None:
        return None
    st = r.get("stages") or {}
    vals = [(st.get(n) or {}).get("seconds") for n in names]
    vals = [v for v in vals if v is not None]
    return float(sum(vals)) if vals else None


def _rest(r: dict[str, Any] | None) -> float | None:
    """Wall time outside the reported stages: interpreter start, imports, reading and
    writing (and for COLMAP the steps it does not time)."""
    if r is None or r.get("wall_s") is None:
        return None
    st = r.get("stages") or {}
    if not st:
        return None
    return float(r["wall_s"]) - sum(float((v or {}).get("seconds") or 0.0) for v in st.values())


def compare_rows(p: dict[str, Any] | None, c: dict[str, Any] | None) -> list[list[str]]:
    """One size, side by side: posernet's run ``p`` and COLMAP's ``c`` (either may be
    ``None`` or a failed / skipped row); the last column is posernet / COLMAP."""

    def num(r: dict[str, Any] | None, key: str) -> float | None:
        v = None if r is None else r.get(key)
        return None if v is None or (isinstance(v, float) and not math.isfinite(v)) else v

    def line(label: str, a: Any, b: Any, fmt: str, ratio: bool = True) -> list[str]:
        q = a / b if ratio and isinstance(a, int | float) and isinstance(b, int | float) \
            and b else None
        return [label, _f(a, fmt), _f(b, fmt), _f(q, "{:.2f}") if ratio else ""]

    def placed(r: dict[str, Any] | None) -> str:
        if r is None or r.get("placed") is None:
            return "-"
        return f"{r['placed']} / {r['size']}"

    def trust(r: dict[str, Any] | None) -> str:
        if r is None or r.get("right") is None:
            return "-"
        return f"{r['right']} / {r['wrong']}"

    def steps(key: str, label: str) -> list[str]:
        a, b = _seconds(p, POSERNET_STEPS[key]), _seconds(c, COLMAP_STEPS[key])
        row = line(label, a, b, "{:.1f}")
        if c is not None and c.get("stages") and COLMAP_STEPS[key] is None:
            row[2] = "(in mapper)"
        return row

    return [
        line("wall (s)", num(p, "wall_s"), num(c, "wall_s"), "{:.1f}"),
        line("CPU, user + system (s)", num(p, "cpu_s"), num(c, "cpu_s"), "{:.1f}"),
        line("peak memory (MB)", num(p, "peak_mb"), num(c, "peak_mb"), "{:.0f}"),
        ["cameras placed", placed(p), placed(c), ""],
        line("largest component / model", num(p, "largest"), num(c, "largest"), "{}",
             ratio=False),
        line("components / models", num(p, "components"), num(c, "components"), "{}",
             ratio=False),
        ["right / wrong (5 deg, 5 % of extent)", trust(p), trust(c), ""],
        line("abs. rot, median (deg)", num(p, "rot_deg"), num(c, "rot_deg"), "{:.3f}"),
        line("abs. pos, median (GT units)", num(p, "pos"), num(c, "pos"), "{:.4f}"),
        line("pairs matched", num(p, "pairs"), num(c, "pairs"), "{}"),
        line("pairs verified", num(p, "verified"), num(c, "verified"), "{}"),
        steps("features", "features (s)"),
        steps("matching", "matching + verification (s)"),
        steps("averaging", "view graph + averaging (s)"),
        steps("ba", "tracks + BA (s)"),
        steps("check", "self-check (s)"),
        steps("mapper", "mapper, all of it (s)"),
        line("rest: start-up, imports, I/O (s)", _rest(p), _rest(c), "{:.1f}"),
        line("load average (1 min) at start", num(p, "load_start"), num(c, "load_start"),
             "{:.2f}", ratio=False),
        ["note", (p or {}).get("note", "") if p else "not run",
         (c or {}).get("note", "") if c else "not run", ""],
    ]


def compare_tables(rows: list[dict[str, Any]], sizes: list[int], mode: str = COLMAP_MATCHING
                   ) -> list[str]:
    """Markdown: per size with a COLMAP row, a heading and its side-by-side table."""
    from _common import table

    out: list[str] = []
    for n in sizes:
        c = next((r for r in rows if r["size"] == n and r.get("kind") == COLMAP), None)
        if c is None:
            continue
        p = next((r for r in rows if r["size"] == n and _is_posernet(r)
                  and r["mode"] == mode), None)
        out += [f"### {n} images: posernet (`pairs.mode={mode}`) and COLMAP global "
                f"({mode} matching)", "", *table(COMPARE_HEADER, compare_rows(p, c)), ""]
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
    ap.add_argument("--colmap", action=argparse.BooleanOptionalAction, default=None,
                    help="also run COLMAP's global mapper (sequential matching) at each size "
                         "(default: when pycolmap imports)")
    ap.add_argument("--seed", type=int, default=0, help="COLMAP mapper seed")
    args = ap.parse_args(argv)
    sizes = args.sizes or ([8, 16] if args.quick else [16, 64, 256])
    if min(sizes) < 2:
        raise SystemExit("bench_scale: --sizes must be >= 2")
    work = Path(args.work or Path(tempfile.gettempdir()) / "posernet-bench-scale")
    work.mkdir(parents=True, exist_ok=True)
    notes = []
    why = br.colmap_status(COLMAP)
    colmap = (why is None) if args.colmap is None else args.colmap
    if args.colmap is None and why:
        notes.append(f"COLMAP left out: {why}")
        print(f"note: COLMAP left out: {why}", file=sys.stderr)
    if colmap and COLMAP_MATCHING not in args.modes:
        notes.append(f"COLMAP runs with {COLMAP_MATCHING} matching but posernet's "
                     f"pairs.mode={COLMAP_MATCHING} is not among --modes: no posernet side")
    compiled = br.compile_bytecode()
    rows = []
    for n in sizes:
        for mode in args.modes:
            if mode == "exhaustive" and n > args.exhaustive_max:
                continue
            rows.append(run(n, mode, work, args.threads, args.timeout, args.quick, args.scene))
        if colmap:
            rows.append(run_colmap(n, work, args.threads, args.timeout, args.quick, args.scene,
                                   args.seed))

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
        *(f"- note: {n}" for n in notes),
        "",
        *table(HEADER, table_rows(rows)),
        "",
    ]
    rel = relative_rows(rows)
    if rel:
        body += ["Relative to exhaustive at the same size (ratios; < 1 is fewer / better / "
                 "faster):", "",
                 *table(["images", "pairs mode", "pairs", "abs. rot", "abs. pos", "wall"], rel),
                 ""]
    if colmap:
        body += [
            "## Beside COLMAP's global mapper",
            "",
            f"- COLMAP {br.versions().get('pycolmap')} through pycolmap in its own process "
            "(bench_real's COLMAP worker): SIFT extraction with the set's intrinsics (one "
            "shared PINHOLE camera, held fixed in the mapper), sequential matching (overlap "
            "10, quadratic overlap: each image with those 1, 2, 4, ..., 512 further on in name "
            "order; loop detection off) with two-view verification, then "
            "`pycolmap.global_mapping` (GLOMAP); models down to 2 images kept; "
            f"{args.threads} thread(s), CPU only; seed {args.seed}. posernet: its "
            "`pairs.mode=sequential` run above (the next `pairs.window` images in file order "
            "plus `pairs.loop_k` loop-closure candidates each, at their defaults); same images, "
            "same intrinsics, same threads",
            "- wall, CPU (user + system) and peak memory (ru_maxrss) of each method's whole "
            "process, interpreter start and imports included; the last column is posernet / "
            "COLMAP of the same invocation. Stage times: posernet's summary.json (features: "
            "proposals + SIFT; matching + verification: pair selection + matching + two-view "
            "geometry; view graph + averaging; tracks + BA; self-check); COLMAP's as the worker "
            "times them (feature extraction; matching including pair selection and "
            "verification; the whole global mapper: view graph calibration, rotation "
            "averaging, tracks, global positioning, BA, retriangulation, model written). rest "
            "= wall minus the timed stages",
            "- errors on the largest component (COLMAP: largest model) after the alignment "
            "both use (abs. rot: best global rotation; abs. pos: similarity on the centres; "
            "medians); right / wrong: bench_real.trust_counts. Pairs matched: pairs selected "
            "and matched (COLMAP: image pairs with matches in its database); verified: pairs "
            "kept after two-view verification (posernet: the view graph's edges)",
            "- one run per method and size on a shared machine: the load average before each "
            "run is in the table",
            "",
            *compare_tables(rows, sizes),
        ]
    title = f"posernet-reconstruct on {', '.join(map(str, sizes))} images" + (
        ", beside COLMAP's global mapper" if colmap else "")
    md = write_results("scale", title, body, args.quick, "cpu", args.out)
    report = {"command": command(), "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
              "machine": {"cores": os.cpu_count(), "threads_per_run": args.threads},
              "versions": br.versions(), "arguments": vars(args), "colmap": colmap,
              "notes": notes, "rows": rows}
    path = atomic_write_json(md.with_suffix(".json"), br._jsonable(report))
    print(f"written: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
