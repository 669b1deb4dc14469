"""``posernet-make-data``: generate a synthetic dataset directory (Hydra app, ``conf/``).

Examples::

    posernet-make-data dataset=paper out_dir=/tmp/posernet-paper workers=2
    posernet-make-data dataset=tiny out_dir=/tmp/tiny overwrite=true
    posernet-make-data preset=easy dataset.small.train=100 resume=true

Errors a user can cause (bad option, existing directory, resume with another config) are
printed as one line without a traceback, with exit status 2.
"""

from __future__ import annotations

import sys
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from . import CONFIG_DIR

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


def run(cfg: DictConfig) -> dict[str, Any]:
    """Generate the dataset described by a composed ``make_data`` config; returns the manifest."""
    from posernet.data.synthetic import generate_dataset

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
    from posernet.data.store import DatasetError
    from posernet.data.synthetic import (
        ConfigError,
        DatasetExistsError,
        GenerationError,
        SamplingError,
    )
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
    ) as exc:
        print(f"posernet-make-data: error: {exc}", file=sys.stderr)
        return 2
    return 0


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="make_data")
def _app(cfg: DictConfig) -> None:
    code = execute(cfg)
    if code:
        sys.exit(code)


def main() -> None:
    """Console-script entry point."""
    _app()


if __name__ == "__main__":
    main()
