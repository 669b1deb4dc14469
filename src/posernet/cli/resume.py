"""Continuing a ``posernet-train`` run in its own folder: the part Hydra and Lightning leave
to the caller.

Neither library resumes a run in place. Hydra gives each run a new output folder (reusing one
means overriding ``hydra.run.dir``) and has no notion of a run's earlier settings; Lightning
restores a ``ModelCheckpoint``'s best-so-far state only when its ``dirpath`` string is the one
saved, and its ``CSVLogger`` deletes an existing ``metrics.csv``. What resuming
``RUN/checkpoints/last.ckpt`` needs beyond that is here, in four pieces:

* :func:`resume_overrides`: the command line, read with Hydra's own argument and override
  parsers, gains ``hydra.run.dir=RUN``, a separate ``hydra.output_subdir`` for the resumed
  job's config and the run's own settings (:func:`run_settings`, read from ``RUN/.hydra``);
* :func:`continues_run`: whether a checkpoint belongs to the job's output folder;
* :func:`relocation_callback`: a Lightning callback re-basing the checkpoint callbacks' saved
  paths when the run folder was moved or copied since;
* :func:`kept_csv_log`: the earlier epochs of ``logs/metrics.csv`` survive the new logger.
"""

from __future__ import annotations

import csv
import os
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

__all__ = ["continues_run", "kept_csv_log", "relocation_callback", "resume_overrides",
           "run_dir_of_checkpoint", "run_settings"]

#: overrides naming the output folder themselves (no folder is chosen for them)
_OWN_FOLDER_KEYS = ("hydra.run.dir", "out_dir")


def run_dir_of_checkpoint(ckpt_path: str | os.PathLike[str]) -> Path | None:
    """The run folder of a checkpoint written by ``posernet-train`` (``RUN/checkpoints/x.ckpt``
    -> ``RUN``, absolute), or ``None`` for a checkpoint stored elsewhere."""
    p = Path(ckpt_path).expanduser().resolve()
    return p.parent.parent if p.parent.name == "checkpoints" else None


def _parsed(overrides: list[str]) -> list[Any] | None:
    """``overrides`` read by Hydra's override parser, or None when Hydra will reject them."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        return OverridesParser.create().parse_overrides(overrides)
    except HydraException:
        return None


def resume_overrides(argv: list[str]) -> list[str]:
    """Command-line arguments that make a resumed run continue in its own folder.

    With ``ckpt_path=RUN/checkpoints/*.ckpt`` (an existing file) and neither ``hydra.run.dir``
    nor ``out_dir`` given: the run's own settings (:func:`run_settings`) that ``argv`` does not
    set come first, and ``hydra.run.dir=RUN`` and ``hydra.output_subdir=.hydra/resume_<date>_
    <time>`` (this job's Hydra config, beside the run's original one) are appended. Sweeps
    (``-m``), other commands and arguments Hydra will reject are returned unchanged.
    """
    from hydra._internal.utils import get_args_parser

    try:
        args = get_args_parser().parse_args(argv)
    except SystemExit:  # Hydra reports its own usage errors
        return list(argv)
    overrides = _parsed(list(args.overrides))
    if args.multirun or not overrides:
        return list(argv)
    given = {o.key_or_group for o in overrides}
    ckpt = [o for o in overrides if o.key_or_group == "ckpt_path" and not o.is_delete()]
    if given & set(_OWN_FOLDER_KEYS) or not ckpt:
        return list(argv)
    value = ckpt[-1].value()
    if value in (None, "", "last") or not Path(str(value)).expanduser().is_file():
        return list(argv)  # nothing to continue (a missing file is reported by train())
    run_dir = run_dir_of_checkpoint(str(value))
    if run_dir is None or '"' in str(run_dir):
        return list(argv)
    inherited = [o for key, o in run_settings(run_dir).items() if key not in given]
    if inherited:
        print(f"posernet-train: continuing {run_dir} with its own settings: "
              + " ".join(inherited), file=sys.stderr)
    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    return [*inherited, *argv, f'hydra.run.dir="{run_dir}"',
            f"hydra.output_subdir=.hydra/resume_{stamp}"]


def run_settings(run_dir: Path) -> dict[str, str]:
    """The command-line overrides a run was started with (Hydra's record of them in
    ``RUN/.hydra/hydra.yaml``) by key, without Hydra's own and ``ckpt_path``, and its
    ``data.root`` (from ``RUN/.hydra/config.yaml``) made absolute against the folder the run
    was started from: what resuming it from any folder needs to train on the same data with
    the same model. Empty when the files are absent."""
    from omegaconf import OmegaConf

    hydra_dir = run_dir / ".hydra"
    try:
        hydra_cfg = OmegaConf.load(hydra_dir / "hydra.yaml").hydra
        overrides = _parsed([str(o) for o in hydra_cfg.overrides.task]) or []
        cwd = Path(str(hydra_cfg.runtime.cwd))
        root = OmegaConf.select(OmegaConf.load(hydra_dir / "config.yaml"), "data.root",
                                default=None)
    except Exception:  # no (or unreadable) Hydra record: nothing to inherit
        return {}
    keep: dict[str, str] = {}
    if root is not None:
        roots = list(root) if OmegaConf.is_list(root) else [root]
        absolute = [str(p if Path(str(p)).is_absolute() else cwd / str(p)) for p in roots]
        keep["data.root"] = "data.root=" + (absolute[0] if len(absolute) == 1
                                            else "[" + ",".join(absolute) + "]")
    for o in overrides:
        if not o.key_or_group.startswith("hydra.") and o.key_or_group not in (
                "ckpt_path", "data.root"):
            keep[o.key_or_group] = str(o.input_line)
    return keep


def continues_run(ckpt_path: Any, out_dir: Path) -> bool:
    """Whether ``ckpt_path`` is a checkpoint of the run folder ``out_dir`` (resume in place)."""
    if ckpt_path in (None, "last"):
        return False
    run_dir = run_dir_of_checkpoint(ckpt_path)
    return run_dir is not None and run_dir == out_dir.resolve()


def relocation_callback(ckpt_path: str) -> Any:
    """A Lightning callback that lets the checkpoint callbacks of a run folder that was moved
    (or copied) since ``ckpt_path`` was written keep their best-so-far state on resume.

    Lightning restores ``best_model_score`` only when the saved ``dirpath`` equals the current
    one; for a callback whose ``dirpath`` holds ``ckpt_path``, the saved paths are re-based
    onto it before Lightning loads them (``on_load_checkpoint`` runs first)."""
    from lightning.pytorch.callbacks import Callback, ModelCheckpoint

    ckpt_dir = os.path.realpath(Path(ckpt_path).expanduser().parent)

    class _ContinueRun(Callback):
        def on_load_checkpoint(self, trainer: Any, pl_module: Any,
                               checkpoint: dict[str, Any]) -> None:
            states = checkpoint.get("callbacks") or {}
            for cb in trainer.checkpoint_callbacks:
                state = states.get(cb.state_key) if isinstance(cb, ModelCheckpoint) else None
                if not isinstance(state, dict) or not cb.dirpath or cb.dirpath != ckpt_dir:
                    continue
                old = state.get("dirpath")
                if not isinstance(old, str) or old == cb.dirpath:
                    continue

                def move(path: Any, old: str = old, new: str = cb.dirpath) -> Any:
                    if isinstance(path, str) and path and Path(path).parent == Path(old):
                        return os.path.join(new, Path(path).name)
                    return path

                state["dirpath"] = cb.dirpath
                for key in ("best_model_path", "kth_best_model_path", "last_model_path"):
                    if key in state:
                        state[key] = move(state[key])
                if isinstance(state.get("best_k_models"), dict):
                    state["best_k_models"] = {move(k): v for k, v in
                                              state["best_k_models"].items()}

    return _ContinueRun()


@contextmanager
def kept_csv_log(logger: Any, epoch: int, global_step: int) -> Iterator[None]:
    """Around ``trainer.fit`` of a run resumed in place: keep the rows of ``logger``'s
    ``metrics.csv`` written before the resumed checkpoint (epoch ``<= epoch``; rows without an
    epoch: ``step < global_step``) and put the new rows after them.

    Lightning's ``CSVLogger`` deletes an existing ``metrics.csv`` when it starts writing, so the
    file is set aside (``metrics.before_resume.csv``) until training ends. Does nothing for
    another logger, no logger or a folder without a log."""
    from lightning.pytorch.loggers import CSVLogger

    log_csv = Path(logger.log_dir) / "metrics.csv" if isinstance(logger, CSVLogger) else None
    if log_csv is None or not log_csv.is_file():
        yield
        return
    history = log_csv.with_name("metrics.before_resume.csv")
    os.replace(log_csv, history)
    warnings.filterwarnings("ignore", message=r"Experiment logs directory .*")
    try:
        yield
    finally:
        _merge_csv_log(log_csv, history, epoch, global_step)


def _merge_csv_log(path: Path, history: Path, epoch: int, global_step: int) -> None:
    """Rewrite ``path`` as the rows of ``history`` written before the resumed checkpoint
    followed by ``path``'s rows (the union of both headers), and remove ``history``."""

    def rows(p: Path) -> tuple[list[str], list[dict[str, str]]]:
        if not p.is_file():
            return [], []
        with p.open(newline="") as f:
            reader = csv.DictReader(f)
            return list(reader.fieldnames or []), list(reader)

    def before(row: dict[str, str]) -> bool:
        try:
            if row.get("epoch"):
                return float(row["epoch"]) <= epoch
            return float(row.get("step") or "nan") < global_step
        except ValueError:
            return True

    old_keys, old_rows = rows(history)
    new_keys, new_rows = rows(path)
    keys = sorted(set(old_keys) | set(new_keys))
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows([r for r in old_rows if before(r)] + new_rows)
    os.replace(tmp, path)
    history.unlink()
