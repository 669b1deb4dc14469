"""Suite-wide settings.

Tiny graphs are dominated by per-op overhead: one torch thread is much faster than two on a
2-core machine (no oversubscription with pytest's own process or a second job).
"""

from __future__ import annotations

import pytest
import torch

torch.set_num_threads(1)


def posernet_train_callbacks(out_dir: object) -> list:
    """The checkpoint callbacks ``posernet-train`` builds from ``conf/callbacks/default.yaml``
    for a run folder ``out_dir`` (best and last, in ``out_dir/checkpoints``)."""
    from hydra import compose, initialize_config_dir
    from lightning.pytorch.callbacks import ModelCheckpoint

    from posernet.cli import CONFIG_DIR
    from posernet.cli.train import _instantiate_dict

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"out_dir={out_dir}"])
    return [c for c in _instantiate_dict(cfg.callbacks) if isinstance(c, ModelCheckpoint)]


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module (timing-insensitive, and no oversubscription on the
    2-core CI box); restored afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
