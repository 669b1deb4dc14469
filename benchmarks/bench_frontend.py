"""The image front end on rendered scenes: cost per image and per pair, accuracy per stage.

For each scene (rendered offline in the 7-Scenes layout, cached in ``--work``) and matcher, the
test sequence goes through ``posernet-reconstruct``'s path: ROI proposals, keypoint matching,
box matching, 5-point on in-box keypoints (KP) and on box centres (BB), one view graph of all
images, then EIG-SE3 on the initial and on the PoserNet-refined (shipped checkpoint) poses.
Prints and writes ``benchmarks/results/frontend.md``:

* proposal recall (top 50, IoU 0.5 / 0.7) against the rendered objects' boxes (<= 25 % of the
  image, as the proposals are filtered);
* wall time per image (read, proposals, features) and per pair (matching, box matching,
  5-point), one process;
* relative-pose errors of KP and BB (median over edges, % of edges under 5 deg) before and
  after PoserNet, and absolute errors after EIG-SE3 (median over cameras, similarity alignment,
  unit-norm translations) -- which is what decides ``posernet-reconstruct``'s ``refine`` default.

    python benchmarks/bench_frontend.py                          # chess + office, SIFT and XFeat
    python benchmarks/bench_frontend.py --scenes chess --frames 10 --matchers sift --quick
"""

from __future__ import annotations

import argparse
import itertools
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from posernet.checkpoints import default_checkpoint
from posernet.data.render import render_intrinsics, render_sevenscenes
from posernet.frontend.features import make_matcher, xfeat_available
from posernet.frontend.images import records_for_images
from posernet.frontend.pipeline import ImageFrontend
from posernet.frontend.proposals import FileProposals, SelectiveSearch, box_iou
from posernet.io import atomic_write_text
from posernet.metrics import absolute_pose_errors_per_camera, relative_pose_errors
from posernet.nn import PoserNet
from posernet.refinement import refine_graphs
from posernet.sync import get_backend

RESULTS = Path(__file__).resolve().parent / "results" / "frontend.md"
BACKENDS = ("eig_se3", "rotation_translation")


def proposal_recall(scene_dir: Path, keys: list[str], fe: ImageFrontend) -> tuple[float, float]:
    """Recall of the rendered objects' boxes (<= 25 % of the image) by the top-50 proposals."""
    gt = FileProposals(scene_dir / "objects.json", top_k=None, max_area=0.25, min_size=8.0)
    hit5 = hit7 = total = 0
    for i, key in enumerate(keys):
        w, h = fe.records[i].size
        boxes = gt(np.zeros((h, w, 3), np.uint8), key).boxes
        if boxes.shape[0] == 0:
            continue
        best = box_iou(boxes, fe.boxes(i)).max(1) if fe.boxes(i).shape[0] else np.zeros(
            boxes.shape[0])
        hit5 += int((best >= 0.5).sum())
        hit7 += int((best >= 0.7).sum())
        total += boxes.shape[0]
    return hit5 / max(total, 1), hit7 / max(total, 1)


def rel_errors(pose: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    rot, tdir = relative_pose_errors(pose.double(), gt.double())
    return {"rot": float(rot.median()), "tdir": float(tdir.median()),
            "rot5": 100.0 * float((rot < 5).double().mean())}


def abs_errors(poses: torch.Tensor, solved: torch.Tensor, gt: torch.Tensor) -> dict[str, float]:
    group = torch.zeros(gt.shape[0], dtype=torch.long)
    rot, pos = absolute_pose_errors_per_camera(poses.double(), gt.double(), group, 1,
                                               valid=solved.bool())
    ok = solved.bool()
    return {"rot": float(rot[ok].median()), "pos": float(pos[ok].median()),
            "placed": int(ok.sum())}


def run_one(scene_dir: Path, matcher_name: str, model: PoserNet, device: str) -> dict:
    seq = sorted(p for p in scene_dir.iterdir() if p.is_dir() and p.name.startswith("seq-"))[-1]
    intr = ",".join(str(v) for v in render_intrinsics(scene_dir))
    records = records_for_images(seq, intr, "*.color.png")
    fe = ImageFrontend(records, SelectiveSearch(), make_matcher(matcher_name))
    n = len(records)
    t0 = time.perf_counter()
    fe.prepare(progress=False)
    fe.evaluate_pairs(list(itertools.combinations(range(n), 2)), progress=False)
    graph, _ = fe.graph(range(n), meta={"name": scene_dir.name})
    wall = time.perf_counter() - t0
    keys = [f"{seq.name}/{r.key}" for r in records]
    out = {"scene": scene_dir.name, "matcher": matcher_name, "images": n,
           "pairs": n * (n - 1) // 2, "edges": graph.num_edges, "wall": wall,
           "summary": fe.summary, "recall": proposal_recall(scene_dir, keys, fe)}
    for est in ("kp", "bb"):
        g = graph.with_estimate(est)
        for bname in BACKENDS:
            res = refine_graphs(model, [g], backend=get_backend(bname), batch_size=1,
                                device=device, progress=False)
            for stage in ("initial", "refined"):
                out[f"{est}_{stage}_rel"] = rel_errors(res.edge_pose[stage][0], g.edge_pose_gt)
                out[f"{est}_{stage}_{bname}"] = abs_errors(res.absolute[stage][0],
                                                           res.solved[stage][0], g.pose_gt)
    return out


def table(rows: list[dict]) -> str:
    lines = [
        "| scene | matcher | images | edges / pairs | recall@0.5 / 0.7 | per image: read / "
        "proposals / features (ms) | per pair: match / boxes / 5-point (ms) |",
        "|---|---|---:|---:|---:|---|---|",
    ]
    for r in rows:
        s, n, p = r["summary"].seconds, r["images"], r["pairs"]
        lines.append(
            f"| {r['scene']} | {r['matcher']} | {n} | {r['edges']} / {p} | "
            f"{r['recall'][0]:.2f} / {r['recall'][1]:.2f} | "
            f"{1e3 * s['read'] / n:.0f} / {1e3 * s['proposals'] / n:.0f} / "
            f"{1e3 * s['features'] / n:.0f} | {1e3 * s['matching'] / p:.1f} / "
            f"{1e3 * s['box_matching'] / p:.1f} / {1e3 * s['five_point'] / p:.1f} |")
    lines += [
        "",
        "| scene | matcher | input | stage | rel. rot (deg) | rel. tdir (deg) | edges < 5 deg "
        "(%) | EIG-SE3 abs. rot (deg) / pos (m) | RotTrans abs. rot (deg) / pos (m) | "
        "cameras placed |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        for est in ("kp", "bb"):
            for stage, label in (("initial", "initial"), ("refined", "PoserNet")):
                rel = r[f"{est}_{stage}_rel"]
                ab = [r[f"{est}_{stage}_{b}"] for b in BACKENDS]
                lines.append(
                    f"| {r['scene']} | {r['matcher']} | {est.upper()} | {label} | "
                    f"{rel['rot']:.2f} | {rel['tdir']:.2f} | {rel['rot5']:.0f} | "
                    + " | ".join(f"{a['rot']:.2f} / {a['pos']:.3f}" for a in ab)
                    + f" | {ab[0]['placed']}/{r['images']} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["chess", "office"])
    ap.add_argument("--frames", type=int, default=16, help="frames of the test sequence")
    ap.add_argument("--matchers", nargs="+", default=None,
                    help="sift, xfeat, xfeat+lighterglue (default: sift and, if installed, xfeat)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default=None, help="folder for the rendered scenes (cached)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--no-write", action="store_true", help="do not write the results table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    matchers = args.matchers or (["sift", "xfeat"] if xfeat_available() else ["sift"])
    work = Path(args.work or Path(tempfile.gettempdir()) / "posernet-bench-frontend")
    model = PoserNet.from_checkpoint(default_checkpoint(), map_location=args.device)
    rows = []
    t_render = {}
    for scene in args.scenes:
        folder = work / f"{scene}-{args.seed}-{args.frames}"
        if not (folder / scene / "render.json").is_file():
            t0 = time.perf_counter()
            render_sevenscenes(folder, scene, seed=args.seed, train_sequences=0,
                               test_sequences=1, frames_per_sequence=args.frames,
                               overwrite=True, progress=False)
            t_render[scene] = (time.perf_counter() - t0) / args.frames
        for m in matchers:
            print(f"{scene} / {m} ...", flush=True)
            rows.append(run_one(folder / scene, m, model, args.device))
    text = table(rows)
    print(text)
    header = (
        f"# Image front end on rendered scenes\n\nMeasured {time.strftime('%Y-%m-%d')} with "
        f"`python benchmarks/bench_frontend.py {' '.join(os.sys.argv[1:])}`. Machine: "
        f"{platform.machine()}, {os.cpu_count()} CPU cores visible (load average at the end: "
        f"{os.getloadavg()[0]:.1f}), torch {torch.__version__} ({args.threads} thread), "
        f"device {args.device}. Scenes rendered by `posernet.data.render` at 640x480 "
        f"(f = 585), one test sequence of {args.frames} frames each"
        + (f" (render: {', '.join(f'{k} {v:.2f} s' for k, v in t_render.items())} per frame)"
           if t_render else "")
        + ". Proposals: selective search (top 50, boxes <= 25 % of the image). Every image "
        "pair is evaluated; one view graph of all images; EIG-SE3 with unit-norm translations and "
        "rotation + translation averaging (RotTrans, scale-free); absolute errors are medians "
        "over cameras after a similarity alignment; PoserNet is "
        "the shipped checkpoint (trained on synthetic graphs).\n\n")
    if not args.no_write:
        atomic_write_text(RESULTS, header + text + "\n")
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
