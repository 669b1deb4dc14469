"""The real image sets of ``benchmarks/data/real`` in the 7-Scenes layout (one test sequence,
PNG frames, the sets' own camera-to-world poses), so ``posernet-make-data source=sevenscenes``
can build front-end test graphs of them. Usage: ``real_layout.py OUT``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2

REAL = Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "real"
SETS = {"redkitchen": "7scenes_redkitchen", "fountain": "strecha_fountain_p11",
        "herzjesu": "strecha_herzjesu_p25", "dino": "middlebury_dino_sparse_ring",
        "redkitchenwide": "7scenes_redkitchen_wide", "squirrel": "squirrel_turntable",
        "entry": "strecha_entry_p10"}


def main(out: Path) -> None:
    for name, folder in SETS.items():
        src = REAL / folder
        seq = out / name / "seq-01"
        seq.mkdir(parents=True, exist_ok=True)
        poses = sorted(src.glob("*.pose.txt"))
        for k, pose in enumerate(poses):
            stem = pose.name[: -len(".pose.txt")]
            image = next(p for p in src.glob(stem + ".*") if p.suffix.lower() in (".jpg", ".png"))
            cv2.imwrite(str(seq / f"frame-{k:06d}.color.png"), cv2.imread(str(image)))
            (seq / f"frame-{k:06d}.pose.txt").write_text(pose.read_text())
        (out / name / "TestSplit.txt").write_text("sequence1\n")
        (out / name / "TrainSplit.txt").write_text("")
        k = json.loads((src / "intrinsics.json").read_text())
        (out / name / "intrinsics.txt").write_text(f"{k['fx']},{k['fy']},{k['cx']},{k['cy']}\n")
        print(name, len(poses), "frames", (out / name / "intrinsics.txt").read_text().strip())


if __name__ == "__main__":
    main(Path(sys.argv[1]))
