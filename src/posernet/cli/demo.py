"""``posernet-demo`` (``make demo``): the whole pipeline on built-in data.

Images (``images.*``): a small scene is rendered offline in the 7-Scenes layout (reused when
already there) and its test sequence goes through ``posernet-reconstruct``: ROI proposals,
keypoint and box matching, 5-point, motion averaging; poses, pictures of matched boxes, the
recovered cameras and (from the rendered pose files) error tables in ``out_dir/reconstruct``.

Graphs:

1. generate the ``demo`` synthetic dataset (seven scenes; reused when already complete);
2. refine the test graphs' relative poses with the shipped PoserNet checkpoint (or, when none
   is available, train one briefly on the demo training split);
3. average initial and refined relative poses into absolute poses (``sync``, EIG-SE3 default);
4. print the paper's tables (relative and absolute) and write them as markdown/CSV, plus PNG
   plots: per-graph errors sorted by the refined error, and cameras of a few graphs in 3D.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from ..data.synthetic.scenes import SCENE_PRESETS
from ..options import DEVICE, option, path
from . import CONFIG_DIR
from .common import check_config, resolve_device, run_app, run_task, set_threads

__all__ = ["DemoSettings", "ImagesOptions", "demo", "main"]

#: the matcher/ configs the images part may pick
MATCHERS = tuple(sorted(p.stem for p in Path(CONFIG_DIR, "matcher").glob("*.yaml")))


@dataclass(frozen=True, kw_only=True)
class DemoSettings:
    """``posernet-demo``'s own keys (``conf/demo.yaml``; ``images`` is :class:`ImagesOptions`,
    the groups declare theirs)."""

    out_dir: str = option("outputs/demo", rule=path(), help="every output of the demo (made "
                          "after checking it can be)")
    seed: int = option(0, ge=0, help="dataset seed")
    workers: int = option(2, ge=1, help="processes for data generation")
    estimate: str = option("kp", choices=("kp", "bb"), help="initial poses to refine (the "
                           "shipped checkpoint was trained on kp)")
    ckpt_path: str | None = option(None, rule=path(), help="null: the checkpoint shipped with "
                                   "posernet")
    train_epochs: int = option(5, ge=1, help="only when no checkpoint is available: train "
                               "briefly on the demo data")
    camera_plots: int = option(3, ge=0, help="graphs drawn in 3D")
    batch_size: int = option(64, ge=1, help="graphs per batch")
    device: str = option("cpu", rule=DEVICE, help="cpu | cuda | cuda:N | auto")
    num_threads: int | None = option(1, ge=1, help="torch CPU threads (null: torch default)")
    digits: int = option(2, ge=0, le=12, help="decimals in the printed and written tables")


@dataclass(frozen=True, kw_only=True)
class ImagesOptions:
    """``images.*``: the demo's part 1, a rendered scene through ``posernet-reconstruct``."""

    enabled: bool = option(True, help="run part 1 (images.enabled=false skips it)")
    scene: str = option("office", choices=sorted(SCENE_PRESETS),
                        help="scene layout of the renderer (the simulator's rooms)")
    seed: int = option(0, ge=0, help="render seed")
    frames: int = option(12, ge=2, help="frames of the rendered test sequence (every pair is "
                         "matched)")
    width: int = option(640, ge=16, help="image width (px)")
    height: int = option(480, ge=16, help="image height (px)")
    focal: float = option(585.0, gt=0, help="focal length (px)")
    matcher: str = option("auto", choices=MATCHERS, help="matcher/ config (auto: XFeat when "
                          "installed, else SIFT)")
    refine: bool = option(False, help="posernet-reconstruct's default (measured: refinement "
                          "hurts good KP input)")


def _model(cfg: DictConfig, data_dir: Path, out_dir: Path, device: str) -> tuple[Any, str]:
    """The shipped checkpoint; without one, a model trained briefly here."""
    from ..checkpoints import default_checkpoint
    from ..nn import PoserNet

    try:
        path = default_checkpoint()
        return PoserNet.from_checkpoint(path, map_location=device), f"shipped: {path.name}"
    except FileNotFoundError as exc:
        print(f"{exc}\n-> training a model for {cfg.train_epochs} epochs on the demo data")
    import json

    from ..conf import compose, quote_value
    from .train import train

    run_dir = out_dir / "train"
    with_cfg = compose("train", [
        f"data.root={quote_value(data_dir)}", f"data.estimate={cfg.estimate}",
        "data.batch_size=16", f"trainer.max_epochs={int(cfg.train_epochs)}", "seed=0",
        f"out_dir={quote_value(run_dir)}", "trainer.enable_model_summary=false",
        f"num_threads={cfg.num_threads or 'null'}"])
    train(with_cfg)  # posernet-train's own training, into OUT/train
    summary = json.loads((run_dir / "metrics.json").read_text())
    ckpt = Path(summary["best_checkpoint"] or summary["last_checkpoint"])
    return PoserNet.from_checkpoint(ckpt, map_location=device), f"trained here: {ckpt}"


def _image_demo(cfg: DictConfig, out: Path) -> dict[str, Any]:
    """Render the demo scene (unless already rendered with the same settings) and run
    ``posernet-reconstruct`` on its test sequence; returns that command's outputs."""
    from ..conf import compose, quote_value
    from ..data.render import read_render_info, render_intrinsics, render_sevenscenes
    from .reconstruct import run as reconstruct

    im = cfg.images
    root = out / "scene"
    folder = root / str(im.scene)
    want = {"scene": str(im.scene), "seed": int(im.seed), "frames_per_sequence": int(im.frames),
            "width": int(im.width), "height": int(im.height), "focal": float(im.focal),
            "train_sequences": 0, "test_sequences": 1}
    try:
        have = read_render_info(folder)
        fresh = any(have.get(k) != v for k, v in want.items())
    except ValueError:  # not rendered yet
        fresh = True
    if fresh:
        print(f"[images] rendering {im.frames} frames of '{im.scene}' -> {folder}")
        render_sevenscenes(root, str(im.scene), seed=int(im.seed), train_sequences=0,
                           test_sequences=1, frames_per_sequence=int(im.frames),
                           width=int(im.width), height=int(im.height), focal=float(im.focal),
                           overwrite=True)
    intr = ",".join(f"{v:g}" for v in render_intrinsics(folder))
    rcfg = compose("reconstruct", [
        f"images={quote_value(folder / 'seq-01')}", f"intrinsics='{intr}'",
        "pattern=*.color.png", f"out_dir={quote_value(out / 'reconstruct')}", "overwrite=true",
        f"matcher={im.matcher}", f"refine={im.refine}",
        f"device={cfg.device}", f"num_threads={cfg.num_threads}", f"digits={cfg.digits}"])
    print("[images] posernet-reconstruct on the rendered images")
    return reconstruct(rcfg)


def demo(cfg: DictConfig) -> dict[str, Any]:
    """Run the demo described by ``cfg``; returns the written files."""
    from ..data.store import open_split
    from ..data.synthetic import generate_dataset
    from ..data.writer import GenerationError
    from ..evaluation import evaluate_result, result_tables
    from ..metrics import align_to_ground_truth
    from ..nn import PoserNet
    from ..plots import plot_cameras, plot_sorted_errors
    from ..refinement import refine_graphs
    from .build import backend_from_config

    check_config(cfg, "demo")
    t0 = time.perf_counter()
    set_threads(cfg.get("num_threads"))
    device = resolve_device(cfg.device)
    given = None  # a checkpoint given on the command line: read before any work
    if cfg.get("ckpt_path"):
        given = (PoserNet.from_checkpoint(cfg.ckpt_path, map_location=device),
                 str(cfg.ckpt_path))
    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Any] = {}
    if cfg.images.enabled:
        files["images"] = _image_demo(cfg, out)
        print(f"[images] done in {time.perf_counter() - t0:.0f} s\n")
    data_dir = out / "data"
    print(f"[1/4] synthetic dataset '{cfg.dataset.name}' -> {data_dir}")
    options = OmegaConf.to_container(cfg.dataset, resolve=True)
    kw = {"seed": int(cfg.seed), "workers": int(cfg.workers)}
    try:  # reuse what an earlier run made
        generate_dataset(options, data_dir, resume=data_dir.exists(), **kw)
    except GenerationError as exc:
        # The demo owns this folder: data from another configuration (an older posernet, other
        # overrides) is replaced rather than mixed.
        print(f"{exc}\n-> regenerating {data_dir}")
        generate_dataset(options, data_dir, overwrite=True, **kw)
    graphs = [g.with_estimate(str(cfg.estimate)) for g in open_split(data_dir, "small", "test")]
    print("[2/4] model")
    model, source = given or _model(cfg, data_dir, out, device)
    backend = backend_from_config(OmegaConf.to_container(cfg.sync, resolve=True))
    print(f"[3/4] refining {len(graphs)} test graphs ({source}) and motion averaging "
          f"({backend!r})")
    result = refine_graphs(model, graphs, backend=backend, batch_size=int(cfg.batch_size),
                           device=device)
    ev = evaluate_result(result)
    tables = result_tables(ev, label=str(cfg.estimate).upper(), backend=result.backend,
                           title=f": {len(graphs)} synthetic test graphs (model {source})")
    print("[4/4] tables and plots\n")
    for key, stem in (("relative", "table"), ("absolute", "abs_table")):
        if key in tables:
            files[key] = tables[key].write(out, stem, digits=int(cfg.digits))
            print(tables[key].to_markdown(int(cfg.digits)) + "\n")
    pg = ev["per_graph"]
    window = max(1, min(50, len(graphs) // 5))
    panels = {
        "relative rotation": {"initial": pg["rel_rot_initial"], "refined": pg["rel_rot_refined"]},
        "relative translation direction": {"initial": pg["rel_tdir_initial"],
                                           "refined": pg["rel_tdir_refined"]},
    }
    ylabels = {}
    if "abs_rot_initial" in pg:
        panels["absolute rotation"] = {"initial": pg["abs_rot_initial"],
                                       "refined": pg["abs_rot_refined"]}
        panels["absolute position"] = {"initial": pg["abs_pos_initial"],
                                       "refined": pg["abs_pos_refined"]}
        ylabels["absolute position"] = "error (m)"
    files["errors_png"] = plot_sorted_errors(out / "errors_sorted.png", panels, window=window,
                                             ylabels=ylabels,
                                             title="Per-graph errors, synthetic test graphs")
    cams = []
    if result.absolute:
        for k in range(min(int(cfg.camera_plots), len(graphs))):
            g = graphs[k]
            poses = {"ground truth": g.pose_gt.double()}
            for stage in ("initial", "refined"):
                poses[stage] = align_to_ground_truth(result.absolute[stage][k], g.pose_gt)
            cams.append(plot_cameras(out / f"cameras_{k}.png", poses,
                                     title=f"{g.name} ({g.meta.get('scene', '')})"))
    files["camera_pngs"] = cams
    print(f"wrote {out}/table.md, abs_table.md, errors_sorted.png and {len(cams)} camera "
          f"plots" + (f"; {out}/reconstruct/: poses.json, matches_*.png, cameras.png"
                      if cfg.images.enabled else "") + f" in {time.perf_counter() - t0:.0f} s")
    return files


def _resume_hint(cfg: DictConfig) -> str | None:
    if Path(str(cfg.out_dir)).is_dir():
        return f"run it again: what is done in {cfg.out_dir} (images, dataset) is reused"
    return None


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="demo")
def _hydra_main(cfg: DictConfig) -> None:
    run_task("posernet-demo", demo, cfg, errors=(ValueError,), resume_hint=_resume_hint)


def main() -> None:
    """Console-script entry point (``posernet-demo``)."""
    run_app("posernet-demo", "demo", _hydra_main)


if __name__ == "__main__":
    main()
