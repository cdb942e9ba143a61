"""No-learning references: predict the next target by extrapolating the observed window.

``last`` repeats the last observed target (for collisions: free flight, no impact at all),
``linear`` extrapolates the last two. They fulfil what the learned simulator asks of a model
(``meta``, ``history``, ``predict``), so they roll out beside the models on equal terms.
``FrameOracle`` is the upper anchor on force scenes: the true law and masses, fed frames.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from bgn.graph import Graph
from bgn.model.newton import shoot
from bgn.model.target_coder import extrapolate, observed_targets
from bgn.sim.nbody import NBodyScene
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


class FrameOracle(nn.Module):
    """The scene's true force law and the true masses, integrated through each frame in
    ``substeps`` Verlet steps from the velocity the last two frames imply (``newton.shoot``):
    what a model that knew the physics exactly could predict from frames alone. Its rollout
    error, beside the exact simulator's predictability, separates what the frame rate loses
    (close encounters a frame does not resolve) from what a learned model loses."""

    def __init__(self, scene: NBodyScene, history: int, substeps: int = 64) -> None:
        super().__init__()
        self.meta, self.history, self.scene, self.substeps = scene.meta, history, scene, substeps
        self.label = f"frame oracle (true law and masses, {substeps} substeps)"

    def predict(self, g: Graph) -> torch.Tensor:
        b = g.num_graphs
        n = g.pos.shape[0] // b
        masses = g.mass.detach().double().cpu().numpy().reshape(b, n)

        def accel(x: torch.Tensor) -> torch.Tensor:
            xs = x.detach().double().cpu().numpy().reshape(b, n, -1)
            a = [self.scene.accelerations(xs[i], masses[i]) for i in range(b)]
            return torch.as_tensor(np.stack(a).reshape(b * n, -1), dtype=x.dtype,
                                   device=x.device)

        dt = g.dt.to(g.vel.dtype)[g.batch][:, None]
        return shoot(accel, g.pos, g.vel[:, 0], dt, self.substeps)
