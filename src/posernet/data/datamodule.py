"""LightningDataModule over a ``posernet-make-data`` dataset directory (usable without Hydra).

Batches are :class:`~posernet.graph.GraphBatch` objects whose ``edge_pose`` is the chosen
initial estimate (``kp`` or ``bb``). Validation graphs come from the held-out tail of the
training sequences, never from the test split.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader

from ..graph import GraphBatch, ViewGraph
from ..options import Rule, option, paths
from .mixture import MixedInitDataset, check_mixture
from .store import SIZES, DatasetError, available_scenes, open_split, read_manifest

__all__ = ["DataOptions", "PoserDataModule", "collate_graphs"]

ESTIMATES = ("kp", "bb")


def _mixture_ok(v: Any) -> bool:
    try:
        check_mixture(v)
    except (ValueError, TypeError):
        return False
    return True


#: ``init_mix``: what :func:`posernet.data.mixture.check_mixture` accepts
MIXTURE = Rule("a mapping of initial-pose sources (kp, bb, gt, recorrupt) to weights >= 0, "
               "not all 0", _mixture_ok, True)


@dataclass(frozen=True, kw_only=True)
class DataOptions:
    """The arguments of :class:`PoserDataModule` (``data.*`` of ``posernet-train`` and
    ``posernet-eval``), each with its range and meaning; the config check applies them before
    any work. (The constructor still checks its arguments itself, with its own messages.)"""

    root: str | Sequence[str] = option(
        rule=paths(), help="the dataset directory (posernet-make-data's default out_dir), or a "
                           "list of them to train on all: data.root=[DIR_A,DIR_B]")
    estimate: str = option("kp", choices=ESTIMATES, help="initial relative poses: kp "
                                                         "(keypoints) or bb (box centres)")
    size: str = option("small", choices=SIZES, help="graph size for training and validation: "
                                                    "small (8 nodes) or large")
    batch_size: int = option(32, ge=1, help="graphs per training batch")
    num_workers: int = option(0, ge=0, help="DataLoader worker processes")
    leave_out_scene: str | None = option(None, help="a scene name: train/validate on the "
                                                    "others, test on it only")
    test_size: str | None = option(None, choices=SIZES, help="graph size of the test split "
                                                             "(null: same as size)")
    shuffle: bool = option(True, help="shuffle the training graphs every epoch (seeded)")
    seed: int = option(0, ge=0, help="seed of the shuffling and of the initial-pose mixture")
    val_size: str | None = option(None, choices=SIZES, help="graph size of the validation "
                                                            "split (null: same as size)")
    eval_batch_size: int | None = option(None, ge=1, help="graphs per validation/test batch "
                                                          "(null: batch_size)")
    init_mix: Mapping[str, float] | None = option(
        None, rule=MIXTURE, help="input-adaptive training: a mixture of initial-pose qualities, "
        "redrawn every epoch, e.g. data.init_mix='{kp: 0.4, bb: 0.1, gt: 0.3, recorrupt: 0.2}' "
        "(null: train on estimate)")
    gt_noise_deg: float = option(3.0, ge=0, help="gt source: ground truth rotated by up to this "
                                                 "angle (degrees)")
    recorrupt_deg: float = option(60.0, ge=0, help="recorrupt source: ground truth rotated by "
                                                   "up to this angle (degrees)")
    mix_edge_fraction: float = option(0.5, ge=0, le=1, help="chance a graph mixes sources per "
                                                            "edge (else one source per graph)")


def _dataset_roots(root: Any) -> list[Path]:
    """``root`` as a non-empty list of distinct dataset directories."""
    many = isinstance(root, Sequence) and not isinstance(root, (str, bytes))
    items = list(root) if many else [root]
    if not items:
        raise ValueError("root must name at least one dataset directory, got an empty list")
    roots = [Path(r) for r in items]
    seen = {r.resolve() for r in roots}
    if len(seen) != len(roots):
        raise ValueError(f"root lists a dataset directory twice: {[str(r) for r in roots]}")
    return roots


def collate_graphs(graphs: Sequence[ViewGraph]) -> GraphBatch:
    """DataLoader collate: concatenate graphs into one :class:`GraphBatch`."""
    return GraphBatch.from_graphs(graphs)


class PoserDataModule(L.LightningDataModule):
    """Train / val / test loaders over ``root``.

    Args:
        root: dataset directory (``manifest.json`` + ``<size>/<split>/<scene>.pt``), or a list
            of them whose splits are concatenated (e.g. datasets generated with different noise
            settings, to train on all of them); a split may be missing from some of them.
        estimate: initial relative poses fed as ``edge_pose``: ``"kp"`` or ``"bb"``.
        size: graph size for training and validation (``"small"`` / ``"large"``).
        batch_size: graphs per batch.
        num_workers: DataLoader worker processes.
        leave_out_scene: train and validate on the other scenes, test on this one only.
        test_size: graph size of the test split (default: ``size``).
        val_size: graph size of the validation split (default: ``size``); e.g. ``"small"``
            when training on large graphs, which have no validation split in the paper preset.
        eval_batch_size: graphs per batch of the validation and test loaders (default:
            ``batch_size``); e.g. 32 to validate a large-graph model (batch 1) on small graphs
            without one step per graph.
        shuffle: shuffle the training graphs each epoch (seeded by ``seed``).
        seed: seed of the shuffling (and of the initial-pose mixture).
        init_mix: train on a mixture of initial-pose qualities instead of ``estimate`` alone:
            a mapping of sources (``kp``, ``bb``, ``gt`` = ground truth + small noise,
            ``recorrupt`` = ground truth + large noise) to weights, redrawn every epoch
            (:class:`posernet.data.mixture.MixedInitDataset`). Default ``None``: off.
            Validation and test keep ``estimate``.
        gt_noise_deg: largest rotation noise of the ``gt`` source (degrees, default 3).
        recorrupt_deg: largest rotation noise of the ``recorrupt`` source (default 60).
        mix_edge_fraction: chance a graph mixes sources per edge rather than per graph (0.5).

    The arguments, with their ranges, are declared once more as :class:`DataOptions`
    (``Options``), which the commands' config check reads.
    """

    Options = DataOptions

    def __init__(
        self,
        root: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
        estimate: str = "kp",
        size: str = "small",
        batch_size: int = 32,
        num_workers: int = 0,
        leave_out_scene: str | None = None,
        test_size: str | None = None,
        shuffle: bool = True,
        seed: int = 0,
        val_size: str | None = None,
        eval_batch_size: int | None = None,
        init_mix: Mapping[str, Any] | None = None,
        gt_noise_deg: float = 3.0,
        recorrupt_deg: float = 60.0,
        mix_edge_fraction: float = 0.5,
    ) -> None:
        super().__init__()
        if init_mix is not None:
            init_mix = check_mixture(init_mix)  # fail early, naming the bad entry
        if estimate not in ESTIMATES:
            raise ValueError(f"estimate must be one of {list(ESTIMATES)}, got {estimate!r}")
        for name, v in (("size", size), ("test_size", test_size), ("val_size", val_size)):
            if v is not None and v not in SIZES:
                raise ValueError(f"{name} must be one of {list(SIZES)}, got {v!r}")
        for name, v in (("batch_size", batch_size), ("eval_batch_size", eval_batch_size)):
            if v is None and name == "eval_batch_size":
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
            raise ValueError(f"num_workers must be an integer >= 0, got {num_workers!r}")
        self.roots = _dataset_roots(root)
        # fail early on a bad directory
        self.manifests = [read_manifest(r) for r in self.roots]
        self.estimate = estimate
        self.size = size
        self.test_size = test_size or size
        self.val_size = val_size or size
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size or batch_size
        self.num_workers = num_workers
        self.shuffle = shuffle
        self.seed = int(seed)
        self.leave_out_scene = leave_out_scene
        self.init_mix = init_mix
        self.gt_noise_deg, self.recorrupt_deg = float(gt_noise_deg), float(recorrupt_deg)
        self.mix_edge_fraction = float(mix_edge_fraction)
        if leave_out_scene is not None:
            scenes = set()
            for r in self.roots:
                for s in SIZES:
                    for p in ("train", "val", "test"):
                        scenes.update(available_scenes(r, s, p))
            if leave_out_scene not in scenes:
                raise DatasetError(
                    f"{self._where}: leave_out_scene {leave_out_scene!r} is not in "
                    f"the dataset (scenes: {sorted(scenes)})"
                )
        self.save_hyperparameters(
            {
                "root": ([str(r) for r in self.roots] if len(self.roots) > 1
                         else str(self.roots[0])),
                "estimate": estimate,
                "size": size,
                "test_size": self.test_size,
                "val_size": self.val_size,
                "batch_size": batch_size,
                "eval_batch_size": self.eval_batch_size,
                "leave_out_scene": leave_out_scene,
                "seed": self.seed,
                **({"init_mix": dict(init_mix), "gt_noise_deg": self.gt_noise_deg,
                    "recorrupt_deg": self.recorrupt_deg,
                    "mix_edge_fraction": self.mix_edge_fraction} if init_mix else {}),
            }
        )
        self.train_graphs: list[ViewGraph] | None = None
        self.val_graphs: list[ViewGraph] | None = None
        self.test_graphs: list[ViewGraph] | None = None

    # ------------------------------------------------------------------ loading

    @property
    def _where(self) -> str:
        return ", ".join(str(r) for r in self.roots)

    def _scenes(self, root: Path, size: str, split: str) -> list[str]:
        have = available_scenes(root, size, split)
        if self.leave_out_scene is None:
            return have
        if split == "test":
            return [s for s in have if s == self.leave_out_scene]
        return [s for s in have if s != self.leave_out_scene]

    def _load(self, size: str, split: str) -> list[ViewGraph]:
        graphs = [g for r in self.roots
                  for g in open_split(r, size, split, self._scenes(r, size, split))]
        if not graphs:
            extra = f" (leave_out_scene={self.leave_out_scene!r})" if self.leave_out_scene else ""
            hint = " or pass val_size='small'" if split == "val" and size == "large" else ""
            raise DatasetError(
                f"{self._where}: no {size} {split} graphs{extra}; generate them "
                f"(dataset.{size}.{split} > 0){hint}"
            )
        return [g.with_estimate(self.estimate) for g in graphs]

    def setup(self, stage: str | None = None) -> None:
        """Load the splits a stage needs (``fit``, ``validate``, ``test``, ``predict``)."""
        if stage in (None, "fit"):
            if self.train_graphs is None:
                self.train_graphs = self._load(self.size, "train")
        if stage in (None, "fit", "validate") and self.val_graphs is None:
            self.val_graphs = self._load(self.val_size, "val")
        if stage in (None, "test", "predict") and self.test_graphs is None:
            self.test_graphs = self._load(self.test_size, "test")

    # ------------------------------------------------------------------ loaders

    def _loader(self, graphs: list[ViewGraph] | None, shuffle: bool, what: str,
                batch_size: int | None = None) -> DataLoader:
        if graphs is None:
            raise RuntimeError(f"call setup() before {what}_dataloader()")
        gen = torch.Generator().manual_seed(self.seed) if shuffle else None
        return DataLoader(
            graphs,
            batch_size=batch_size or self.batch_size,
            shuffle=shuffle,
            generator=gen,
            collate_fn=collate_graphs,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        if self.init_mix is None or self.train_graphs is None:
            return self._loader(self.train_graphs, self.shuffle, "train")
        mixed = MixedInitDataset(self.train_graphs, self.init_mix, self.gt_noise_deg,
                                 self.recorrupt_deg, self.mix_edge_fraction, self.seed)
        return self._loader(mixed, self.shuffle, "train")  # type: ignore[arg-type]

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_graphs, False, "val", self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.test_graphs, False, "test", self.eval_batch_size)

    def predict_dataloader(self) -> DataLoader:
        return self._loader(self.test_graphs, False, "predict", self.eval_batch_size)
