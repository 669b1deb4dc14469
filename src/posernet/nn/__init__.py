"""PoserNet's network: pure-torch scatter ops, the ``PoserConv`` layer, the model and the loss.

Nothing here imports Lightning or Hydra: another GNN can import :class:`PoserConv` for the
price of torch alone.
"""

from ..scatter import scatter_count, scatter_max, scatter_mean, scatter_sum
from .conv import PoserConv, PoserConvOutput, graph_inputs
from .loss import PoserLoss, PoserNetLoss, posernet_loss
from .mlp import MLP
from .model import PoserNet

__all__ = [
    "MLP",
    "PoserConv",
    "PoserConvOutput",
    "PoserLoss",
    "PoserNet",
    "PoserNetLoss",
    "graph_inputs",
    "posernet_loss",
    "scatter_count",
    "scatter_max",
    "scatter_mean",
    "scatter_sum",
]
