"""``posernet-refine``: the main job on your own view graphs.

Reads a graph file (posernet ``.pt`` or the authors' JSON), refines every edge's relative pose
with a PoserNet checkpoint (default: the one shipped with posernet), averages initial and
refined poses into absolute camera poses with the chosen backend (``sync=eig_se3`` by default,
``sync=none`` to skip), and writes everything to one JSON file (format in
:func:`posernet.refinement.result_to_json`). When the graphs carry ground truth, the paper's
tables are printed and written next to it (``table.md``/``.csv``, ``abs_table.md``/``.csv``).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from ..data.inputs import ESTIMATES
from ..options import DEVICE, option, path
from . import CONFIG_DIR
from .common import (
    check_config,
    resolve_device,
    run_app,
    run_task,
    set_threads,
)

__all__ = ["RefineSettings", "main", "refine"]


@dataclass(frozen=True, kw_only=True)
class RefineSettings:
    """``posernet-refine``'s own keys (``conf/refine.yaml``; the ``sync`` group declares its
    own)."""

    input: str = option(rule=path(), help="a posernet .pt graph file, a folder of them, or an "
                        "authors' .json")
    split: str = option("test", help="which list of a .json file, or which split of a dataset "
                        "root")
    size: str = option("small", choices=("small", "large", "all"),
                       help="graph size, for a dataset root (a make-data folder)")
    estimate: str | None = option("kp", choices=ESTIMATES, help="initial poses to refine (free: "
                                  "a .json's free keypoint 5-point; gt: ground truth; null: the "
                                  "stored edge_pose)")
    strict: bool = option(True, help=".json: reject (true) or skip with a warning (false) "
                          "malformed graphs")
    ckpt_path: str | None = option(None, rule=path(), help="null: the checkpoint shipped with "
                                   "posernet (trained on synthetic data)")
    output: str = option("${out_dir}/refined.json", rule=path(),
                         help="the JSON file of refined and averaged poses")
    batch_size: int = option(64, ge=1, help="graphs per batch")
    guard: bool = option(False, help="keep the input rotation/direction on edges where the "
                         "model's own confidence predicts its output would be worse than the "
                         "input (input-adaptive checkpoints, e.g. the shipped one)")
    confidence_weights: bool = option(True, help="start motion averaging's IRLS from the "
                                      "confidence (uniform without)")
    check_inputs: bool = option(True, help="one warning line when the inputs look unlike the "
                                "training data or the refined poses are less cycle-consistent "
                                "than the input")
    device: str = option("cpu", rule=DEVICE, help="cpu | cuda | cuda:N | auto")
    num_threads: int | None = option(1, ge=1, help="torch CPU threads (null: torch default)")
    digits: int = option(2, ge=0, le=12, help="decimals in the printed and written tables")
    out_dir: str = option("${hydra:runtime.output_dir}", rule=path(),
                          help="the run's folder (holds output by default)")


def refine(cfg: DictConfig) -> dict[str, Any]:
    """Run the refine job described by ``cfg``; returns the output paths and tables."""
    from ..checkpoints import resolve_checkpoint
    from ..data.inputs import load_input_graphs
    from ..evaluation import evaluate_result, result_tables
    from ..guard import load_refiner
    from ..io import atomic_write_json
    from ..refinement import refine_graphs, result_to_json
    from .build import backend_from_config

    check_config(cfg, "refine")
    set_threads(cfg.get("num_threads"))
    device = resolve_device(cfg.device)
    ckpt = resolve_checkpoint(cfg.get("ckpt_path"))
    model, guard = load_refiner(ckpt, device, keep_inputs=bool(cfg.get("guard", False)))
    backend = backend_from_config(OmegaConf.to_container(cfg.sync, resolve=True)) \
        if cfg.get("sync") else None
    estimate = cfg.get("estimate")
    graphs = load_input_graphs(cfg.input, split=cfg.split, estimate=estimate,
                               strict=bool(cfg.strict), size=str(cfg.get("size", "small")),
                               log=print)
    has_conf = bool(getattr(model, "confidence", False))
    weighted = bool(cfg.get("confidence_weights", True)) and has_conf and backend is not None
    result = refine_graphs(model, graphs, backend=backend, batch_size=int(cfg.batch_size),
                           device=device, guard=guard.keep_inputs, weighted=weighted)
    info: dict[str, Any] = {"input": str(cfg.input), "estimate": estimate,
                            "checkpoint": str(ckpt), "guard": guard.keep_inputs,
                            "confidence_weights": weighted}
    if bool(cfg.get("check_inputs", True)):
        line, report = guard.check(graphs, result)
        info["input_check"] = report
        if line:
            print(f"posernet-refine: {line}", file=sys.stderr)
    out = {"output": atomic_write_json(cfg.output, result_to_json(result, info), indent=1)}
    if any(g.edge_pose_gt is not None for g in graphs):  # graphs without it are counted
        ev = evaluate_result(result)
        tables = result_tables(ev, label=str(estimate or "input").upper(),
                               backend=result.backend, title=f": {len(graphs)} graphs")
        out_dir = Path(cfg.output).parent
        for key, stem in (("relative", "table"), ("absolute", "abs_table")):
            if key in tables:
                tables[key].write(out_dir, stem, digits=int(cfg.digits))
                print(tables[key].to_markdown(int(cfg.digits)) + "\n")
        out["tables"] = tables
    print(f"wrote {out['output']} ({len(graphs)} graphs)")
    return out


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="refine")
def _hydra_main(cfg: DictConfig) -> None:
    run_task("posernet-refine", refine, cfg, errors=(ValueError,))


def main() -> None:
    """Console-script entry point (``posernet-refine``)."""
    run_app("posernet-refine", "refine", _hydra_main)


if __name__ == "__main__":
    main()
