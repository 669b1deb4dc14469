"""Input-adaptive refinement: its evaluation.

``python research/adaptive.py --data DIR --model NAME=CKPT [--model ...] --out DIR``

For every model, on the ``test`` graphs of a dataset (the held-out generator variant,
``research/conf/dataset/heldout.yaml``, for the final numbers; never used for training or
selection):

* ``graphs.md|csv``: per-graph median (paper style: median over graphs of each graph's mean
  edge error) of initial and refined rotation / direction errors, per input: ``KP``, ``BB``,
  ``GT`` (ground-truth relative poses, unit translations: the "leave it alone" test) and
  ``GT+noise`` (ground truth rotated by 0-20 degrees, direction by 0-40, to populate the middle
  bins).
* ``bins.md|csv``: per-edge errors pooled over the inputs (``all``: KP, BB, GT and GT+noise)
  and per input, binned by initial rotation error (< 3, 3-10, 10-30, > 30 degrees): mean and
  median initial vs refined rotation and direction errors, and the 95 % bootstrap interval
  (resampling graphs) of the change of the mean rotation error.
* ``absolute.md|csv`` (``--absolute``): KP input averaged with EIG-SE3 and
  ``rotation_translation``, uniform vs confidence-weighted IRLS start (and the guard).
* ``confidence.md|csv`` (models with a confidence head): per input, the correlation of the
  logs of predicted and actual errors, and the AUC with which the predicted input rotation error
  tells input edges under 3 degrees from 3-10 degree ones.
* ``refined_vs_initial.png``: binned refined vs initial error per edge (rotation, direction).
* ``summary.json``: everything above as numbers.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from posernet.graph import ViewGraph
from posernet.io import atomic_path, atomic_write_json, atomic_write_text
from posernet.metrics import per_graph_mean, relative_pose_errors

__all__ = ["BINS", "bin_table", "edge_errors_for", "evaluate_models", "main", "mean_change_ci"]

#: initial rotation error bins (degrees)
BINS: tuple[tuple[float, float], ...] = ((0.0, 3.0), (3.0, 10.0), (10.0, 30.0),
                                         (30.0, math.inf))
INPUTS = ("KP", "BB", "GT", "GT+noise")


def bin_label(lo: float, hi: float) -> str:
    return f"< {hi:g}" if lo == 0 else (f"> {lo:g}" if math.isinf(hi) else f"{lo:g}-{hi:g}")


def make_inputs(graphs: Sequence[ViewGraph], seed: int = 0) -> dict[str, list[ViewGraph]]:
    """The four inputs of the evaluation (see the module docstring)."""
    from posernet.data.mixture import perturb_poses

    gen = torch.Generator().manual_seed(seed)
    out: dict[str, list[ViewGraph]] = {k: [] for k in INPUTS}
    for g in graphs:
        if g.edge_pose_gt is None:
            raise ValueError(f"graph {g.name!r} has no edge_pose_gt: cannot evaluate")
        gt = g.edge_pose_gt.clone()
        gt[:, 4:] = torch.nn.functional.normalize(gt[:, 4:], dim=-1)
        out["KP"].append(g.with_estimate("kp"))
        out["BB"].append(g.with_estimate("bb"))
        out["GT"].append(dataclasses.replace(g, edge_pose=gt))
        rot = torch.rand(g.num_edges, generator=gen, dtype=gt.dtype) * 20.0
        out["GT+noise"].append(dataclasses.replace(
            g, edge_pose=perturb_poses(gt, rot, 2.0 * rot, gen)))
    return out


def edge_errors_for(model: torch.nn.Module | None, graphs: Sequence[ViewGraph],
                    guard: bool = False) -> dict[str, Tensor]:
    """Per-edge errors (degrees) of the input and of the refined poses, with each edge's graph:
    ``rot_init, rot_ref, tdir_init, tdir_ref [E]``, ``graph [E]``; plus ``sigma [E, 4]``
    (degrees) when the model has a confidence head."""
    from posernet.refinement import refine_graphs

    res = refine_graphs(model, graphs, progress=False, guard=guard)
    gt = torch.cat([g.edge_pose_gt for g in graphs]).double()
    graph = torch.arange(len(graphs)).repeat_interleave(
        torch.tensor([g.num_edges for g in graphs]))
    out = {"graph": graph}
    for stage, key in (("initial", "init"), ("refined", "ref")):
        est = torch.cat(res.edge_pose[stage]).double()
        out[f"rot_{key}"], out[f"tdir_{key}"] = relative_pose_errors(est, gt)
    if res.confidence:
        out["sigma"] = torch.cat(res.confidence).double()
    return out


def per_graph_medians(err: dict[str, Tensor], num_graphs: int) -> dict[str, float]:
    """Paper-style medians over graphs of each graph's mean edge error."""
    return {k: float(per_graph_mean(err[k], err["graph"], num_graphs).nanquantile(0.5))
            for k in ("rot_init", "rot_ref", "tdir_init", "tdir_ref")}


def mean_change_ci(delta: Tensor, graph: Tensor, num_graphs: int, reps: int = 2000,
                   level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Bootstrap confidence interval of ``delta.mean()`` resampling whole graphs.

    The edges of one graph (and of every input made from it) are not independent, so graphs
    are the resampled unit: ``reps`` draws of ``num_graphs`` graphs with replacement, each
    draw's mean over its edges. ``delta [E]``, ``graph [E]`` (ids in ``[0, num_graphs)``);
    NaN entries are left out. Returns the ``level`` percentile interval (NaN without edges)."""
    ok = ~torch.isnan(delta)
    if not bool(ok.any()):
        return float("nan"), float("nan")
    d, g = delta[ok].double(), graph[ok]
    total = torch.zeros(num_graphs, dtype=torch.float64).index_add_(0, g, d)
    count = torch.bincount(g, minlength=num_graphs).double()
    gen = torch.Generator().manual_seed(seed)
    draws = torch.randint(num_graphs, (reps, num_graphs), generator=gen)
    w = torch.zeros(reps, num_graphs, dtype=torch.float64).scatter_add_(
        1, draws, torch.ones(reps, num_graphs, dtype=torch.float64))
    means = (w @ total) / (w @ count).clamp_min(1.0)
    means = means[(w @ count) > 0]
    tail = (1.0 - level) / 2.0
    lo, hi = torch.quantile(means, torch.tensor([tail, 1.0 - tail], dtype=torch.float64))
    return float(lo), float(hi)


def bin_table(err: dict[str, Tensor]) -> list[dict[str, Any]]:
    """Rows per initial-rotation-error bin: edge count, mean/median initial and refined errors;
    with ``err["graph"]`` also the 95 % bootstrap interval (over graphs) of the change of the
    mean rotation error, ``rot_change_lo`` / ``rot_change_hi`` (refined minus initial)."""
    rows = []
    graph = err.get("graph")
    for lo, hi in BINS:
        sel = (err["rot_init"] >= lo) & (err["rot_init"] < hi)
        row: dict[str, Any] = {"bin": bin_label(lo, hi), "edges": int(sel.sum())}
        for k in ("rot_init", "rot_ref", "tdir_init", "tdir_ref"):
            v = err[k][sel]
            v = v[~torch.isnan(v)]
            row[f"{k}_mean"] = float(v.mean()) if v.numel() else float("nan")
            row[f"{k}_median"] = float(v.median()) if v.numel() else float("nan")
        if graph is not None:
            row["rot_change_lo"], row["rot_change_hi"] = mean_change_ci(
                (err["rot_ref"] - err["rot_init"])[sel], graph[sel], int(graph.max()) + 1)
        rows.append(row)
    return rows


def _cat(errs: Sequence[dict[str, Tensor]]) -> dict[str, Tensor]:
    """Pool the per-edge errors of several inputs (the same graphs: ``graph`` ids are kept, so
    one graph's edges under every input resample together)."""
    keys = [k for k in ("rot_init", "rot_ref", "tdir_init", "tdir_ref", "graph")
            if k in errs[0]]
    return {k: torch.cat([e[k] for e in errs]) for k in keys}


def lever_row(name: str, m: dict[str, Any]) -> dict[str, Any]:
    """The one-line comparison of a model (see ``levers.md``)."""
    pg = m["per_graph"]
    row: dict[str, Any] = {"model": name, "GT rot": pg["GT"]["rot_ref"],
                           "GT tdir": pg["GT"]["tdir_ref"],
                           "KP rot": pg["KP"]["rot_ref"], "KP tdir": pg["KP"]["tdir_ref"],
                           "BB rot": pg["BB"]["rot_ref"], "BB tdir": pg["BB"]["tdir_ref"]}
    bins = m["bins"]["all"]
    for b in bins:
        row[f"rot {b['bin']}"] = b["rot_ref_mean"]
    for b in bins:
        row[f"tdir {b['bin']}"] = b["tdir_ref_mean"]
    if "rot_change_lo" in bins[0]:
        row[f"rot {bins[0]['bin']}: change, 95% CI"] = \
            f"{bins[0]['rot_change_lo']:+.3f} .. {bins[0]['rot_change_hi']:+.3f}"
    row["worse rot"] = sum(b["rot_ref_mean"] > b["rot_init_mean"] for b in bins)
    row["worse tdir"] = sum(b["tdir_ref_mean"] > b["tdir_init_mean"] for b in bins)
    return row


def absolute_rows(model: torch.nn.Module, graphs: Sequence[ViewGraph],
                  has_conf: bool, label_in: str = "KP") -> list[dict[str, Any]]:
    """One input (``label_in``: KP or BB) averaged with EIG-SE3 and rotation_translation:
    uniform vs confidence-weighted IRLS start (modes ``start`` and ``prior``) and the guard;
    median absolute errors."""
    from posernet.evaluation import evaluate_result
    from posernet.refinement import refine_graphs
    from posernet.sync import get_backend

    rows = []
    variants: list[tuple[str, dict[str, Any], bool, bool]] = [("uniform", {}, False, False)]
    if has_conf:
        variants += [("confidence (start)", {"weight_mode": "start"}, True, False),
                     ("confidence (prior)", {"weight_mode": "prior"}, True, False),
                     ("guard + confidence (prior)", {"weight_mode": "prior"}, True, True)]
    for bname in ("eig_se3", "rotation_translation"):
        for label, opts, weighted, guard in variants:
            backend = get_backend(bname, **opts)
            res = refine_graphs(model, graphs, backend=backend, progress=False,
                                weighted=weighted, guard=guard)
            ev = evaluate_result(res)
            for stage in ("initial", "refined"):
                if stage == "initial" and (guard or label == "confidence (start)"):
                    continue  # the guard does not change the input; one weighted input row
                a = ev["absolute"][stage]
                rows.append({"backend": bname, "poses": label_in if stage == "initial"
                             else f"{label_in} + PoserNet", "weights": label,
                             "rot_median_deg": a["rot"].median,
                             "pos_median": a["trans"].median})
    return rows


def separation_auc(score: Tensor, positive: Tensor) -> float:
    """Probability that a random positive scores higher than a random negative (ties count
    half): the area under the ROC curve of ``score [N]`` for the booleans ``positive [N]``
    (Mann-Whitney, average ranks for ties); NaN without both classes."""
    n1 = int(positive.sum())
    n0 = positive.numel() - n1
    if n1 == 0 or n0 == 0:
        return float("nan")
    _, inv, counts = torch.unique(score.double(), return_inverse=True, return_counts=True)
    group_rank = torch.cumsum(counts, 0).double() - (counts.double() - 1.0) / 2.0
    r = group_rank[inv][positive].sum()
    return float((r - n1 * (n1 + 1) / 2) / (n1 * n0))


def _log_corr(pred: Tensor, actual: Tensor) -> float:
    """Correlation of the logs of predicted and actual errors (both floored at 1e-3) over the
    finite entries; NaN with fewer than three."""
    ok = torch.isfinite(actual) & torch.isfinite(pred)
    if int(ok.sum()) < 3:
        return float("nan")
    logs = torch.stack((pred[ok], actual[ok])).clamp_min(1e-3).log()
    return float(torch.corrcoef(logs)[0, 1])


def confidence_rows(name: str, errs: dict[str, dict[str, Tensor]]) -> list[dict[str, Any]]:
    """How good the predicted errors are, per input: correlation of log predicted and log
    actual error (output and input rotation, output direction) and the AUC with which the
    predicted input error tells input edges under 3 degrees from 3-10 degree ones (the
    decision the gate must make to leave good poses alone)."""
    rows = []
    for inp, e in errs.items():
        s, init = e["sigma"], e["rot_init"]
        near = init < 10.0
        rows.append({
            "model": name, "input": inp, "edges": int(init.numel()),
            "corr_rot_out": _log_corr(s[:, 0], e["rot_ref"]),
            "corr_tdir_out": _log_corr(s[:, 1], e["tdir_ref"]),
            "corr_rot_in": _log_corr(s[:, 2], init),
            "auc_in_lt3_vs_3to10": separation_auc(-s[near, 2], init[near] < 3.0),
        })
    return rows


def _md(rows: Sequence[dict[str, Any]], digits: int = 2) -> str:
    if not rows:
        return ""
    keys = list(rows[0])

    def fmt(v: Any) -> str:
        return f"{v:.{digits}f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def _csv(rows: Sequence[dict[str, Any]]) -> str:
    if not rows:
        return ""
    keys = list(rows[0])
    return "\n".join([",".join(keys)] + [",".join(
        f"{r[k]:.6g}" if isinstance(r[k], float) else str(r[k]) for k in keys)
        for r in rows]) + "\n"


def write_table(out: Path, stem: str, rows: Sequence[dict[str, Any]], title: str) -> None:
    atomic_write_text(out / f"{stem}.md", f"# {title}\n\n" + _md(rows))
    atomic_write_text(out / f"{stem}.csv", _csv(rows))


def plot_binned(curves: dict[str, dict[str, Tensor]], path: Path) -> Path:
    """Binned refined vs initial error per edge (log bins), rotation and direction panels;
    a ``"NAME + guard"`` curve is drawn dashed in NAME's colour, without its band."""
    from matplotlib.figure import Figure

    n_models = sum(not n.endswith(" + guard") for n in curves)
    many = n_models > 3  # bands would hide the lines
    legend_rows = (len(curves) + 2) // 3 if many else 0  # the shared legend's rows, 3 columns
    fig = Figure(figsize=(11, 4.6 + 0.25 * legend_rows), dpi=110)
    for k, (what, lim) in enumerate((("rot", (0.05, 180.0)), ("tdir", (0.5, 180.0)))):
        ax = fig.add_subplot(1, 2, k + 1)
        edges = np.logspace(np.log10(lim[0]), np.log10(lim[1]), 22)
        colors: dict[str, str] = {}
        if n_models > 10:  # more models than the default cycle's ten distinct colours
            from matplotlib import colormaps

            ax.set_prop_cycle(color=colormaps["tab20"].colors)
        for name, err in curves.items():
            x = err[f"{what}_init"].numpy()
            y = err[f"{what}_ref"].numpy()
            ok = ~(np.isnan(x) | np.isnan(y))
            # exact inputs (error 0) go into the first bin instead of off the log axis
            x, y = np.maximum(x[ok], lim[0] * 1.01), np.maximum(y[ok], lim[0])
            idx = np.digitize(x, edges)
            cx, my, q1, q3 = [], [], [], []
            for b in range(1, len(edges)):
                sel = idx == b
                if sel.sum() >= 5:
                    cx.append(np.sqrt(edges[b - 1] * edges[b]))
                    my.append(y[sel].mean())
                    q1.append(np.quantile(y[sel], 0.25))
                    q3.append(np.quantile(y[sel], 0.75))
            base = name.removesuffix(" + guard")
            if base != name and base in colors:  # the guarded run: its model's colour, dashed
                ax.plot(cx, my, ls="--", lw=1.2, color=colors[base], label=f"{name} (mean)")
                continue
            line = ax.plot(cx, my, marker="o", ms=3, label=f"{name} (mean)")[0]
            colors[name] = line.get_color()
            if not many:
                ax.fill_between(cx, q1, q3, color=line.get_color(), alpha=0.15)
        ax.plot(lim, lim, "k--", lw=1, label="refined = initial")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(*lim)
        ax.set_ylim(lim[0], lim[1])
        ax.set_xlabel(f"initial {'rotation' if what == 'rot' else 'direction'} error per edge "
                      "(deg)")
        ax.set_ylabel("refined error (deg), binned mean" + ("" if many else "; band: 25-75%"))
        ax.grid(True, which="both", alpha=0.3)
        if not many:
            ax.legend(fontsize=7, loc="upper left")
    if many:  # one legend under both panels
        handles, labels = fig.axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=3)
    fig.suptitle("Refined vs initial relative-pose error per edge (KP, BB, GT, GT+noise "
                 "inputs pooled; exact inputs in the leftmost bin)")
    fig.tight_layout(rect=(0, 0.03 * legend_rows, 1, 1))
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    return path


def evaluate_models(models: dict[str, str], data: str | Path | Sequence[str | Path],
                    out: str | Path, split: str = "test", absolute: bool = True,
                    max_graphs: int | None = None) -> dict[str, Any]:
    """Run the whole evaluation (module docstring) and write its files under ``out``.

    ``data``: a dataset root, or several whose ``split`` graphs are evaluated together."""
    from posernet.data.inputs import load_input_graphs
    from posernet.nn import PoserNet

    out = Path(out)
    roots = [data] if isinstance(data, (str, Path)) else list(data)
    graphs = [g for root in roots
              for g in load_input_graphs(root, split=split, estimate=None, log=lambda *_: None)]
    data = ", ".join(str(r) for r in roots)
    if max_graphs:
        graphs = graphs[:max_graphs]
    out.mkdir(parents=True, exist_ok=True)  # after the input loaded: bad input writes nothing
    inputs = make_inputs(graphs)
    B = len(graphs)
    summary: dict[str, Any] = {"data": str(data), "split": split, "graphs": B, "models": {}}
    graph_rows, bin_rows, abs_rows, lever_rows, conf_rows = [], [], [], [], []
    curves: dict[str, dict[str, Tensor]] = {}
    for name, ckpt in models.items():
        model = PoserNet.from_checkpoint(ckpt)
        errs = {k: edge_errors_for(model, v) for k, v in inputs.items()}
        m: dict[str, Any] = {"checkpoint": str(ckpt), "per_graph": {}, "bins": {}}
        for inp, e in errs.items():
            med = per_graph_medians(e, B)
            m["per_graph"][inp] = med
            graph_rows.append({"model": name, "input": inp, **med})
        pooled = _cat(list(errs.values()))
        curves[name] = pooled
        for inp, e in [("all", pooled), *errs.items()]:
            rows = bin_table(e)
            m["bins"][inp] = rows
            bin_rows += [{"model": name, "input": inp, **r} for r in rows]
        lever_rows.append(lever_row(name, m))
        if getattr(model, "confidence", False):
            m["confidence"] = confidence_rows(name, errs)
            conf_rows += m["confidence"]
            guarded = {k: edge_errors_for(model, v, guard=True) for k, v in inputs.items()}
            m["guard_per_graph"] = {k: per_graph_medians(v, B) for k, v in guarded.items()}
            for inp in guarded:
                graph_rows.append({"model": f"{name} + guard", "input": inp,
                                   **m["guard_per_graph"][inp]})
            g_pooled = _cat(list(guarded.values()))
            m["guard_bins"] = {inp: bin_table(e) for inp, e in
                               [("all", g_pooled), *guarded.items()]}
            for inp, rows in m["guard_bins"].items():
                bin_rows += [{"model": f"{name} + guard", "input": inp, **r} for r in rows]
            curves[f"{name} + guard"] = g_pooled
            lever_rows.append(lever_row(f"{name} + guard", {"per_graph": m["guard_per_graph"],
                                                           "bins": m["guard_bins"]}))
        if absolute:
            conf = bool(getattr(model, "confidence", False))
            rows = [*absolute_rows(model, inputs["KP"], conf, "KP"),
                    *absolute_rows(model, inputs["BB"], conf, "BB")]
            abs_rows += [{"model": name, **r} for r in rows]
            m["absolute"] = rows
        summary["models"][name] = m
        print(f"[adaptive] {name}: " + ", ".join(
            f"{k} rot {v['rot_init']:.2f}->{v['rot_ref']:.2f} tdir {v['tdir_init']:.2f}->"
            f"{v['tdir_ref']:.2f}" for k, v in m["per_graph"].items()), flush=True)
    title = f"{data} ({split}, {B} graphs)"
    write_table(out, "graphs", graph_rows,
                f"Per-graph medians of mean edge errors (deg): {title}")
    write_table(out, "bins", bin_rows,
                f"Per-edge errors binned by initial rotation error (deg): {title}")
    write_table(out, "levers", lever_rows,
                f"One row per model: per-graph medians (deg) for GT/KP/BB input, and the mean "
                f"refined rotation / direction error of the pooled per-edge bins (initial "
                f"rotation error < 3, 3-10, 10-30, > 30 deg; 'worse': bins whose mean got "
                f"worse than the initial mean): {title}")
    if conf_rows:
        write_table(out, "confidence", conf_rows,
                    f"Predicted per-edge errors vs actual ones (correlation of logs) and the AUC "
                    f"with which the predicted input rotation error separates input edges under "
                    f"3 deg from 3-10 deg ones: {title}")
    if abs_rows:
        write_table(out, "absolute", abs_rows,
                    f"Absolute poses after motion averaging, KP and BB input (median rotation deg, "
                    f"median position, similarity-aligned, unit-norm translations): {title}")
    plot_binned(curves, out / "refined_vs_initial.png")
    atomic_write_json(out / "summary.json", _finite(summary))
    return summary


def _finite(obj: Any) -> Any:
    """JSON-safe copy: NaN / inf floats (empty bins) become ``None``."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def guard_report(models: dict[str, str], sets: dict[str, Sequence[ViewGraph]],
                 out: str | Path) -> list[dict[str, Any]]:
    """The guard on named graph sets: its warning line (or none) per model and set, and the
    per-graph median rotation / direction errors without and with ``guard=true``."""
    from posernet.checkpoints import read_checkpoint
    from posernet.graph import GraphBatch
    from posernet.guard import check_inputs, cycle_inconsistency, warning_line
    from posernet.nn import PoserNet
    from posernet.refinement import refine_graphs

    rows = []
    for name, ckpt in models.items():
        model = PoserNet.from_checkpoint(ckpt)
        stats = (read_checkpoint(ckpt).get("posernet") or {}).get("input_stats")
        for set_name, graphs in sets.items():
            graphs = list(graphs)
            batch = GraphBatch.from_graphs(graphs)
            res = refine_graphs(model, graphs, progress=False)
            cyc = {st: float(cycle_inconsistency(batch, torch.cat(p).to(batch.edge_pose.dtype))
                             .mean()) for st, p in res.edge_pose.items()}
            line = warning_line(check_inputs(stats, graphs), cyc["initial"], cyc["refined"])
            err = per_graph_medians(edge_errors_for(model, graphs), len(graphs))
            row: dict[str, Any] = {"model": name, "graphs": set_name, **err}
            if getattr(model, "confidence", False):
                g = per_graph_medians(edge_errors_for(model, graphs, guard=True), len(graphs))
                row.update({"rot_guard": g["rot_ref"], "tdir_guard": g["tdir_ref"]})
            else:
                row.update({"rot_guard": float("nan"), "tdir_guard": float("nan")})
            row["warning"] = line or "-"
            rows.append(row)
    write_table(Path(out), "guard", rows, "Guard: warning line and per-graph medians (deg) "
                "without / with guard=true")
    return rows


def random_graphs(n: int = 60, seed: int = 0) -> list[ViewGraph]:
    """Out-of-distribution graphs (random boxes and cameras, 10 deg initial noise, as in the
    test suite's authors'-schema files)."""
    from posernet.testing import random_view_graph

    gen = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        g = random_view_graph(num_nodes=8, extra_edges=10, generator=gen, name=f"ood{i}")
        g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose}
        out.append(g)
    return out


def paper_tables(ckpt: str | Path, data: str | Path, out: str | Path, label: str,
                 paper_dir: str | Path | None = None) -> dict[str, Path]:
    """Table 1 / Table 3 rows (paper layout) of one checkpoint on a dataset's test split.

    Writes ``table1.md|csv`` (relative poses, KP and BB input) and ``table3.md|csv`` (EIG-SE3
    and rotation_translation, uniform and confidence-weighted IRLS start) under ``out``; with
    ``paper_dir`` (e.g. ``results/paper``) ``table1_with_paper.md`` / ``table3_with_paper.md``
    put the new rows under the existing table, whose rows (paper, paper-faithful model) are
    kept verbatim.
    """
    from posernet.data.inputs import load_input_graphs
    from posernet.evaluation import evaluate_result, result_tables
    from posernet.nn import PoserNet
    from posernet.refinement import refine_graphs
    from posernet.report import ABSOLUTE_GROUPS, ResultTable, TableRow
    from posernet.sync import get_backend

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    model = PoserNet.from_checkpoint(ckpt)
    has_conf = bool(getattr(model, "confidence", False))
    graphs = load_input_graphs(data, split="test", estimate=None, log=lambda *_: None)
    rel_rows, abs_rows = [], []
    for est in ("bb", "kp"):
        inp = [g.with_estimate(est) for g in graphs]
        for bname, short in (("eig_se3", "EIG-SE3"), ("rotation_translation", "RotTrans")):
            modes = [False, True] if has_conf else [False]
            for weighted in modes:
                res = refine_graphs(model, inp, backend=get_backend(bname, weight_mode="prior"),
                                    progress=False, weighted=weighted)
                ev = evaluate_result(res)
                tabs = result_tables(ev, label=est.upper(), backend=res.backend)
                if bname == "eig_se3" and not weighted:
                    rel = {r.labels[1]: r for r in tabs["relative"].rows}
                    rel_rows.append(TableRow((est.upper(), f"{label}"), rel["PoserNet"].cells))
                tag = " (confidence-weighted)" if weighted else ""
                for r in tabs["absolute"].rows:
                    stage = (f"{short}{tag}" if r.labels[1] == bname
                             else f"{short} + {label}{tag}")
                    if r.labels[1] == bname and weighted:
                        stage = f"{short} (input confidence from {label})"
                    abs_rows.append(TableRow((stage, est.upper()), r.cells, placed=r.placed))
    t1 = ResultTable(rows=rel_rows, title=f"Table 1 rows: {label}",
                     note=f"{len(graphs)} test graphs of {data}; checkpoint {ckpt}")
    t3 = ResultTable(rows=abs_rows, label_names=("method", "init"), groups=ABSOLUTE_GROUPS,
                     title=f"Table 3 rows: {label}",
                     note=f"{len(graphs)} test graphs of {data}; unit-norm relative translations "
                          "(EIG-SE3), scale-free (RotTrans); similarity alignment; confidence "
                          "weights: IRLS 'prior' mode")
    paths = {}
    for name, tab in (("table1", t1), ("table3", t3)):
        paths[name] = tab.write(out, name)[0]
        if paper_dir is not None:
            src = Path(paper_dir) / name / "table.md"
            if src.is_file():
                text = (src.read_text()
                        + f"\n\n**Rows added (input-adaptive refinement): {label}**\n\n"
                        + tab.to_markdown())
                paths[f"{name}_with_paper"] = atomic_write_text(
                    out / f"{name}_with_paper.md", text)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python research/adaptive.py",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--data", action="append", required=True,
                   help="dataset root (posernet-make-data output); repeat it to evaluate the "
                        "test graphs of several datasets together")
    p.add_argument("--model", action="append", required=True,
                   help="NAME=CHECKPOINT (repeatable); NAME=shipped for the shipped one")
    p.add_argument("--out", required=True, help="output folder (e.g. research/adaptive)")
    p.add_argument("--split", default="test")
    p.add_argument("--no-absolute", action="store_true", help="skip motion averaging")
    p.add_argument("--max-graphs", type=int, default=None)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--guard", action="store_true",
                   help="instead: the guard report on the --data KP test graphs and on random "
                        "out-of-distribution graphs, for every --model")
    p.add_argument("--guard-set", action="append", metavar="NAME=DIR",
                   help="with --guard: another dataset root whose KP test graphs are checked")
    p.add_argument("--paper-tables", default=None, metavar="LABEL",
                   help="instead: Table 1/3 rows of the (single) --model, labelled LABEL")
    p.add_argument("--paper-dir", default=None,
                   help="with --paper-tables: the runner's folder (e.g. results/paper) whose "
                        "tables the rows are appended to (in new files)")
    a = p.parse_args(argv)
    try:
        return _run(p, a)
    except (FileNotFoundError, ValueError) as exc:  # bad data / checkpoint: one line, exit 1
        print(f"{p.prog}: error: {exc}", file=sys.stderr)
        return 1


def _run(p: argparse.ArgumentParser, a: argparse.Namespace) -> int:
    for root in a.data:
        if not Path(root).exists():
            raise FileNotFoundError(f"--data {root}: no such dataset folder (posernet-make-data "
                                    "writes one)")
    if (a.guard or a.paper_tables) and len(a.data) != 1:
        p.error("--guard and --paper-tables take one --data (--guard-set adds more to --guard)")
    torch.set_num_threads(a.threads)
    models = {}
    for spec in a.model:
        if "=" not in spec:
            p.error(f"--model must be NAME=CHECKPOINT, got {spec!r}")
        name, path = spec.split("=", 1)
        if path == "shipped":
            from posernet.checkpoints import default_checkpoint

            path = str(default_checkpoint())
        models[name] = path
    from posernet.checkpoints import read_checkpoint

    for path in models.values():  # every checkpoint readable before any output
        read_checkpoint(path)
    if a.guard:
        from posernet.data.inputs import load_input_graphs

        sets: dict[str, Sequence[ViewGraph]] = {}
        for spec in [f"{Path(a.data[0]).name}={a.data[0]}", *(a.guard_set or [])]:
            set_name, root = spec.split("=", 1)
            sets[f"{set_name} KP"] = load_input_graphs(root, split=a.split, estimate="kp",
                                                       size="all", log=lambda *_: None)
        sets["random (OOD)"] = random_graphs()
        guard_report(models, sets, a.out)
        return 0
    if a.paper_tables:
        if len(models) != 1:
            p.error("--paper-tables takes exactly one --model")
        paper_tables(next(iter(models.values())), a.data[0], a.out, a.paper_tables, a.paper_dir)
        return 0
    evaluate_models(models, a.data, a.out, a.split, not a.no_absolute, a.max_graphs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
