"""Training data for a refiner of the image front end's edges: rendered, degraded 7-Scenes-layout
scenes run through ``posernet-make-data source=sevenscenes`` (SIFT, selective search, USAC).

One dataset folder per scene (each scene has its own lens: focal drawn in [FMIN, FMAX], and an
uncorrected radial distortion from :class:`posernet.data.degrade.Degradation`), so training
takes ``data.root=[...]`` over them. Run from the repository root::

    .venv/bin/python research/frontend_refiner/build_data.py --out /tmp/fe --seed 100
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from posernet.data.degrade import Degradation
from posernet.data.render import render_sevenscenes

SCENES = ["chess", "fire", "heads", "office", "pumpkin", "stairs"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--frames", type=int, default=50, help="frames per sequence")
    ap.add_argument("--train", type=int, default=100, help="train graphs per scene")
    ap.add_argument("--val", type=int, default=10)
    ap.add_argument("--test", type=int, default=20)
    ap.add_argument("--locality", type=float, default=0.5)
    ap.add_argument("--fmin", type=float, default=480.0)
    ap.add_argument("--fmax", type=float, default=620.0)
    ap.add_argument("--sizes", default="640x480",
                    help="image sizes WxH, one drawn per scene (focal scaled with the width)")
    ap.add_argument("--min-boxes", type=int, default=5,
                    help="box_matching.min_boxes: matched boxes an edge needs")
    ap.add_argument("--graph-size", type=int, default=8)
    ap.add_argument("--edge-rule", default="boxes", choices=["boxes", "verified"],
                    help="sevenscenes.edge_rule: the paper's (boxes) or posernet-reconstruct's")
    ap.add_argument("--tag", default="", help="suffix of the data folders")
    args = ap.parse_args()
    out = Path(args.out)
    rng = np.random.default_rng(args.seed)
    record = {}
    exe = Path(sys.executable).parent / "posernet-make-data"
    for scene in args.scenes.split(","):
        sizes = [tuple(int(v) for v in wh.split("x")) for wh in args.sizes.split(",")]
        width, height = sizes[int(rng.integers(len(sizes)))]
        focal = float(np.round(rng.uniform(args.fmin, args.fmax) * width / 640, 1))
        t0 = time.perf_counter()
        render_sevenscenes(out / "render", scene, seed=args.seed, train_sequences=2,
                           test_sequences=1, frames_per_sequence=args.frames, focal=focal,
                           width=width, height=height, overwrite=True, progress=False,
                           degrade=Degradation(), name=scene + args.tag)
        t1 = time.perf_counter()
        cmd = [str(exe), "source=sevenscenes", f"root={out / 'render'}",
               f"scenes=[{scene + args.tag}]",
               f"intrinsics={focal},{focal},{width / 2},{height / 2}", "frame_step=1",
               "matcher=sift", f"box_matching.min_boxes={args.min_boxes}",
               f"sevenscenes.small.graph_size={args.graph_size}",
               f"sevenscenes.edge_rule={args.edge_rule}",
               f"sevenscenes.locality={args.locality}", f"sevenscenes.small.train={args.train}",
               f"sevenscenes.small.val={args.val}", f"sevenscenes.small.test={args.test}",
               "sevenscenes.large.train=0", "sevenscenes.large.test=0",
               f"out_dir={out / ('data_' + scene + args.tag)}", "overwrite=true",
               "progress=false"]
        log = out / f"make_data_{scene}{args.tag}.log"
        with open(log, "w") as fh:
            rc = subprocess.call(cmd, stdout=fh, stderr=subprocess.STDOUT)
        record[scene + args.tag] = {"focal": focal, "size": [width, height], "render_s": t1 - t0,
                         "make_data_s": time.perf_counter() - t1, "rc": rc,
                         "command": " ".join(cmd)}
        r = record[scene + args.tag]
        print(scene + args.tag, r["focal"], r["size"], f"{t1 - t0:.0f} s render,",
              f"{r['make_data_s']:.0f} s make-data, rc {rc}", flush=True)
        if rc:
            print(log.read_text()[-2000:], file=sys.stderr)
            return 1
    (out / f"build{args.tag}.json").write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
