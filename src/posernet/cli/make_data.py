"""``posernet-make-data``: generate a graph dataset directory (Hydra app, ``conf/``), synthetic
or from real images in the 7-Scenes layout.

Examples::

    posernet-make-data dataset=paper out_dir=/tmp/posernet-paper workers=2
    posernet-make-data dataset=tiny out_dir=/tmp/tiny overwrite=true
    posernet-make-data preset=easy dataset.small.train=100 resume=true
    posernet-make-data source=sevenscenes root=/data/7scenes scenes=[chess,fire] \
        intrinsics=585,585,320,240 proposals=edge_boxes matcher=sift out_dir=/tmp/7s

Errors a user can cause (bad option, existing directory, resume with another config, a root
that is not in 7-Scenes layout, bad intrinsics) are printed as one line without a traceback,
with exit status 2.
"""

from __future__ import annotations

import sys
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from . import CONFIG_DIR
from .common import quote_list_args, report_error, user_errors

__all__ = ["execute", "main", "run"]


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


FRONTEND_GROUPS = ("proposals", "matcher", "box_matching", "relpose")
_SEVENSCENES_KEYS = ("root", "scenes", "intrinsics")


def _run_sevenscenes(cfg: DictConfig) -> dict[str, Any]:
    """``source=sevenscenes``: graphs of the images under ``root`` through the front end."""
    from posernet.data.sevenscenes_graphs import generate_sevenscenes
    from posernet.data.synthetic import ConfigError

    for group in FRONTEND_GROUPS:
        # full keys ("proposals.path") or relative ones, depending on the OmegaConf version
        missing = sorted(k if k.startswith(f"{group}.") else f"{group}.{k}"
                         for k in OmegaConf.missing_keys(cfg[group]))
        if missing:
            raise ConfigError(f"{group}={_choice(group)} needs "
                              + ", ".join(f"{k}=..." for k in missing))
    return generate_sevenscenes(
        OmegaConf.to_container(cfg.sevenscenes, resolve=True),
        cfg.out_dir or "outputs/data/sevenscenes",
        frontend={g: OmegaConf.to_container(cfg[g], resolve=True) for g in FRONTEND_GROUPS},
        seed=cfg.seed,
        overwrite=bool(cfg.overwrite),
        resume=bool(cfg.resume),
        export_json_files=bool(cfg.export_json),
        progress=bool(cfg.progress),
    )


def _choice(group: str) -> str:
    from hydra.core.hydra_config import HydraConfig

    try:
        return str(HydraConfig.get().runtime.choices.get(group))
    except ValueError:  # not running under Hydra
        return "..."


def run(cfg: DictConfig) -> dict[str, Any]:
    """Generate the dataset described by a composed ``make_data`` config; returns the manifest."""
    from posernet.data.synthetic import ConfigError, generate_dataset

    source = str(cfg.get("source") or "synthetic")
    if source == "sevenscenes":
        return _run_sevenscenes(cfg)
    if source != "synthetic":
        raise ConfigError(f"invalid option source: must be synthetic or sevenscenes, got "
                          f"{source!r}")
    given = [k for k in _SEVENSCENES_KEYS if cfg.get(k) is not None]
    if given:
        raise ConfigError(f"{', '.join(k + '=' for k in given)} "
                          f"{'is an option' if len(given) == 1 else 'are options'} of "
                          f"source=sevenscenes (the synthetic generator takes "
                          f"dataset.scenes=...); add source=sevenscenes")
    dataset = _dataset_config(cfg)
    out_dir = cfg.out_dir or f"outputs/data/{dataset.get('name', 'dataset')}"
    return generate_dataset(
        dataset,
        out_dir,
        seed=cfg.seed,
        workers=cfg.workers,
        overwrite=bool(cfg.overwrite),
        resume=bool(cfg.resume),
        export_json_files=bool(cfg.export_json),
        progress=bool(cfg.progress),
    )


def execute(cfg: DictConfig) -> int:
    """Run and turn user errors into one line on stderr; returns the exit status (0 or 2)."""
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
    from posernet.graph import GraphValidationError


    try:
        run(cfg)
    except (
        ConfigError,
        DatasetExistsError,
        GenerationError,
        SamplingError,
        DatasetError,
        GraphValidationError,
        OSError,
        SevenScenesError,
        ImageError,
        ProposalError,
        MatcherError,
        *user_errors(),  # failed instantiation of a front-end stage: its root cause
    ) as exc:
        report_error("posernet-make-data", exc)
        return 2
    return 0


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="make_data")
def _app(cfg: DictConfig) -> None:
    code = execute(cfg)
    if code:
        sys.exit(code)


def main() -> None:
    """Console-script entry point."""
    sys.argv = quote_list_args(sys.argv, ("intrinsics", "scenes"))
    _app()


if __name__ == "__main__":
    main()
