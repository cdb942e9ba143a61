"""Forward decoder (paper section "Decoder definition and design", Eq. 5).

One two-layer raw-residual head per spatial dimension maps ``H̃_CV`` to that component of the
target: ``y_d = s(H̃_CV W0_d + H̃_CV) W1_d``. The raw path is zero-padded or truncated to the
hidden width (``ops.pad_features``). ``shared=True`` (ablation) uses one head for all D outputs.
"""

from __future__ import annotations

import torch
from torch import nn

from bgn.model.ops import activation, pad_features


class RawResidualHead(nn.Module):
    """``x -> s(x W0 + pad(x)) W1``: two linear layers, raw residual on the first."""

    def __init__(self, in_features: int, hidden: int, out_features: int,
                 act: str = "silu") -> None:
        super().__init__()
        self.hidden = hidden
        self.linear0 = nn.Linear(in_features, hidden)
        self.linear1 = nn.Linear(hidden, out_features)
        self.act = activation(act)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear1(self.act(self.linear0(x) + pad_features(x, self.hidden)))


class Decoder(nn.Module):
    """``H̃_CV`` (N, F) -> normalised target (N, D)."""

    def __init__(self, in_features: int, hidden: int, dim: int, act: str = "silu",
                 shared: bool = False) -> None:
        super().__init__()
        self.shared = shared
        if shared:
            self.heads = nn.ModuleList([RawResidualHead(in_features, hidden, dim, act)])
        else:  # Eq. 5: one head per dimension
            self.heads = nn.ModuleList(RawResidualHead(in_features, hidden, 1, act)
                                       for _ in range(dim))

    def forward(self, h_cv: torch.Tensor) -> torch.Tensor:
        return torch.cat([head(h_cv) for head in self.heads], dim=-1)
