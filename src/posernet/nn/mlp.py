"""The small multi-layer perceptron used for PoserNet's update functions ``Psi_E`` and ``Psi_N``."""

from __future__ import annotations

import itertools

from torch import Tensor, nn

__all__ = ["MLP"]


class MLP(nn.Module):
    """``num_layers`` fully connected layers with leaky ReLU between them.

    The paper's ``Psi`` (supplementary, "Implementation Details"): three linear layers of 32
    units, each followed by a leaky ReLU. ``act_last=False`` drops the activation after the last
    layer, which a regression head needs (a leaky ReLU would squash negative pose entries).

    Args:
        in_dim: input features.
        out_dim: output features.
        hidden: units of each hidden layer (default 32).
        num_layers: number of linear layers, >= 1 (default 3).
        negative_slope: slope of the leaky ReLU (default 0.01).
        act_last: apply the activation after the last layer too (default True).

    Shapes: ``(*, in_dim) -> (*, out_dim)``.
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        hidden: int = 32,
        num_layers: int = 3,
        negative_slope: float = 0.01,
        act_last: bool = True,
    ) -> None:
        super().__init__()
        if num_layers < 1:
            raise ValueError(f"MLP needs at least one layer, got num_layers={num_layers}")
        if min(in_dim, out_dim, hidden) < 1:
            raise ValueError(f"MLP sizes must be positive: in={in_dim} out={out_dim} "
                             f"hidden={hidden}")
        self.in_dim, self.out_dim, self.hidden = in_dim, out_dim, hidden
        self.num_layers, self.negative_slope, self.act_last = num_layers, negative_slope, act_last
        dims = [in_dim] + [hidden] * (num_layers - 1) + [out_dim]
        layers: list[nn.Module] = []
        for k, (a, b) in enumerate(itertools.pairwise(dims)):
            layers.append(nn.Linear(a, b))
            if k < num_layers - 1 or act_last:
                layers.append(nn.LeakyReLU(negative_slope))
        self.net = nn.Sequential(*layers)

    def reset_parameters(self) -> None:
        """Re-initialise every linear layer (PyTorch's default initialisation)."""
        for m in self.net:
            if isinstance(m, nn.Linear):
                m.reset_parameters()

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({self.in_dim} -> {self.out_dim}, hidden={self.hidden}, "
                f"layers={self.num_layers}, act_last={self.act_last})")
