"""Input-adaptive refinement: cycle features, gate / confidence head, its loss, the
initial-pose mixture, confidence-weighted motion averaging, the guard and refined.json."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

from posernet import GraphBatch, PoserNet, save_graphs
from posernet.checkpoints import CHECKPOINT_TAG
from posernet.geometry import rotation_error_deg
from posernet.lit.posernet_module import SECTIONS, PoserNetModule, module_hparams
from posernet.nn.adaptive import (
    CYCLE_DIM,
    HEAD_IN_DIM,
    EdgeHead,
    blend_poses,
    cycle_features,
    edge_errors,
    heteroscedastic_nll,
)
from posernet.testing import random_view_graph

ADAPTIVE = {"residual": True, "unit_output": True, "edge_hidden": 8, "gate": True,
            "confidence": True, "cycle_feature": True}


def graphs(n: int, seed: int = 0, rot_noise_deg: float = 10.0) -> list:
    gen = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n):
        g = random_view_graph(num_nodes=6 + i % 3, extra_edges=6, generator=gen,
                              rot_noise_deg=rot_noise_deg, name=f"a{i}")
        g.estimates = {"kp": g.edge_pose, "bb": g.edge_pose}
        g.meta["scene"] = "heads"
        out.append(g)
    return out


def gt_input(g):
    gt = g.edge_pose_gt.clone()
    gt[:, 4:] = torch.nn.functional.normalize(gt[:, 4:], dim=-1)
    return dataclasses.replace(g, edge_pose=gt.to(g.edge_pose.dtype))


# --------------------------------------------------------------------------- network


def test_adaptive_options_default_off_and_old_parameters_unchanged() -> None:
    for k in ("gate", "confidence", "cycle_feature"):
        assert SECTIONS["net"][k] is False
    torch.manual_seed(0)
    a = PoserNet()
    assert a.head is None and not a.adaptive
    names = [n for n, _ in a.named_parameters()]
    assert not any(n.startswith("head.") for n in names)
    hp = module_hparams()
    assert {k: hp["loss"][k] for k in ("alpha", "raw", "confidence", "correction", "harm")} == {
        "alpha": 0.1, "raw": 0.0, "confidence": 0.0, "correction": 0.0, "harm": 0.0}
    with pytest.raises(ValueError, match="edge_hidden >= 3"):
        PoserNet(cycle_feature=True)


def test_gate_and_confidence_shapes_and_gradients() -> None:
    torch.manual_seed(0)
    model = PoserNet(**ADAPTIVE)
    batch = GraphBatch.from_graphs(graphs(3))
    out = model(batch, return_extras=True)
    E = batch.num_edges
    assert out.pose.shape == (E, 7) and out.raw.shape == (E, 7)
    assert out.gate.shape == (E, 2) and bool(((out.gate > 0) & (out.gate < 1)).all())
    assert out.sigma.shape == (E, 4) and bool((out.sigma > 0).all())
    torch.testing.assert_close(model(batch), out.pose)  # plain forward = final pose
    loss = (out.pose.sum() + out.sigma.log().sum())
    loss.backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_gate_zero_returns_the_input_and_one_the_prediction() -> None:
    g = graphs(1)[0]
    pred = torch.nn.functional.normalize(torch.randn(g.num_edges, 7), dim=-1)
    keep = blend_poses(g.edge_pose, pred, torch.zeros(g.num_edges))
    assert float(rotation_error_deg(keep[:, :4], g.edge_pose[:, :4]).max()) < 1e-3
    torch.testing.assert_close(keep[:, 4:], torch.nn.functional.normalize(g.edge_pose[:, 4:],
                                                                          dim=-1))
    take = blend_poses(g.edge_pose, pred, torch.ones(g.num_edges))
    assert float(rotation_error_deg(take[:, :4], pred[:, :4]).max()) < 1e-3


def test_cycle_features_zero_on_consistent_poses_and_flag_a_corrupted_edge() -> None:
    g = gt_input(graphs(1)[0])
    f = cycle_features(g.edge_index, g.edge_pose, g.num_nodes)
    assert f.shape == (g.num_edges, CYCLE_DIM)
    assert float(f[:, :2].abs().max()) < 1e-3 and bool((f[:, 2] == 1).any())
    bad = g.edge_pose.clone()
    on_tri = int(f[:, 2].nonzero()[0, 0])
    from posernet.geometry import quaternion_multiply

    quarter = torch.tensor([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])
    bad[on_tri, :4] = quaternion_multiply(quarter, bad[on_tri, :4])  # a 90 degree error
    fb = cycle_features(g.edge_index, bad, g.num_nodes)
    # every triangle through the edge sees exactly its error (the other edges are exact)
    assert fb[on_tri, 0].item() == pytest.approx(math.pi / 2, abs=1e-3)
    assert fb[on_tri, 1].item() == pytest.approx(math.pi / 2, abs=1e-3)
    # flipping the stored direction of every edge (inverse poses) gives the same features
    from posernet.geometry import invert_pose_vec

    flipped = cycle_features(g.edge_index.flip(0), invert_pose_vec(bad), g.num_nodes)
    torch.testing.assert_close(flipped, fb, atol=1e-5, rtol=0)


def test_heteroscedastic_loss_is_minimal_at_the_true_error() -> None:
    err = torch.tensor([0.01, 0.2, 1.5])
    s = torch.logspace(-3, 1, 4001)[:, None]
    nll = heteroscedastic_nll(err[None], s)
    best = s[nll.argmin(dim=0), 0]
    torch.testing.assert_close(best, err, rtol=3e-3, atol=0)
    # and the head's parametrisation reaches it by gradient descent
    head = EdgeHead(gate=False, confidence=True)
    feats = torch.randn(64, HEAD_IN_DIM)
    target = torch.full((64, 4), 0.3)
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    for _ in range(300):
        opt.zero_grad()
        heteroscedastic_nll(target, head(feats)[1]).mean().backward()
        opt.step()
    with torch.no_grad():
        assert float((head(feats)[1] - 0.3).abs().max()) < 0.03


def test_module_trains_every_loss_term() -> None:
    torch.manual_seed(0)
    module = PoserNetModule(net=ADAPTIVE, loss={"raw": 0.5, "confidence": 0.1,
                                                "correction": 0.1, "harm": 1.0})
    batch = GraphBatch.from_graphs(graphs(2))
    module.log = lambda *a, **k: None  # type: ignore[method-assign]
    loss = module._step(batch, "train")
    loss.backward()
    assert all(p.grad is not None for p in module.parameters())


# --------------------------------------------------------------------------- mixture


def test_mixture_draws_are_valid_reproducible_and_cover_the_sources() -> None:
    from posernet.data.mixture import MixedInitDataset

    gs = graphs(4)
    gt_only = MixedInitDataset(gs, {"gt": 1.0}, gt_noise_deg=0.0, seed=1)
    g0 = gt_only[0]
    err = rotation_error_deg(g0.edge_pose[:, :4], gs[0].edge_pose_gt[:, :4])
    assert float(err.max()) < 1e-2
    mixed_a = MixedInitDataset(gs, {"kp": 1, "gt": 1, "recorrupt": 1}, seed=3)
    mixed_b = MixedInitDataset(gs, {"kp": 1, "gt": 1, "recorrupt": 1}, seed=3)
    first, again = mixed_a[1].edge_pose, mixed_b[1].edge_pose
    torch.testing.assert_close(first, again)  # same seed, same visit
    assert not torch.equal(mixed_a[1].edge_pose, first)  # the next epoch draws anew
    assert torch.allclose(first[:, 4:].norm(dim=-1), torch.ones(len(first)), atol=1e-5)
    with pytest.raises(ValueError, match="unknown source"):
        MixedInitDataset(gs, {"sift": 1.0})
    no_bb = [dataclasses.replace(g, estimates={"kp": g.edge_pose}) for g in gs]
    with pytest.raises(ValueError, match=r"\['bb'\]"):
        MixedInitDataset(no_bb, {"bb": 1.0})


# --------------------------------------------------------------------------- motion averaging


def test_irls_with_uniform_initial_weights_equals_the_published_irls() -> None:
    from posernet.sync import get_backend

    gs = graphs(4)
    batch = GraphBatch.from_graphs(gs)
    for name in ("eig_se3", "rotation_translation"):
        backend = get_backend(name, solver="dense")
        ref = backend.solve_with_info(batch, batch.edge_pose)
        for mode in ("start", "prior"):
            b = get_backend(name, solver="dense", weight_mode=mode)
            for w in (torch.ones(batch.num_edges), torch.full((batch.num_edges, 2), 3.0)):
                got = b.solve_with_info(batch, batch.edge_pose, edge_weight=w)
                assert torch.equal(got.poses, ref.poses), (name, mode)
                assert torch.equal(got.edge_weight, ref.edge_weight)
    with pytest.raises(ValueError, match="edge_weight"):
        get_backend("eig_se3").solve(batch, batch.edge_pose, edge_weight=torch.zeros(3))


def test_confidence_weights_down_weight_a_corrupted_edge() -> None:
    from posernet.metrics import absolute_pose_errors
    from posernet.sync import get_backend

    g = gt_input(graphs(1, seed=4)[0])
    pose = g.edge_pose.clone()
    pose[0, :4] = torch.tensor([0.0, 0.0, 1.0, 0.0])
    w = torch.ones(g.num_edges)
    w[0] = 1e-3
    backend = get_backend("eig_se3", robust=False)  # no IRLS: only the weights can help
    uni = backend.solve(g, pose)
    wtd = backend.solve(g, pose, edge_weight=w)
    nb = torch.zeros(g.num_nodes, dtype=torch.long)
    e_uni = absolute_pose_errors(uni.double(), g.pose_gt.double(), nb, 1)[0]
    e_wtd = absolute_pose_errors(wtd.double(), g.pose_gt.double(), nb, 1)[0]
    assert float(e_wtd) < 0.5 * float(e_uni)


# --------------------------------------------------------------------------- guard


def test_guard_warns_on_shifted_inputs_and_not_on_in_distribution_ones() -> None:
    from posernet.guard import check_inputs, input_statistics, warning_line

    train = graphs(40, seed=1)
    stats = input_statistics(train)
    assert check_inputs(stats, graphs(10, seed=2)) == []
    shifted = [dataclasses.replace(g, node_attr=g.node_attr + torch.tensor([0, 0, 1.5, 0]))
               for g in graphs(10, seed=2)]
    reasons = check_inputs(stats, shifted)
    assert len(reasons) == 1 and reasons[0].startswith("node_focal")
    # in the user's units (pixels), not the network's normalised ones
    assert "median 1462 outside the training range [585, 585]" in reasons[0]
    worse = graphs(10, seed=2, rot_noise_deg=120.0)
    assert any(r.startswith("cycle_deg") for r in check_inputs(stats, worse))
    better = [gt_input(g) for g in graphs(10, seed=2)]  # better inputs are no reason to warn
    assert not any(r.startswith("cycle_deg") for r in check_inputs(stats, better))
    line = warning_line(reasons, 2.0, 5.0)
    assert line is not None and "\n" not in line and "node_focal" in line
    assert "less cycle-consistent" in line
    assert warning_line([], 2.0, 2.1) is None


def _confident_model(keep: bool, gate: float = 3.0) -> PoserNet:
    """An adaptive net whose error head says the input is better (``keep``) or worse; its
    gates are ``sigmoid(gate)`` (an untrained network: its prediction is noise)."""
    torch.manual_seed(0)
    model = PoserNet(**ADAPTIVE).eval()
    last = model.head.mlp.net[-1]
    with torch.no_grad():
        last.weight.zero_()
        # outputs: rotation / direction gate logits, log-scales of rot_out, tdir_out, rot_in,
        # tdir_in
        last.bias.copy_(torch.tensor([gate, gate, 0.0, 0.0, -2.0, -2.0] if keep
                                     else [gate, gate, -2.0, -2.0, 0.0, 0.0]))
    return model


def test_guard_keeps_the_input_where_the_confidence_says_so() -> None:
    from posernet.refinement import refine_graphs

    gs = graphs(3)
    kept = refine_graphs(_confident_model(True), gs, progress=False, guard=True)
    for k, g in enumerate(gs):
        assert bool(kept.kept_input[k].all())
        err = rotation_error_deg(kept.edge_pose["refined"][k][:, :4], g.edge_pose[:, :4])
        assert float(err.max()) < 1e-2
    # confidence says "refine", and the (nearly closed) gates keep the graph as consistent
    free = refine_graphs(_confident_model(False, gate=-8.0), gs, progress=False, guard=True)
    assert not any(bool(m.any()) for m in free.kept_input)
    plain = refine_graphs(_confident_model(False, gate=-8.0), gs, progress=False)
    for a, b in zip(free.edge_pose["refined"], plain.edge_pose["refined"], strict=True):
        torch.testing.assert_close(a, b)
    # an untrained prediction makes exact input graphs less cycle-consistent: kept whole
    exact = [gt_input(g) for g in gs]
    noisy = refine_graphs(_confident_model(False), exact, progress=False, guard=True)
    assert all(bool(m.all()) for m in noisy.kept_input)
    for k, g in enumerate(exact):
        err = rotation_error_deg(noisy.edge_pose["refined"][k][:, :4], g.edge_pose[:, :4])
        assert float(err.max()) < 1e-2
    with pytest.raises(ValueError, match="confidence head"):
        refine_graphs(PoserNet(), gs, progress=False, guard=True)


def _write_checkpoint(path: Path, model: PoserNet, stats: dict | None) -> Path:
    module = PoserNetModule(net=ADAPTIVE)
    module.model = model
    ckpt = {"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
            "posernet": {"tag": CHECKPOINT_TAG, **({"input_stats": stats} if stats else {})}}
    torch.save(ckpt, path)
    return path


def test_refine_writes_confidence_and_the_guard_warning(tmp_path: Path, capsys) -> None:
    from hydra import compose, initialize_config_dir

    from posernet.cli import CONFIG_DIR
    from posernet.cli.refine import refine
    from posernet.guard import input_statistics

    stats = input_statistics(graphs(30, seed=1))
    ckpt = _write_checkpoint(tmp_path / "a.ckpt", _confident_model(True), stats)
    shifted = [dataclasses.replace(g, node_attr=g.node_attr + torch.tensor([0, 0, 1.5, 0]))
               for g in graphs(3)]
    src = save_graphs(tmp_path / "g.pt", shifted)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="refine", overrides=[
            f"input={src}", f"ckpt_path={ckpt}", f"out_dir={tmp_path}", "guard=true",
            "estimate=null", "hydra.runtime.output_dir=."], return_hydra_config=False)
    refine(cfg)
    err = capsys.readouterr().err
    assert sum("WARNING" in ln for ln in err.splitlines()) == 1 and "node_focal" in err
    rec = json.loads((tmp_path / "refined.json").read_text())
    edge = rec["graphs"][0]["edges"][0]
    assert set(edge["confidence"]) == {"rot_err_deg", "tdir_err_deg", "input_rot_err_deg",
                                       "input_tdir_err_deg"}
    assert all(math.isfinite(v) and v > 0 for v in edge["confidence"].values())
    assert edge["kept_input"] == {"rotation": True, "direction": True}
    assert rec["guard"] is True and rec["confidence_weights"] is True
    assert rec["input_check"]["warning"] is not None
    # the absolute table says the input's averaging was weighted by the model too
    from posernet.evaluation import evaluate_result, result_tables
    from posernet.nn import PoserNet
    from posernet.refinement import refine_graphs
    from posernet.sync import get_backend

    model = PoserNet.from_checkpoint(ckpt)
    res = refine_graphs(model, shifted, backend=get_backend("eig_se3"), weighted=True)
    table = result_tables(evaluate_result(res), backend=res.backend)["absolute"]
    assert "weighted by PoserNet's confidence" in table.to_markdown()
    res = refine_graphs(model, shifted, backend=get_backend("eig_se3"), weighted=False)
    table = result_tables(evaluate_result(res), backend=res.backend)["absolute"]
    assert "weighted" not in table.to_markdown()


def capture_logs(module: PoserNetModule) -> dict[str, float]:
    """Route ``module.log`` into the returned dict (name -> last value)."""
    logged: dict[str, float] = {}

    def log(name: str, value: torch.Tensor, **_: object) -> None:
        logged[name] = float(torch.as_tensor(value).detach())

    module.log = log  # type: ignore[method-assign]
    return logged


def test_harm_term_is_the_excess_error_over_the_input_and_trains_the_gate_shut() -> None:
    torch.manual_seed(0)
    exact = graphs(3, rot_noise_deg=0.0)  # ground-truth input: any change does harm
    for g in exact:
        g.edge_pose = g.edge_pose_gt.clone()
        g.edge_pose[:, 4:] = g.edge_pose[:, 4:] / g.edge_pose[:, 4:].norm(dim=-1, keepdim=True)
    batch = GraphBatch.from_graphs(exact)
    module = PoserNetModule(net=ADAPTIVE, loss={"harm": 1.0})
    logged = capture_logs(module)
    module._step(batch, "train")
    with torch.no_grad():
        out = module(batch)
        expected = edge_errors(out, batch.edge_pose_gt).sum(-1).mean()
    assert float(expected) > 1e-3
    assert logged["train/loss_harm"] == pytest.approx(float(expected), rel=1e-4)
    opt = torch.optim.Adam(module.parameters(), lr=1e-2)
    for _ in range(60):
        opt.zero_grad()
        module._step(batch, "train").backward()
        opt.step()
    module._step(batch, "train")
    assert logged["train/loss_harm"] < 0.3 * float(expected)


def _harm_gradient(loss: dict, batch: GraphBatch, state: dict) -> dict[str, torch.Tensor]:
    """Gradient of the hinge alone: the step's gradient with it minus the one without."""
    grads = []
    for lh in (loss, {**loss, "harm": 0.0}):
        module = PoserNetModule(net=ADAPTIVE, loss=lh)
        module.load_state_dict(state)
        module.log = lambda *a, **k: None  # type: ignore[method-assign]
        module._step(batch, "train").backward()
        grads.append({n: p.grad.clone() for n, p in module.named_parameters()
                      if p.grad is not None})
    return {n: grads[0][n] - grads[1].get(n, torch.zeros_like(grads[0][n])) for n in grads[0]}


def test_relative_harm_term_weighs_harm_by_the_input_error_and_trains_the_prediction() -> None:
    torch.manual_seed(0)
    batch = GraphBatch.from_graphs(graphs(3, rot_noise_deg=5.0))
    loss = {"harm": 1.0, "harm_scale": 0.01}
    module = PoserNetModule(net=ADAPTIVE, loss=loss)
    logged = capture_logs(module)
    module._step(batch, "train")
    with torch.no_grad():
        e_in = edge_errors(batch.edge_pose, batch.edge_pose_gt)
        e_out = edge_errors(module(batch), batch.edge_pose_gt)
        expected = ((e_out - e_in).clamp_min(0.0) / (e_in + 0.01)).sum(-1).mean()
    assert float(expected) > 1e-3
    assert logged["train/loss_harm"] == pytest.approx(float(expected), rel=1e-4)
    # relative: the hinge reaches the message-passing layers (the prediction); absolute (the
    # default scale 0) with a gate: only the gate / confidence head
    state = module.state_dict()
    rel = _harm_gradient(loss, batch, state)
    absolute = _harm_gradient({"harm": 1.0}, batch, state)
    mp = [n for n in rel if not n.startswith("model.head.")]
    assert mp and max(float(rel[n].abs().max()) for n in mp) > 1e-6
    assert max(float(absolute[n].abs().max()) for n in mp) < 1e-9


def test_load_refiner_reads_the_checkpoint_once_for_the_model_and_its_guard(monkeypatch) -> None:
    """The network and the guard's training statistics come from one reading of the file;
    keeping inputs needs a confidence head."""
    import posernet.checkpoints as ck
    from posernet.checkpoints import default_checkpoint, resolve_checkpoint
    from posernet.guard import Guard, load_refiner

    reads = []
    real = ck.read_checkpoint

    def counting(path, *a, **k):
        reads.append(path)
        return real(path, *a, **k)

    monkeypatch.setattr(ck, "read_checkpoint", counting)
    model, guard = load_refiner(default_checkpoint(), keep_inputs=True)
    assert len(reads) == 1 and not model.training
    assert isinstance(guard, Guard) and guard.keep_inputs and guard.stats is not None
    old = resolve_checkpoint("shipped:posernet_synthetic_kp_v1.ckpt")  # no confidence head
    with pytest.raises(ValueError, match="guard=true needs a checkpoint with a confidence head"):
        load_refiner(old, keep_inputs=True)
    _, plain = load_refiner(old)
    assert not plain.keep_inputs
