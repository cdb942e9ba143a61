"""What the dynamics head predicts: the target itself, or its change from the history.

At the paper's frame rates the target (acceleration of a force scene, next velocity of
collisions) changes little from one frame to the next, so repeating or linearly
extrapolating the observed targets is already a strong prediction. A network that outputs
the whole target must first reproduce that smooth part. With a prior it predicts only what
the history does not already say (the same idea as GNS predicting accelerations rather than
positions):

- ``none``: the normalised target (the paper);
- ``last``: target minus the last observed target, ``a[t-1] = (v[t] - v[t-1]) / dt`` for force
  scenes, ``v[t]`` for collisions (whose change is zero between impacts);
- ``linear``: target minus ``2 y[t-1] - y[t-2]`` (force scenes; needs history >= 2);
- ``auto`` (default): ``linear`` for accelerations, ``last`` for velocities (a linear
  extrapolation of velocities across an impact doubles the error there).

gravity_r2 is the exception (``target_prior: none`` for every model there, set in
``conf/dataset_model/gravity_r2_<model>.yaml``): at 1/r^2 close encounters the linear
extrapolation errs by more than the target varies, and no parameterisation wins both the MSE
of Table 1 and the median error; the scene default takes the one that wins the MSE.

The prior is computed from the clean input window only (no leak of the target; a baseline's
training noise corrupts what its network sees, not the prior). Residuals are normalised by the
robust scale of the training split's target differences (``target_diff1``, ``target_diff2`` in
``bgn.data.stats``). Those residuals are heavy-tailed (close encounters, light particles): an
MSE in robust units is set by a handful of frames, so the default dynamics loss (``auto``) for
accelerations is a Huber loss (quadratic within ``huber_delta`` robust units, linear beyond).
For collisions the change of velocity is zero except at impacts, and impacts are what the MSE
of Table 1 measures: a Huber loss fits them like a median and loses them, so ``auto`` keeps
the MSE there, as it does with no prior (the paper). ``relative`` scores each particle's squared
error over its own target's size, so that small accelerations (far pairs) weigh as much as an
encounter's. The metrics are always on the physical target. The measurements behind each
choice: docs/results.md, "Measurements behind the defaults".
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from bgn.graph import Graph
from bgn.model.normalizer import Normalizer, robust_scale
from bgn.sim import SceneMeta

PRIORS = ("auto", "none", "last", "linear")
LOSSES = ("auto", "mse", "huber", "relative")
# dynamics_loss=relative: a target this many times smaller than the batch's median in squared
# size counts half (a floor against dividing by the zero-crossings of a target)
RELATIVE_FLOOR = 1e-3
_DIFF_STATS = {"last": "target_diff1", "linear": "target_diff2"}


def relative_squared_error(predicted: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(N,) each row's squared error over the squared size of its ``target`` (N, D), the size
    floored at ``RELATIVE_FLOOR`` times the batch's median size: every distance of a pair law
    weighs alike. The floor is the median's, not the mean's: on gravity_r2 the close
    encounters set the mean, and the law loss's former floor, 1e-4 of the mean, covered over
    half the particles, whose errors then counted as absolute ones (docs/results.md, "The
    network's law per distance band")."""
    size = (target * target).sum(-1)
    return ((predicted - target) ** 2).sum(-1) / (size + relative_floor(size))


def relative_floor(size: torch.Tensor) -> torch.Tensor:
    """The floor of ``relative_squared_error``'s squared sizes ``size`` (N,): a target this
    much smaller than the batch's median counts half."""
    return RELATIVE_FLOOR * size.median().detach() + 1e-30


def observed_targets(g: Graph, kind: str) -> torch.Tensor:
    """The targets of the frames before ``t`` that the velocity window determines, newest
    first: (N, k+1, D) velocities for velocity targets, (N, k, D) finite-difference
    accelerations for acceleration targets (exactly ``bgn.data.targets.targets``)."""
    if kind == "velocity":
        return g.vel
    if g.dt is None:
        raise ValueError("an acceleration prior needs the frame spacing: the graph has no dt "
                         "(graphs from bgn.data.dataset.frame_graph carry it)")
    dt = g.dt.to(g.vel.dtype)[g.batch][:, None, None]
    return (g.vel[:, :-1] - g.vel[:, 1:]) / dt


def extrapolate(seen: torch.Tensor, prior: str) -> torch.Tensor:
    """(N, D) prediction of the next target from ``observed_targets`` (newest first):
    ``last`` repeats ``y[t-1]``, ``linear`` is ``2 y[t-1] - y[t-2]``."""
    if prior == "last":
        return seen[:, 0]
    if prior == "linear":
        return 2 * seen[:, 0] - seen[:, 1]
    raise ValueError(f"no extrapolation named {prior!r}; use last or linear")


def resolve_prior(prior: str, target: str, history: int) -> tuple[str, int, int]:
    """``(prior, needed, available)``: the prior ``auto`` stands for, the observed targets it
    needs and those a window of ``history`` past velocities gives."""
    if prior == "auto":
        prior = "linear" if target == "acceleration" and history >= 2 else "last"
    available = history + 1 if target == "velocity" else history
    return prior, {"none": 0, "last": 1, "linear": 2}.get(prior, 0), available


def prior_hint(prior: str, needed: int, history: int, available: int,
               asked: str | None = None) -> str:
    """Why a window is too short for a prior, and the settings that work (``asked``: the
    setting that chose ``prior``, e.g. auto)."""
    fits = [p for p, n in (("last", 1), ("none", 0)) if n <= available and p != prior]
    shown = prior if asked in (None, prior) else f"{asked} (here {prior})"
    return (f"model.target_prior={shown} needs {needed} observed target(s), a window of "
            f"dataset.history={history} gives {available}: raise dataset.history to "
            f"{history + needed - available} or set model.target_prior={fits[0]}")


class TargetCoder(nn.Module):
    """Physical target <-> what the dynamics head outputs, for one ``prior`` (see module doc)."""

    def __init__(self, normalizer: Normalizer, stats: Mapping[str, Any], meta: SceneMeta,
                 history: int, prior: str = "none", loss: str = "mse",
                 huber_delta: float = 1.0) -> None:
        super().__init__()
        if prior not in PRIORS:
            raise ValueError(f"target_prior={prior!r}; choose one of {PRIORS}")
        if loss not in LOSSES:
            raise ValueError(f"dynamics_loss={loss!r}; choose one of {LOSSES}")
        if not huber_delta > 0:
            raise ValueError(f"huber_delta={huber_delta} must be > 0")
        prior, needed, available = resolve_prior(prior, meta.target, history)
        if loss == "auto":  # heavy-tailed residuals (force scenes) vs impacts that are the signal
            loss = "huber" if meta.target == "acceleration" and prior != "none" else "mse"
        self.loss_name, self.huber_delta = loss, float(huber_delta)
        if available < needed:
            raise ValueError(prior_hint(prior, needed, history, available))
        self.normalizer, self.prior_name, self.kind = normalizer, prior, meta.target
        if prior != "none":
            name = _DIFF_STATS[prior]
            if name not in stats:
                raise KeyError(f"the training statistics lack {name!r} (files written before "
                               "dataset schema 3): regenerate the dataset with "
                               "python -m bgn.train.generate, or use target_prior=none")
            scale = float(robust_scale(stats, name).mean())
            self.register_buffer("residual_scale", torch.tensor(scale, dtype=torch.float32))
        else:
            self.residual_scale = None

    def prior(self, g: Graph) -> torch.Tensor:
        """(N, D) the part of the target predicted from the window alone (physical units)."""
        if self.prior_name == "none":
            return torch.zeros_like(g.target)
        return extrapolate(observed_targets(g, self.kind), self.prior_name)

    def encode(self, g: Graph) -> torch.Tensor:
        """The graph's target in the head's units, (N, D)."""
        return self.code(g, g.target)

    def code(self, g: Graph, target: torch.Tensor) -> torch.Tensor:
        """A physical target of graph ``g`` in the head's units (the inverse of ``decode``)."""
        if self.residual_scale is None:
            return self.normalizer.target(target)
        return (target - self.prior(g)) / self.residual_scale

    def loss(self, output: torch.Tensor, g: Graph) -> torch.Tensor:
        """The dynamics loss ``L_Dec`` of the head's output against the graph's target, over
        the particles the model predicts (kinematic ones, moved by the source, are skipped)."""
        moved = slice(None) if g.kinematic is None else ~g.kinematic
        if self.loss_name == "relative":
            # each particle's squared error over its own target's size, both physical (so
            # neither the normaliser nor a prior's residual units enter): every distance weighs
            # alike, where a squared error is set by the few close encounters and leaves a
            # law's far tail unlearned (relative_squared_error)
            target = g.target.to(output.dtype)[moved]
            return relative_squared_error(self.decode(g, output)[moved], target).mean()
        y = self.encode(g)[moved]
        output = output[moved]
        if self.loss_name == "huber":
            return F.huber_loss(output, y, delta=self.huber_delta)
        return F.mse_loss(output, y)

    def decode(self, g: Graph, output: torch.Tensor) -> torch.Tensor:
        """The head's output -> physical target, (N, D)."""
        if self.residual_scale is None:
            return self.normalizer.denormalize_target(output)
        return output * self.residual_scale + self.prior(g)

