"""``posernet-eval``: evaluate a PoserNet checkpoint on a test set, print the paper's table.

The table (paper Table 1 layout) gives, per graph, the % of test graphs whose mean edge error is
below 3/5/10/30/45 degrees and the median over graphs, for the orientation and the translation
direction, for the initial poses and the PoserNet-refined ones. It is printed and written
atomically as ``table.md`` and ``table.csv`` in the output folder. Per-graph errors and rows come
from :mod:`posernet.metrics` (``relative_errors_per_graph``/``relative_rows``, and through
:func:`posernet.sync.evaluate.absolute_table` ``absolute_errors_per_graph``/``absolute_rows``),
the code behind every other table. Examples::

    posernet-eval ckpt_path=outputs/train/.../checkpoints/best.ckpt data.root=outputs/data/tiny
    posernet-eval ckpt_path=... graphs=some/graphs.pt estimate=bb

With ``sync=<backend>`` (not ``none``) the relative poses are also averaged into absolute poses
and an absolute-pose table is written (``abs_table.md`` / ``abs_table.csv``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf

from . import CONFIG_DIR
from .common import check_config, quiet_lightning, resolve_device, run_app, run_task, set_threads

__all__ = ["evaluate", "main"]


def _batches_from_files(path: Path, estimate: str | None, batch_size: int) -> Iterator[Any]:
    from ..graph import GraphBatch
    from ..pipeline import load_input_graphs

    graphs = load_input_graphs(path, estimate=estimate)
    for i in range(0, len(graphs), batch_size):
        yield GraphBatch.from_graphs(graphs[i:i + batch_size])


def _test_batches(cfg: DictConfig) -> tuple[Iterable[Any], str]:
    """The test batches and a short description of where they come from."""
    if cfg.get("graphs"):
        path = Path(cfg.graphs)
        return _batches_from_files(path, cfg.get("estimate"), int(cfg.batch_size)), str(path)
    dm = hydra.utils.instantiate(cfg.data)
    if hasattr(dm, "prepare_data"):
        dm.prepare_data()
    if hasattr(dm, "setup"):
        dm.setup("test")
    return dm.test_dataloader(), f"{cfg.data.get('root')} (test split)"


def evaluate(cfg: DictConfig) -> dict[str, Any]:
    """Evaluate ``cfg.ckpt_path`` on the configured test set; return the tables and paths."""
    from ..graph import GraphValidationError
    from ..metrics import relative_errors_per_graph, relative_rows
    from ..nn import PoserNet
    from ..report import ResultTable, TableRow

    check_config(cfg, "eval")
    quiet_lightning()
    set_threads(cfg.get("num_threads"))
    device = torch.device(resolve_device(cfg.device))
    # The bare network: evaluating needs neither Lightning nor the optimiser state.
    from ..checkpoints import resolve_checkpoint

    module = PoserNet.from_checkpoint(resolve_checkpoint(cfg.ckpt_path), map_location=device)
    batches, source = _test_batches(cfg)
    sync_name = str(cfg.sync.get("name", "none")) if cfg.get("sync") else "none"
    sync = _sync_backend(cfg) if sync_name != "none" else None

    # Per-graph errors per stage (``initial``/``refined``), from the shared table code.
    errs: dict[str, dict[str, list[torch.Tensor]]] = {"initial": {}, "refined": {}}
    abs_errs: dict[str, Any] = {}
    n_graphs = 0
    with torch.inference_mode():
        for batch in batches:
            batch = batch.to(device)
            if batch.edge_pose_gt is None:
                raise GraphValidationError(
                    f"test graphs from {source} have no ground truth (edge_pose_gt): nothing "
                    f"to evaluate against")
            refined = module(batch)
            n = batch.num_graphs
            n_graphs += n
            for stage, pose in (("initial", batch.edge_pose), ("refined", refined)):
                per_graph = relative_errors_per_graph(pose, batch.edge_pose_gt,
                                                      batch.edge_batch, n)
                for key, v in per_graph.items():
                    errs[stage].setdefault(key, []).append(v.cpu())
            if sync is not None:
                _collect_absolute(sync, batch, refined, abs_errs)
    if n_graphs == 0:
        raise FileNotFoundError(f"no test graphs found in {source}")
    est = cfg.get("estimate")
    label = str(est).upper() if est else "input"
    names = {"initial": "Initial", "refined": "PoserNet"}
    table = ResultTable(
        rows=[TableRow((label, names[stage]),
                       relative_rows({k: torch.cat(v) for k, v in errs[stage].items()}))
              for stage in ("initial", "refined")],
        title=f"Relative poses: {n_graphs} test graphs from {source}",
        note=f"Checkpoint: {cfg.ckpt_path}",
    )
    out_dir = Path(cfg.out_dir)
    md, csv = table.write(out_dir, "table", digits=int(cfg.digits))
    print(table.to_markdown(int(cfg.digits)))
    result: dict[str, Any] = {"table": table, "markdown": md, "csv": csv}
    if sync is not None and abs_errs:
        result.update(_absolute_table(abs_errs, label, sync_name, out_dir, int(cfg.digits)))
    print(f"wrote {md} and {csv}")
    return result


# --------------------------------------------------------------------------- motion averaging
# Minimal and guarded: the motion-averaging backends live in ``posernet.sync`` (another issue).


def _sync_backend(cfg: DictConfig) -> Any:
    try:
        from .. import sync as sync_lib
    except ImportError as exc:
        raise FileNotFoundError(f"motion averaging is not available ({exc})") from exc
    return sync_lib.backend_from_config(OmegaConf.to_container(cfg.sync, resolve=True))


def _collect_absolute(sync: Any, batch: Any, refined: torch.Tensor,
                      out: dict[str, Any]) -> None:
    """Per-graph absolute errors after motion averaging of the initial and refined poses."""
    from ..sync.evaluate import absolute_table

    if batch.pose_gt is None:
        return
    for stage, pose in (("initial", batch.edge_pose), ("refined", refined)):
        t = absolute_table(batch, pose, sync)
        per_stage = out.setdefault(stage, {"rot": [], "trans": []})
        per_stage["rot"].append(t["per_graph"]["rotation_deg"].cpu())
        per_stage["trans"].append(t["per_graph"]["position_m"].cpu())
        out["note"] = (f"Scale: {t['backend'].get('scale_label', t['scale'])}; alignment: "
                       f"{t['alignment']} per connected component; rotations aligned by the "
                       f"{t['rotation_gauge']}"
                       + (" -- ORACLE scale" if t["oracle"] else ""))


def _absolute_table(abs_errs: dict[str, Any], label: str, sync_name: str,
                    out_dir: Path, digits: int) -> dict[str, Any]:
    from ..metrics import absolute_rows
    from ..report import ABSOLUTE_GROUPS, ResultTable, TableRow

    rows = [
        TableRow((label, name), absolute_rows(
            {k: torch.cat(v) for k, v in abs_errs[stage].items()}))
        for stage, name in (("initial", sync_name), ("refined", f"{sync_name} + PoserNet"))
    ]
    table = ResultTable(rows=rows, groups=ABSOLUTE_GROUPS, note=abs_errs.get("note"),
                        title=f"Absolute poses after motion averaging ({sync_name})")
    md, csv = table.write(out_dir, "abs_table", digits=digits)
    print(table.to_markdown(digits))
    return {"abs_table": table, "abs_markdown": md, "abs_csv": csv}


@hydra.main(version_base="1.3", config_path=CONFIG_DIR, config_name="eval")
def _hydra_main(cfg: DictConfig) -> None:
    run_task("posernet-eval", evaluate, cfg, errors=(ValueError,))


def main() -> None:
    """Console-script entry point (``posernet-eval``)."""
    run_app("posernet-eval", "eval", _hydra_main)


if __name__ == "__main__":
    main()
