"""The Lightning layer: the refiner's module (:mod:`.refiner`), the learned synchronisation's
(:mod:`.sync`), what they share (:mod:`.base`: sectioned hyper-parameters, the checkpoint tag)
and the one Trainer builder with its determinism policy (:mod:`.trainer`)."""

from .base import SectionedModule, fill_sections
from .learned_sync_module import LearnedSyncModule, sync_module_hparams
from .posernet_module import (
    PoserNetModule,
    load_posernet_checkpoint,
    module_hparams,
)
from .trainer import build_trainer, determinism_policy, trainer_from_config

__all__ = [
    "LearnedSyncModule",
    "PoserNetModule",
    "SectionedModule",
    "build_trainer",
    "determinism_policy",
    "fill_sections",
    "load_posernet_checkpoint",
    "module_hparams",
    "sync_module_hparams",
    "trainer_from_config",
]
