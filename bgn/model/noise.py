"""Training noise for rollouts: corrupt the input window, correct the target.

A model trained on clean windows has never seen the small errors that its own predictions
feed back into a rollout, and nothing teaches it to undo them: a residual on a history
extrapolation (``bgn.model.target_coder``) even carries them forward. Following Sanchez-Gonzalez
et al. 2020 (their random-walk noise), every training window gets a random walk added to its
velocities, the positions follow the noisy velocities, and the target is corrected so that
the step lands on the *true* next velocity: the model learns to pull a perturbed state back
onto the trajectory instead of continuing the perturbation.

Noise is a property of training, not of a model: the same function serves every model
(``PhysicsModel.corrupt``), so BGN and the baselines train for rollouts on equal terms.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import torch

from bgn.graph import Graph


def random_walk(shape: tuple[int, ...], std: float, like: torch.Tensor) -> torch.Tensor:
    """(N, k+1, D) noise on a velocity window stored newest first: increments of std
    ``std / sqrt(k+1)`` summed from the oldest entry to the newest, so the newest velocity's
    noise has std ``std`` and consecutive velocities are perturbed coherently (a drift, as a
    rollout's errors are), not independently."""
    steps = shape[1]
    increments = torch.randn(shape, dtype=like.dtype, device=like.device) * (std / steps**0.5)
    return increments.flip(1).cumsum(1).flip(1)


def add_random_walk_noise(g: Graph, std: torch.Tensor | float, kind: str) -> Graph:
    """The graph with random-walk noise of ``std`` (physical velocity units at the newest
    velocity) on its window, its positions moved consistently and its target corrected.

    Velocities are backward differences ``v[t-j] = (x[t-j] - x[t-j-1]) / dt`` of positions
    ``x[t-k-1] .. x[t]``; holding the oldest position, the noisy velocities move ``x[t]`` by
    ``dt * sum_j n_j`` (walls move with it; the edge set stays, its lengths follow). The
    target (``kind``: the scene's ``meta.target``) is corrected so that the model's step
    gives the true next velocity ``v[t+1]``: an acceleration ``(v[t+1] - v[t]) / dt`` becomes
    ``a - n_0 / dt``; a next-velocity target is the true ``v[t+1]`` already.
    """
    if g.dt is None:
        raise ValueError("training noise needs the frame spacing: the graph has no dt "
                         "(graphs from bgn.data.dataset carry it)")
    noise = random_walk(tuple(g.vel.shape), 1.0, g.vel) * std
    if g.kinematic is not None:  # moved by the source: their frames are given, never noisy
        noise = noise * (~g.kinematic).to(noise.dtype)[:, None, None]
    dt = g.dt.to(g.vel.dtype)[g.batch][:, None]                    # (N, 1)
    shift = dt * noise.sum(1)                                      # (N, D) moves x[t]
    target = g.target - noise[:, 0] / dt if kind == "acceleration" else g.target
    return moved(g, shift, vel=g.vel + noise, target=target)


def moved(g: Graph, shift: torch.Tensor, **changes: Any) -> Graph:
    """The graph with every position moved by ``shift`` (N, D), its wall distances with them
    (``[x - lo, hi - x]``), and the other fields in ``changes`` replaced."""
    wall = None if g.wall is None else g.wall + torch.cat([shift, -shift], dim=-1)
    return replace(g, pos=g.pos + shift, wall=wall, **changes)
