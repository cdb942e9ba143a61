"""Unrolled training: the model's own next frames as inputs, the true trajectory as targets.

Training noise (``bgn.model.noise``) perturbs windows with a chosen distribution; a rollout
perturbs them with the model's own errors. Unrolling feeds a training window through the
model S more steps (the "push-forward" trick of Brandstetter et al. 2022: the inputs of step
s are the model's frames, without gradient through them, so a step costs one more forward
and backward and no memory grows with S) and asks each step for the target that lands on the
true next velocity, exactly as noise's corrected target does. The model learns to correct
the errors it makes, at the distribution it makes them.

The graph keeps its edges over the unrolled steps (complete graphs do not change; a radius
graph built with the dataset's margin still holds the pairs that can touch within a few
frames), so only the dynamics head is trained on unrolled steps.
"""

from __future__ import annotations

import torch

from bgn.data.targets import step
from bgn.graph import Graph
from bgn.model.base import ModelOutput, PhysicsModel
from bgn.model.noise import moved


def advance(g: Graph, predicted: torch.Tensor, kind: str, s: int) -> Graph:
    """The graph one frame after ``g`` when the model's step takes ``predicted`` (physical
    target, (N, D)), with the target that reaches the true velocity ``g.future_vel[:, s]``:
    that velocity itself for next-velocity scenes, ``(v_true - v_model) / dt`` for
    acceleration scenes (the inverse of ``bgn.data.targets.step``)."""
    if g.future_vel is None or g.dt is None:
        raise ValueError("unrolled training needs graphs with future velocities and dt: set "
                         "dataset.unroll > 0")
    dt = g.dt.to(g.vel.dtype)[g.batch][:, None]
    if g.kinematic is not None:  # moved by the source: their true step, never the model's
        predicted = torch.where(g.kinematic[:, None], g.target.to(predicted.dtype), predicted)
    pos, vel = step(g.pos, g.vel[:, 0], predicted.to(g.vel.dtype), dt, kind)
    v_true = g.future_vel[:, s]
    target = v_true if kind == "velocity" else (v_true - vel) / dt
    return moved(g, pos - g.pos, vel=torch.cat([vel[:, None], g.vel[:, :-1]], dim=1),
                 target=target, frame=g.frame + 1)


def unrolled_loss(model: PhysicsModel, g: Graph, out: ModelOutput) -> torch.Tensor:
    """Mean dynamics loss of the ``S = g.future_vel.shape[1]`` steps that follow ``g`` when
    ``model`` is fed its own frames (``out``: its outputs on ``g``). Push-forward: no gradient
    flows through the inputs of a step, only through its prediction."""
    if g.future_vel is None or g.future_vel.shape[1] == 0:
        raise ValueError("unrolled training needs graphs with future velocities: set "
                         "dataset.unroll > 0")
    predicted = model.denormalize_target(out.target.detach(), g)
    losses = []
    for s in range(g.future_vel.shape[1]):
        g = advance(g, predicted, model.meta.target, s)
        target = model.forward_target(g)
        losses.append(model.target_coder.loss(target, g))
        predicted = model.denormalize_target(target.detach(), g)
    return torch.stack(losses).mean()
