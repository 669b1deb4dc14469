"""The network, its training and the pipeline on CUDA (skipped without a GPU).

CI has no GPU; these run wherever one is present. Training uses Lightning's
``deterministic=True`` as the experiment runner does, so every op on the training path must
have a deterministic CUDA kernel (``bincount`` has none: it raised here before).
"""

from __future__ import annotations

import pytest
import torch

from posernet import GraphBatch, PoserNet
from posernet.testing import random_view_graph

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")


def graphs(n: int = 6) -> list:
    g = torch.Generator().manual_seed(0)
    return [random_view_graph(num_nodes=6, extra_edges=5, generator=g, name=f"g{k}")
            for k in range(n)]


def test_posernet_on_cuda_matches_cpu():
    torch.manual_seed(0)
    model = PoserNet(depth=2).double()
    batch = GraphBatch.from_graphs(graphs())
    cpu = model(batch.to("cpu"), edge_pose=batch.edge_pose.double())
    gpu = model.to("cuda")(batch.to("cuda"), edge_pose=batch.edge_pose.double().cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-9, rtol=1e-9)


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


def test_refine_pipeline_on_cuda_matches_cpu():
    from posernet.refine import refine_graphs
    from posernet.sync import get_backend

    torch.use_deterministic_algorithms(True)  # as after a Lightning fit with deterministic=True
    try:
        torch.manual_seed(0)
        model = PoserNet(depth=2)
        gs = graphs()
        cpu = refine_graphs(model, gs, backend=get_backend("eig_se3"), device="cpu",
                            progress=False)
        gpu = refine_graphs(model, gs, backend=get_backend("eig_se3"), device="cuda",
                            progress=False)
    finally:
        torch.use_deterministic_algorithms(False)
    for stage in ("initial", "refined"):
        for a, b in zip(gpu.absolute[stage], cpu.absolute[stage], strict=True):
            torch.testing.assert_close(a.cpu().double(), b.double(), atol=1e-3, rtol=1e-3)
