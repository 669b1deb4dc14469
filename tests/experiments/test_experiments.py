"""The paper's experiments: scales, the training multiruns, the collected tables (fast checks;
the whole quick scale end to end is slow)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from posernet.experiments import EXPERIMENTS, parse_only, run_experiments
from posernet.experiments.__main__ import main
from posernet.experiments.collect import table3_backends


def test_parse_only_defaults_and_subsets() -> None:
    assert parse_only(None) == list(EXPERIMENTS)
    assert parse_only("") == list(EXPERIMENTS)
    assert parse_only("table3, table1,table3") == ["table3", "table1"]


def test_unknown_experiment_lists_valid_names() -> None:
    with pytest.raises(ValueError, match="valid: .*table1.*loo.*plots"):
        parse_only("table1,tabel9")


def test_cli_rejects_bad_arguments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["--out", str(tmp_path), "--only", "nope"])
    assert exc.value.code == 2
    assert "valid:" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path), "--scale", "huge"])
    with pytest.raises(ValueError, match="unknown scale"):
        run_experiments("huge", tmp_path)


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("experiments")
    status = run_experiments("quick", out, echo=None)
    return out, status


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_quick_scale_runs_every_experiment(quick_run: tuple[Path, dict]) -> None:
    out, status = quick_run
    assert all(status[name]["ok"] for name in EXPERIMENTS), status
    summary = (out / "summary.md").read_text()
    for name in EXPERIMENTS:
        assert f"| {name} | ok |" in summary
    assert "Total wall time" in summary
    for name in ("table1", "table2", "table3", "depth", "loo"):
        assert (out / name / "table.md").is_file() and (out / name / "table.csv").is_file()
    assert not list(out.rglob("*.tmp*"))  # atomic writes leave no temporary files


@pytest.mark.slow
def test_quick_tables_have_paper_and_our_rows(quick_run: tuple[Path, dict]) -> None:
    out, _ = quick_run
    t1 = {(r["source"], r["input"], r["stage"]): r for r in _rows(out / "table1" / "table.csv")}
    for src in ("paper", "ours"):
        for inp in ("KP", "BB"):
            for stage in ("Initial", "PoserNet"):
                assert (src, inp, stage) in t1
    assert float(t1[("paper", "KP", "PoserNet")]["rot_median"]) == pytest.approx(7.31)
    assert t1[("ours", "KP", "PoserNet")]["runs"] == "2"
    assert "± " in (out / "table1" / "table.md").read_text()
    assert 0.0 <= float(t1[("ours", "-", "Constant prior")]["tdir_median"]) <= 180.0
    digest = (out / "digest.md").read_text()
    assert "Table 3" in digest and "Leave one scene out" in digest and "| KP | PoserNet |" in digest

    t2 = {(r["source"], r["train"], r["test"]) for r in _rows(out / "table2" / "table.csv")}
    for train in ("Raw", "Small", "Large"):
        for test in ("Small", "Large"):
            assert ("ours", train, test) in t2 and ("paper", train, test) in t2

    t3 = {(r["source"], r["method"], r["init"]) for r in _rows(out / "table3" / "table.csv")}
    assert ("paper", "EIG-SE3 + PoserNet", "KP") in t3
    for inp in ("KP", "BB"):
        assert ("ours", "EIG-SE3", inp) in t3 and ("ours", "EIG-SE3 + PoserNet", inp) in t3
    assert "rotation_translation" in table3_backends()
    assert ("ours", "RotTrans + PoserNet", "KP") in t3
    for inp in ("KP", "BB"):  # end to end, and the learned synchronisation beside MultiReg
        assert ("ours", "EIG-SE3 + PoserNet (end-to-end)", inp) in t3
        assert ("ours", "RotTrans + PoserNet (end-to-end)", inp) in t3
        for method in ("MultiReg", "MultiReg + PoserNet"):
            assert ("paper", method, inp) in t3
        assert ("ours", "Learned sync", inp) in t3 and ("ours", "Learned sync + PoserNet",
                                                         inp) in t3

    depth = {r["depth"]: r for r in _rows(out / "depth" / "table.csv")}
    assert set(depth) == {"2", "3", "4", "5"}
    assert float(depth["4"]["rot_median_paper"]) == pytest.approx(9.4)
    assert {r["alpha"] for r in _rows(out / "depth" / "alpha.csv")} == {"0.1", "0.5", "1"}

    loo = {r["test scene"]: r for r in _rows(out / "loo" / "table.csv")}
    assert {"chess", "fire", "heads", "median"} <= set(loo)
    assert float(loo["median"]["rot_median_paper"]) == pytest.approx(8.04)
    per_scene = [int(r["graphs"]) for k, r in loo.items()
                 if k not in ("median", "all (trained on every scene)")]
    assert int(loo["median"]["graphs"]) == sum(per_scene) > 0


@pytest.mark.slow
def test_quick_plots_exist(quick_run: tuple[Path, dict]) -> None:
    out, _ = quick_run
    plots = out / "plots"
    for est in ("kp", "bb"):
        assert (plots / f"errors_sorted_{est}.png").stat().st_size > 1000
        assert (plots / f"cameras_{est}_0.png").stat().st_size > 1000
    assert "errors_sorted_kp.png" in (plots / "index.md").read_text()


@pytest.mark.slow
def test_rerun_trains_nothing_and_collect_only_reads_the_models(
        quick_run: tuple[Path, dict]) -> None:
    out, status = quick_run
    assert len(status["train"]["trained"]) == len(status["train"]["models"]) == 26
    again = run_experiments("quick", out, only="table1", echo=None)
    assert again["table1"]["ok"] and again["train"]["trained"] == []
    collected = run_experiments("quick", out, only="table1", collect_only=True, echo=None)
    assert "train" not in collected and collected["table1"]["ok"]
    # each model's multirun left its Hydra record and its training log in the model folder
    run = out / "models" / "kp-small-d3-a0.1" / "seed0"
    assert (run / ".hydra" / "overrides.yaml").is_file() and (run / "metrics.json").is_file()
    assert "model.net.depth=3" in (run / ".hydra" / "overrides.yaml").read_text()


def test_collect_only_names_the_command_that_trains_a_missing_model(tmp_path: Path) -> None:
    from posernet.experiments.collect import Context
    from posernet.experiments.models import ModelSpec, load_scale

    ctx = Context(load_scale("quick"), tmp_path)
    with pytest.raises(FileNotFoundError, match=r"kp-small-d2-a0.1 seed 1 is not trained.*"
                       r"posernet-train -m \+experiment=table1_kp .*seed=1"):
        ctx.checkpoint(ModelSpec(), 1)


def test_summary_merges_runs_into_one_table(tmp_path: Path) -> None:
    from posernet.experiments.collect import write_summary
    from posernet.experiments.models import load_scale

    scale = load_scale("quick")
    ok = {"ok": True, "seconds": 1.5, "files": [str(tmp_path / "table1" / "table.md")],
          "error": None, "trained": ["kp-small-d2-a0.1/seed0"],
          "models": ["kp-small-d2-a0.1/seed0", "bb-small-d2-a0.1/seed0"]}
    done = tmp_path / "models" / "kp-small-d2-a0.1" / "seed0" / "metrics.json"
    done.parent.mkdir(parents=True)
    done.write_text('{"best_checkpoint": "x.ckpt", "train_seconds": 12.4}')
    write_summary(tmp_path, scale, {"table1": ok}, 2.0, "cpu", (2, 1))
    bad = {"ok": False, "seconds": 3.0, "files": [], "error": "ValueError: boom", "trained": []}
    text = write_summary(tmp_path, scale, {"loo": bad}, 3.0, "cpu", (2, 1)).read_text()
    assert "| table1 | ok | 1.5 | 1 | 2 (12) | table1/table.md |" in text
    assert "| loo | FAILED (ValueError: boom) | 3.0 | 0 | 0 (0) |" in text
    assert "logical cores" in text and "torch" in text
    # a different scale starts a fresh record
    other = write_summary(tmp_path, load_scale("medium"), {"loo": bad}, 3.0, "cpu",
                          (50, 150)).read_text()
    assert "table1" not in other


@pytest.mark.parametrize("name", ["quick", "medium", "paper"])
def test_scale_datasets_resolve(name: str) -> None:
    from posernet.data.synthetic.config import resolve_options
    from posernet.experiments.models import load_scale

    scale = load_scale(name)
    opts = resolve_options(scale.dataset)
    assert opts.small.test > 0 and opts.large.test > 0 and scale.seeds
    if name == "medium":  # a tenth of the paper's small graphs, the same simulator settings
        paper = resolve_options("paper")
        assert (opts.small.train, opts.small.test) == (paper.small.train // 10,
                                                       paper.small.test // 10)
        assert opts.keypoints == paper.keypoints and opts.large == paper.large
        assert opts.detector == paper.detector and opts.matching == paper.matching


def test_scale_files_are_checked(tmp_path: Path) -> None:
    from posernet.experiments.models import load_scale

    assert load_scale("quick", ["scale.seeds=[3]"]).seeds == (3,)
    with pytest.raises(ValueError, match="must not be empty"):
        load_scale("quick", ["scale.seeds=[]"])
    with pytest.raises(ValueError, match="needs exactly the keys"):
        load_scale("quick", ["+scale.typo=1"])


@pytest.mark.slow
def test_interrupted_model_resumes_from_last_epoch(quick_run: tuple[Path, dict],
                                                   tmp_path: Path) -> None:
    import json

    from posernet.experiments.models import ModelSpec, load_scale

    src, _ = quick_run
    spec = ModelSpec()
    run_dir = tmp_path / "models" / spec.key / "seed0"
    one = load_scale("quick", ["scale.seeds=[0]", "scale.train=['trainer.max_epochs=1']"])
    status = run_experiments(one, tmp_path, only="table1", data=src / "data", train_only=True,
                             echo=None)
    assert "kp-small-d2-a0.1/seed0" in status["train"]["trained"]
    assert json.loads((run_dir / "metrics.json").read_text())["epochs"] == 1
    (run_dir / "metrics.json").unlink()  # as if killed after its first epoch
    three = load_scale("quick", ["scale.seeds=[0]", "scale.train=['trainer.max_epochs=3']"])
    status = run_experiments(three, tmp_path, only="table1", data=src / "data", echo=None)
    assert status["train"]["trained"] == ["kp-small-d2-a0.1/seed0"]  # bb had finished
    assert json.loads((run_dir / "metrics.json").read_text())["epochs"] == 3
    log = (tmp_path / "models" / "logs" / "00_table1_kp.log").read_text()
    assert f"Resuming from {run_dir / 'checkpoints' / 'last.ckpt'}" in log
    epochs = {r["epoch"] for r in _rows(run_dir / "logs" / "metrics.csv") if r.get("epoch")}
    assert {"0", "1", "2"} <= epochs  # epoch 0 of the first run kept, 1-2 appended
    assert status["table1"]["ok"]


def test_prior_pose_is_the_mean_ground_truth_pose() -> None:
    from posernet.experiments.collect import prior_pose
    from posernet.geometry import quaternion_angle
    from posernet.testing import random_view_graph

    gen = torch.Generator().manual_seed(0)
    graphs = [random_view_graph(generator=gen, dtype=torch.float64) for _ in range(3)]
    q = torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=torch.float64)
    q = q / q.norm()
    t = torch.tensor([0.2, -0.4, 1.0], dtype=torch.float64)
    for g in graphs:  # every edge the same motion, with varying baselines and quaternion signs
        n = g.num_edges
        sign = torch.where(torch.arange(n) % 2 == 0, 1.0, -1.0).double()[:, None]
        g.edge_pose_gt = torch.cat([q * sign, t * torch.linspace(0.5, 3.0, n)[:, None]], 1)
    pose = prior_pose(graphs)
    assert quaternion_angle(pose[:4], q).item() == pytest.approx(0.0, abs=1e-6)
    assert torch.allclose(pose[4:], t / t.norm(), atol=1e-9)
    with pytest.raises(ValueError, match="no edges"):
        prior_pose([])


def test_digest_pairs_ours_with_the_paper(tmp_path: Path) -> None:
    from posernet.experiments.digest import digest_markdown, write_digest

    with pytest.raises(FileNotFoundError, match="no experiment tables"):
        digest_markdown(tmp_path)
    (tmp_path / "table1").mkdir()
    (tmp_path / "table1" / "table.csv").write_text(
        "source,input,stage,rot_median,rot_median_std,tdir_median,tdir_median_std,runs\n"
        "paper,KP,PoserNet,7.31,0.11,14.54,0.14,3\n"
        "ours,KP,PoserNet,6.42,0.22,63.07,3.99,3\n"
        "ours,KP,Initial,24.79,0,72.6,0,1\n")
    (tmp_path / "loo").mkdir()
    (tmp_path / "loo" / "table.csv").write_text(
        "test scene,rot_median,rot_median_std,rot_median_paper,tdir_median,tdir_median_std,"
        "tdir_median_paper,graphs,runs\nchess,6.05,0.0,7.27,58.1,0.0,21.03,100,1\n")
    text = write_digest(tmp_path).read_text()
    assert "| KP | PoserNet | 6.4 ± 0.2 | 7.3 ± 0.1 | 63.1 ± 4.0 | 14.5 ± 0.1 |" in text
    assert "| KP | Initial | 24.8 |  | 72.6 |  |" in text  # no paper row: empty cells
    assert "| chess | 6.0 | 7.3 | 58.1 | 21.0 |" in text


def test_required_models_list_each_model_once() -> None:
    from posernet.experiments.models import load_scale, required_models

    scale, scenes = load_scale("quick"), ["chess", "fire", "heads"]
    jobs = required_models(scale, list(EXPERIMENTS), scenes)
    assert len(jobs) == len(set(jobs))
    for name in EXPERIMENTS:
        assert set(required_models(scale, [name], scenes)) <= set(jobs)
    # quick: KP/BB x 2 seeds, large x 2 seeds, depth 3-5, alpha 0.5/1, one model per scene;
    # table 3: end-to-end KP/BB and learned sync raw/refined KP/BB, x 2 seeds
    assert len(jobs) == 4 + 2 + 3 + 2 + len(scenes) + 4 + 8


def _job_overrides(argv: list[str], value: object, seed: int) -> list[str]:
    """One job of a multirun's argv: its sweeps set to one value, ``-m`` dropped."""
    out = []
    for a in argv[1:]:
        key, _, v = a.partition("=")
        if key == "seed":
            a = f"seed={seed}"
        elif "," in v and not v.startswith(("'", "[")):
            a = f"{key}={value}"
        out.append(a)
    return out


def test_multiruns_train_what_the_collector_reads(tmp_path: Path) -> None:
    """Each job of each multirun composes the model its folder name says, the same config as
    the collector's ``train_config`` (what ``posernet-train +experiment=<file>`` gives), and
    lands in ``models/<key>/seed<k>``."""
    from omegaconf import OmegaConf

    from posernet.conf import compose
    from posernet.experiments.collect import Context
    from posernet.experiments.models import load_scale, multirun_commands, required_models

    for scale_name in ("quick", "paper"):
        scale = load_scale(scale_name)
        ctx = Context(scale, tmp_path)
        jobs = required_models(scale, list(EXPERIMENTS), ["chess", "fire"])
        runs = multirun_commands(scale, jobs, ctx.models, ctx.data_root)
        assert sum(r.jobs for r in runs) == len(jobs)
        by_key = {sp.key: sp for sp, _ in jobs}
        for run in runs:
            argv = run.argv(ctx.models)
            assert argv[0] == "-m" and "ckpt_path=last" in argv
            values = run.swept[1] if run.swept else [None]
            for key, value in zip(run.keys, values, strict=True):
                for seed in run.seeds:
                    cfg = compose("train", _job_overrides(argv, value, seed),
                                  return_hydra_config=True)
                    assert OmegaConf.select(cfg, "hydra.sweep.subdir") == f"{key}/seed{seed}"
                    assert cfg.hydra.sweep.dir == str(ctx.models.resolve())
                    theirs = ctx.train_config(by_key[key])
                    for part in ("model", "trainer.max_epochs", "data.estimate", "data.size",
                                 "data.batch_size", "data.leave_out_scene"):
                        mine = OmegaConf.select(cfg, part)
                        if part == "model" and by_key[key].refined:
                            ref = mine.input.refiner_ckpt
                            assert ref == str(ctx.models.resolve() / by_key[key].key.replace(
                                "sync-kp-refined", "kp-small-d2-a0.1").replace(
                                "sync-bb-refined", "bb-small-d2-a0.1")
                                / f"seed{seed}" / "checkpoints" / "best.ckpt")
                            continue
                        assert mine == OmegaConf.select(theirs, part), (key, part)
                    assert cfg.seed == seed and cfg.test_after_training is False
                    assert cfg.data.root == str(ctx.data_root.resolve())


def test_runner_models_are_posernet_train_experiment_configs(tmp_path: Path) -> None:
    """Every model is posernet-train's config composed with one experiment file: the same
    values as ``posernet-train +experiment=<file>``."""
    from posernet.conf import compose
    from posernet.experiments.collect import Context
    from posernet.experiments.models import ModelSpec, load_scale, sweep_values

    ctx = Context(load_scale("paper"), tmp_path)
    for spec, name in ((ModelSpec(), "table1_kp"), (ModelSpec(estimate="bb"), "table1_bb"),
                       (ModelSpec(size="large"), "large_graphs"),
                       (ModelSpec(depth=4), "depth_sweep"), (ModelSpec(alpha=0.5), "alpha_sweep"),
                       (ModelSpec(leave_out="fire"), "leave_one_out"),
                       (ModelSpec(kind="end_to_end"), "end_to_end")):
        assert spec.experiment()[0] == name
        ours = ctx.train_config(spec)
        theirs = compose("train", [f"+experiment={name}", f"model.net.depth={spec.depth}",
                                   f"model.loss.alpha={spec.alpha}"]
                         + ([f"data.leave_out_scene={spec.leave_out}"] if spec.leave_out else []))
        for key in ("model", "trainer.max_epochs", "data.estimate", "data.size",
                    "data.batch_size", "data.eval_batch_size", "data.val_size",
                    "data.leave_out_scene"):
            node_a, node_b = ours, theirs
            for part in key.split("."):
                node_a, node_b = node_a[part], node_b[part]
            assert node_a == node_b, (name, key)
    assert ctx.epochs() == (50, 150)  # the paper scale: the experiment files' own epochs
    large = ctx.train_config(ModelSpec(size="large"))
    assert (large.model.optimizer.lr, large.data.batch_size) == (0.01, 1)
    # the quick scale overrides sizes only
    quick = Context(load_scale("quick"), tmp_path)
    assert quick.epochs() == (2, 1)
    assert quick.train_config(ModelSpec(size="large")).data.batch_size == 1
    assert ctx.train_config(ModelSpec(kind="end_to_end")).model.loss.end_to_end is True
    assert ModelSpec(kind="sync", refined=True).key == "sync-kp-refined"
    assert ModelSpec(kind="end_to_end", estimate="bb").key == "e2e-bb-small-d2-a0.1"
    assert sweep_values("depth_sweep", "model.net.depth") == [2, 3, 4, 5]
    assert sweep_values("alpha_sweep", "model.loss.alpha") == [0.1, 0.5, 1]


@pytest.mark.slow
def test_parallel_training_with_the_joblib_launcher(quick_run: tuple[Path, dict],
                                                    tmp_path: Path) -> None:
    from posernet.experiments.models import launcher_available

    if not launcher_available("joblib"):
        pytest.skip("hydra-joblib-launcher not installed (the [sweeps] extra)")
    data = quick_run[0] / "data"
    status = run_experiments("quick", tmp_path, only="table1", jobs=2, train_only=True,
                             data=data, echo=None)
    assert sorted(status) == ["data", "train"]
    assert len(status["train"]["trained"]) == 4
    assert not (tmp_path / "data").exists()  # --data: nothing generated into OUT
    log = (tmp_path / "models" / "logs" / "00_table1_bb.log").read_text()
    assert "hydra/launcher=joblib hydra.launcher.n_jobs=2" in log and "Joblib" in log
    status = run_experiments("quick", tmp_path, only="table1", data=data, collect_only=True,
                             echo=None)
    assert status["table1"]["ok"]
    # the same models as one job at a time: the same table
    assert (tmp_path / "table1" / "table.csv").read_bytes() == \
        (quick_run[0] / "table1" / "table.csv").read_bytes()


def test_submitit_launcher_is_configured_by_overrides(tmp_path: Path) -> None:
    """A SLURM cluster: the multiruns with ``hydra/launcher=submitit_slurm`` and its options
    compose (nothing is submitted)."""
    from posernet.conf import compose
    from posernet.experiments.models import (
        ModelSpec,
        launcher_available,
        launcher_overrides,
        load_scale,
        multirun_commands,
    )

    if not launcher_available("submitit_slurm"):
        pytest.skip("hydra-submitit-launcher not installed (the [slurm] extra)")
    extra = [*launcher_overrides("submitit_slurm", 1), "hydra.launcher.partition=gpu",
             "hydra.launcher.timeout_min=600", "hydra.launcher.gpus_per_node=1"]
    run = multirun_commands(load_scale("paper"), [(ModelSpec(), 0)], tmp_path / "models",
                            tmp_path / "data", device="cuda")[0]
    argv = run.argv(tmp_path / "models", extra)
    cfg = compose("train", _job_overrides(argv, None, 0), return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert "submitit" in launcher._target_.lower() and "Slurm" in launcher._target_
    assert (launcher.partition, launcher.timeout_min, launcher.gpus_per_node) == ("gpu", 600, 1)
    assert cfg.trainer.accelerator == "gpu"


def test_unknown_or_missing_launcher_is_a_clear_error(tmp_path: Path) -> None:
    from posernet.experiments.models import launcher_overrides

    with pytest.raises(ValueError, match="unknown launcher 'ray'"):
        launcher_overrides("ray", 1)
    with pytest.raises(ValueError, match="exclude each other"):
        run_experiments("quick", tmp_path, train_only=True, collect_only=True, echo=None)


def test_bad_data_or_jobs_are_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.*manifest.json"):
        run_experiments("quick", tmp_path, data=tmp_path / "nope", echo=None)
    with pytest.raises(ValueError, match="jobs must be an integer >= 1"):
        run_experiments("quick", tmp_path, jobs=0, echo=None)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="--out .*file/out: cannot create the folder"):
        run_experiments("quick", tmp_path / "file" / "out", echo=None)
    assert main(["--out", str(tmp_path), "--data", str(tmp_path / "nope")]) == 1


def test_quote_value_round_trips_awkward_paths() -> None:
    from posernet.conf import compose, quote_value

    for path in ("/tmp/a b=c", "/tmp/it's", "x\\", "/data/${oops}", "/t/[1,2]"):
        assert compose("train", [f"data.root={quote_value(path)}"]).data.root == path
