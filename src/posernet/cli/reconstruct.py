"""``posernet-reconstruct``: a folder of photos in, absolute camera poses out.

    posernet-reconstruct images=photos/ intrinsics=585,585,320,240 out_dir=out

Runs pair selection -> keypoint matching (ROI proposals and box matching when a stage uses
boxes) -> 5-point (KP) with two-view verification -> PoserNet (shipped checkpoint, with
``refine=true``; off by default, see ``posernet/conf/reconstruct.yaml``) -> robust motion
averaging (``sync=``) -> tracks, triangulation and bundle adjustment (``ba=true``), then
writes into ``out_dir``: ``poses.json`` (format ``posernet-poses``), ``sparse/<k>/`` (the
bundle-adjusted cameras and points as COLMAP models, one per component: text, or binary
when an image name has a space, which the text format cannot hold),
``transforms.json`` (nerfstudio) and ``trajectory_tum.txt`` (TUM RGB-D trajectory) of the
largest component, ``summary.json`` (counts and per-stage timings), ``matches_<k>.png``
(image pairs with their matches) and ``cameras.png`` (the recovered cameras in 3D). With a
pose file per image (``<name>.pose.txt``, 7-Scenes layout, or ``gt_poses=DIR``) it also
prints and writes the error tables (``table.md``, ``abs_table.md``). A run that places no
camera still writes ``poses.json`` and ``summary.json`` and exits with status 3. Ctrl-C is
one line saying what the same command reuses when run again (the front-end cache in
``out_dir/cache``), exit status 130; outputs being written then are removed again.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NoReturn

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from ..options import DEVICE, anything, boolean, choice, one_of, option, path
from ..threads import available_cores
from . import CONFIG_DIR
from .common import (
    check_config,
    resolve_device,
    run_app,
    run_task,
    set_threads,
)
from .validation import ConfigValueError

#: exit status of a run that worked but placed no camera (poses.json says why)
EXIT_NOTHING_PLACED = 3
#: exit status of a run whose self-check left fewer than two cameras (outputs written, every
#: camera unsolved with its reason in poses.json)
EXIT_UNVERIFIED = 4

__all__ = ["ReconstructSettings", "main", "run"]

#: what ``intrinsics`` takes (read, and reported, by the intrinsics loader)
INTRINSICS = "FX,FY,CX,CY, [FX,FY,CX,CY], a JSON / 3x3 text file, or auto"


@dataclass(frozen=True, kw_only=True)
class ReconstructSettings:
    """``posernet-reconstruct``'s own keys (``conf/reconstruct.yaml``; its blocks ``pairs``,
    ``verify``, ``bundle``, ``check`` and its groups declare theirs)."""

    images: str = option(rule=path(), help="folder of images (every image file except 7-Scenes "
                         "*.depth.png)")
    pattern: str | None = option(None, help='glob inside the folder, e.g. "*.color.png"')
    strict: bool = option(False, help="an unreadable or empty image file: skipped with one line "
                          "(false) or stop (true)")
    intrinsics: str | Sequence[float] = option(
        "auto", rule=anything(INTRINSICS), help="FX,FY,CX,CY | [FX,FY,CX,CY] | a JSON file "
        "(shared or per image) | a 3x3 text file | auto: EXIF focal length, else 1.2 x the "
        "longest side (refined by BA)")
    gt_poses: str | None = option("auto", rule=path(), help="auto: <name>.pose.txt beside every "
                                  "image (7-Scenes) -> error tables | none | a folder of pose "
                                  "files | a COLMAP model folder (images.bin/.txt, by name) | a "
                                  "TUM groundtruth.txt (poses within 20 ms of TUM-style image "
                                  "timestamps)")
    out_dir: str = option("outputs/reconstruct", rule=path(), help="every output of the run "
                          "(made once there is output)")
    overwrite: bool = option(False, help="out_dir holding a finished run (or other files): "
                             "replace its outputs (true) or stop with one line (false); a folder "
                             "with only an interrupted run's cache/ is resumed either way")
    refine: bool = option(False, help="PoserNet refinement before averaging. Off by default: on "
                          "real photos bundle adjustment on keypoints decides the poses "
                          "(refine=true changes the absolute rotation by under 3 %, and costs "
                          "2.5-5.5 s of CPU), and KP poses without it gain nothing either; it "
                          "helps box-centre input without bundle adjustment (estimate=bb "
                          "ba=false: 29 -> 7 deg on RedKitchen, 51 -> 17 on fountain-P11; "
                          'docs/model-card.md, "The front-end checkpoint").')
    guard: bool = option(False, help="with refine: keep the input pose where the model's "
                         "confidence says refinement would not help (needs a confidence head, "
                         "as the shipped one)")
    check_inputs: bool = option(True, help="with refine: one warning line when the images' graph "
                                "looks unlike the model's training data or refinement made it "
                                "less cycle-consistent")
    ckpt_path: str | None = option("shipped:posernet_frontend_kp.ckpt", rule=path(), help="the "
                                   "refiner: the shipped checkpoint fine-tuned on the image front "
                                   "end's graphs (rendered, degraded photos; its guard statistics "
                                   "cover ordinary cameras); shipped: the synthetic one")
    estimate: str = option("kp", choices=("kp", "bb"), help="initial poses: kp (5-point on "
                           "keypoints: every match of the pair with edge_rule=verified, those "
                           "in matched boxes with boxes) or bb (box centres)")
    edge_rule: str = option("verified", choices=("verified", "boxes"), help="which image pairs "
                            "become edges: verified (every pair whose two-view geometry passes; "
                            "its matched boxes, however few, ride along) or boxes (the paper's "
                            "rule: box_matching.min_boxes matched boxes). estimate=bb always "
                            "needs the boxes.")
    kp_top_pairs: int = option(0, ge=0, help="edge_rule=boxes: KP from the N box pairs sharing "
                               "most matches (0: all, the paper's)")
    seed: int = option(0, ge=0, help="RANSAC seed")
    boxes: bool | str = option("auto", rule=one_of(choice("auto"), boolean(),
                                                   expected="auto, true or false"),
                               help="Object boxes (ROI proposals): auto detects them only when a "
                               "stage uses them (refine=true, estimate=bb, edge_rule=boxes); "
                               "keypoints alone make the verified edges and the tracks.")
    max_image_size: int | None = option(1600, ge=32, help="keypoints found on a copy at most "
                                        "this long (px; null: full size), mapped back to "
                                        "full-resolution pixels: a 4000x3000 photo costs what a "
                                        "1600x1200 does")
    cache: bool = option(True, help="out_dir/cache keeps each image's features and each pair's "
                         "verified matches: the same command after an interruption (or with "
                         "overwrite=true and other averaging / bundle options) resumes instead "
                         "of recomputing")
    workers: int = option(0, ge=0, help="threads for the per-image and per-pair stages (0: "
                          "every available core)")
    pictures: int = option(4, ge=0, help="image pairs drawn with their matches (and cameras.png, "
                           "cameras.html); 0: none")
    device: str = option("cpu", rule=DEVICE, help="cpu | cuda | cuda:N | auto")
    num_threads: int | None = option(1, ge=1, help="torch CPU threads (null: torch default)")
    progress: bool = option(True, help="progress bars of the stages")
    digits: int = option(2, ge=0, le=12, help="decimals in the printed and written tables")
    ba: bool = option(True, help="Final stage: keypoint tracks from the verified matches, "
                      "triangulation and robust bundle adjustment of the averaged cameras "
                      "(posernet.sfm; Levenberg-Marquardt). ba=false: averaging only.")
    self_check: bool = option(True, help="After the last stage every placed camera is held "
                              "against the evidence it came from (posernet.sfm.selfcheck): its "
                              "verified image pairs, coinciding centres, its 3D points and their "
                              "triangulation angles. A camera that fails is reported unsolved, "
                              "with the reason, in every output; a run left with fewer than two "
                              "cameras exits with status 4.")


def _pictures(rec: Any, out: Path, k: int) -> list[Path]:
    """``k`` edges spread over the ranking by matched boxes (or, without boxes, by verified
    matches), each drawn with the matches its verified pose explains (and its boxes)."""
    import numpy as np

    from ..frontend.images import read_image
    from ..match_pictures import draw_matches

    fe, g = rec.frontend, rec.graph
    if k <= 0 or g.num_edges == 0:
        return []
    boxes = fe.summary.boxes
    if boxes:
        score = torch.bincount(g.pair_edge, minlength=g.num_edges)
    else:
        score = torch.tensor([fe.pair(i, j).num_inliers for i, j in g.edge_index.T.tolist()])
    order = torch.argsort(score, descending=True, stable=True)
    # spread over the ranking: the best-matched pairs are neighbours, the others show more
    picks = sorted({round(float(q)) for q in np.linspace(0, g.num_edges - 1, min(k, g.num_edges))})
    paths = []
    for n, e in enumerate(order[picks].tolist()):
        i, j = (int(v) for v in g.edge_index[:, e])
        a, b = (i, j) if i < j else (j, i)
        pm = fe.matches.pairs[(a, b)]
        pr, m, verified = pm.geometry, pm.matches, pm.verified()
        ra, rb = fe.records[a], fe.records[b]
        what = f"{len(m)} matches, {len(verified)} verified (drawn)"
        if boxes:
            what += f", {pr.box_a.size} matched boxes"
        paths.append(draw_matches(
            read_image(ra.path), read_image(rb.path), verified, out / f"matches_{n}.png",
            boxes_a=fe.images[a].boxes if boxes else None,
            boxes_b=fe.images[b].boxes if boxes else None,
            box_pairs=np.stack([pr.box_a, pr.box_b], axis=1) if boxes else None, max_lines=80,
            title=f"{ra.key} <-> {rb.key}: {what}"))
    return paths


def _camera_plot(rec: Any, out: Path) -> Path | None:
    from ..metrics import align_to_ground_truth
    from ..plots import plot_cameras
    from ..reconstruction import GT_UNITS, gauge_fixed

    res, stage, g = rec.result, rec.stage, rec.graph
    if not res.absolute:
        return None
    solved = res.solved[stage][0].bool()
    comp = res.component[stage][0]
    if not bool(solved.any()):
        return None
    # the largest component: other components have their own, unrelated frame
    main = int(torch.mode(comp[solved]).values)
    keep = solved & (comp == main)
    poses = {}
    if g.pose_gt is not None:
        gt = g.pose_gt.double()[keep]
        poses["ground truth"] = gt
        for s in res.absolute:
            poses[s] = align_to_ground_truth(res.absolute[s][0].double()[keep], gt)
    else:
        poses[stage] = gauge_fixed(res.absolute[stage][0], keep, comp)[keep]
    has_gt = g.pose_gt is not None
    return plot_cameras(out / "cameras.png", poses,
                        title=f"{int(keep.sum())} of {g.num_nodes} cameras (largest component)"
                              + ("\naligned to the ground truth by a similarity" if has_gt
                                 else "\npositions up to one similarity: no metric scale"),
                        links=stage if has_gt else None,
                        units=GT_UNITS if has_gt else "scale-free")


def run(cfg: DictConfig) -> dict[str, Any]:
    """Run the reconstruct job described by ``cfg``; returns the written files and tables."""
    from hydra.utils import instantiate

    from ..checkpoints import resolve_checkpoint
    from ..evaluation import evaluate_result, result_tables
    from ..frontend.images import records_for_images
    from ..frontend.pipeline import ImageFrontend
    from ..guard import load_refiner
    from ..io import atomic_write_json, atomic_write_text
    from ..reconstruction import (
        GT_UNITS,
        NothingPlaced,
        focal_mode,
        main_first_line,
        poses_json,
        reconstruct,
        refocus_line,
        stage_choice_line,
        trajectory_errors_table,
        write_camera_view,
        write_colmap_models,
    )
    from .build import backend_from_config

    check_config(cfg, "reconstruct")  # out_dir included: made only once there is output
    t0 = time.perf_counter()
    set_threads(cfg.get("num_threads"))
    device = resolve_device(cfg.device)
    out = Path(cfg.out_dir)
    replace = _claim_out_dir(out, bool(cfg.get("overwrite", False)))
    skipped: list[tuple[str, str]] | None = None if cfg.get("strict", False) else []
    workers = int(cfg.workers) or available_cores()
    records = records_for_images(cfg.images, OmegaConf.to_object(cfg.intrinsics)
                                 if OmegaConf.is_config(cfg.intrinsics) else cfg.intrinsics,
                                 cfg.get("pattern"), cfg.get("gt_poses"), skipped=skipped,
                                 workers=workers)
    for name, why in skipped or []:
        print(f"posernet-reconstruct: skipped {name}: {why} (strict=true to stop instead)",
              file=sys.stderr)
    if len(records) < 2:
        raise ValueError(f"images: {cfg.images} holds {len(records)} image(s); need at least "
                         "2 to place cameras")
    model, ckpt, checks = None, None, None
    if cfg.refine:
        ckpt = resolve_checkpoint(cfg.get("ckpt_path"))
        model, checks = load_refiner(ckpt, device, keep_inputs=bool(cfg.get("guard", False)))
    guard = checks is not None and checks.keep_inputs
    backend = backend_from_config(OmegaConf.to_container(cfg.sync, resolve=True))
    proposals = instantiate(cfg.proposals)  # checked (a missing boxes file) even when unused
    frontend = ImageFrontend(
        records, proposals if _needs_boxes(cfg) else None,
        instantiate(cfg.matcher),
        rules=instantiate(cfg.box_matching), pose=instantiate(cfg.relpose),
        verify=instantiate(cfg.verify), estimate=str(cfg.estimate),
        edge_rule=str(cfg.edge_rule),
        kp_top_pairs=int(cfg.kp_top_pairs), seed=int(cfg.seed),
        workers=workers,
        cache=out / "cache" if cfg.get("cache", True) else None,
        max_image_size=cfg.get("max_image_size"))
    has_gt = all(r.c2w is not None for r in records)
    guessed = {s: sum(r.intrinsics_source == s for r in records) for s in ("exif", "prior")}
    if any(guessed.values()):
        mode = focal_mode(records, str(cfg.bundle.refine_focal)) if cfg.ba else "none"
        print(f"intrinsics: {guessed['exif']} image(s) from EXIF, {guessed['prior']} from the "
              "prior (focal length 1.2 x the longest side, principal point at the centre); "
              + ("bundle adjustment refines the focal length" if mode != "none" else
                 "not refined (bundle.refine_focal=none or ba=false)"))
    print(f"[1/3] {len(records)} images from {cfg.images} "
          f"({'with' if has_gt else 'without'} ground-truth poses); matcher "
          f"{getattr(frontend.matcher, 'name', type(frontend.matcher).__name__)}")
    bundle = instantiate(cfg.bundle) if cfg.ba else None
    info: dict[str, Any] = {"images": str(cfg.images), "estimate": str(cfg.estimate),
                            "checkpoint": str(ckpt) if ckpt else None, "guard": guard,
                            "skipped_images": [{"file": n, "reason": w}
                                               for n, w in skipped or []]}
    try:
        rec = reconstruct(frontend, model, backend, device=device, name=Path(cfg.images).name,
                          estimate=str(cfg.estimate), progress=bool(cfg.progress), guard=guard,
                          bundle_adjust=bool(cfg.ba), bundle=bundle,
                          pairs=instantiate(cfg.pairs),
                          check=instantiate(cfg.check) if cfg.self_check else False,
                          release_descriptors=True)  # the front end is not used again
    except NothingPlaced as err:
        if replace:
            _clear_outputs(out)
        _report_nothing_placed(err, out, info, int(cfg.pictures), t0)
    # from here on everything comes from rec (typed results), not from the front end
    summary = rec.frontend.summary
    print("[2/3] front end: " + "\n      ".join(
        [*rec.pairs.lines(), *summary.lines(),
         *([main_first_line(rec.main_first)] if rec.main_first else []),
         *([refocus_line(rec.refocus)] if rec.refocus else [])]))
    if checks is not None and bool(cfg.get("check_inputs", True)):
        line, info["input_check"] = checks.check([rec.graph], rec.result)
        if line:
            print(f"posernet-reconstruct: {line}", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    if replace:
        _clear_outputs(out)
    with _all_or_none(out):  # an interrupted or failed run leaves no partial set
        record = poses_json(rec, info)  # built once: poses.json and the summary share it
        files: dict[str, Any] = {"poses": atomic_write_json(out / "poses.json", record,
                                                            indent=1)}
        files["colmap"] = write_colmap_models(out / "sparse", rec, workers)
        if _solved_any(record):
            from ..export import write_nerfstudio, write_tum

            files["nerfstudio"] = write_nerfstudio(out / "transforms.json", record["cameras"],
                                                   cfg.images)
            files["tum"] = write_tum(out / "trajectory_tum.txt", record["cameras"])
        solved = sum(c["solved"] for c in record["cameras"].values())
        print(f"[3/3] {'PoserNet + ' if model is not None else ''}{backend!r}"
              f"{' + bundle adjustment' if bundle is not None else ''}: {solved} of "
              f"{len(records)} cameras placed ({rec.graph.num_edges} edges)")
        for stage, runs in rec.sfm.items():
            for r in runs:
                print(f"      {stage}: "
                      + "\n      ".join(line for line in r.lines()[-4:] if line))
        if rec.check is not None:
            print("      " + rec.check.line([r.key for r in records]))
        if (choice := stage_choice_line(rec)) is not None:
            print("      " + choice)
        print("      seconds: " + ", ".join(
            f"{k.replace('_', ' ')} {v['seconds']:.2f}"
            + (f" ({1000 * v['seconds'] / v['items']:.1f} ms x {v['items']})"
               if k in ("images", "pairs") and v["items"] else "")
            for k, v in rec.stages.items())
            + f"; peak memory {max(v['peak_mb'] for v in rec.stages.values()):.0f} MB")
        files["summary"] = atomic_write_json(out / "summary.json", {
            **info, "frontend": summary.to_dict(),
            "pair_selection": record["pair_selection"], "stages": rec.stages,
            "cameras_placed": solved, "self_check": record["self_check"],
            "main_first": record["main_first"],
            "edges": rec.graph.num_edges, "rotation_only_edges": summary.rotation_only,
            "rejected_pairs": summary.rejected and dict(summary.rejected),
            "bundle_adjustment": record["bundle_adjustment"],
            "seconds_total": round(time.perf_counter() - t0, 2)})
        files["pictures"] = _pictures(rec, out, int(cfg.pictures))
        files["cameras_png"] = _camera_plot(rec, out) if int(cfg.pictures) > 0 else None
        files["html"] = (write_camera_view(out / "cameras.html", rec, record, workers)
                         if int(cfg.pictures) > 0 else None)
        if has_gt:
            ev = evaluate_result(rec.result)
            tables = result_tables(ev, label=str(cfg.estimate).upper(),
                                   backend=rec.result.backend,
                                   title=f": {len(records)} images of {Path(cfg.images).name}",
                                   units=GT_UNITS)
            for key, stem in (("relative", "table"), ("absolute", "abs_table")):
                if key in tables:
                    tables[key].write(out, stem, digits=int(cfg.digits))
                    print(tables[key].to_markdown(int(cfg.digits)) + "\n")
            files["tables"] = tables
            files["evaluation"] = ev
            traj = trajectory_errors_table(rec, record)
            if traj is not None:
                print(traj)
                files["trajectory_errors"] = atomic_write_text(out / "trajectory_errors.md",
                                                               traj)
    binary = any((p / "images.bin").is_file() for p in files["colmap"])
    colmap = (f", COLMAP model{'s' if len(files['colmap']) > 1 else ''} in "
              + ", ".join(str(p) for p in files["colmap"])
              + (" (binary: an image name has a space, which COLMAP's text format cannot "
                 "hold)" if binary else "")) if files["colmap"] else ""
    more = ", nerfstudio transforms.json, TUM trajectory_tum.txt" if "tum" in files else ""
    print(f"wrote {files['poses']}{colmap}{more} and pictures in {out} "
          f"({time.perf_counter() - t0:.0f} s)")
    if rec.check is not None and not rec.check.verified:
        print(f"posernet-reconstruct: {rec.check.line()} (exit status {EXIT_UNVERIFIED})",
              file=sys.stderr)
        raise SystemExit(EXIT_UNVERIFIED)
    return files


#: what a run writes into out_dir (removed before a run replaces an earlier one there)
_OUTPUTS = ("poses.json", "summary.json", "cameras.png", "cameras.html", "matches_*.png",
            "table.md",
            "trajectory_errors.md",
            "table.csv", "abs_table.md", "abs_table.csv", "transforms.json",
            "trajectory_tum.txt", "sparse")


def _claim_out_dir(out: Path, overwrite: bool) -> bool:
    """Check ``out`` before any work: new, empty, or holding only an interrupted run's
    ``cache/`` (resumed) is fine; a finished run (``poses.json``) or other files need
    ``overwrite=true``, else a one-line error. Returns whether earlier outputs must be removed
    (:func:`_clear_outputs`, just before the new ones are written, so that a run that fails
    early loses nothing)."""
    if not out.is_dir():
        return False
    entries = [p for p in out.iterdir() if p.name != "cache"]
    if not entries:
        return False
    if not overwrite:
        what = ("a finished run (poses.json)" if (out / "poses.json").is_file()
                else f"{len(entries)} other file(s), e.g. {sorted(p.name for p in entries)[0]}")
        raise ValueError(f"out_dir: {out} holds {what}; overwrite=true replaces its outputs "
                         "(the feature/match cache is reused), or choose another out_dir")
    return True


def _remove_outputs(out: Path) -> int:
    """Remove the outputs a run writes from ``out`` (never its cache or unknown files);
    returns how many were removed."""
    import shutil

    removed = 0
    for pattern in _OUTPUTS:
        for p in out.glob(pattern):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed += 1
    return removed


def _clear_outputs(out: Path) -> None:
    """Remove an earlier run's outputs from ``out`` (never its cache or unknown files)."""
    removed = _remove_outputs(out)
    print(f"out_dir: replaced the previous outputs in {out} ({removed} removed; its cache "
          "was reused)")


@contextmanager
def _all_or_none(out: Path) -> Iterator[None]:
    """The outputs written inside the block form one set: when the block is interrupted
    (Ctrl-C) or fails, the ones already written are removed again, so that ``out`` holds a
    complete run or none (each file is written atomically, and a lone ``poses.json`` would
    pass for a finished run). Only its cache stays, and the same command resumes from it.
    The outputs of an earlier run are gone by then (removed just before the block)."""
    try:
        yield
    except BaseException as exc:
        if not isinstance(exc, SystemExit):
            _remove_outputs(out)
        raise


def _resume_hint(cfg: DictConfig) -> str:
    """After Ctrl-C: what the same command reuses when run again (the front-end cache's
    entries in ``out_dir/cache``, counted on disk) and what it does again."""
    out = Path(str(cfg.out_dir))
    if not cfg.get("cache", True):
        return "nothing was cached (cache=false): running it again starts over"
    folders = sorted((out / "cache").glob("*/options.json"), key=lambda p: p.stat().st_mtime)
    done = {kind: sum(1 for _ in folders[-1].parent.glob(f"{kind}/*.npz")) if folders else 0
            for kind in ("images", "pairs")}
    if not any(done.values()):
        return "nothing was finished yet: running it again starts over"
    return (f"run the same command again to resume: it reuses the front-end work kept in "
            f"{out / 'cache'} ({done['images']} image(s): features; {done['pairs']} image "
            "pair(s): matches and two-view verification) and computes the rest again (other "
            "images and pairs, averaging, bundle adjustment, outputs)")


def _solved_any(record: dict[str, Any]) -> bool:
    return any(c.get("solved") for c in record["cameras"].values())


def _report_nothing_placed(err: Any, out: Path, info: dict[str, Any], pictures: int,
                           t0: float) -> NoReturn:
    """A run that placed no camera still writes poses.json (every camera unsolved, every pair
    with its rejection reason), summary.json and pictures of the pairs with the most matches
    (to see why), then exits with :data:`EXIT_NOTHING_PLACED`."""

    from ..frontend.images import read_image
    from ..io import atomic_write_json
    from ..match_pictures import draw_matches
    from ..reconstruction import unplaced_json

    fe = err.frontend
    print("[2/3] front end: " + "\n      ".join([*err.pairs.lines(), *fe.summary.lines()]))
    out.mkdir(parents=True, exist_ok=True)
    with _all_or_none(out):
        record = unplaced_json(err, info)
        atomic_write_json(out / "poses.json", record, indent=1)
        atomic_write_json(out / "summary.json", {
            **info, "frontend": fe.summary.to_dict(),
            "pair_selection": record["pair_selection"], "stages": err.stages,
            "cameras_placed": 0, "edges": 0, "rejected_pairs": dict(fe.summary.rejected),
            "seconds_total": round(time.perf_counter() - t0, 2)})
        # the pairs with the most matches; ties in pair order
        best = sorted(((k, p.matches) for k, p in fe.matches.pairs.items()
                       if p.matches is not None),
                      key=lambda kv: -len(kv[1]))[:max(pictures, 0)]
        for n, ((a, b), m) in enumerate(best):
            ra, rb, pr = fe.records[a], fe.records[b], fe.pair(a, b)
            draw_matches(read_image(ra.path), read_image(rb.path), m, out / f"matches_{n}.png",
                         max_lines=80, title=f"{ra.key} <-> {rb.key}: {len(m)} matches, "
                         f"rejected ({pr.reason or pr.status})")
    print(f"posernet-reconstruct: placed no camera: {err}; wrote {out / 'poses.json'} (every "
          f"camera unsolved, every pair with its reason){' and pictures' if best else ''}",
          file=sys.stderr)
    raise SystemExit(EXIT_NOTHING_PLACED)


def _needs_boxes(cfg: DictConfig) -> bool:
    """``boxes=auto``: detect boxes only when a stage uses them (PoserNet, box-centre input,
    the paper's edge rule); ``true`` / ``false`` decide. Contradictions are config errors."""
    users = [name for name, used in (("refine=true", bool(cfg.refine)),
                                     ("estimate=bb", str(cfg.estimate) == "bb"),
                                     ("edge_rule=boxes", str(cfg.edge_rule) == "boxes")) if used]
    choice = cfg.get("boxes", "auto")
    if choice is False and users:
        raise ConfigValueError(f"boxes=false, but {' and '.join(users)} needs the boxes")
    return bool(users) if choice == "auto" else bool(choice)


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="reconstruct")
def _hydra_main(cfg: DictConfig) -> None:
    # ImageError, ProposalError and MatcherError are ValueErrors
    run_task("posernet-reconstruct", run, cfg, errors=(ValueError,), resume_hint=_resume_hint)


def main() -> None:
    """Console-script entry point (``posernet-reconstruct``)."""
    run_app("posernet-reconstruct", "reconstruct", _hydra_main, list_args=("intrinsics",),
            direct=_direct)


def _direct(cfg: DictConfig) -> None:
    run_task("posernet-reconstruct", run, cfg, errors=(ValueError,), resume_hint=_resume_hint)


if __name__ == "__main__":
    main()
