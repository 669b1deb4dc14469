"""Check each real set's ground truth against two-view geometry from the images.

For consecutive image pairs (sorted by name, and the wrap-around pair for rings): SIFT + ratio
test, cv2.findEssentialMat + recoverPose on undistorted points with the set's K, and compare the
estimated relative rotation with the ground truth ``R_j R_i^T`` (world-to-camera rotations).
Also reports the angle between estimated and GT translation directions.

    .venv/bin/python benchmarks/data/real/verify_sets.py [set ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "src"))
from posernet.frontend.images import read_image, records_for_images

HERE = Path(__file__).resolve().parent


def rot_angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def undist_norm(pts: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    d = np.zeros(5) if dist is None else dist
    return cv2.undistortPoints(pts.reshape(-1, 1, 2), K, d).reshape(-1, 2)


def check_pair(ra, rb, sift, ring=False):
    ia, ib = read_image(ra.path), read_image(rb.path)
    ga, gb = cv2.cvtColor(ia, cv2.COLOR_BGR2GRAY), cv2.cvtColor(ib, cv2.COLOR_BGR2GRAY)
    ka, da = sift.detectAndCompute(ga, None)
    kb, db = sift.detectAndCompute(gb, None)
    if da is None or db is None:
        return None
    m = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [x[0] for x in m if len(x) == 2 and x[0].distance < 0.8 * x[1].distance]
    if len(good) < 15:
        return dict(matches=len(good))
    pa = np.float32([ka[g.queryIdx].pt for g in good])
    pb = np.float32([kb[g.trainIdx].pt for g in good])
    na, nb = undist_norm(pa, ra.K, ra.dist), undist_norm(pb, rb.K, rb.dist)
    f = 0.5 * (ra.K[0, 0] + ra.K[1, 1])
    E, mask = cv2.findEssentialMat(na, nb, np.eye(3), cv2.RANSAC, 0.999, 1.0 / f)
    if E is None or E.shape != (3, 3):
        return dict(matches=len(good))
    n_in, R, t, mask2 = cv2.recoverPose(E, na, nb, np.eye(3), mask=mask)
    wa, wb = np.linalg.inv(ra.c2w), np.linalg.inv(rb.c2w)
    R_gt = wb[:3, :3] @ wa[:3, :3].T
    t_gt = wb[:3, 3] - R_gt @ wa[:3, 3]
    err = rot_angle(R @ R_gt.T)
    tn = t.ravel() / np.linalg.norm(t)
    tg = t_gt / max(np.linalg.norm(t_gt), 1e-12)
    terr = float(np.degrees(np.arccos(np.clip(abs(tn @ tg), -1, 1))))
    # ground-truth epipolar check, independent of the (for narrow lenses ill-conditioned) E
    # decomposition: distance of the E-RANSAC inliers to the GT epipolar lines, in pixels
    inl = mask2.ravel() > 0 if mask2 is not None else np.ones(len(na), bool)
    tx = np.array([[0, -t_gt[2], t_gt[1]], [t_gt[2], 0, -t_gt[0]], [-t_gt[1], t_gt[0], 0]])
    E_gt = tx @ R_gt
    xa = np.c_[na, np.ones(len(na))]
    xb = np.c_[nb, np.ones(len(nb))]
    la = xa @ E_gt.T  # epipolar lines in b
    lb = xb @ E_gt  # epipolar lines in a
    num = np.abs(np.sum(xb * la, axis=1))
    sampson = num**2 / (la[:, 0] ** 2 + la[:, 1] ** 2 + lb[:, 0] ** 2 + lb[:, 1] ** 2)
    epi_px = np.sqrt(sampson) * f
    return dict(matches=len(good), inliers=int(n_in), rot_gt=rot_angle(R_gt), rot_err=err,
                t_err=terr, base=float(np.linalg.norm(t_gt)),
                epi_med=float(np.median(epi_px[inl])) if inl.any() else float("nan"),
                gt_consistent=int((epi_px < 2.0).sum()))


def verify(folder: Path, contrast: float = 0.04, ring: bool = False) -> list[float]:
    recs = records_for_images(folder, str(folder / "intrinsics.json"))
    assert all(r.c2w is not None for r in recs), f"{folder}: missing poses"
    sift = cv2.SIFT_create(8000, contrastThreshold=contrast)
    print(f"== {folder.name}: {len(recs)} images")
    pairs = [(i, i + 1) for i in range(len(recs) - 1)] + ([(len(recs) - 1, 0)] if ring else [])
    errs, epis = [], []
    for i, j in pairs:
        r = check_pair(recs[i], recs[j], sift)
        if r is None or "rot_err" not in r:
            print(f"  {recs[i].key} -> {recs[j].key}: too few matches {r}")
            continue
        errs.append(r["rot_err"])
        epis.append(r["epi_med"])
        print(f"  {recs[i].key} -> {recs[j].key}: matches {r['matches']:4d} inl {r['inliers']:4d}"
              f" | GT rot {r['rot_gt']:6.2f} | rot err {r['rot_err']:6.2f} deg"
              f" | t-dir err {r['t_err']:5.1f} deg | GT-epi {r['epi_med']:5.2f} px,"
              f" {r['gt_consistent']:4d} matches < 2 px")
    e = np.array(errs)
    if e.size:
        print(f"  rotation error: median {np.median(e):.2f} deg, max {e.max():.2f} deg, "
              f"{(e < 2).sum()}/{e.size} pairs < 2 deg; GT-epipolar median over pairs "
              f"{np.median(epis):.2f} px")
    return errs


if __name__ == "__main__":
    names = sys.argv[1:] or sorted(
        p.name for p in HERE.iterdir() if (p / "intrinsics.json").is_file()
    )
    for n in names:
        dark = "dino" in n  # dark, weakly textured object on black: more (weaker) SIFT points
        verify(HERE / n, contrast=0.01 if dark else 0.04, ring="ring" in n or "turntable" in n)
