"""``posernet-make-data``: generate a graph dataset directory (Hydra app,
``posernet/conf/make_data.yaml``), synthetic or from real images in the 7-Scenes layout.

Examples::

    posernet-make-data dataset=paper out_dir=/tmp/posernet-paper workers=2
    posernet-make-data dataset=tiny out_dir=/tmp/tiny overwrite=true
    posernet-make-data preset=easy dataset.small.train=100 resume=true
    posernet-make-data source=sevenscenes root=/data/7scenes scenes=[chess,fire] \
        intrinsics=585,585,320,240 proposals=edge_boxes matcher=sift out_dir=/tmp/7s

Errors a user can cause (bad option, existing directory, resume with another config, a root
that is not in 7-Scenes layout, bad intrinsics, an unwritable out_dir) are printed as one line
without a traceback, with exit status 1. Ctrl-C stops with exit status 130; the complete files
are kept and ``resume=true`` finishes the dataset.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from ..options import anything, option, path
from . import CONFIG_DIR
from .common import check_config, run_app, run_task

__all__ = ["MakeDataSettings", "execute", "main", "run"]


@dataclass(frozen=True, kw_only=True)
class MakeDataSettings:
    """``posernet-make-data``'s own keys (``conf/make_data.yaml``; ``sevenscenes`` is
    :class:`posernet.data.sevenscenes_graphs.SevenScenesOptions`, the groups declare theirs)."""

    source: str = option("synthetic", choices=("synthetic", "sevenscenes"), help="synthetic "
                         "(the simulator, dataset=...) or sevenscenes (images under root=)")
    out_dir: str | None = option(None, rule=path(), help="dataset directory; default "
                                 "outputs/data/<preset name> (or .../sevenscenes)")
    preset: str | None = option(None, help="alternative to dataset=NAME; dataset.* overrides "
                                "still apply on top")
    seed: int = option(0, ge=0, help="master seed: same config + seed => bit-identical graph "
                       "files")
    workers: int = option(2, ge=1, help="synthetic: worker processes; sevenscenes: threads for "
                          "per-image stages")
    overwrite: bool = option(False, help="replace an existing dataset in out_dir")
    resume: bool = option(False, help="keep the complete files of an interrupted run, make the "
                          "rest")
    export_json: bool = option(False, help="also write json/<size>.json in the authors' schema")
    progress: bool = option(True, help="tqdm progress bars (sevenscenes: also images and pairs "
                            "of each file)")
    root: str | None = option(None, rule=path(), help="source=sevenscenes: folder holding the "
                              "scene folders (chess/, fire/, ...), or one scene folder")
    scenes: Sequence[str] | None = option(None, rule=anything("a list of scene folders"),
                                          help="source=sevenscenes: scene folders to use, e.g. "
                                          "[chess,fire]; null: every one under root")
    intrinsics: str | Sequence[float] | None = option(
        None, rule=anything("FX,FY,CX,CY, [FX,FY,CX,CY], a JSON / 3x3 text file, or auto"),
        help="source=sevenscenes: FX,FY,CX,CY | [FX,FY,CX,CY] | a JSON / 3x3 text file; null: "
        "585,585,320,240")
    frame_step: int = option(10, ge=1, help="source=sevenscenes: every n-th frame of each "
                             "1000-frame, 30 Hz sequence")


def _dataset_config(cfg: DictConfig) -> Any:
    """The dataset options: ``cfg.dataset``, or preset ``cfg.preset`` with dataset.* overrides."""
    from hydra.core.hydra_config import HydraConfig

    from posernet.data.synthetic.config import load_preset

    preset = cfg.get("preset")
    try:
        choice = HydraConfig.get().runtime.choices.get("dataset")
        task = list(HydraConfig.get().overrides.task)
    except ValueError:  # not running under Hydra
        choice, task = None, []
    if preset is None or preset == choice:
        return OmegaConf.to_container(cfg.dataset, resolve=True)
    base = OmegaConf.create(load_preset(str(preset)).to_dict())
    overrides = [o.lstrip("+") for o in task if o.lstrip("+").startswith("dataset.")]
    dot = OmegaConf.from_dotlist([o[len("dataset.") :] for o in overrides])
    return OmegaConf.to_container(OmegaConf.merge(base, dot), resolve=True)


_SEVENSCENES_KEYS = ("root", "scenes", "intrinsics")


def _run_sevenscenes(cfg: DictConfig) -> dict[str, Any]:
    """``source=sevenscenes``: graphs of the images under ``root`` through the front end."""
    from posernet.data.sevenscenes_graphs import FRONTEND_GROUPS, generate_sevenscenes

    from .build import frontend_stages

    return generate_sevenscenes(
        OmegaConf.to_container(cfg.sevenscenes, resolve=True),
        _out_dir(cfg),
        frontend=frontend_stages({g: OmegaConf.to_container(cfg[g], resolve=True)
                                  for g in FRONTEND_GROUPS}),
        seed=cfg.seed,
        overwrite=bool(cfg.overwrite),
        resume=bool(cfg.resume),
        export_json_files=bool(cfg.export_json),
        progress=bool(cfg.progress),
    )


def _out_dir(cfg: DictConfig) -> str:
    """``out_dir``, by default ``outputs/data/<preset name>`` (``.../sevenscenes``)."""
    if cfg.get("out_dir"):
        return str(cfg.out_dir)
    if cfg.get("source") == "sevenscenes":
        return "outputs/data/sevenscenes"
    return f"outputs/data/{cfg.get('preset') or cfg.dataset.get('name', 'dataset')}"


def run(cfg: DictConfig) -> dict[str, Any]:
    """Generate the dataset described by a composed ``make_data`` config; returns the manifest."""
    from posernet.data.synthetic import ConfigError, generate_dataset

    check_config(cfg, "make_data")
    if cfg.get("source") == "sevenscenes":
        return _run_sevenscenes(cfg)
    given = [k for k in _SEVENSCENES_KEYS if cfg.get(k) is not None]
    if given:
        raise ConfigError(f"{', '.join(k + '=' for k in given)} "
                          f"{'is an option' if len(given) == 1 else 'are options'} of "
                          f"source=sevenscenes (the synthetic generator takes "
                          f"dataset.scenes=...); add source=sevenscenes")
    return generate_dataset(
        _dataset_config(cfg),
        _out_dir(cfg),
        seed=cfg.seed,
        workers=cfg.workers,
        overwrite=bool(cfg.overwrite),
        resume=bool(cfg.resume),
        export_json_files=bool(cfg.export_json),
        progress=bool(cfg.progress),
    )


def _user_errors() -> tuple[type[BaseException], ...]:
    from posernet.data.sevenscenes import SevenScenesError
    from posernet.data.store import DatasetError
    from posernet.data.synthetic import (
        ConfigError,
        DatasetExistsError,
        GenerationError,
        SamplingError,
    )
    from posernet.frontend.features import MatcherError
    from posernet.frontend.images import ImageError
    from posernet.frontend.proposals import ProposalError

    return (ConfigError, DatasetExistsError, GenerationError, SamplingError, DatasetError, OSError,
            SevenScenesError, ImageError, ProposalError, MatcherError)


def _resume_hint(cfg: DictConfig) -> str | None:
    """After Ctrl-C: how to finish the dataset, when its folder was started."""
    from pathlib import Path

    from posernet.data.writer import JOB_FILE

    out = _out_dir(cfg)
    if (Path(out) / JOB_FILE).is_file():
        return f"the complete files in {out} are kept: run it again with resume=true to finish"
    return None


def execute(cfg: DictConfig) -> int:
    """Run under the commands' error policy; returns the exit status: 0, 1 (a user error,
    reported in one line on stderr) or 130 (interrupted)."""
    try:
        run_task("posernet-make-data", run, cfg, errors=_user_errors(),
                 resume_hint=_resume_hint)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="make_data")
def _app(cfg: DictConfig) -> None:
    code = execute(cfg)
    if code:
        sys.exit(code)


def main() -> None:
    """Console-script entry point."""
    run_app("posernet-make-data", "make_data", _app, list_args=("intrinsics", "scenes"))


if __name__ == "__main__":
    main()
