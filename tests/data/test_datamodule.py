"""PoserDataModule: batches of GraphBatch, estimate choice, leave-one-scene-out, device moves."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from posernet.data.datamodule import PoserDataModule
from posernet.data.store import DatasetError
from posernet.data.synthetic import generate_dataset, load_preset
from posernet.graph import GraphBatch


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    d = load_preset("tiny").to_dict()
    d["small"].update(graph_size=4, train=3, val=1, test=2)
    d["large"].update(graph_size=5, train=1, val=0, test=1, scenes=["chess"])
    r = tmp_path_factory.mktemp("dm") / "ds"
    generate_dataset(d, r, seed=3, workers=1, progress=False, echo=None)
    return r


def test_loaders_yield_graph_batches_with_the_chosen_estimate(root: Path):
    for est in ("kp", "bb"):
        dm = PoserDataModule(root, estimate=est, batch_size=2, shuffle=False)
        dm.setup("fit")
        batches = list(dm.train_dataloader())
        assert sum(b.num_graphs for b in batches) == 6
        for b in batches:
            assert isinstance(b, GraphBatch)
            assert torch.equal(b.edge_pose, b.estimates[est])
            assert b.edge_pose_gt is not None and b.pose_gt is not None
        val = list(dm.val_dataloader())
        assert {m["split"] for b in val for m in b.metas} == {"val"}
    dm.setup("test")
    assert {m["split"] for b in dm.test_dataloader() for m in b.metas} == {"test"}


def test_kp_and_bb_differ(root: Path):
    kp = PoserDataModule(root, estimate="kp", shuffle=False)
    bb = PoserDataModule(root, estimate="bb", shuffle=False)
    kp.setup("test")
    bb.setup("test")
    a, b = next(iter(kp.test_dataloader())), next(iter(bb.test_dataloader()))
    assert torch.equal(a.edge_pose_gt, b.edge_pose_gt)
    assert not torch.equal(a.edge_pose, b.edge_pose)


def test_leave_one_scene_out(root: Path):
    dm = PoserDataModule(root, leave_out_scene="chess", batch_size=8)
    dm.setup()
    assert {g.meta["scene"] for g in dm.train_graphs} == {"fire"}
    assert {g.meta["scene"] for g in dm.val_graphs} == {"fire"}
    assert {g.meta["scene"] for g in dm.test_graphs} == {"chess"}
    with pytest.raises(DatasetError, match="kitchen"):
        PoserDataModule(root, leave_out_scene="kitchen")


def test_shuffle_is_seeded(root: Path):
    def order(seed):
        dm = PoserDataModule(root, batch_size=1, seed=seed)
        dm.setup("fit")
        return [b.metas[0]["name"] for b in dm.train_dataloader()]

    assert order(0) == order(0)
    assert sorted(order(0)) == sorted(order(1))


def test_sizes_and_missing_splits(root: Path):
    dm = PoserDataModule(root, size="small", test_size="large")
    dm.setup("test")
    assert [g.num_nodes for g in dm.test_graphs] == [5]
    with pytest.raises(DatasetError, match="val_size='small'"):
        PoserDataModule(root, size="large").setup("fit")
    dm = PoserDataModule(root, size="large", val_size="small")
    dm.setup("fit")
    assert dm.train_graphs[0].num_nodes == 5 and dm.val_graphs[0].num_nodes == 4


def test_eval_batch_size_sets_validation_and_test_batches(root: Path):
    # a large-graph model (batch 1) validated on small graphs: not one step per graph
    dm = PoserDataModule(root, size="large", val_size="small", batch_size=1, eval_batch_size=2)
    dm.setup("fit")
    dm.setup("test")
    assert [b.num_graphs for b in dm.train_dataloader()] == [1]
    n = len(dm.val_graphs)
    assert n >= 2
    assert [b.num_graphs for b in dm.val_dataloader()] == [min(2, n - k) for k in range(0, n, 2)]
    assert dm.test_dataloader().batch_size == 2
    default = PoserDataModule(root, batch_size=3)
    assert default.eval_batch_size == 3
    with pytest.raises(ValueError, match="eval_batch_size must be an integer >= 1"):
        PoserDataModule(root, eval_batch_size=0)


def test_bad_arguments(root: Path, tmp_path: Path):
    with pytest.raises(ValueError, match="estimate"):
        PoserDataModule(root, estimate="free")
    with pytest.raises(ValueError, match="batch_size"):
        PoserDataModule(root, batch_size=0)
    with pytest.raises(ValueError, match="size"):
        PoserDataModule(root, size="medium")
    with pytest.raises(DatasetError, match="not found"):
        PoserDataModule(tmp_path / "nothing")
    dm = PoserDataModule(root)
    with pytest.raises(RuntimeError, match="setup"):
        dm.train_dataloader()


def test_transfer_batch_to_device_moves_everything(root: Path):
    dm = PoserDataModule(root, batch_size=3)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    moved = dm.transfer_batch_to_device(batch, torch.device("meta"), 0)
    assert isinstance(moved, GraphBatch)
    assert moved.edge_pose.device.type == "meta" and moved.ptr.device.type == "meta"
    assert all(v.device.type == "meta" for v in moved.estimates.values())
    assert moved.metas == batch.metas
    back = dm.transfer_batch_to_device(batch, torch.device("cpu"), 0)
    assert torch.equal(back.edge_index, batch.edge_index)


@pytest.mark.filterwarnings(
    "ignore::DeprecationWarning", "ignore::FutureWarning", "ignore:.*LeafSpec"
)
def test_works_with_a_lightning_trainer(root: Path):
    import lightning as L

    class Probe(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(7))
            self.seen = []

        def training_step(self, batch, _):
            self.seen.append(batch.num_graphs)
            return ((batch.edge_pose - self.w) ** 2).mean()

        def validation_step(self, batch, _):
            return None

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    model = Probe()
    trainer = L.Trainer(
        max_epochs=1,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    trainer.fit(model, datamodule=PoserDataModule(root, batch_size=4))
    assert sum(model.seen) == 6


@pytest.fixture(scope="module")
def second_root(tmp_path_factory) -> Path:
    """Another dataset (other seed and keypoint noise) without a test split."""
    d = load_preset("tiny").to_dict()
    d["small"].update(graph_size=4, train=2, val=1, test=0)
    d["large"].update(train=0, val=0, test=0)
    d["keypoints"]["pixel_noise"] = 3.0
    r = tmp_path_factory.mktemp("dm2") / "ds2"
    generate_dataset(d, r, seed=5, workers=1, progress=False, echo=None)
    return r


def test_a_list_of_roots_concatenates_their_splits(root: Path, second_root: Path):
    one, two = PoserDataModule(root), PoserDataModule(second_root)
    both = PoserDataModule([root, second_root], leave_out_scene=None)
    for dm in (one, two, both):
        dm.setup("fit")
    names = [g.name for g in both.train_graphs]
    assert names == [g.name for g in one.train_graphs] + [g.name for g in two.train_graphs]
    assert len(both.val_graphs) == len(one.val_graphs) + len(two.val_graphs)
    # the second dataset has no test split: the first one's test graphs alone
    both.setup("test")
    one.setup("test")
    assert [g.name for g in both.test_graphs] == [g.name for g in one.test_graphs]
    assert both.hparams["root"] == [str(root), str(second_root)]
    assert one.hparams["root"] == str(root)
    # leave-one-scene-out sees the scenes of every root
    PoserDataModule([second_root, root], leave_out_scene="chess").setup("fit")


def test_a_bad_list_of_roots_names_the_problem(root: Path, tmp_path: Path):
    with pytest.raises(ValueError, match="at least one"):
        PoserDataModule([])
    with pytest.raises(ValueError, match="twice"):
        PoserDataModule([root, root])
    with pytest.raises(DatasetError, match="nothing"):
        PoserDataModule([root, tmp_path / "nothing"])
    with pytest.raises(DatasetError, match="not a complete dataset"):
        PoserDataModule([root, root.parent])  # a folder that is not a dataset
