"""The network, motion averaging, refinement, training and the commands on CUDA, each against
the CPU result (skipped without a GPU).

CI has no GPU; these run wherever one is present (``pytest tests/test_cuda.py``). Training
uses Lightning's ``deterministic=True`` as the experiment runner does, so every op on the
training path must have a deterministic CUDA kernel. ``tests/test_cuda_ops_on_cpu.py`` catches
the two kinds of CUDA-only failure (bool scatter reductions, deterministic-mode errors) on the
CPU.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from device_cases import (
    ADAPTIVE,
    backend_variants,
    net_graphs,
    save_learned_sync,
    sync_graphs,
    translation_weights,
)

from posernet import GraphBatch, PoserNet, save_graphs
from posernet.sync import available_backends, get_backend
from posernet.testing import random_view_graph

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

BIN = Path(sys.executable).parent


def graphs(n: int = 6) -> list:
    g = torch.Generator().manual_seed(0)
    return [random_view_graph(num_nodes=6, extra_edges=5, generator=g, name=f"g{k}")
            for k in range(n)]


def as_double(batch: GraphBatch) -> GraphBatch:
    """``batch`` with every floating tensor in float64 (indices kept)."""
    return batch.apply(lambda t: t.double() if t.is_floating_point() else t)


def gauge_free(poses: torch.Tensor, component: torch.Tensor) -> torch.Tensor:
    """``M_i M_a^{-1}`` with ``a`` the first camera of ``i``'s component: what is left of
    absolute poses ``[N, 4, 4]`` once each component's own gauge is taken out."""
    poses = poses.detach().cpu().double()
    comp = component.detach().cpu()
    first = {int(c): int((comp == c).nonzero()[0]) for c in comp.unique()}
    anchor = torch.stack([poses[first[int(c)]] for c in comp])
    return poses @ torch.linalg.inv(anchor)


@pytest.fixture(scope="module")
def learned_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return save_learned_sync(tmp_path_factory.mktemp("learned") / "learned.ckpt")


@pytest.fixture
def deterministic():
    """Deterministic algorithms, as after a Lightning fit with ``deterministic=True``."""
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(False)


# --------------------------------------------------------------------------- the network


@pytest.mark.parametrize("net", [{"depth": 2}, {"depth": 2, **ADAPTIVE}],
                         ids=["posernet", "adaptive"])
def test_posernet_on_cuda_matches_cpu(net: dict[str, Any], deterministic: None) -> None:
    torch.manual_seed(0)
    model = PoserNet(**net).double().eval()
    batch = as_double(GraphBatch.from_graphs(graphs()))
    with torch.no_grad():
        cpu = model(batch, return_extras=True)
        gpu = model.to("cuda")(batch.to("cuda"), return_extras=True)
    assert gpu.pose.device.type == "cuda"
    torch.testing.assert_close(gpu.pose.cpu(), cpu.pose, atol=1e-9, rtol=1e-9)
    for a, b in ((gpu.gate, cpu.gate), (gpu.sigma, cpu.sigma)):
        assert (a is None) == (b is None)
        if a is not None:
            torch.testing.assert_close(a.cpu(), b, atol=1e-9, rtol=1e-9)


# --------------------------------------------------------------------------- motion averaging


@pytest.mark.parametrize("name", available_backends())
def test_sync_backend_on_cuda_matches_cpu(name: str, learned_ckpt: Path) -> None:
    batch = GraphBatch.from_graphs(sync_graphs())
    w = translation_weights(batch.edge_index.shape[1])
    # the learned network runs in float32: its round-off is float32's
    tol = 1e-4 if name == "learned" else 1e-6
    for options in backend_variants(name, learned_ckpt):
        def backend(device: str, options: dict[str, Any] = options) -> Any:
            return get_backend(name, **options, **({"device": device} if name == "learned"
                                                   else {}))

        for weights in (None, w):
            cpu = backend("cpu").solve_with_info(batch, batch.edge_pose, edge_weight=weights)
            gpu = backend("cuda").solve_with_info(
                batch.to("cuda"), batch.edge_pose.cuda(),
                edge_weight=None if weights is None else weights.cuda())
            what = (name, options, weights is not None)
            assert gpu.poses.device.type == "cuda", what
            assert torch.equal(gpu.solved.cpu(), cpu.solved), what
            assert torch.equal(gpu.component.cpu(), cpu.component), what
            # where the edges leave positions free (a camera on one edge), the answer is the
            # ridge's choice, fixed to about 1e-5 by float64 round-off
            free = cpu.info.get("parallel_rigid") is not None and not bool(
                cpu.info["parallel_rigid"].all())
            torch.testing.assert_close(gauge_free(gpu.poses, gpu.component),
                                       gauge_free(cpu.poses, cpu.component),
                                       atol=max(tol, 1e-4) if free else tol, rtol=0,
                                       msg=lambda m, what=what: f"{what}: {m}")
            torch.testing.assert_close(gpu.edge_weight.cpu(), cpu.edge_weight, atol=tol,
                                       rtol=0, msg=lambda m, what=what: f"{what}: {m}")


# --------------------------------------------------------------------------- refinement


@pytest.mark.parametrize("case", ["posernet-eig_se3", "adaptive-rotation_translation-guard"])
def test_refine_pipeline_on_cuda_matches_cpu(case: str, deterministic: None) -> None:
    from posernet.evaluation import evaluate_result
    from posernet.refinement import refine_graphs

    torch.manual_seed(0)
    kind, backend, *rest = case.split("-")
    model = PoserNet(depth=2, **(ADAPTIVE if kind == "adaptive" else {}))
    extra = {"guard": True, "weighted": True} if rest else {}
    gs = net_graphs(6)
    cpu = refine_graphs(model, gs, backend=get_backend(backend), device="cpu", progress=False,
                        batch_size=4, **extra)
    gpu = refine_graphs(model, gs, backend=get_backend(backend), device="cuda",
                        progress=False, batch_size=4, **extra)
    for stage in ("initial", "refined"):
        for a, b in zip(gpu.edge_pose[stage], cpu.edge_pose[stage], strict=True):
            torch.testing.assert_close(a.double(), b.double(), atol=1e-4, rtol=1e-4)
        for k in range(len(gs)):
            assert torch.equal(gpu.solved[stage][k], cpu.solved[stage][k])
            torch.testing.assert_close(
                gauge_free(gpu.absolute[stage][k], gpu.component[stage][k]),
                gauge_free(cpu.absolute[stage][k], cpu.component[stage][k]),
                atol=1e-3, rtol=1e-3)
    for a, b in zip(gpu.kept_input, cpu.kept_input, strict=True):
        assert torch.equal(a, b)
    ev_gpu, ev_cpu = evaluate_result(gpu), evaluate_result(cpu)
    for key, v in ev_cpu["per_graph"].items():
        torch.testing.assert_close(ev_gpu["per_graph"][key].double(), v.double(), atol=1e-3,
                                   rtol=1e-3, equal_nan=True, msg=lambda m, key=key: f"{key}: {m}")


# --------------------------------------------------------------------------- training


def test_training_on_cuda_is_deterministic(tmp_path):
    import lightning as L
    from torch.utils.data import DataLoader

    from posernet.data.datamodule import collate_graphs
    from posernet.lit import PoserNetModule

    data = graphs(16)

    def weights(module: torch.nn.Module) -> torch.Tensor:
        return torch.cat([p.detach().cpu().flatten() for p in module.parameters()])

    def fit() -> tuple[torch.Tensor, torch.Tensor]:
        L.seed_everything(0, workers=True, verbose=False)
        module = PoserNetModule()
        start = weights(module)
        trainer = L.Trainer(accelerator="gpu", devices=1, max_epochs=3, deterministic=True,
                            logger=False, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False,
                            default_root_dir=str(tmp_path))
        loader = DataLoader(data, batch_size=4, collate_fn=collate_graphs)
        trainer.fit(module, loader, DataLoader(data, batch_size=8, collate_fn=collate_graphs))
        assert torch.isfinite(trainer.callback_metrics["val/loss"])
        return start, weights(module)

    start, w1 = fit()
    _, w2 = fit()
    assert not torch.equal(start, w1)  # it trained
    assert torch.equal(w1, w2)  # same seed on the same GPU: the same weights


@pytest.mark.parametrize("kind", ["adaptive", "end_to_end", "learned_sync"])
def test_training_step_on_cuda_matches_cpu(kind: str, deterministic: None) -> None:
    from posernet.lit import LearnedSyncModule, PoserNetModule

    def make() -> torch.nn.Module:
        torch.manual_seed(0)
        return {
            "adaptive": lambda: PoserNetModule(net={"depth": 2, **ADAPTIVE},
                                               loss={"raw": 0.5, "confidence": 0.1}),
            "end_to_end": lambda: PoserNetModule(net={"depth": 2}, loss={"end_to_end": True}),
            "learned_sync": lambda: LearnedSyncModule(net={"hidden": 8, "rounds": 2}),
        }[kind]().double()

    batch = as_double(GraphBatch.from_graphs(net_graphs(4)))
    out = {}
    for device in ("cpu", "cuda"):
        module = make().to(device)
        module.log = lambda *a, **k: None  # type: ignore[method-assign]
        loss = module.training_step(batch.to(device), 0)
        loss.backward()
        grads = torch.cat([p.grad.flatten() for p in module.parameters() if p.grad is not None])
        out[device] = (loss.detach().cpu(), grads.cpu())
    torch.testing.assert_close(out["cuda"][0], out["cpu"][0], atol=1e-8, rtol=1e-8)
    torch.testing.assert_close(out["cuda"][1], out["cpu"][1], atol=1e-7, rtol=1e-6)


# --------------------------------------------------------------------------- the commands


def _command(module: str, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    r = subprocess.run([sys.executable, "-m", f"posernet.cli.{module}", *args],
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-3000:]
    return r


def _table(path: Path) -> tuple[list[list[str]], np.ndarray]:
    """Labels and numbers of a results table's CSV."""
    rows = list(csv.reader(path.read_text().splitlines()))
    labels, numbers = [], []
    for row in rows[1:]:
        labels.append([c for c in row if not _is_number(c)])
        numbers.append([float(c) for c in row if _is_number(c)])
    return labels, np.asarray(numbers, dtype=float)


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _same_tables(a: Path, b: Path, names: tuple[str, ...]) -> None:
    for name in names:
        la, xa = _table(a / f"{name}.csv")
        lb, xb = _table(b / f"{name}.csv")
        assert la == lb, name
        np.testing.assert_allclose(xa, xb, atol=1e-3, rtol=1e-4, err_msg=name)


def _cameras(graph: dict[str, Any], stage: str) -> tuple[torch.Tensor, torch.Tensor, list]:
    """World-to-camera poses, components and solved flags of one graph of refined.json."""
    cams = [c[stage] for c in graph["cameras"].values()]
    solved = [bool(c["solved"]) for c in cams]
    eye = np.eye(4).tolist()
    poses = torch.tensor([c["world_to_camera"] if c["solved"] else eye for c in cams],
                         dtype=torch.float64)
    comp = torch.tensor([c["component"] if c["solved"] else -1 - k
                         for k, c in enumerate(cams)])
    return poses, comp, solved


@pytest.mark.slow
def test_refine_command_on_cuda_matches_cpu(tmp_path: Path) -> None:
    src = save_graphs(tmp_path / "g.pt", net_graphs(5))
    for dev in ("cpu", "cuda"):
        _command("refine", f"input={src}", f"hydra.run.dir={tmp_path / dev}", f"device={dev}",
                 "sync=rotation_translation", "guard=true", "digits=6")
    cpu, gpu = (json.loads((tmp_path / d / "refined.json").read_text()) for d in ("cpu", "cuda"))
    assert len(gpu["graphs"]) == len(cpu["graphs"]) == 5
    assert gpu["cameras_placed"] == cpu["cameras_placed"]
    for g_gpu, g_cpu in zip(gpu["graphs"], cpu["graphs"], strict=True):
        for e_gpu, e_cpu in zip(g_gpu["edges"], g_cpu["edges"], strict=True):
            assert e_gpu["kept_input"] == e_cpu["kept_input"]
            np.testing.assert_allclose(e_gpu["refined"]["matrix"], e_cpu["refined"]["matrix"],
                                       atol=1e-4)
        for stage in ("initial", "refined"):
            p_gpu, c_gpu, s_gpu = _cameras(g_gpu, stage)
            p_cpu, c_cpu, s_cpu = _cameras(g_cpu, stage)
            assert s_gpu == s_cpu
            torch.testing.assert_close(gauge_free(p_gpu, c_gpu), gauge_free(p_cpu, c_cpu),
                                       atol=1e-3, rtol=1e-3)
    _same_tables(tmp_path / "cpu", tmp_path / "cuda", ("table", "abs_table"))


@pytest.mark.slow
def test_eval_command_on_cuda_matches_cpu(tmp_path: Path) -> None:
    from posernet.checkpoints import default_checkpoint

    src = save_graphs(tmp_path / "g.pt", net_graphs(6))
    for dev in ("cpu", "cuda"):
        _command("evaluate", f"ckpt_path={default_checkpoint()}", f"graphs={src}",
                 "estimate=kp", "sync=eig_se3", f"device={dev}", "digits=6",
                 f"hydra.run.dir={tmp_path / dev}")
    _same_tables(tmp_path / "cpu", tmp_path / "cuda", ("table", "abs_table"))


@pytest.mark.slow
def test_reconstruct_with_refinement_on_cuda_matches_cpu(tmp_path: Path) -> None:
    from posernet.data.render import render_intrinsics, render_sevenscenes

    scene = render_sevenscenes(tmp_path / "render", "chess", seed=3, train_sequences=0,
                               test_sequences=1, frames_per_sequence=8, width=320, height=240,
                               focal=292.5, progress=False)
    intr = ",".join(f"{v:g}" for v in render_intrinsics(scene))
    # the renderer's object boxes as proposals (keyed by file name, as the images folder is
    # seq-01): the same boxes on both runs, and no contrib OpenCV needed on the GPU machine
    objects = json.loads((scene / "objects.json").read_text())
    objects["images"] = {Path(k).name: v for k, v in objects["images"].items()
                         if k.startswith("seq-01/")}
    boxes = tmp_path / "boxes.json"
    boxes.write_text(json.dumps(objects))
    env = dict(os.environ, OMP_NUM_THREADS="1")
    for dev in ("cpu", "cuda"):
        # SIFT on the CPU and no bundle adjustment: the device is the only difference (the
        # refiner and motion averaging run on it)
        r = subprocess.run([str(BIN / "posernet-reconstruct"), f"images={scene / 'seq-01'}",
                            f"intrinsics={intr}", f"out_dir={tmp_path / dev}", "matcher=sift",
                            "refine=true", "ba=false", "pictures=0", f"device={dev}",
                            "progress=false", "proposals=file", f"proposals.path={boxes}"],
                           capture_output=True, text=True, timeout=600, env=env)
        assert r.returncode == 0, r.stderr[-3000:]
    cpu, gpu = (json.loads((tmp_path / d / "poses.json").read_text())["cameras"]
                for d in ("cpu", "cuda"))
    assert sorted(gpu) == sorted(cpu) and any(c["solved"] for c in cpu.values())
    for name, c in cpu.items():
        assert gpu[name]["solved"] == c["solved"], name
        if c["solved"]:  # each component's first camera at the identity: no gauge left
            np.testing.assert_allclose(gpu[name]["world_to_camera"], c["world_to_camera"],
                                       atol=1e-4, err_msg=name)
