"""The research evaluation script of input-adaptive refinement (``research/adaptive.py``):
not part of the package, run as ``python research/adaptive.py``; tested here so the commands
the model card quotes keep working."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest
import torch

_PATH = Path(__file__).resolve().parents[2] / "research" / "adaptive.py"
_spec = importlib.util.spec_from_file_location("adaptive_eval", _PATH)
assert _spec is not None and _spec.loader is not None
sys.modules["adaptive_eval"] = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sys.modules["adaptive_eval"])


def test_evaluation_command_reports_bad_input_in_one_line(tmp_path, capsys) -> None:
    from adaptive_eval import main

    from posernet.testing import write_random_dataset

    out = tmp_path / "out"
    assert main(["--data", str(tmp_path / "nope"), "--out", str(out), "--model",
                 "shipped=shipped"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--data" in err and "nope" in err
    data = write_random_dataset(tmp_path / "data", {"test": 1})
    assert main(["--data", str(data), "--out", str(out), "--model",
                 f"a={tmp_path / 'missing.ckpt'}", "--no-absolute"]) == 1
    assert "checkpoint not found" in capsys.readouterr().err
    assert not out.exists()


def test_separation_auc_matches_the_pairwise_definition() -> None:
    from adaptive_eval import separation_auc

    gen = torch.Generator().manual_seed(0)
    for _ in range(20):
        n = int(torch.randint(2, 40, (1,), generator=gen))
        score = torch.randint(0, 6, (n,), generator=gen).double()  # many ties
        positive = torch.rand(n, generator=gen) < 0.4
        if positive.all() or not positive.any():
            assert math.isnan(separation_auc(score, positive))
            continue
        p, q = score[positive][:, None], score[~positive][None, :]
        expected = float(((p > q).double() + 0.5 * (p == q).double()).mean())
        assert separation_auc(score, positive) == pytest.approx(expected, abs=1e-12)
    s = torch.arange(6.0)
    assert separation_auc(s, s > 2) == 1.0 and separation_auc(-s, s > 2) == 0.0


def test_mean_change_ci_resamples_whole_graphs() -> None:
    from adaptive_eval import mean_change_ci

    graph = torch.arange(6).repeat_interleave(4)  # 6 graphs, 4 edges each
    # the same change everywhere: no spread, whatever graphs are drawn
    lo, hi = mean_change_ci(torch.full((24,), 0.25), graph, 6)
    assert lo == pytest.approx(0.25) and hi == pytest.approx(0.25)
    # the vectorised draws equal a loop over the same draws
    gen = torch.Generator().manual_seed(3)
    delta = torch.randn(24, generator=gen, dtype=torch.float64)
    draws = torch.randint(6, (50, 6), generator=torch.Generator().manual_seed(0))
    loop = torch.stack([torch.cat([delta[graph == k] for k in row]).mean() for row in draws])
    want = torch.quantile(loop, torch.tensor([0.025, 0.975], dtype=torch.float64))
    got = mean_change_ci(delta, graph, 6, reps=50, seed=0)
    assert got == pytest.approx(want.tolist(), abs=1e-12)
    assert got[0] <= float(delta.mean()) <= got[1]
    # one graph that changed a lot: the interval spans "no change" to "worse"
    delta = torch.zeros(24)
    delta[graph == 0] = 5.0
    lo, hi = mean_change_ci(delta, graph, 6)
    assert lo == 0.0 and hi > 1.0
    nan = mean_change_ci(torch.full((4,), float("nan")), torch.zeros(4, dtype=torch.long), 1)
    assert all(math.isnan(v) for v in nan)


@pytest.mark.slow
def test_evaluation_command_writes_every_table_and_the_plot(tmp_path) -> None:
    from adaptive_eval import main

    from posernet.testing import write_random_dataset

    data = write_random_dataset(tmp_path / "data", {"test": 2})
    out = tmp_path / "out"
    assert main(["--data", str(data), "--out", str(out), "--model", "shipped=shipped",
                 "--no-absolute", "--threads", "1"]) == 0
    for stem in ("graphs", "bins", "levers", "confidence"):
        assert (out / f"{stem}.md").is_file() and (out / f"{stem}.csv").is_file()
    assert "rot < 3: change, 95% CI" in (out / "levers.md").read_text()
    assert (out / "refined_vs_initial.png").stat().st_size > 10_000
    summary = json.loads((out / "summary.json").read_text())
    conf = summary["models"]["shipped"]["confidence"]
    assert [r["input"] for r in conf] == ["KP", "BB", "GT", "GT+noise"]
    for r in conf:
        auc = r["auc_in_lt3_vs_3to10"]
        assert auc is None or 0.0 <= auc <= 1.0  # None: a class is empty (JSON has no NaN)
        # exact (ground-truth) input has no spread to correlate with: None there
        assert (r["corr_rot_in"] is None) if r["input"] == "GT" else \
            -1.0 <= r["corr_rot_in"] <= 1.0


@pytest.mark.slow
def test_evaluation_command_pools_the_test_graphs_of_several_datasets(tmp_path) -> None:
    """--data A --data B: one evaluation over both test splits (the bins count every edge)."""
    from adaptive_eval import main

    from posernet.testing import write_random_dataset

    a = write_random_dataset(tmp_path / "a", {"test": 1})
    b = write_random_dataset(tmp_path / "b", {"test": 2}, seed=1)
    counts = {}
    for name, roots in (("a", [a]), ("b", [b]), ("ab", [a, b])):
        out = tmp_path / f"out_{name}"
        args = [x for r in roots for x in ("--data", str(r))]
        assert main([*args, "--out", str(out), "--model", "shipped=shipped", "--no-absolute",
                     "--threads", "1"]) == 0
        summary = json.loads((out / "summary.json").read_text())
        counts[name] = (summary["graphs"], sum(r["edges"] for r in
                                               summary["models"]["shipped"]["bins"]["all"]))
        assert str(a if name == "a" else b) in summary["data"]
    assert counts["ab"] == tuple(x + y for x, y in zip(counts["a"], counts["b"], strict=True))
    # the guard report and the paper tables take one dataset: a usage error, nothing written
    with pytest.raises(SystemExit) as exc:
        main(["--data", str(a), "--data", str(b), "--out", str(tmp_path / "g"), "--model",
              "shipped=shipped", "--guard"])
    assert exc.value.code == 2 and not (tmp_path / "g").exists()
