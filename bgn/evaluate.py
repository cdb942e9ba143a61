"""Evaluation of a trained checkpoint on the test split (used by ``bgn.experiments``).

Forward metrics (MSE in physical units, NMSE = MSE / training target variance as the
LightningModule logs it, median relative error, the no-learning references), the inverse
and type metrics of ``bgn.metrics`` on the model's mass samples and type logits, and rollout
metrics of the model and the no-learning references through the learned simulator.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bgn.checkpoints import read
from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.graph import Graph, collate
from bgn.metrics import (
    binary_f1,
    inverse_metrics,
    kde_modes,
    r2_score,
    recovered_modes,
    rollout_metrics,
    type_metrics,
)
from bgn.model.encoder import approach_gap
from bgn.model.references import REFERENCES, Extrapolation
from bgn.model.target import extrapolate, observed_targets
from bgn.module import PhysicsModule
from bgn.rollout import predictability, rollout_many, rollout_starts
from bgn.simulator import Predictor

# the metric functions live in bgn.metrics; imports of them from here keep working
__all__ = ["batches", "evaluate_model", "evaluate_rollouts", "inverse_metrics", "kde_modes",
           "load_model", "mass_figure", "r2_score", "recovered_modes", "type_metrics"]


# ----------------------------------------------------------------------------- loading
def load_model(ckpt: str | Path) -> PhysicsModule:
    """The LightningModule of a checkpoint, on the CPU, in eval mode; read with
    ``weights_only=True``, and an unreadable file is named (``bgn.checkpoints.read``)."""
    read(ckpt)  # a missing, truncated or foreign file: one CheckpointError naming it
    return PhysicsModule.load_from_checkpoint(ckpt, map_location="cpu", weights_only=True).eval()


def batches(dataset: FrameDataset, indices: list[int], batch_size: int) -> list[Graph]:
    """The frames ``indices`` of ``dataset`` as batched graphs of ``batch_size`` frames."""
    return [collate([dataset[i] for i in indices[s:s + batch_size]])
            for s in range(0, len(indices), batch_size)]


# ----------------------------------------------------------------------------- evaluation
@torch.no_grad()
def evaluate_model(module: PhysicsModule, dataset: FrameDataset, max_frames: int | None = 256,
                   mass_frames: int = 32, mass_samples: int = 32, batch_size: int = 16,
                   seed: int = 0) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Metrics of one model on a test dataset, and the arrays behind the mass figure
    (``{"true_mass": (N,), "sampled_mass": (S, N)}``, empty without an inverse head)."""
    torch.manual_seed(seed)  # the flow's samples and relmass noise are random
    model = module.model
    heads = model.heads
    variance = module.target_variance.mean().item()
    indices = evenly_spaced(len(dataset), max_frames)  # covers every test simulation
    sq_err, rel_err = [], []
    # references without learning: repeat the last observed target, extrapolate the last two
    ref_err: dict[str, list[torch.Tensor]] = {"last": [], "linear": []}
    logits, types, rel_pred, rel_true = [], [], [], []
    contact_scene = module.meta.interaction == "contact"
    contacts: dict[str, list[torch.Tensor]] = {"true": [], "head": [], "toi_rule": []}
    for g in batches(dataset, indices, batch_size):
        pred = model.predict(g)
        sq_err.append(((pred - g.target) ** 2).flatten())
        seen = observed_targets(g, module.meta.target)
        for name in ref_err if seen.shape[1] > 1 else ("last",):
            ref_err[name].append(((extrapolate(seen, name) - g.target) ** 2).flatten())
        rel_err.append((pred - g.target).norm(dim=-1)
                       / g.target.norm(dim=-1).clamp_min(1e-12))
        if contact_scene:  # the window's time-of-impact rule, with or without a contact head
            contacts["true"].append(g.edge_contact > 0.5)
            contacts["toi_rule"].append(approach_gap(g) <= 0)
        if heads & {"type", "relmass", "contact"}:
            out = model(g)
            if "contact" in heads and contact_scene:
                contacts["head"].append(out.contact > 0)       # logit > 0: probability > 0.5
            if "type" in heads:
                logits.append(out.type_logits)
                types.append(g.types)
            if "relmass" in heads:
                rel_pred.append(model.denormalize_relmass(out.relmass))
                rel_true.append(g.edge_rel_log_mass)
    mse = torch.cat(sq_err).mean().item()
    metrics: dict[str, Any] = {"mse": mse, "nmse": mse / variance,
                               "median_relative_error": torch.cat(rel_err).median().item(),
                               "n_frames": len(indices)}
    for name, errors in ref_err.items():
        if errors:
            metrics[f"nmse_{name}_extrapolation"] = torch.cat(errors).mean().item() / variance
    if logits:
        metrics.update(type_metrics(torch.cat(logits).numpy(), torch.cat(types).numpy()))
    if contacts["true"]:
        true_contacts = torch.cat(contacts["true"]).numpy()
        metrics["contact_rate"] = float(true_contacts.mean())
        for name in ("head", "toi_rule"):
            if contacts[name]:
                metrics[f"contact_f1_{name}"] = binary_f1(torch.cat(contacts[name]).numpy(),
                                                          true_contacts)
    if rel_pred:
        metrics["relmass_r2"] = r2_score(torch.cat(rel_pred).numpy(), torch.cat(rel_true).numpy())
    arrays: dict[str, np.ndarray] = {}
    if model.has_inverse:
        # every particle of a subset of test frames, each sampled mass_samples times
        true_mass, sampled = [], []
        for g in batches(dataset, evenly_spaced(len(dataset), mass_frames), batch_size):
            sampled.append(model.sample_mass(g, mass_samples))
            true_mass.append(g.mass)
        arrays = {"true_mass": torch.cat(true_mass).double().numpy(),
                  "sampled_mass": torch.cat(sampled, dim=1).double().numpy()}
        with np.errstate(divide="ignore", invalid="ignore"):
            metrics.update(inverse_metrics(np.log(arrays["true_mass"]),
                                           np.log(arrays["sampled_mass"])))
        metrics["mass_particles"] = int(arrays["true_mass"].shape[0])
    return metrics, arrays


def evaluate_rollouts(model: Predictor, dataset: FrameDataset, n_steps: int = 100,
                      starts_per_sim: int = 1, max_sims: int | None = None,
                      references: bool = True) -> dict[str, float]:
    """Rollout metrics (``bgn.metrics.rollout_metrics``) of ``model`` from the same start
    frames of every test simulation (frame 100 first), keyed ``rollout/<metric>``, and of the
    no-learning references beside it (``rollout_last/...``, ``rollout_linear/...``) and the
    scene's predictability limit (``predictability/...``: the exact simulator from positions
    1e-6 off, ``bgn.rollout.predictability``). Steps are capped by the file's length.
    Momentum is scored where the scene conserves it (no walls)."""
    n_steps = min(n_steps, dataset.file.n_frames - dataset.history - 2)
    starts = rollout_starts(dataset, n_steps, starts_per_sim)
    sims = evenly_spaced(dataset.file.n_sims, max_sims)
    predictors: dict[str, Predictor] = {"rollout": model}
    if references:
        for prior in REFERENCES:
            if prior == "linear" and dataset.meta.target == "velocity":
                continue  # across an impact a linear extrapolation of velocities doubles it
            predictors[f"rollout_{prior}"] = Extrapolation(dataset.meta, dataset.history, prior)
    runs = {key: partial(rollout_many, predictor, dataset, sims, starts, n_steps)
            for key, predictor in predictors.items()}
    if references:  # the true simulator from positions 1e-6 off: the chaos floor
        runs["predictability"] = partial(predictability, dataset, sims, starts, n_steps)
    metrics: dict[str, float] = {}
    for key, run in runs.items():
        t = run()
        values = rollout_metrics(t.predicted, t.true, t.masses, dataset.dt, dataset.scene.energy,
                                 t.first_non_finite, dataset.meta.box,
                                 momentum=dataset.meta.box is None,
                                 contacts=((t.radii, t.types)
                                           if dataset.meta.interaction == "contact" else None))
        values["seconds_per_step"] = t.seconds_per_step
        metrics.update({f"{key}/{name}": value for name, value in values.items()})
    return metrics


def mass_figure(arrays: dict[str, np.ndarray], path: str | Path) -> Path:
    """Write the KDE of true vs sampled masses (``figures.mass_density``) as a PNG."""
    from bgn.figures import mass_density, save

    return save(mass_density(arrays["true_mass"], arrays["sampled_mass"].ravel()), path)
