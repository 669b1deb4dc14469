"""The models the paper's experiments need, and the ``posernet-train`` multiruns that train them.

A scale (``conf/scale/<name>.yaml``: dataset preset, seeds, training overrides) and the
experiments asked for give a list of ``(ModelSpec, seed)`` jobs. Jobs that share an experiment
file (``conf/experiment/*.yaml``) and differ only in the seed and in the one value that file
sweeps (depth, alpha, left-out scene) become one Hydra multirun::

    posernet-train -m +experiment=depth_sweep model.net.depth=3,4,5 seed=0 \\
        data.root=DATA ckpt_path=last hydra.sweep.dir=OUT/models \\
        hydra.sweep.subdir='kp-small-d${model.net.depth}-a0.1/seed${seed}'

so each model lands in ``OUT/models/<key>/seed<k>/`` (its ``metrics.json`` marks it finished)
and a launcher plugin spreads the jobs: ``hydra/launcher=joblib`` on one machine,
``hydra/launcher=submitit_slurm`` on a cluster (:func:`multirun_commands` prints the commands
to run there). ``ckpt_path=last`` makes a rerun of an interrupted multirun resume each job from
its own last checkpoint; finished jobs are left out of the commands.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

__all__ = [
    "EXPERIMENTS",
    "Job",
    "ModelSpec",
    "Multirun",
    "Scale",
    "finished_run",
    "load_scale",
    "multirun_commands",
    "parse_only",
    "required_models",
    "scale_names",
    "sweep_values",
    "train_models",
]

#: the experiments, in the order they run
EXPERIMENTS = ("table1", "table2", "table3", "depth", "loo", "plots")


def scale_names() -> list[str]:
    """Scales shipped in (or put into) ``conf/scale/``."""
    from ..conf import config_root

    folder = config_root() / "scale"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


@dataclass(frozen=True)
class Scale:
    """A ``conf/scale/<name>.yaml`` file: the dataset preset, the seeds of the tables
    (``seeds``) and of the ablations (``ablation_seeds``), ``posernet-train`` overrides of every
    model (``train``) and of those trained on large graphs (``train_large``, after ``train``),
    evaluation batch size, camera plots per input and whether data generation shows a bar."""

    name: str
    dataset: str
    data_seed: int
    seeds: tuple[int, ...]
    ablation_seeds: tuple[int, ...]
    train: tuple[str, ...]
    train_large: tuple[str, ...]
    eval_batch: int
    camera_plots: int
    progress_bar: bool


def load_scale(name: str, overrides: Sequence[str] = ()) -> Scale:
    """The scale ``name`` (``quick``, ``medium``, ``paper``), with Hydra ``overrides`` of its
    fields (e.g. ``["scale.seeds=[0]"]``)."""
    from dataclasses import fields

    from omegaconf import OmegaConf

    from ..conf import compose

    names = scale_names()
    if name not in names:
        raise ValueError(f"unknown scale {name!r}; valid: {names}")
    data = OmegaConf.to_container(compose("experiments", [f"scale={name}", *overrides]).scale,
                                  resolve=True)
    want = [f.name for f in fields(Scale)]
    if not isinstance(data, dict) or sorted(data) != sorted(want):
        have = sorted(data) if isinstance(data, dict) else data
        raise ValueError(f"conf/scale/{name}.yaml: needs exactly the keys {want}, has {have}")
    if not data["seeds"] or not data["ablation_seeds"]:
        raise ValueError(f"conf/scale/{name}.yaml: seeds and ablation_seeds must not be empty")
    return Scale(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})


@dataclass(frozen=True)
class ModelSpec:
    """One model to train: input estimate, graph size, depth, alpha, left-out scene, and its
    kind: ``posernet`` (the paper's training), ``end_to_end`` (trained through a differentiable
    synchronisation) or ``sync`` (the learned synchronisation, on raw input or, ``refined``, on
    the edges of the ``posernet`` model of the same estimate and seed)."""

    estimate: str = "kp"
    size: str = "small"
    depth: int = 2
    alpha: float = 0.1
    leave_out: str | None = None
    kind: str = "posernet"
    refined: bool = False

    @property
    def key(self) -> str:
        """Folder name of the model, e.g. ``kp-small-d2-a0.1``, ``kp-small-d2-a0.1-loo_fire``,
        ``e2e-kp-small-d2-a0.1`` or ``sync-kp-refined``."""
        if self.kind == "sync":
            return f"sync-{self.estimate}-{'refined' if self.refined else 'raw'}"
        alpha = self.alpha if isinstance(self.alpha, str) else f"{self.alpha:g}"
        k = f"{self.estimate}-{self.size}-d{self.depth}-a{alpha}"
        k = ("e2e-" + k) if self.kind == "end_to_end" else k
        return k + (f"-loo_{self.leave_out}" if self.leave_out else "")

    def experiment(self) -> tuple[str, dict[str, Any]]:
        """The ``conf/experiment`` file that trains this model and the overrides that make it
        this one (the swept value; the others restate the file's own values)."""
        if self.kind == "sync":
            return "learned_sync", {"data.estimate": self.estimate, "data.size": self.size}
        if self.kind == "end_to_end":
            name = "end_to_end"
        elif self.size == "large":
            name = "large_graphs"
        elif self.leave_out:
            name = "leave_one_out"
        elif self.depth != 2:
            name = "depth_sweep"
        elif self.alpha != 0.1:
            name = "alpha_sweep"
        else:
            name = f"table1_{self.estimate}"
        overrides: dict[str, Any] = {"data.estimate": self.estimate, "data.size": self.size,
                                     "model.net.depth": self.depth,
                                     "model.loss.alpha": self.alpha}
        if self.leave_out:
            overrides["data.leave_out_scene"] = self.leave_out
        return name, overrides


Job = tuple[ModelSpec, int]

# the field each sweep file varies, and the override that sets it
_SWEPT = {"depth_sweep": ("depth", "model.net.depth"),
          "alpha_sweep": ("alpha", "model.loss.alpha"),
          "leave_one_out": ("leave_out", "data.leave_out_scene")}


def sweep_values(experiment: str, key: str) -> list[Any]:
    """The values a sweep file (``depth_sweep``, ``alpha_sweep``) declares for ``key``."""
    from omegaconf import OmegaConf

    from ..conf import compose

    cfg = compose("train", [f"+experiment={experiment}"], return_hydra_config=True)
    params = cfg.hydra.sweeper.get("params") or {}
    if key not in params:
        raise ValueError(f"experiment/{experiment}.yaml declares no sweep over {key}")
    return list(OmegaConf.create(f"v: [{params[key]}]").v)  # "2,3,4,5" -> [2, 3, 4, 5]


def required_models(scale: Scale, names: Sequence[str], scenes: Sequence[str]) -> list[Job]:
    """Every ``(spec, seed)`` the experiments ``names`` need at ``scale``, each once, in a
    stable order (a refined learned sync after the PoserNet model it reads). ``scenes``: the
    dataset's scenes (one left-out model each)."""
    seeds, ablation = list(scale.seeds), list(scale.ablation_seeds)
    table1 = [(ModelSpec(estimate=e), s) for e in ("bb", "kp") for s in seeds]
    extra = [ModelSpec(estimate=e, kind="end_to_end") for e in ("bb", "kp")]
    extra += [ModelSpec(estimate=e, kind="sync", refined=r) for r in (False, True)
              for e in ("bb", "kp")]
    sweeps = [*(ModelSpec(depth=d) for d in sweep_values("depth_sweep", "model.net.depth")),
              *(ModelSpec(alpha=a) for a in sweep_values("alpha_sweep", "model.loss.alpha"))]
    per_experiment: dict[str, list[Job]] = {
        "table1": table1,
        "table2": [(ModelSpec(size=z), s) for z in ("small", "large") for s in seeds],
        "table3": table1 + [(sp, s) for sp in extra for s in seeds],
        "depth": [(sp, s) for sp in sweeps for s in ablation],
        "loo": [(sp, s) for sp in [*(ModelSpec(leave_out=sc) for sc in scenes), ModelSpec()]
                for s in ablation],
        "plots": [(ModelSpec(estimate=e), seeds[0]) for e in ("kp", "bb")],
    }
    return list(dict.fromkeys(job for n in names for job in per_experiment[n]))


def parse_only(only: str | Sequence[str] | None) -> list[str]:
    """Experiment names from ``"table1,table3"`` (or a list); all of them for ``None``/empty."""
    if only is None:
        return list(EXPERIMENTS)
    names = [n.strip() for n in (only.split(",") if isinstance(only, str) else only)]
    names = [n for n in names if n]
    if not names:
        return list(EXPERIMENTS)
    bad = [n for n in names if n not in EXPERIMENTS]
    if bad:
        raise ValueError(f"unknown experiment(s) {bad}; valid: {list(EXPERIMENTS)}")
    return list(dict.fromkeys(names))


def finished_run(run_dir: Path) -> Path | None:
    """The checkpoint of a finished training run in ``run_dir`` (best, else last; found beside
    its ``metrics.json`` even when the folder was moved), or None when it has not finished."""
    import json

    try:
        summary = json.loads((run_dir / "metrics.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    for name in (summary.get("best_checkpoint"), summary.get("last_checkpoint")):
        if name:
            path = run_dir / "checkpoints" / Path(name).name
            if path.is_file():
                return path
    return None


@dataclass(frozen=True)
class Multirun:
    """One ``posernet-train -m`` call: an experiment file, fixed overrides, swept values."""

    experiment: str
    overrides: tuple[str, ...]
    swept: tuple[str, tuple[Any, ...]] | None  # (override key, values) besides the seeds
    seeds: tuple[int, ...]
    subdir: str  # hydra.sweep.subdir, with ${...} for the swept value and the seed
    keys: tuple[str, ...]  # the model folders it writes (for messages)

    @property
    def jobs(self) -> int:
        """Models this multirun trains: seeds x swept values."""
        return len(self.seeds) * (len(self.swept[1]) if self.swept else 1)

    def argv(self, models: Path, launcher: Sequence[str] = ()) -> list[str]:
        """The Hydra command-line arguments (after ``posernet-train``)."""
        from ..conf import quote_value

        swept = ([f"{self.swept[0]}={','.join(str(v) for v in self.swept[1])}"]
                 if self.swept else [])
        return ["-m", f"+experiment={self.experiment}", *self.overrides, *swept,
                f"seed={','.join(str(s) for s in self.seeds)}",
                f"hydra.sweep.dir={quote_value(models.resolve())}",
                f"hydra.sweep.subdir='{self.subdir}'",  # keeps its ${...}: not quote_value
                "~hydra.callbacks.sweep_summary", *launcher]


def _common_overrides(scale: Scale, spec: ModelSpec, data_root: Path, device: str,
                      threads: int | None) -> list[str]:
    from ..conf import quote_value

    large = list(scale.train_large) if spec.size == "large" else []
    return [f"trainer={'gpu' if device == 'cuda' else 'cpu'}", *scale.train, *large,
            f"data.root={quote_value(data_root.resolve())}", "test_after_training=false",
            f"num_threads={threads or 'null'}", "trainer.enable_progress_bar=false",
            "trainer.enable_model_summary=false", "ckpt_path=last"]


def multirun_commands(scale: Scale, jobs: Sequence[Job], models: Path, data_root: Path,
                      device: str = "cpu", threads: int | None = 1) -> list[Multirun]:
    """Group ``jobs`` into the fewest multiruns (one per experiment file and fixed values, the
    swept value and the seeds crossed), in the order of their first job.

    A refined learned sync reads the PoserNet model of its estimate and seed
    (``model.input.refiner_ckpt``); it is listed after the multirun that trains that model.
    """
    from ..conf import quote_value

    groups: dict[tuple[Any, ...], dict[str, Any]] = {}
    for spec, seed in jobs:
        name, values = spec.experiment()
        field, key = _SWEPT.get(name, (None, None))
        base = replace(spec, **{field: "{swept}"}) if field else spec
        fixed = {k: v for k, v in values.items() if k != key}
        if spec.kind == "sync" and spec.refined:  # that seed's PoserNet refines its input
            refiner = models.resolve() / ModelSpec(estimate=spec.estimate, size=spec.size).key
            fixed["model.input.refiner_ckpt"] = (quote_value(f"{refiner}/seed")[:-1]
                                                 + "${seed}/checkpoints/best.ckpt'")
        g = groups.setdefault((name, base, tuple(sorted(fixed.items()))),
                              {"spec": spec, "fixed": fixed, "values": {}, "field": field,
                               "key": key})
        if field:
            g["values"].setdefault(getattr(spec, field), set()).add(seed)
        else:
            g["values"].setdefault(None, set()).add(seed)

    runs: list[Multirun] = []
    for (name, base, _), g in groups.items():
        # one multirun per distinct seed set (a grid: every value with every seed)
        by_seeds: dict[tuple[int, ...], list[Any]] = {}
        for value, seeds in g["values"].items():
            by_seeds.setdefault(tuple(sorted(seeds)), []).append(value)
        for seeds, values in by_seeds.items():
            overrides = [f"{k}={v}" for k, v in g["fixed"].items()]
            overrides += _common_overrides(scale, g["spec"], data_root, device, threads)
            field, key = g["field"], g["key"]
            template = base.key
            if field:
                template = template.replace("{swept}", "${" + key + "}")
                keys = tuple(replace(base, **{field: v}).key for v in values)
            else:
                keys = (base.key,)
            runs.append(Multirun(name, tuple(overrides),
                                 (key, tuple(values)) if field else None, seeds,
                                 template + "/seed${seed}", keys))
    return runs


def launcher_overrides(launcher: str, jobs: int) -> list[str]:
    """Hydra overrides that pick the launcher plugin: ``basic`` (one job after another),
    ``joblib`` (``jobs`` processes on this machine), ``submitit_local`` / ``submitit_slurm``
    (a cluster; configure it further with ``hydra.launcher.*`` overrides)."""
    if launcher == "basic":
        return []
    if launcher == "joblib":
        return ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={jobs}"]
    if launcher in ("submitit_local", "submitit_slurm"):
        return [f"hydra/launcher={launcher}"]
    raise ValueError(f"unknown launcher {launcher!r}; valid: basic, joblib, submitit_local, "
                     "submitit_slurm")


def launcher_available(launcher: str) -> bool:
    """Whether the Hydra plugin of ``launcher`` is installed (``basic`` always is)."""
    import importlib.util

    module = {"basic": None, "joblib": "hydra_plugins.hydra_joblib_launcher",
              "submitit_local": "hydra_plugins.hydra_submitit_launcher",
              "submitit_slurm": "hydra_plugins.hydra_submitit_launcher"}.get(launcher)
    if module is None:
        return launcher == "basic"
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def train_models(runs: Sequence[Multirun], models: Path, launcher: Sequence[str] = (),
                 log_dir: Path | None = None, echo: Any = print) -> None:
    """Run each multirun as a ``posernet-train -m`` subprocess, one after another (its jobs in
    parallel as the launcher allows); its output goes to ``log_dir/<n>_<experiment>.log``.

    Raises RuntimeError naming the log when a multirun fails (the models it finished stay).
    """
    from tqdm.auto import tqdm

    log_dir = log_dir or models / "logs"
    log_dir.mkdir(parents=True, exist_ok=True)
    say = echo or (lambda _msg: None)
    total = sum(r.jobs for r in runs)
    with tqdm(total=total, desc="train: models", unit="model") as bar:
        for n, run in enumerate(runs):
            argv = [sys.executable, "-m", "posernet.cli.train", *run.argv(models, launcher)]
            log = log_dir / f"{n:02d}_{run.experiment}.log"
            say(f"[train] {' '.join(run.keys)} seeds {list(run.seeds)} -> {log}")
            with open(log, "w", encoding="utf-8") as fh:
                fh.write("$ " + " ".join(argv) + "\n")
                fh.flush()
                rc = subprocess.call(argv, stdout=fh, stderr=subprocess.STDOUT)
            if rc != 0:
                tail = log.read_text(encoding="utf-8", errors="replace").splitlines()[-15:]
                raise RuntimeError(f"training multirun {run.experiment} failed (exit {rc}); "
                                   f"log {log}:\n" + "\n".join(tail))
            bar.update(run.jobs)
