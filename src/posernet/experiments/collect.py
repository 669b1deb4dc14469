"""Collect the paper's tables from trained models: evaluate them and write paper-layout tables.

Every experiment writes ``<out>/<experiment>/table.md`` and ``table.csv`` (the paper's numbers
beside ours); :func:`run_experiments` also writes ``<out>/summary.md`` with the wall time of
each. The models are read from ``<out>/models/<model>/seed<k>/``, where the ``posernet-train``
multiruns of :mod:`posernet.experiments.models` put them; :func:`run_experiments` first generates
the scale's dataset and runs the multiruns for the models not trained yet (``collect_only``
skips that and names the missing models).
"""

from __future__ import annotations

import json
import logging
import os
import platform
import statistics
import sys
import time
import traceback
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from ..io import atomic_write_json, atomic_write_text
from ..report import (
    ABSOLUTE_GROUPS,
    MedianRow,
    MedianTable,
    ResultTable,
    TableRow,
    interleave,
    mean_std_row,
    ours,
)
from . import paper_numbers as P
from .digest import write_digest
from .models import (
    EXPERIMENTS,
    ModelSpec,
    Scale,
    finished_run,
    launcher_available,
    launcher_overrides,
    load_scale,
    multirun_commands,
    parse_only,
    required_models,
    sweep_values,
    train_models,
)

__all__ = ["TABLES", "Context", "run_experiments"]

log = logging.getLogger(__name__)


@dataclass
class Context:
    """State shared by the experiments of one run: folders, caches of results."""

    scale: Scale
    out: Path
    device: str = "cpu"
    data_root: Path | None = None  # default: ``<out>/data``
    threads: int | None = 1  # torch CPU threads of each training job (None: torch's default)
    _graphs: dict[tuple[Any, ...], list[Any]] = field(default_factory=dict)
    _evals: dict[tuple[Any, ...], dict[str, Any]] = field(default_factory=dict)
    _results: dict[tuple[Any, ...], Any] = field(default_factory=dict)
    used: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.data_root is None:
            self.data_root = self.out / "data"

    # ---------------------------------------------------------------- data
    def ensure_data(self, workers: int = 2) -> None:
        """Generate the scale's synthetic dataset (resumed / reused when already there)."""
        from ..data.synthetic import generate_dataset

        generate_dataset(self.scale.dataset, self.data_root, seed=self.scale.data_seed,
                         workers=workers, resume=self.data_root.exists(),
                         progress=self.scale.progress_bar, echo=None)

    def graphs(self, size: str, estimate: str, scene: str | None = None) -> list[Any]:
        """Test graphs of ``size`` (optionally one scene) with ``estimate`` as initial poses."""
        from ..data.store import open_split

        key = (size, estimate, scene)
        if key not in self._graphs:
            gs = open_split(self.data_root, size, "test", None if scene is None else [scene])
            if not gs:
                raise ValueError(f"{self.data_root}: no {size} test graphs"
                                 + (f" for scene {scene!r}" if scene else ""))
            self._graphs[key] = [g.with_estimate(estimate) for g in gs]
        return self._graphs[key]

    def scenes(self) -> list[str]:
        """Scenes with small graphs (train or test: a dataset made for training elsewhere may
        have no test split)."""
        from ..data.store import available_scenes

        have = {*available_scenes(self.data_root, "small", "train"),
                *available_scenes(self.data_root, "small", "test")}
        return sorted(have)

    # ---------------------------------------------------------------- models
    @property
    def models(self) -> Path:
        """Folder of the trained models: ``<key>/seed<k>/`` each."""
        return self.out / "models"

    def checkpoint(self, spec: ModelSpec, seed: int) -> Path:
        """The checkpoint of the finished model ``spec``/``seed``; FileNotFoundError naming the
        multirun that trains it when it has not finished."""
        run_dir = self.models / spec.key / f"seed{seed}"
        found = finished_run(run_dir)
        if found is None:
            run = multirun_commands(self.scale, [(spec, seed)], self.models, self.data_root,
                                    self.device, self.threads)[0]
            raise FileNotFoundError(
                f"model {spec.key} seed {seed} is not trained ({run_dir} has no finished "
                f"run); train it with: posernet-train {' '.join(run.argv(self.models))}")
        return found

    def epochs(self) -> tuple[int, int]:
        """Training epochs of the small- and the large-graph models (from their configs)."""
        return tuple(int(self.train_config(ModelSpec(size=z)).trainer.max_epochs)
                     for z in ("small", "large"))  # type: ignore[return-value]

    def train_config(self, spec: ModelSpec) -> Any:
        """``posernet-train``'s config of model ``spec``: its experiment file, the spec's and
        the scale's overrides (what the multirun composes, less folders and seed)."""
        from ..conf import compose

        name, values = spec.experiment()
        large = list(self.scale.train_large) if spec.size == "large" else []
        return compose("train", [f"+experiment={name}",
                                 *(f"{k}={v}" for k, v in values.items()),
                                 *self.scale.train, *large])

    # ---------------------------------------------------------------- evaluation
    def result(self, spec: ModelSpec, seed: int, size: str = "small",
               backend: str | None = None, scene: str | None = None) -> Any:
        """:class:`~posernet.refinement.RefineResult` of ``spec``/``seed`` on the test graphs."""
        from ..nn import PoserNet
        from ..refinement import refine_graphs
        from ..sync import get_backend

        key = (spec, seed, size, backend, scene)
        self.used.append(f"{spec.key}/seed{seed}")
        if key not in self._results:
            model = PoserNet.from_checkpoint(self.checkpoint(spec, seed), map_location=self.device)
            self._results[key] = refine_graphs(
                model, self.graphs(size, spec.estimate, scene),
                backend=None if backend is None else get_backend(backend),
                batch_size=self.scale.eval_batch, device=self.device, progress=False)
        return self._results[key]

    def sync_result(self, estimate: str, seed: int, refined: bool) -> Any:
        """:class:`~posernet.refinement.RefineResult` of the learned synchronisation trained on
        raw (``refined=False``: the initial stage) or on refined input (the PoserNet model of
        the same estimate and seed refines first: the refined stage), on the small test
        graphs."""
        from ..nn import PoserNet
        from ..refinement import refine_graphs
        from ..sync.learned import LearnedSync

        key = ("learned", estimate, seed, refined)
        sync_spec = ModelSpec(estimate=estimate, kind="sync", refined=refined)
        self.used += [f"{sync_spec.key}/seed{seed}"] + (
            [f"{ModelSpec(estimate=estimate).key}/seed{seed}"] if refined else [])
        if key not in self._results:
            sync = self.checkpoint(sync_spec, seed)
            model = (PoserNet.from_checkpoint(self.checkpoint(ModelSpec(estimate=estimate), seed),
                                              map_location=self.device) if refined else None)
            self._results[key] = refine_graphs(
                model, self.graphs("small", estimate),
                backend=LearnedSync(ckpt_path=str(sync), device=self.device),
                batch_size=self.scale.eval_batch, device=self.device, progress=False)
        return self._results[key]

    def sync_evaluation(self, estimate: str, seed: int, refined: bool) -> dict[str, Any]:
        """:func:`~posernet.evaluation.evaluate_result` of :meth:`sync_result` (cached)."""
        from ..evaluation import evaluate_result

        key = ("learned", estimate, seed, refined)
        if key not in self._evals:
            self._evals[key] = evaluate_result(self.sync_result(estimate, seed, refined))
        return self._evals[key]

    def evaluation(self, spec: ModelSpec, seed: int, size: str = "small",
                   backend: str | None = None, scene: str | None = None) -> dict[str, Any]:
        """:func:`~posernet.evaluation.evaluate_result` of :meth:`result` (cached)."""
        from ..evaluation import evaluate_result

        key = (spec, seed, size, backend, scene)
        if key not in self._evals:
            self._evals[key] = evaluate_result(self.result(spec, seed, size, backend, scene))
        return self._evals[key]


def _seed_row(evals: Sequence[dict[str, Any]], kind: str, stage: str,
              labels: tuple[str, ...]) -> TableRow:
    """Mean ± std over seeds of one stage's threshold rows (``kind``: relative/absolute)."""
    return mean_std_row([TableRow(labels, e[kind][stage]) for e in evals], labels)


def _note(ctx: Context, extra: str = "") -> str:
    s = ctx.scale
    small, large = ctx.epochs()
    return (f"Scale `{s.name}` (synthetic data, {ctx.data_root}); ours: "
            f"{len(s.seeds)} seed(s) {list(s.seeds)}, {small} epochs (small), "
            f"{large} (large). Paper: 7-Scenes, 7000 small / 5 large test graphs, "
            f"3 seeds.{extra}")


# --------------------------------------------------------------------------- experiments
def table1(ctx: Context, out: Path) -> list[Path]:
    """Table 1: initial vs refined relative poses, KP and BB, small graphs."""
    seeds = ctx.scale.seeds
    specs = {e: ModelSpec(estimate=e) for e in ("bb", "kp")}
    paper = {k: P.paper_row(("paper", *k), v) for k, v in P.TABLE1.items()}
    mine: dict[tuple[str, ...], TableRow] = {}
    for est, spec in specs.items():
        evals = [ctx.evaluation(spec, s) for s in seeds]
        inp = est.upper()
        mine[(inp, "Initial")] = ours(TableRow((inp, "Initial"), evals[0]["relative"]["initial"]))
        mine[(inp, "PoserNet")] = ours(_seed_row(evals, "relative", "refined",
                                                 (inp, "PoserNet")))
    mine[("-", "Constant prior")] = ours(prior_row(ctx, ("-", "Constant prior")))
    table = ResultTable(rows=interleave(paper, mine), label_names=("source", "input", "stage"),
                        title="Table 1: refinement of relative poses, small graphs",
                        note=_note(ctx, " Constant prior: every edge gets the training set's "
                                   "mean relative pose (chordal mean rotation, mean translation "
                                   "direction), a floor any useful model must beat."))
    return list(table.write(out))


def prior_pose(train: Sequence[Any]) -> torch.Tensor:
    """``[7]`` mean ground-truth edge pose of ``train`` graphs: chordal mean rotation, mean
    translation direction (both projected back onto unit length)."""
    from ..geometry import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion

    gt = torch.cat([g.edge_pose_gt for g in train]).double() if train else torch.zeros(0, 7)
    if gt.shape[0] == 0:
        raise ValueError("prior_pose: the training graphs have no edges")
    M = quaternion_to_rotation_matrix(gt[:, :4]).sum(0)
    U, _, Vh = torch.linalg.svd(M)
    D = torch.diag(torch.tensor([1.0, 1.0, torch.det(U @ Vh).sign().item()], dtype=M.dtype))
    t = gt[:, 4:] / gt[:, 4:].norm(dim=-1, keepdim=True).clamp_min(1e-12)
    t = t.mean(0)
    return torch.cat([rotation_matrix_to_quaternion(U @ D @ Vh), t / t.norm().clamp_min(1e-12)])


def prior_row(ctx: Context, labels: tuple[str, ...]) -> TableRow:
    """Errors of the constant :func:`prior_pose` predictor on the small test graphs."""
    from ..data.store import open_split
    from ..metrics import relative_errors_per_graph, relative_rows

    pose = prior_pose(open_split(ctx.data_root, "small", "train", None))
    test = ctx.graphs("small", "kp")
    gt = torch.cat([g.edge_pose_gt for g in test]).double()
    batch = torch.cat([torch.full((g.num_edges,), k) for k, g in enumerate(test)])
    return TableRow(labels, relative_rows(
        relative_errors_per_graph(pose.expand_as(gt), gt, batch, len(test))))


def table2(ctx: Context, out: Path) -> list[Path]:
    """Table 2: train on small / large graphs, test on small / large graphs (KP)."""
    seeds = ctx.scale.seeds
    specs = {"Small": ModelSpec(size="small"), "Large": ModelSpec(size="large")}
    large = ctx.train_config(specs["Large"])
    paper = {k: P.paper_row(("paper", *k), v, 7000 if k[1] == "Small" else 5)
             for k, v in P.TABLE2.items()}
    mine: dict[tuple[str, ...], TableRow] = {}
    for test in ("Small", "Large"):
        for train, spec in specs.items():
            evals = [ctx.evaluation(spec, s, size=test.lower()) for s in seeds]
            if train == "Small":
                mine[("Raw", test)] = ours(TableRow(("Raw", test),
                                                    evals[0]["relative"]["initial"]))
            mine[(train, test)] = ours(_seed_row(evals, "relative", "refined", (train, test)))
    order = [(a, b) for b in ("Small", "Large") for a in ("Raw", "Small", "Large")]
    rows = interleave({k: paper[k] for k in order}, {k: mine[k] for k in order})
    table = ResultTable(rows=rows, label_names=("source", "train", "test"),
                        title="Table 2: small vs large graphs (KP)",
                        note=_note(ctx, f" Large models: lr {large.model.optimizer.lr:g}, "
                                   f"batch {large.data.batch_size}."))
    return list(table.write(out))


BACKEND_NAMES = {"eig_se3": "EIG-SE3", "rotation_translation": "RotTrans", "gtsam": "GTSAM"}


def table3_backends() -> list[str]:
    """Motion-averaging backends compared in Table 3 (``gtsam`` only when importable)."""
    from ..sync import available_backends

    have = available_backends()
    return [b for b in ("eig_se3", "rotation_translation", "gtsam") if b in have]


def table3(ctx: Context, out: Path) -> list[Path]:
    """Table 3: absolute poses from motion averaging of initial vs refined relative poses, with
    every backend; PoserNet trained end to end through a differentiable synchronisation (then
    each backend); the learned synchronisation on raw and refined input beside the paper's
    MultiReg."""
    seeds = ctx.scale.seeds
    specs = {e: ModelSpec(estimate=e) for e in ("bb", "kp")}
    e2e = {e: ModelSpec(estimate=e, kind="end_to_end") for e in ("bb", "kp")}
    rows: list[TableRow] = []
    notes: list[str] = []
    backends = table3_backends()
    for b in tqdm(backends, desc="table3: backends", leave=False):
        name = BACKEND_NAMES.get(b, b)
        paper = ({(f"{name}{'' if st == 'Initial' else ' + PoserNet'}", inp):
                  P.paper_row(("paper", f"{name}{'' if st == 'Initial' else ' + PoserNet'}",
                               inp), v) for (st, inp), v in P.TABLE3_EIG.items()}
                 if b == "eig_se3" else {})
        mine: dict[tuple[str, ...], TableRow] = {}
        try:
            for stage, label in (("initial", name), ("refined", f"{name} + PoserNet"),
                                 ("end_to_end", f"{name} + PoserNet (end-to-end)")):
                for est, spec in specs.items():
                    lab = (label, est.upper())
                    if stage == "initial":
                        row = TableRow(lab, ctx.evaluation(spec, seeds[0], backend=b)
                                       ["absolute"]["initial"])
                    else:
                        model = spec if stage == "refined" else e2e[est]
                        evals = [ctx.evaluation(model, s, backend=b) for s in seeds]
                        row = _seed_row(evals, "absolute", "refined", lab)
                    mine[lab] = ours(row)
        except Exception as exc:  # one backend failing must not lose the others' rows
            if b == backends[0]:
                raise
            notes.append(f"{name}: FAILED ({type(exc).__name__}: {exc}), no rows")
            continue
        desc = ctx.result(specs["kp"], seeds[0], backend=b).backend or {}
        alignment = ctx.evaluation(specs["kp"], seeds[0], backend=b).get("alignment")
        notes.append(f"{name}: scale {desc.get('scale_label', desc.get('scale', '?'))}, "
                     f"alignment {alignment}")
        rows += interleave(paper, mine)
    rows += _learned_sync_rows(ctx, notes)
    table = ResultTable(rows=rows, label_names=("source", "method", "init"),
                        groups=ABSOLUTE_GROUPS,
                        title="Table 3: motion averaging, absolute poses",
                        note=_note(ctx, " Alignment: Umeyama on camera centres, per "
                                   "connected component. Backends: " + "; ".join(notes)
                                   + ". End-to-end: PoserNet trained through a differentiable "
                                   "spectral synchronisation with a loss on aligned absolute "
                                   "poses (+ the relative loss), then evaluated with each "
                                   "backend. Learned sync: our MultiReg-style network (not the "
                                   "authors' MultiReg), trained on raw or on PoserNet-refined "
                                   "edges, beside the paper's MultiReg rows."))
    return list(table.write(out))


def _learned_sync_rows(ctx: Context, notes: list[str]) -> list[TableRow]:
    """Learned synchronisation on raw and on refined input (KP, BB), the paper's MultiReg
    rows above ours."""
    seeds = ctx.scale.seeds
    paper: dict[tuple[str, ...], TableRow] = {}
    mine: dict[tuple[str, ...], TableRow] = {}
    for refined, stage in ((False, "initial"), (True, "refined")):
        for est in ("bb", "kp"):
            key = (stage, est)
            p_label = "MultiReg" + (" + PoserNet" if refined else "")
            cells = P.TABLE3_MULTIREG[("PoserNet" if refined else "Initial", est.upper())]
            paper[key] = P.paper_row(("paper", p_label, est.upper()), cells)
            lab = ("Learned sync" + (" + PoserNet" if refined else ""), est.upper())
            evals = [ctx.sync_evaluation(est, s, refined) for s in seeds]
            mine[key] = ours(_seed_row(evals, "absolute", stage, lab))
    desc = ctx.sync_result("kp", seeds[0], False).backend or {}
    notes.append(f"Learned sync: scale {desc.get('scale_label', desc.get('scale', '?'))}")
    return interleave(paper, mine)


def _medians(evals: Sequence[dict[str, Any]]) -> tuple[list[float], list[float]]:
    return ([e["relative"]["refined"]["rot"].median for e in evals],
            [e["relative"]["refined"]["tdir"].median for e in evals])


def depth(ctx: Context, out: Path) -> list[Path]:
    """Supplementary: GNN depth ablation (KP) and a sweep of the loss weight alpha."""
    seeds = ctx.scale.ablation_seeds
    dspecs = {d: ModelSpec(depth=d) for d in sweep_values("depth_sweep", "model.net.depth")}
    aspecs = {a: ModelSpec(alpha=a) for a in sweep_values("alpha_sweep", "model.loss.alpha")}
    files: list[Path] = []
    full: list[TableRow] = []
    for what, specs, paper in (("depth", dspecs, P.DEPTH_MEDIANS),
                               ("alpha", aspecs, {0.1: P.DEPTH_MEDIANS[2]})):
        mt = MedianTable(what, title=f"PoserNet median errors vs {what} (KP, small graphs)")
        for v, spec in specs.items():
            evals = [ctx.evaluation(spec, s) for s in seeds]
            rot, tdir = _medians(evals)
            mt.rows.append(MedianRow(f"{v:g}", rot, tdir, paper.get(v),
                                     evals[0]["relative"]["refined"]["rot"].count))
            full.append(_seed_row(evals, "relative", "refined", (what, f"{v:g}")))
        mt.note = ("Paper (supplementary): every depth trained for 24 h, depth 2 best; "
                   "alpha 0.1 is the paper's setting (its row: the depth-2 model). "
                   + _note(ctx).replace(f"{len(ctx.scale.seeds)} seed(s) {list(ctx.scale.seeds)}",
                                        f"{len(seeds)} seed(s) {list(seeds)}"))
        files += mt.write(out, "table" if what == "depth" else "alpha")
    files += ResultTable(rows=full, label_names=("setting", "value"),
                         title="Depth and alpha sweeps: full threshold table (ours)").write(
        out, "full")
    return files


def loo(ctx: Context, out: Path) -> list[Path]:
    """Supplementary: leave-one-scene-out; train on the other scenes, test on the left-out one."""
    seeds = ctx.scale.ablation_seeds
    scenes = ctx.scenes()
    if len(scenes) < 2:
        raise ValueError(f"loo needs at least two scenes, the dataset has {scenes}")
    specs = {sc: ModelSpec(leave_out=sc) for sc in scenes}
    allspec = ModelSpec()
    mt = MedianTable("test scene", title="Leave-one-scene-out (KP, small graphs)")
    per_scene: list[tuple[list[float], list[float]]] = []
    tested = 0
    full: list[TableRow] = []
    for sc, spec in specs.items():
        evals = [ctx.evaluation(spec, s, scene=sc) for s in seeds]
        rot, tdir = _medians(evals)
        per_scene.append((rot, tdir))
        count = evals[0]["relative"]["refined"]["rot"].count
        tested += count
        mt.rows.append(MedianRow(sc, rot, tdir, P.LOO_MEDIANS.get(sc), count))
        full.append(_seed_row(evals, "relative", "refined", ("left out", sc)))
    # median over the scenes' tests, seed by seed
    med_rot = [statistics.median(r[k] for r, _ in per_scene) for k in range(len(seeds))]
    med_tdir = [statistics.median(t[k] for _, t in per_scene) for k in range(len(seeds))]
    mt.rows.append(MedianRow("median", med_rot, med_tdir, P.LOO_MEDIANS["median"], tested))
    all_evals = [ctx.evaluation(allspec, s) for s in seeds]
    rot, tdir = _medians(all_evals)
    mt.rows.append(MedianRow("all (trained on every scene)", rot, tdir, P.LOO_MEDIANS["all"],
                             all_evals[0]["relative"]["refined"]["rot"].count))
    full.append(_seed_row(all_evals, "relative", "refined", ("none", "all")))
    mt.note = ("median: median of the per-scene medians (graphs: all the per-scene tests). "
               + _note(ctx).replace(f"{len(ctx.scale.seeds)} seed(s) {list(ctx.scale.seeds)}",
                                    f"{len(seeds)} seed(s) {list(seeds)}"))
    files = list(mt.write(out))
    files += ResultTable(rows=full, label_names=("left out", "test"),
                         title="Leave-one-scene-out: full threshold table (ours)").write(
        out, "full")
    return files


def plots(ctx: Context, out: Path) -> list[Path]:
    """Supplementary plots: sorted per-graph errors (rolling mean) and 3D cameras (EIG-SE3)."""
    from ..metrics import align_to_ground_truth
    from ..plots import plot_cameras, plot_sorted_errors

    seed = ctx.scale.seeds[0]
    files: list[Path] = []
    lines = ["# Supplementary plots", "",
             f"Model seed {seed}; absolute poses from EIG-SE3, aligned to ground truth as "
             "the tables measure them: camera centres by a similarity (Umeyama on the "
             "centres), orientations by the rotation that best aligns the rotations.", ""]
    for est in ("kp", "bb"):
        spec = ModelSpec(estimate=est)
        res = ctx.result(spec, seed, backend="eig_se3")
        pg = ctx.evaluation(spec, seed, backend="eig_se3")["per_graph"]
        n = len(res.graphs)
        window = min(50, max(1, n // 5))
        panels = {
            "relative rotation": {"initial": pg["rel_rot_initial"],
                                  "refined": pg["rel_rot_refined"]},
            "relative translation direction": {"initial": pg["rel_tdir_initial"],
                                               "refined": pg["rel_tdir_refined"]},
            "absolute rotation (EIG-SE3)": {"initial": pg["abs_rot_initial"],
                                            "refined": pg["abs_rot_refined"]},
            "absolute position (EIG-SE3)": {"initial": pg["abs_pos_initial"],
                                            "refined": pg["abs_pos_refined"]},
        }
        f = plot_sorted_errors(out / f"errors_sorted_{est}.png", panels, window=window,
                               ylabels={"absolute position (EIG-SE3)": "error (m)"},
                               title=f"{est.upper()}: per-graph errors sorted by the refined "
                                     f"error, rolling mean over {window} graphs")
        files.append(f)
        lines.append(f"- `{f.name}`: {est.upper()}, {n} test graphs, window {window}")
        for k in range(min(ctx.scale.camera_plots, n)):
            g = res.graphs[k]
            gt = g.pose_gt.double()
            poses = {"ground truth": gt}
            for stage in ("initial", "refined"):
                poses[stage] = align_to_ground_truth(res.absolute[stage][k], gt)
            f = plot_cameras(out / f"cameras_{est}_{k}.png", poses,
                             title=f"{est.upper()} {g.name} ({g.meta.get('scene', '')}): GT vs "
                                   "initial vs refined (EIG-SE3)")
            files.append(f)
            lines.append(f"- `{f.name}`: cameras of graph {g.name}")
    files.append(atomic_write_text(out / "index.md", "\n".join(lines) + "\n"))
    return files


TABLES: dict[str, Callable[[Context, Path], list[Path]]] = {
    "table1": table1, "table2": table2, "table3": table3, "depth": depth, "loo": loo,
    "plots": plots,
}


def _quiet() -> None:
    """Silence Lightning's banner lines and known-harmless warnings (our own output stays)."""
    import lightning  # noqa: F401 - configures its loggers on import; override them after

    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", message=r".*does not have many workers.*")
    warnings.filterwarnings("ignore", message=r".*treespec, LeafSpec.*")
    warnings.filterwarnings("ignore", message=r".*small number of batches.*")
    warnings.filterwarnings("ignore", message=r".*Checkpoint directory .* exists.*")


def run_experiments(scale: str | Scale, out: str | Path, only: str | Sequence[str] | None = None,
                    device: str = "cpu", num_threads: int | None = 1, workers: int = 2,
                    echo: Callable[[str], None] | None = print, jobs: int = 1,
                    launcher: str | None = None, hydra: Sequence[str] = (),
                    train_only: bool = False, collect_only: bool = False,
                    data: str | Path | None = None) -> dict[str, dict[str, Any]]:
    """Run the chosen experiments at ``scale`` into ``out``; return ``{name: status}``.

    Three steps: the scale's synthetic dataset (``<out>/data``, or ``data``: an existing
    dataset directory), the ``posernet-train`` multiruns of the models not trained yet
    (``launcher``: ``basic``, ``joblib`` with ``jobs`` processes, ``submitit_local`` or
    ``submitit_slurm``; default ``joblib`` when ``jobs`` > 1 and installed; ``hydra``: extra
    overrides of every multirun, e.g. ``hydra.launcher.partition=gpu``), then the tables. A
    failing experiment is recorded in ``summary.md`` (with its error) and the others still run.
    ``train_only`` stops after training; ``collect_only`` trains nothing (a missing model fails
    its experiments with the command that trains it). ``device``: ``cpu``, ``cuda`` or ``auto``.
    """
    if isinstance(scale, str):
        scale = load_scale(scale)
    names = parse_only(only)
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    if device not in ("cpu", "cuda"):
        raise ValueError(f"device must be cpu, cuda or auto, got {device!r}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be an integer >= 1, got {jobs!r}")
    if launcher is None:
        launcher = "joblib" if jobs > 1 and launcher_available("joblib") else "basic"
    launch = [*launcher_overrides(launcher, jobs), *hydra]
    if not collect_only and not launcher_available(launcher):
        raise ValueError(f"launcher {launcher!r}: its Hydra plugin is not installed (pip "
                         f"install hydra-{launcher.split('_')[0]}-launcher)")
    if train_only and collect_only:
        raise ValueError("train_only and collect_only exclude each other")
    if data is not None and not (Path(data) / "manifest.json").is_file():
        raise FileNotFoundError(f"--data {data}: not a complete posernet dataset (no "
                                "manifest.json); generate one with posernet-make-data")
    if num_threads:
        torch.set_num_threads(int(num_threads))
    _quiet()
    say = echo or (lambda _msg: None)
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"--out {out}: cannot create the folder ({exc.strerror})") from None
    ctx = Context(scale, out, device=device, data_root=None if data is None else Path(data),
                  threads=num_threads)
    t_all = time.perf_counter()
    status: dict[str, dict[str, Any]] = {}
    t0 = time.perf_counter()
    if data is None:
        say(f"[data] synthetic dataset for scale '{scale.name}' -> {ctx.data_root}")
        ctx.ensure_data(workers)
    else:
        say(f"[data] using the dataset in {ctx.data_root}")
    status["data"] = {"ok": True, "seconds": time.perf_counter() - t0, "files": [],
                      "error": None, "trained": [], "models": []}
    if not collect_only:
        t0 = time.perf_counter()
        models = required_models(scale, names, ctx.scenes())
        todo = [(sp, s) for sp, s in models
                if finished_run(ctx.models / sp.key / f"seed{s}") is None]
        runs = multirun_commands(scale, todo, ctx.models, ctx.data_root, device, num_threads)
        say(f"[train] {len(todo)} of {len(models)} models to train for {','.join(names)}: "
            f"{len(runs)} posernet-train multirun(s), launcher {launcher}")
        train_models(runs, ctx.models, launch, echo=say)
        status["train"] = {"ok": True, "seconds": time.perf_counter() - t0, "files": [],
                           "error": None,
                           "trained": [f"{sp.key}/seed{s}" for sp, s in todo],
                           "models": [f"{sp.key}/seed{s}" for sp, s in models]}
    for name in ([] if train_only else names):
        say(f"[{name}] running")
        t0 = time.perf_counter()
        used_before = len(ctx.used)
        exp_dir = out / name
        exp_dir.mkdir(parents=True, exist_ok=True)
        try:
            files = TABLES[name](ctx, exp_dir)
            err = None
        except Exception as exc:  # recorded; the others still run
            files, err = [], f"{type(exc).__name__}: {exc}"
            log.debug("experiment %s failed", name, exc_info=True)
            trace = "" if isinstance(exc, FileNotFoundError) else f"\n{traceback.format_exc()}"
            say(f"[{name}] FAILED: {err}{trace}")
        dt = time.perf_counter() - t0
        status[name] = {"ok": err is None, "seconds": dt, "files": [str(f) for f in files],
                        "error": err, "trained": [],
                        "models": list(dict.fromkeys(ctx.used[used_before:]))}
        if err is None:
            say(f"[{name}] done in {dt:.1f} s -> {exp_dir}/table.md"
                if (exp_dir / "table.md").exists() else f"[{name}] done in {dt:.1f} s")
    write_summary(out, scale, status, time.perf_counter() - t_all, device, ctx.epochs())
    say(f"summary: {out / 'summary.md'}")
    if any(st["ok"] for n, st in status.items() if n in TABLES) and any(
            out.glob("*/table.csv")):  # e.g. --only plots writes no table
        say(f"digest (medians, ours vs paper): {write_digest(out)}")
    return status


def machine_description(device: str) -> str:
    """One line naming the machine: CPU, cores, torch threads, GPU when used, versions."""
    from ..report import cpu_model

    cpu = cpu_model()
    gpu = (f", GPU {torch.cuda.get_device_name(0)}"
           if device == "cuda" and torch.cuda.is_available() else "")
    return (f"{cpu}, {os.cpu_count()} logical cores, {torch.get_num_threads()} torch thread(s)"
            f"{gpu}; Python {platform.python_version()}, torch {torch.__version__}, "
            f"{platform.system()} {platform.release()}")


def _train_seconds(run_dir: Path) -> float:
    """Training time recorded in a model's ``metrics.json`` (0 when missing)."""
    try:
        summary = json.loads((run_dir / "metrics.json").read_text())
        return float(summary.get("train_seconds") or 0.0)
    except (OSError, ValueError):
        return 0.0


def write_summary(out: Path, scale: Scale, status: dict[str, dict[str, Any]], total: float,
                  device: str, epochs: tuple[int, int]) -> Path:
    """``summary.md`` (+ ``summary.json``): wall time, status, models and files of each experiment.

    Runs into the same ``out`` (``--only`` subsets, possibly in parallel processes) are merged:
    each experiment keeps the entry of the latest run that ran it, with its command and machine.
    """
    record = out / "summary.json"
    try:
        merged = json.loads(record.read_text()) if record.is_file() else {}
    except json.JSONDecodeError:
        merged = {}
    if merged.get("scale") != scale.name:
        merged = {}
    runs = merged.get("runs", {})
    command = "python -m posernet.experiments " + " ".join(sys.argv[1:]) \
        if Path(sys.argv[0]).parent.name == "experiments" else " ".join(sys.argv)
    stamp = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    for name, st in status.items():
        runs[name] = {**st, "command": command, "machine": machine_description(device),
                      "finished": stamp, "run_total_seconds": total}
    merged = {"scale": scale.name, "runs": runs}
    atomic_write_json(record, merged)

    lines = [f"# PoserNet experiments, scale `{scale.name}`", "",
             f"Seeds {list(scale.seeds)} (tables 1-3), {list(scale.ablation_seeds)} (depth, "
             f"alpha, loo); epochs {epochs[0]} small / {epochs[1]} large. "
             "The models are trained first (row `train`: posernet-train multiruns of the "
             "models not yet in models/) and shared between the experiments; an experiment's "
             "wall time is its evaluation.", "",
             "| experiment | status | wall time (s) | models trained | models used "
             "(their training, s) | table | finished |",
             "|---|---|---:|---:|---:|---|---|"]
    order = ["data", "train", *EXPERIMENTS]
    for name in sorted(runs, key=lambda n: order.index(n) if n in order else len(order)):
        st = runs[name]
        table = next((Path(f).relative_to(out).as_posix() for f in st["files"]
                      if f.endswith(("table.md", "index.md"))), "")
        state = "ok" if st["ok"] else f"FAILED ({st['error']})"
        models = st.get("models", [])
        train_s = sum(_train_seconds(out / "models" / m) for m in models)
        lines.append(f"| {name} | {state} | {st['seconds']:.1f} | {len(st['trained'])} | "
                     f"{len(models)} ({train_s:.0f}) | {table} | {st['finished']} |")
    commands = dict.fromkeys((st["command"], st["machine"]) for st in runs.values())
    lines += ["", "Commands and machines:", ""]
    lines += [f"- `{cmd}` on {machine}" for cmd, machine in commands]
    lines += ["", f"Total wall time of the last run: {total:.1f} s."]
    return atomic_write_text(out / "summary.md", "\n".join(lines) + "\n")
