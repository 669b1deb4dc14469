"""PoserNetModule: training lowers the validation error, checkpoints round-trip, runs repeat."""

from __future__ import annotations

import warnings
from pathlib import Path

import lightning as L
import pytest
import torch
from torch.utils.data import DataLoader

from posernet.checkpoints import CheckpointError, read_checkpoint
from posernet.cli import CONFIG_DIR
from posernet.graph import GraphBatch
from posernet.lit import PoserNetModule, load_posernet_checkpoint
from posernet.lit.trainer import build_trainer
from posernet.nn import PoserNet
from posernet.testing import random_view_graph

pytestmark = pytest.mark.filterwarnings(
    "ignore::UserWarning", "ignore::DeprecationWarning", "ignore::FutureWarning")




def graphs(n: int, seed: int) -> list:
    g = torch.Generator().manual_seed(seed)
    return [random_view_graph(extra_edges=6, pairs_per_edge=(2, 6), rot_noise_deg=20.0,
                              generator=g, name=f"g{seed}-{i}") for i in range(n)]


def loader(gs: list, batch_size: int = 8, shuffle: bool = False) -> DataLoader:
    return DataLoader(gs, batch_size=batch_size, shuffle=shuffle,
                      collate_fn=GraphBatch.from_graphs,
                      generator=torch.Generator().manual_seed(0))


def trainer(tmp: Path | None = None, epochs: int = 1, **kw) -> L.Trainer:
    callbacks = kw.pop("callbacks", [])
    return build_trainer(accelerator="cpu", devices=1, max_epochs=epochs, logger=False,
                         enable_progress_bar=False, enable_model_summary=False,
                         enable_checkpointing=bool(callbacks), callbacks=callbacks,
                         num_sanity_val_steps=0, default_root_dir=tmp, **kw)


@pytest.fixture(scope="module")
def data() -> tuple[list, list]:
    return graphs(96, 0), graphs(24, 1)


def val_rot(module: PoserNetModule, val: list) -> float:
    t = trainer()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = t.validate(module, loader(val), verbose=False)
    return float(res[0]["val/rot_err_deg"])


@pytest.mark.slow
def test_training_lowers_validation_rotation_error(data, tmp_path: Path) -> None:
    train, val = data
    L.seed_everything(0, workers=True)
    module = PoserNetModule(optimizer={"lr": 5e-3})
    before = val_rot(module, val)
    t = trainer(tmp_path, epochs=6)
    t.fit(module, loader(train, shuffle=True), loader(val))
    after = val_rot(module, val)
    assert after < before - 20.0, (before, after)  # measured: ~127 -> ~76 degrees
    names = set(t.callback_metrics)
    assert {"train/loss", "val/loss", "val/rot_err_deg", "val/tdir_err_deg",
            "val/rot_err_deg_init"} <= names


def test_per_graph_medians(data) -> None:
    """val/rot_err_deg_init is the median over graphs of each graph's mean edge error."""
    from posernet.metrics import per_graph_mean, relative_pose_errors

    _, val = data
    b = GraphBatch.from_graphs(val)
    rot, _ = relative_pose_errors(b.edge_pose, b.edge_pose_gt)
    expected = per_graph_mean(rot, b.edge_batch, b.num_graphs).quantile(0.5)
    t = trainer()
    res = t.validate(PoserNetModule(), loader(val, batch_size=5), verbose=False)[0]
    assert res["val/rot_err_deg_init"] == pytest.approx(float(expected), rel=1e-5)


def test_checkpoint_round_trip(data, tmp_path: Path) -> None:
    train, val = data
    L.seed_everything(1, workers=True)
    module = PoserNetModule(net={"depth": 3, "node_hidden": 16, "edge_hidden": 4,
                                 "residual": True}, loss={"alpha": 0.3})
    ckpt = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path, filename="best",
                                               monitor="val/loss", save_last=True)
    trainer(tmp_path, epochs=1, callbacks=[ckpt], limit_train_batches=2).fit(
        module, loader(train[:16]), loader(val[:8]))
    path = tmp_path / "best.ckpt"
    assert path.is_file() and (tmp_path / "last.ckpt").is_file()
    batch = GraphBatch.from_graphs(val[:4])
    module.eval()
    expected = module(batch)
    loaded = PoserNetModule.load_from_checkpoint(path, map_location="cpu")  # no Hydra needed
    assert loaded.hparams.net["depth"] == 3 and loaded.hparams.net["residual"]
    # the input-adaptive terms default to 0 and end-to-end training is off: the paper's
    assert loaded.hparams.loss == {"alpha": 0.3, "raw": 0.0, "confidence": 0.0,
                                   "correction": 0.0, "harm": 0.0, "harm_scale": 0.0,
                                   "end_to_end": False, "relative_weight": 1.0,
                                   "absolute_weight": 1.0, "position_weight": 1.0}
    loaded.eval()
    torch.testing.assert_close(loaded(batch), expected)
    ours = load_posernet_checkpoint(path)
    torch.testing.assert_close(ours(batch), expected)
    bare = PoserNet.from_checkpoint(path)  # the network alone, without Lightning
    torch.testing.assert_close(bare(batch), expected)
    stored = read_checkpoint(path)
    assert stored["posernet"]["tag"] == "posernet.PoserNetModule"
    # plain nested values: readable with weights_only=True, and every section filled in
    assert sorted(stored["hyper_parameters"]) == ["loss", "net", "optimizer", "scheduler"]
    assert stored["hyper_parameters"]["optimizer"] == {"lr": 1e-3, "weight_decay": 0.0}


def test_last_checkpoint_is_the_latest_epoch_even_without_improvement(data,
                                                                       tmp_path: Path) -> None:
    from helpers import posernet_train_callbacks

    train, val = data
    L.seed_everything(1, workers=True)
    # weights never change: val/loss never improves after epoch 0
    module = PoserNetModule(optimizer={"lr": 0.0})
    trainer(tmp_path, epochs=3, callbacks=posernet_train_callbacks(tmp_path),
            limit_train_batches=2).fit(module, loader(train[:16]), loader(val[:8]))
    folder = tmp_path / "checkpoints"
    epoch = {name: torch.load(folder / f"{name}.ckpt", weights_only=False)["epoch"]
             for name in ("best", "last")}
    assert epoch == {"best": 0, "last": 2}  # resuming from last.ckpt repeats no epoch
    assert sorted(p.name for p in folder.glob("*.ckpt")) == ["best.ckpt", "last.ckpt"]


def test_bad_checkpoints_give_clear_errors(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_posernet_checkpoint(tmp_path / "missing.ckpt")
    junk = tmp_path / "junk.ckpt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_posernet_checkpoint(junk)
    other = tmp_path / "other.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(1)}, "hparams_name": "kwargs"}, other)
    with pytest.raises(CheckpointError, match="not a PoserNet checkpoint"):
        load_posernet_checkpoint(other)
    wrong = tmp_path / "wrong.ckpt"
    torch.save({"state_dict": {"w": torch.zeros(1)}, "hyper_parameters": {},
                "posernet": {"tag": "posernet.PoserNetModule"}}, wrong)
    with pytest.raises(CheckpointError, match="does not fit"):
        load_posernet_checkpoint(wrong)
    with pytest.raises(CheckpointError, match="does not fit"):
        PoserNet.from_checkpoint(wrong)
    with pytest.raises(CheckpointError, match="not a PoserNet checkpoint"):
        PoserNet.from_checkpoint(other)
    # one reader for both loaders: extra (non-network) weights are refused by both alike
    extra = tmp_path / "extra.ckpt"
    module = PoserNetModule(net={"depth": 1})
    torch.save({"state_dict": {**module.state_dict(), "head.w": torch.zeros(1)},
                "hyper_parameters": dict(module.hparams),
                "posernet": {"tag": "posernet.PoserNetModule"}}, extra)
    for load in (load_posernet_checkpoint, PoserNet.from_checkpoint):
        with pytest.raises(CheckpointError, match="does not fit.*head.w"):
            load(extra)
    good = tmp_path / "good.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "posernet": {"tag": "posernet.PoserNetModule"}}, good)
    loaded = load_posernet_checkpoint(good)
    assert not loaded.training and loaded.hparams.net["depth"] == 1
    for name, value in module.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value)


def test_seeded_runs_are_reproducible(data, tmp_path: Path) -> None:
    train, val = data

    def run() -> dict:
        L.seed_everything(123, workers=True)
        module = PoserNetModule()
        trainer(tmp_path, epochs=1, limit_train_batches=3, limit_val_batches=1).fit(
            module, loader(train[:24], shuffle=True), loader(val[:8]))
        return module.state_dict()

    a, b = run(), run()
    assert all(torch.equal(a[k], b[k]) for k in a)
    L.seed_everything(124, workers=True)
    c = PoserNetModule().state_dict()
    assert not all(torch.equal(a[k], c[k]) for k in a)  # the check can fail


def test_optimizer_and_scheduler() -> None:
    module = PoserNetModule(optimizer={"lr": 0.02}, scheduler={"patience": 3})
    conf = module.configure_optimizers()
    opt, sched = conf["optimizer"], conf["lr_scheduler"]
    assert isinstance(opt, torch.optim.Adam) and opt.param_groups[0]["lr"] == 0.02
    assert isinstance(sched["scheduler"], torch.optim.lr_scheduler.ReduceLROnPlateau)
    assert sched["scheduler"].patience == 3 and sched["monitor"] == "val/loss"
    assert module.num_parameters == sum(p.numel() for p in module.model.parameters())


# --------------------------------------------------------------------------- unused parameters

MODEL_CONFIG_DIR = Path(CONFIG_DIR) / "model"
MODEL_CONFIGS = sorted(p.stem for p in MODEL_CONFIG_DIR.glob("*.yaml"))
# the checkpoint shipped before input-adaptive refinement (converted once to the current layout)
SHIPPED = (Path(__file__).resolve().parents[2] / "src" / "posernet" / "checkpoints"
           / "posernet_synthetic_kp_v1.ckpt")


def test_model_configs_are_found() -> None:
    assert {"posernet", "posernet_large", "residual"} <= set(MODEL_CONFIGS)


@pytest.mark.parametrize("name", MODEL_CONFIGS)
def test_every_parameter_of_each_model_config_gets_a_gradient(name: str, data) -> None:
    """DDP without find_unused_parameters: the module's own training loss (every model config:
    PoserNet variants, end to end, the learned synchronisation) must reach every parameter."""
    import hydra
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"model={name}"])
    torch.manual_seed(0)
    module = hydra.utils.instantiate(cfg.model)
    assert isinstance(module, L.LightningModule)
    module.log = lambda *args, **kwargs: None  # no Trainer attached
    batch = GraphBatch.from_graphs(data[0][:4])
    module.training_step(batch, 0).backward()
    for pname, p in module.named_parameters():
        assert p.grad is not None, f"model={name}: {pname} is not used by the loss"
        assert p.grad.abs().sum() > 0, f"model={name}: {pname} gets a zero gradient"


def test_the_v1_checkpoint_loads_in_the_current_layout(data, tmp_path: Path) -> None:
    """The checkpoint shipped before input-adaptive refinement, converted once: sections, no
    unused last-round weights, no optimiser state; Lightning loads it and training can start
    from its weights."""
    ckpt = torch.load(SHIPPED, weights_only=True)
    assert set(ckpt["hyper_parameters"]) == {"net", "loss", "optimizer", "scheduler"}
    assert not any(".psi_node." in k and k.startswith("model.convs.1.")
                   for k in ckpt["state_dict"])
    assert "optimizer_states" not in ckpt
    loaded = PoserNetModule.load_from_checkpoint(SHIPPED, map_location="cpu")
    assert loaded.hparams.net["depth"] == 2 and loaded.hparams.optimizer["lr"] == 1e-3
    assert loaded.hparams.scheduler["patience"] == 3
    train, val = data
    module = PoserNetModule(**ckpt["hyper_parameters"])
    module.load_state_dict(ckpt["state_dict"])  # strict
    t = trainer(tmp_path, epochs=1, limit_train_batches=2, limit_val_batches=1)
    t.fit(module, loader(train[:16]), loader(val[:8]))
    assert t.global_step == 2


def test_hyper_parameters_come_in_sections_only() -> None:
    from posernet.lit import module_hparams

    hp = module_hparams(net={"depth": 3, "residual": True}, loss={"alpha": 0.5})
    assert hp["net"]["depth"] == 3 and hp["net"]["residual"] is True
    assert hp["loss"]["alpha"] == 0.5 and hp["optimizer"] == {"lr": 1e-3, "weight_decay": 0.0}
    with pytest.raises(TypeError, match=r"unknown net hyper-parameter\(s\) \['lr'\]"):
        PoserNetModule(net={"lr": 0.1})
    with pytest.raises(TypeError):
        PoserNetModule(depth=3)  # the flat names of an unreleased layout are gone
