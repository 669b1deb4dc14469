"""``posernet-eval``: evaluate a PoserNet checkpoint on a test set, print the paper's table.

The table (paper Table 1 layout) gives, per graph, the % of test graphs whose mean edge error is
below 3/5/10/30/45 degrees and the median over graphs, for the orientation and the translation
direction, for the initial poses and the PoserNet-refined ones. It is printed and written
atomically as ``table.md`` and ``table.csv`` in the output folder. Refinement, averaging and
the tables are ``posernet-refine``'s (:func:`posernet.refinement.refine_graphs`,
:func:`~posernet.evaluation.evaluate_result`, :func:`~posernet.evaluation.result_tables`), the
code behind every other table. Examples::

    posernet-eval ckpt_path=outputs/train/.../checkpoints/best.ckpt data.root=outputs/data/tiny
    posernet-eval ckpt_path=... graphs=some/graphs.pt estimate=bb

With ``sync=<backend>`` (not ``none``) the relative poses are also averaged into absolute poses
and an absolute-pose table is written (``abs_table.md`` / ``abs_table.csv``, with the cameras
placed per stage).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from ..data.inputs import ESTIMATES
from ..options import DEVICE, option, path
from . import CONFIG_DIR
from .common import check_config, quiet_lightning, resolve_device, run_app, run_task, set_threads

__all__ = ["EvalSettings", "evaluate", "main"]


@dataclass(frozen=True, kw_only=True)
class EvalSettings:
    """``posernet-eval``'s own keys (``conf/eval.yaml``; its groups declare theirs)."""

    seed: int = option(0, ge=0, help="seed of the data module (data.seed follows it)")
    ckpt_path: str = option(rule=path(), help="a checkpoint written by posernet-train")
    graphs: str | None = option(None, rule=path(), help="a graph file (.pt), a folder of them, "
                                "or an authors' .json (its test split); null: data's test split")
    estimate: str | None = option("${data.estimate}", choices=ESTIMATES, help="initial poses to "
                                  "refine (free: an authors' .json's free keypoint 5-point; gt: "
                                  "ground truth; null: the stored edge_pose)")
    batch_size: int = option("${data.batch_size}", ge=1, help="graphs per batch")
    device: str = option("cpu", rule=DEVICE, help="cpu | cuda | cuda:N | auto")
    digits: int = option(2, ge=0, le=12, help="decimals in the printed and written tables")
    num_threads: int | None = option(1, ge=1, help="torch CPU threads (null: torch default)")
    out_dir: str = option("${hydra:runtime.output_dir}", rule=path(),
                          help="where table.md / table.csv (and abs_table.*) are written")


def _test_graphs(cfg: DictConfig) -> tuple[list[Any], str]:
    """The test graphs and a short description of where they come from."""
    from ..data.inputs import load_input_graphs

    if cfg.get("graphs"):
        path = Path(cfg.graphs)
        return list(load_input_graphs(path, estimate=cfg.get("estimate"))), str(path)
    dm = hydra.utils.instantiate(cfg.data)
    if hasattr(dm, "prepare_data"):
        dm.prepare_data()
    if hasattr(dm, "setup"):
        dm.setup("test")
    return list(dm.test_graphs), f"{cfg.data.get('root')} (test split)"


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate ``cfg.ckpt_path`` on the configured test set; return the tables and paths.

    The same path as ``posernet-refine`` (:func:`posernet.refinement.refine_graphs`,
    :func:`~posernet.evaluation.evaluate_result`, :func:`~posernet.evaluation.result_tables`):
    the relative table, and with ``sync=`` the absolute one with the cameras placed per stage.
    Motion averaging is never weighted by the model's confidence here, so the ``Initial`` rows
    are the input's own."""
    from ..checkpoints import resolve_checkpoint
    from ..evaluation import evaluate_result, result_tables
    from ..graph import GraphValidationError
    from ..nn import PoserNet
    from ..refinement import refine_graphs

    check_config(cfg, "eval")
    quiet_lightning()
    set_threads(cfg.get("num_threads"))
    device = torch.device(resolve_device(cfg.device))
    # The bare network: evaluating needs neither Lightning nor the optimiser state.
    module = PoserNet.from_checkpoint(resolve_checkpoint(cfg.ckpt_path), map_location=device)
    graphs, source = _test_graphs(cfg)
    if not graphs:
        raise FileNotFoundError(f"no test graphs found in {source}")
    if any(g.edge_pose_gt is None for g in graphs):
        raise GraphValidationError(f"test graphs from {source} have no ground truth "
                                   "(edge_pose_gt): nothing to evaluate against")
    sync_name = str(cfg.sync.get("name", "none")) if cfg.get("sync") else "none"
    sync = _sync_backend(cfg) if sync_name != "none" else None
    result = refine_graphs(module, graphs, backend=sync, batch_size=int(cfg.batch_size),
                           device=device, progress=False, weighted=False)
    est = cfg.get("estimate")
    label = str(est).upper() if est else "input"
    tables = result_tables(evaluate_result(result), label=label, backend=result.backend,
                           title=f": {len(graphs)} test graphs from {source}")
    out_dir = Path(cfg.out_dir)
    digits = int(cfg.digits)
    table = tables["relative"]
    table.note = "; ".join(x for x in (table.note, f"Checkpoint: {cfg.ckpt_path}") if x)
    md, csv = table.write(out_dir, "table", digits=digits)
    print(table.to_markdown(digits))
    out: dict[str, Any] = {"table": table, "markdown": md, "csv": csv}
    written = [md, csv]
    if "absolute" in tables:
        amd, acsv = tables["absolute"].write(out_dir, "abs_table", digits=digits)
        print(tables["absolute"].to_markdown(digits))
        out.update(abs_table=tables["absolute"], abs_markdown=amd, abs_csv=acsv)
        written += [amd, acsv]
    print("wrote " + ", ".join(str(p) for p in written))
    return out


def _sync_backend(cfg: DictConfig) -> Any:
    from .build import backend_from_config

    return backend_from_config(OmegaConf.to_container(cfg.sync, resolve=True))


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="eval")
def _hydra_main(cfg: DictConfig) -> None:
    run_task("posernet-eval", evaluate, cfg, errors=(ValueError,))


def main() -> None:
    """Console-script entry point (``posernet-eval``)."""
    run_app("posernet-eval", "eval", _hydra_main)


if __name__ == "__main__":
    main()
