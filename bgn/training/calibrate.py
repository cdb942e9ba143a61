"""Rollout calibration of the soft-contact head's dissipation, after the fit.

A one-step fit sees a contact one frame at a time. How much energy a pile of discs loses over
many contacts it barely sees, and the longer the fit runs the less its contacts dissipate
(docs/results.md, "Granular media"): its rollouts keep too much speed and the pile stays loose.
So after the fit one constant is set on what it governs, rollouts: the damping ratio of the
pair contacts (the walls' kept in proportion), chosen by a golden-section search in log space
so that the mean speed of rollouts from windows of the training split follows the recorded
one over ``HORIZON`` frames (the mean squared difference of their logs). Only the training
split is read; the value the fit found is one of the candidates, so the calibration never
leaves the training misfit worse. docs/design.md#soft-contact-head-granular-media.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.model.soft_contact import SoftContactHead
from bgn.rollout import rollout_many, rollout_starts
from bgn.training.checkpoints import save_atomic

log = logging.getLogger(__name__)

HORIZON = 100                 # frames each calibration rollout runs
SIMS = 4                      # training simulations rolled out (evenly spaced)
ZETA_RANGE = (1e-3, 1.0)      # the pair damping ratios searched (log-spaced bracket)
ITERATIONS = 10               # golden-section steps: the bracket shrinks to 0.618^10 of 3 decades


def soft_contact_head(model: nn.Module) -> SoftContactHead | None:
    """A model's soft-contact head (BGN's ``force_head``), or None."""
    head = getattr(model, "force_head", None)
    return head if isinstance(head, SoftContactHead) else None


def speed_misfit(predicted: np.ndarray, true: np.ndarray) -> float:
    """Mean over rollouts and frames of the squared difference of the logs of the mean speed
    (per frame, from frame differences) of ``predicted`` and ``true`` (R, T, N, D); a failed
    rollout (non-finite) counts as infinitely wrong."""
    if not np.isfinite(predicted).all():
        return math.inf

    def mean_speed(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.diff(x, axis=1), axis=-1).mean(-1)      # (R, T-1)

    tiny = 1e-12
    return float(np.mean((np.log(mean_speed(predicted) + tiny)
                          - np.log(mean_speed(true) + tiny)) ** 2))


def calibrate_dissipation(model: nn.Module, dataset: FrameDataset, horizon: int = HORIZON,
                          sims: int = SIMS, iterations: int = ITERATIONS) -> dict[str, Any]:
    """Set ``model``'s soft-contact damping to the value whose rollouts from ``dataset`` (the
    training split) keep its mean speed best (module doc); the record of the search."""
    head = soft_contact_head(model)
    if head is None:
        raise ValueError(f"{type(model).__name__} has no soft-contact head to calibrate")
    horizon = min(int(horizon), dataset.file.n_frames - dataset.history - 2)
    chosen = evenly_spaced(dataset.file.n_sims, sims)
    starts = rollout_starts(dataset, horizon)
    pair0, wall0 = float(head.pair.zeta().detach()), float(head.wall.zeta().detach())
    ratio = wall0 / pair0 if pair0 > 0 else 1.0
    tried: dict[float, float] = {}
    was_training = model.training
    model.eval()

    def misfit(zeta: float) -> float:
        head.pair.set_zeta(zeta)
        head.wall.set_zeta(zeta * ratio)
        t = rollout_many(model, dataset, chosen, starts, horizon)
        tried[zeta] = speed_misfit(t.predicted, t.true)
        return tried[zeta]

    fit = misfit(pair0)
    lo, hi = (math.log(z) for z in ZETA_RANGE)
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = hi - g * (hi - lo), lo + g * (hi - lo)
    fc, fd = misfit(math.exp(c)), misfit(math.exp(d))
    for _ in range(iterations):
        if fc < fd:
            hi, d, fd = d, c, fc
            c = hi - g * (hi - lo)
            fc = misfit(math.exp(c))
        else:
            lo, c, fc = c, d, fd
            d = lo + g * (hi - lo)
            fd = misfit(math.exp(d))
    best = min(tried, key=tried.get)
    head.pair.set_zeta(best)
    head.wall.set_zeta(best * ratio)
    model.train(was_training)
    record = {"horizon": horizon, "simulations": [int(s) for s in chosen],
              "starts": [int(s) for s in starts], "pair_zeta_fit": pair0,
              "wall_zeta_fit": wall0, "misfit_fit": fit, "pair_zeta": best,
              "wall_zeta": best * ratio, "misfit": tried[best],
              "pair_restitution": head.pair.restitution(),
              "wall_restitution": head.wall.restitution(),
              "tried": [[z, m] for z, m in sorted(tried.items())]}
    log.info("soft contacts calibrated on %d training rollouts of %d frames: pair damping "
             "ratio %.4g -> %.4g (restitution %.3g), speed misfit %.3g -> %.3g",
             len(chosen) * len(starts), horizon, pair0, best, record["pair_restitution"],
             fit, tried[best])
    return record


def calibrate_checkpoint(path: Path, dataset: FrameDataset) -> dict[str, Any]:
    """``calibrate_dissipation`` of the model in checkpoint ``path``, written back into it
    (its damping parameters and the record, under ``"calibration"``; replaced whole, so a
    crash leaves the old file)."""
    from bgn.training.module import load_model

    module = load_model(path)
    record = calibrate_dissipation(module.model, dataset)
    state = {f"model.{k}": v for k, v in module.model.state_dict().items()}
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    for key in ckpt["state_dict"]:
        if key.endswith(("pair.damping", "wall.damping")) and key in state:
            ckpt["state_dict"][key] = state[key].detach().clone()
    ckpt["calibration"] = record
    save_atomic(ckpt, path)
    return record
