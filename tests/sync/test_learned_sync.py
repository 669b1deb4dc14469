"""Learned synchronisation: se(3) exp/log, the network's symmetries, the loss, the Lightning
module, the ``learned`` backend and its configs (training and CLI round trips are slow)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from posernet.checkpoints import CheckpointError, default_checkpoint
from posernet.cli import CONFIG_DIR
from posernet.cli.build import backend_from_config
from posernet.geometry import (
    axis_angle_to_rotation_matrix,
    make_se3,
    matrix_to_pose_vec,
    relative_pose,
    se3_exp,
    se3_log,
)
from posernet.graph import GraphBatch, ViewGraph
from posernet.sync import available_backends, get_backend
from posernet.sync.learned import (
    LEARNED_SYNC_TAG,
    LearnedSync,
    LearnedSyncNet,
    all_pairs,
    learned_sync_loss,
)
from posernet.testing import random_view_graph

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning", "ignore::DeprecationWarning")


def graphs(k: int = 4, n: int = 6, seed: int = 0, **kw) -> list[ViewGraph]:
    g = torch.Generator().manual_seed(seed)
    return [random_view_graph(n, 4, pairs_per_edge=(1, 3), dets_per_node=4, generator=g,
                              name=f"g{i}", **kw) for i in range(k)]


def batch(k: int = 4, n: int = 6, seed: int = 0, **kw) -> GraphBatch:
    return GraphBatch.from_graphs(graphs(k, n, seed, **kw))


def random_se3(seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return se3_exp(torch.randn(6, generator=g, dtype=torch.float64))


def small_net(**kw) -> LearnedSyncNet:
    torch.manual_seed(0)
    return LearnedSyncNet(**{"hidden": 16, "rounds": 3, **kw}).double()


def save_module_checkpoint(module, path: Path) -> Path:
    """What Lightning writes, reduced to what the loaders read (fast; the CLI test writes a
    real one)."""
    torch.save({"state_dict": module.state_dict(),
                "hyper_parameters": dict(module.hparams),
                "posernet": {"tag": module.CHECKPOINT_TAG, "version": "test"}}, path)
    return path


# --------------------------------------------------------------------------- se(3) exp / log

finite = st.floats(-1.0, 1.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(st.lists(finite, min_size=3, max_size=3), st.lists(finite, min_size=3, max_size=3),
       st.floats(0.0, 3.1))
def test_se3_exp_log_round_trip(axis, v, angle):
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm() * angle if a.norm() > 1e-6 else torch.zeros(3, dtype=torch.float64)
    xi = torch.cat((a, 3 * torch.tensor(v, dtype=torch.float64)))
    T = se3_exp(xi)
    R = T[:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(R, axis_angle_to_rotation_matrix(a), atol=1e-12)
    assert torch.allclose(se3_log(T), xi, atol=1e-9)
    assert torch.allclose(se3_exp(se3_log(T)), T, atol=1e-12)


def test_se3_exp_log_batched_float32_and_gradients_at_zero():
    xi = torch.randn(5, 7, 6) * 0.5
    assert se3_exp(xi).shape == (5, 7, 4, 4)
    assert torch.allclose(se3_log(se3_exp(xi)), xi, atol=1e-5)
    assert torch.equal(se3_exp(torch.zeros(6)), torch.eye(4))
    z = torch.zeros(3, 6, dtype=torch.float64, requires_grad=True)
    se3_log(se3_exp(z)).sum().backward()
    assert torch.allclose(z.grad, torch.ones_like(z))  # the identity map's derivative


def test_se3_exp_composes_one_parameter_subgroup():
    xi = torch.tensor([0.3, -0.2, 0.5, 1.0, 2.0, -0.5], dtype=torch.float64)
    assert torch.allclose(se3_exp(xi) @ se3_exp(xi), se3_exp(2 * xi), atol=1e-12)


# --------------------------------------------------------------------------- network


def test_output_shapes_rounds_and_dtype():
    b = batch()
    net = small_net()
    outs = net(b, return_all=True)
    assert len(outs) == 3 and all(o.shape == (b.num_nodes, 4, 4) for o in outs)
    assert outs[-1].dtype == torch.float64
    assert torch.equal(net(b), outs[-1])
    R = outs[-1][:, :3, :3]
    assert torch.allclose(R @ R.mT, torch.eye(3, dtype=torch.float64).expand_as(R), atol=1e-9)


def test_spectral_init_is_eig_se3_unit():
    b = batch()
    init = small_net().initial_poses(b)
    ref = get_backend("eig_se3", robust=False, scale="unit").solve(b, b.edge_pose.double())
    assert torch.allclose(init, ref)
    eye = small_net(init="identity").initial_poses(b)
    assert torch.equal(eye, torch.eye(4, dtype=torch.float64).expand(b.num_nodes, 4, 4))


@pytest.mark.parametrize("use_confidence", [False, True])
def test_gauge_equivariance(use_confidence):
    """Right-multiplying every initial pose by one G right-multiplies every output by G."""
    b = batch()
    net = small_net(use_confidence=use_confidence)
    init = net.initial_poses(b)
    conf = torch.rand(b.num_edges, dtype=torch.float64) if use_confidence else None
    G = random_se3(1)
    out = net(b, confidence=conf, init_pose=init)
    out_g = net(b, confidence=conf, init_pose=init @ G)
    assert torch.allclose(out_g, out @ G, atol=1e-9)
    assert (out - init).abs().max() > 1e-6  # it did move


def test_node_permutation_equivariance():
    graph = graphs(1, 7)[0]
    net = small_net()
    init = net.initial_poses(graph)
    perm = torch.randperm(graph.num_nodes, generator=torch.Generator().manual_seed(3))
    inv = torch.argsort(perm)  # new index of each old node
    out = net.propagate(graph.edge_index, graph.edge_pose, init)[0][-1]
    out_p = net.propagate(inv[graph.edge_index], graph.edge_pose, init[perm])[0][-1]
    assert torch.allclose(out_p, out[perm], atol=1e-9)


def test_edge_storage_direction_does_not_matter():
    """Storing edge i -> j as j -> i with the inverse pose gives the same poses."""
    from posernet.geometry import invert_pose_vec

    graph = graphs(1, 7)[0]
    net = small_net()
    init = net.initial_poses(graph)
    flip = torch.arange(graph.num_edges) % 2 == 0
    ei = torch.where(flip, graph.edge_index.flip(0), graph.edge_index)
    ep = graph.edge_pose.double()
    ep = torch.where(flip[:, None], invert_pose_vec(ep), ep)
    a = net.propagate(graph.edge_index, graph.edge_pose, init)[0][-1]
    b = net.propagate(ei, ep, init)[0][-1]
    assert torch.allclose(a, b, atol=1e-9)


def test_isolated_node_keeps_its_initial_pose_and_components_stay_apart():
    # two components {0, 1, 2} and {3, 4}, node 5 isolated
    gt = make_se3(axis_angle_to_rotation_matrix(torch.randn(6, 3, dtype=torch.float64)),
                  torch.randn(6, 3, dtype=torch.float64))
    ei = torch.tensor([[0, 1, 0, 3], [1, 2, 2, 4]])
    ep = matrix_to_pose_vec(relative_pose(gt[ei[0]], gt[ei[1]]))
    ep[:, 4:] += 0.1  # inconsistent: there is something to move
    net = small_net(init="identity")
    init = random_se3(5).expand(6, 4, 4).clone()
    init[3:5] = init[3:5] @ random_se3(6)
    out = net.propagate(ei, ep, init)[0][-1]
    assert torch.equal(out[5], init[5])
    # each component has its own gauge: moving one's initial poses leaves the other alone
    init2 = init.clone()
    init2[3:5] = init2[3:5] @ random_se3(7)
    out2 = net.propagate(ei, ep, init2)[0][-1]
    assert torch.allclose(out2[:3], out[:3], atol=1e-12)


def test_bad_network_arguments():
    with pytest.raises(ValueError, match="init="):
        LearnedSyncNet(init="random")
    with pytest.raises(ValueError, match="rounds must be an integer"):
        LearnedSyncNet(rounds=0)
    with pytest.raises(ValueError, match="step_scale"):
        LearnedSyncNet(step_scale=0)


# --------------------------------------------------------------------------- loss


def test_all_pairs():
    ptr = torch.tensor([0, 2, 5, 5, 9])
    i, j, g = all_pairs(ptr)
    want = [(a, b) for lo, hi in ((0, 2), (2, 5), (5, 9)) for a in range(lo, hi)
            for b in range(a + 1, hi)]
    assert sorted(zip(i.tolist(), j.tolist(), strict=True)) == want
    assert torch.equal(g, torch.tensor([0] + [1] * 3 + [3] * 6))


def test_loss_is_zero_at_ground_truth_up_to_a_similarity():
    b = batch()
    gt = b.pose_gt.double()
    G = random_se3(2)
    scaled = gt @ G
    scaled[:, :3, 3] *= 3.7  # a global scale: the translation term only sees directions
    out = learned_sync_loss([gt, scaled], b.pose_gt, b.ptr)
    assert float(out.loss) < 1e-6 and out.per_round.shape == (2,)
    init = small_net().initial_poses(b)
    bad = learned_sync_loss(init, b.pose_gt, b.ptr)
    assert float(bad.rotation) > 1e-3 and float(bad.translation) > 1e-3


def test_loss_weights_later_rounds_more():
    b = batch()
    gt = b.pose_gt.double()
    noisy = small_net(init="identity").initial_poses(b)  # all at the identity: bad
    early_bad = learned_sync_loss([noisy, gt], b.pose_gt, b.ptr, gamma=0.5)
    late_bad = learned_sync_loss([gt, noisy], b.pose_gt, b.ptr, gamma=0.5)
    assert float(early_bad.loss) < float(late_bad.loss)
    assert torch.allclose(early_bad.per_round.flip(0), late_bad.per_round)


def test_gradient_reaches_every_parameter():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=["model=learned_sync",
                                                      "model.net.use_confidence=true"])
    torch.manual_seed(0)
    module = instantiate(cfg.model)
    b = batch()
    outs = module(b, return_all=True)
    learned_sync_loss(outs, b.pose_gt, b.ptr).loss.backward()
    for name, p in module.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_training_lowers_the_validation_loss():
    """A few dozen Adam steps on tiny graphs (identity start: much to learn)."""
    train, val = batch(16, 6, seed=1), batch(8, 6, seed=2)
    torch.manual_seed(0)
    net = LearnedSyncNet(hidden=16, rounds=4, init="identity")
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)

    def val_loss() -> float:
        with torch.no_grad():
            return float(learned_sync_loss(net(val, return_all=True), val.pose_gt,
                                           val.ptr).loss)

    before = val_loss()
    for _ in range(40):
        opt.zero_grad()
        learned_sync_loss(net(train, return_all=True), train.pose_gt, train.ptr).loss.backward()
        opt.step()
    after = val_loss()
    assert after < 0.8 * before, (before, after)


# --------------------------------------------------------------------------- Lightning module


def test_module_sections_and_plain_hyper_parameters(tmp_path):
    from posernet.lit.learned_sync_module import SECTIONS, LearnedSyncModule, sync_module_hparams

    m = LearnedSyncModule(net={"hidden": 8, "rounds": 2}, loss={"gamma": 0.5})
    assert m.CHECKPOINT_TAG == LEARNED_SYNC_TAG == "posernet.LearnedSyncModule"
    assert set(m.hparams) == set(SECTIONS)
    assert m.hparams.net["hidden"] == 8 and m.hparams.net["init"] == "spectral"
    assert m.hparams.input["refiner_ckpt"] is None
    path = save_module_checkpoint(m, tmp_path / "m.ckpt")
    ckpt = torch.load(path, weights_only=True)  # plain values only
    assert LearnedSyncModule(**ckpt["hyper_parameters"]).hparams == m.hparams
    assert all(k.startswith("net.") for k in ckpt["state_dict"])
    with pytest.raises(TypeError, match=r"unknown net hyper-parameter\(s\) \['depth'\]"):
        LearnedSyncModule(net={"depth": 2})
    with pytest.raises(TypeError, match="unknown LearnedSyncModule section"):
        sync_module_hparams(model={})


def test_module_step_logs_losses_and_absolute_errors():
    from posernet.lit.learned_sync_module import LearnedSyncModule

    m = LearnedSyncModule(net={"hidden": 8, "rounds": 2})
    logged = {}
    m.log = lambda name, value, **kw: logged.__setitem__(name, float(value))  # type: ignore
    b = batch()
    loss = m.validation_step(b, 0)
    assert torch.isfinite(loss)
    m.on_validation_epoch_end()
    for k in ("val/loss", "val/loss_rot", "val/loss_tdir", "val/loss_init", "val/abs_rot_err_deg",
              "val/abs_pos_err", "val/abs_rot_err_deg_init", "val/abs_pos_err_init"):
        assert k in logged, k
    assert logged["val/abs_rot_err_deg_init"] >= 0


def test_refined_input_uses_a_frozen_posernet_outside_the_checkpoint():
    from posernet.lit.learned_sync_module import LearnedSyncModule

    shipped = str(default_checkpoint())
    m = LearnedSyncModule(net={"hidden": 8, "rounds": 2}, input={"refiner_ckpt": shipped})
    b = batch()
    refined = m.input_poses(b)
    assert refined.shape == b.edge_pose.shape and not refined.requires_grad
    assert not torch.allclose(refined, b.edge_pose)
    assert all(k.startswith("net.") for k in m.state_dict())  # the refiner is not saved
    assert all(p.requires_grad is False for p in m.refiner.parameters())
    bad = LearnedSyncModule(input={"refiner_ckpt": "/nonexistent/posernet.ckpt"})
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        bad.setup("fit")


# --------------------------------------------------------------------------- backend


@pytest.fixture(scope="module")
def sync_ckpt(tmp_path_factory) -> Path:
    from posernet.lit.learned_sync_module import LearnedSyncModule

    torch.manual_seed(0)
    m = LearnedSyncModule(net={"hidden": 8, "rounds": 3})
    return save_module_checkpoint(m, tmp_path_factory.mktemp("ls") / "learned.ckpt")


def test_backend_solves_a_batch_like_the_network(sync_ckpt):
    from posernet.lit.learned_sync_module import LearnedSyncModule

    assert "learned" in available_backends()
    be = get_backend("learned", ckpt_path=str(sync_ckpt))
    assert isinstance(be, LearnedSync) and be.name == "learned" and not be.metric
    b = batch()
    res = be.solve_with_info(b)
    assert res.poses.shape == (b.num_nodes, 4, 4) and res.poses.dtype == b.edge_pose.dtype
    assert res.solved.all() and res.scale == "unit" and res.metric is False
    assert torch.equal(res.iterations, torch.full((b.num_graphs,), 3))
    assert res.edge_weight.shape == (b.num_edges,)
    assert ((res.edge_weight > 0) & (res.edge_weight < 1)).all()
    ckpt = torch.load(sync_ckpt, weights_only=True)
    m = LearnedSyncModule(**ckpt["hyper_parameters"])
    m.load_state_dict(ckpt["state_dict"])
    with torch.no_grad():
        ref = m(b)
    assert torch.allclose(res.poses.double(), ref, atol=1e-5)
    d = be.describe()
    assert d["backend"] == "learned" and d["rounds"] == 3 and d["trained_on"] == "raw input"
    # loaded once: a second backend on the same file shares the cached network
    assert get_backend("learned", ckpt_path=str(sync_ckpt)).network is be.network


def test_backend_isolated_node_and_components(sync_ckpt):
    g = graphs(1, 6)[0]
    keep = (g.edge_index != 5).all(0)  # node 5 loses its edges
    g.edge_index, g.edge_pose = g.edge_index[:, keep], g.edge_pose[keep]
    g.edge_pose_gt = g.edge_pose_gt[keep]
    g.pair_edge = torch.zeros(0, dtype=torch.long)
    g.pair_src = g.pair_dst = torch.zeros(0, dtype=torch.long)
    res = get_backend("learned", ckpt_path=str(sync_ckpt)).solve_with_info(g)
    assert res.solved.tolist() == [True] * 5 + [False]
    assert torch.equal(res.poses[5], torch.eye(4))
    assert res.component[5] != res.component[0]
    with pytest.raises(ValueError, match="not connected"):
        get_backend("learned", ckpt_path=str(sync_ckpt), disconnected="error").solve(g)


def test_backend_config_file(sync_ckpt):
    cfg = OmegaConf.load(Path(CONFIG_DIR) / "sync" / "learned.yaml")
    assert cfg.name == "learned" and OmegaConf.is_missing(cfg, "ckpt_path")
    cfg.ckpt_path = str(sync_ckpt)
    be = backend_from_config(cfg)
    assert isinstance(be, LearnedSync)
    for k, v in cfg.items():
        if k not in ("name", "_target_"):
            assert getattr(be.options, k) == v


def test_backend_bad_inputs_are_clear(sync_ckpt, tmp_path):
    with pytest.raises(ValueError, match="needs ckpt_path="):
        get_backend("learned")
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        get_backend("learned", ckpt_path=str(tmp_path / "nope.ckpt"))
    with pytest.raises(CheckpointError, match="this is a PoserNet checkpoint"):
        get_backend("learned", ckpt_path=str(default_checkpoint()))
    with pytest.raises(ValueError, match="scale='given' is not supported"):
        get_backend("learned", ckpt_path=str(sync_ckpt), scale="given")
    with pytest.raises(ValueError, match="device: .tpu. is not one of cpu, cuda, cuda:N, auto"):
        get_backend("learned", ckpt_path=str(sync_ckpt), device="tpu")
    broken = tmp_path / "broken.ckpt"
    ckpt = torch.load(sync_ckpt, weights_only=True)
    ckpt["hyper_parameters"]["net"]["hidden"] = 9  # weights no longer fit
    torch.save(ckpt, broken)
    with pytest.raises(CheckpointError, match="weights do not fit"):
        get_backend("learned", ckpt_path=str(broken))


def test_config_validation_reports_one_line(sync_ckpt, tmp_path):
    from hydra import compose, initialize_config_dir

    from posernet.cli.validation import ConfigValueError, check_config

    def cfg(*o: str):
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            return compose(config_name="eval", overrides=[
                "ckpt_path=x.ckpt", f"out_dir={tmp_path}", "sync=learned", *o])

    with pytest.raises(ConfigValueError, match=r"^sync.ckpt_path: a value is required"):
        check_config(cfg(), "eval")
    with pytest.raises(ConfigValueError, match=r"^sync=learned: .*PoserNet checkpoint") as e:
        check_config(cfg(f"sync.ckpt_path={default_checkpoint()}"), "eval")
    assert "\n" not in str(e.value)
    with pytest.raises(ConfigValueError, match=r"^sync.device: 'gpu' is not one of"):
        check_config(cfg(f"sync.ckpt_path={sync_ckpt}", "sync.device=gpu"), "eval")
    check_config(cfg(f"sync.ckpt_path={sync_ckpt}"), "eval")


def test_importing_posernet_sync_does_not_import_the_learned_backend():
    code = ("import sys, posernet.sync as s; assert 'posernet.sync.learned' not in sys.modules; "
            "assert s.LearnedSync.__module__ == 'posernet.sync.learned'")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]


# --------------------------------------------------------------------------- CLI round trip


@pytest.mark.slow
def test_train_cli_then_backend_then_eval(tmp_path):
    """``posernet-train model=learned_sync`` (1 epoch), the checkpoint as ``sync=learned``,
    then ``posernet-eval ... sync=learned sync.ckpt_path=...``."""
    from posernet.testing import write_random_dataset

    data = write_random_dataset(tmp_path / "data", {"train": 4, "val": 2, "test": 2})
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "0"}
    run = tmp_path / "run"
    res = subprocess.run(
        [sys.executable, "-m", "posernet.cli.train", "model=learned_sync", f"data.root={data}",
         "trainer.max_epochs=1", "data.batch_size=4", "model.net.hidden=16",
         "model.net.rounds=2", f"hydra.run.dir={run}", "num_threads=1",
         "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"],
        capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    ckpt = run / "checkpoints" / "best.ckpt"
    assert ckpt.is_file() and "LearnedSyncModule" in res.stdout
    metrics = (run / "logs" / "metrics.csv").read_text().splitlines()[0]
    assert "val/abs_rot_err_deg" in metrics and "val/abs_rot_err_deg_init" in metrics

    be = LearnedSync(ckpt_path=str(ckpt))
    b = batch()
    assert be.solve(b).shape == (b.num_nodes, 4, 4)

    out = tmp_path / "eval"
    res = subprocess.run(
        [sys.executable, "-m", "posernet.cli.evaluate", f"ckpt_path={default_checkpoint()}",
         f"data.root={data}", "sync=learned", f"sync.ckpt_path={ckpt}",
         f"hydra.run.dir={out}", "num_threads=1"],
        capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "learned" in res.stdout

    # a PoserNet checkpoint given as sync.ckpt_path: one clear line, no traceback
    res = subprocess.run(
        [sys.executable, "-m", "posernet.cli.evaluate", f"ckpt_path={default_checkpoint()}",
         f"data.root={data}", "sync=learned", f"sync.ckpt_path={default_checkpoint()}",
         f"hydra.run.dir={tmp_path / 'bad'}"],
        capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert "PoserNet checkpoint" in res.stderr
