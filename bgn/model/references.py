"""No-learning references: predict the next target by extrapolating the observed window.

``last`` repeats the last observed target (for collisions: free flight, no impact at all),
``linear`` extrapolates the last two. They fulfil what the learned simulator asks of a model
(``meta``, ``history``, ``predict``), so they roll out beside the models on equal terms.
"""

from __future__ import annotations

import torch
from torch import nn

from bgn.graph import Graph
from bgn.model.target import extrapolate, observed_targets
from bgn.sim.scene import SceneMeta

REFERENCES = ("last", "linear")


class Extrapolation(nn.Module):
    """The target predicted from the input window alone (``prior``: last or linear)."""

    def __init__(self, meta: SceneMeta, history: int, prior: str) -> None:
        super().__init__()
        if prior not in REFERENCES:
            raise ValueError(f"no reference named {prior!r}; choose one of {REFERENCES}")
        self.meta, self.history, self.prior = meta, history, prior
        self.label = f"{prior} extrapolation"

    def predict(self, g: Graph) -> torch.Tensor:
        return extrapolate(observed_targets(g, self.meta.target), self.prior)
