"""Evaluation of a trained checkpoint on the test split (used by ``bgn.experiments``).

Forward metrics (MSE in physical units, NMSE = MSE / training target variance as the
LightningModule logs it, median relative error, the no-learning references), the inverse
metrics of ``bgn.metrics`` on the flow's posterior beside the prior-only sampler and the
force-law estimator (``evaluate_inverse``, ``bgn.inverse_references``), type metrics, and
rollout metrics of the model and the no-learning references through the learned simulator.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import norm

from bgn.checkpoints import CheckpointError, read
from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.graph import Graph, collate
from bgn.inverse_references import MassPrior, impact_log_mass, physical_log_mass
from bgn.metrics import (
    COVERAGE_LEVELS,
    aggregate_gaussian,
    binary_f1,
    calibration_metrics,
    coverage_curve,
    fit_radius_map,
    inverse_metrics,
    kde_modes,
    r2_score,
    recovered_modes,
    relative_mass_error,
    rollout_metrics,
    type_metrics,
)
from bgn.model.encoder import approach_gap
from bgn.model.impulse import ContactImpulseHead
from bgn.model.references import REFERENCES, Extrapolation
from bgn.model.target import extrapolate, observed_targets
from bgn.module import PhysicsModule
from bgn.rollout import predictability, rollout_many, rollout_starts
from bgn.simulator import Predictor

# the metric functions live in bgn.metrics; imports of them from here keep working
__all__ = ["batches", "calibrate_mass_posterior", "evaluate_model", "evaluate_rollouts",
           "inverse_metrics", "kde_modes", "load_model", "mass_figure", "r2_score",
           "recovered_modes", "type_metrics"]


# ----------------------------------------------------------------------------- loading
def load_model(ckpt: str | Path) -> PhysicsModule:
    """The LightningModule of a checkpoint, on the CPU, in eval mode; read with
    ``weights_only=True``, and an unreadable file is named (``bgn.checkpoints.read``)."""
    record = read(ckpt)  # a missing, truncated or foreign file: one CheckpointError naming it
    try:
        module = PhysicsModule.load_from_checkpoint(ckpt, map_location="cpu", weights_only=True)
    except RuntimeError as err:  # torch: "Error(s) in loading state_dict ... key(s) ..."
        if "state_dict" not in str(err):
            raise
        model = ((record.get("hyper_parameters") or {}).get("model_config") or {}).get("name")
        detail = " ".join(str(err).split())[:300]
        raise CheckpointError(
            f"checkpoint {ckpt} does not fit this version of bgn's {model or 'model'}: it was "
            "written by a bgn whose model had other weights (torch says: "
            f"{detail}); retrain it with this version (python -m bgn.train ...)") from None
    return module.eval()


def batches(dataset: FrameDataset, indices: list[int], batch_size: int) -> list[Graph]:
    """The frames ``indices`` of ``dataset`` as batched graphs of ``batch_size`` frames."""
    return [collate([dataset[i] for i in indices[s:s + batch_size]])
            for s in range(0, len(indices), batch_size)]


# ----------------------------------------------------------------------------- evaluation
@torch.no_grad()
def calibrate_mass_posterior(module: PhysicsModule, dataset: FrameDataset,
                             frames: int | None = 256, batch_size: int = 16,
                             ) -> dict[str, float]:
    """Fit the mass flow's radius map on ``frames`` evenly spaced frames of ``dataset`` (the
    validation split: never the split it is scored on), set it on the model
    (``InverseModel.calibration``) and return its scale at the levels 0.5 and 0.9
    (``m(z) / z``: 1 where the flow was calibrated, > 1 where overconfident). The map makes
    the central intervals of the flow hold their levels on those frames
    (``bgn.metrics.fit_radius_map``): post-hoc recalibration of a posterior that maximum
    likelihood left miscalibrated."""
    inverse = module.model.inverse
    inverse.calibration = torch.empty(2, 0)            # fit the raw flow's base values
    values = [module.model.mass_base_value(g).double().numpy()
              for g in batches(dataset, evenly_spaced(len(dataset), frames), batch_size)]
    z, r = fit_radius_map(np.concatenate(values))
    inverse.calibration = torch.tensor(np.stack([z, r]), dtype=torch.float32)
    return {f"mass_calibration_scale{int(level * 100)}": float(np.interp(q, z, r) / q)
            for level in (0.5, 0.9) for q in [norm.ppf((1 + level) / 2)]}


@torch.no_grad()
def evaluate_model(module: PhysicsModule, dataset: FrameDataset, max_frames: int | None = 256,
                   mass_frames: int = 32, mass_samples: int = 32, batch_size: int = 16,
                   seed: int = 0, inverse: bool = True,
                   calibration: FrameDataset | None = None,
                   ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Metrics of one model on a test dataset, and the arrays behind the mass figure
    (``evaluate_inverse``; empty without an inverse head, or with ``inverse=False``: the
    forward error alone, as ``bgn.pareto`` needs it per checkpoint). ``calibration``: the split
    the mass flow's calibration is fitted on first (``calibrate_mass_posterior``, on
    ``mass_frames`` of its frames; ``mass_calibration_scale50/90`` in the metrics); None keeps
    the model's own (none after training)."""
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
    if model.has_inverse and inverse:
        if calibration is not None:
            metrics.update(calibrate_mass_posterior(module, calibration, mass_frames,
                                                    batch_size))
        inverse_values, arrays = evaluate_inverse(module, dataset, mass_frames, mass_samples,
                                                  batch_size, seed)
        metrics.update(inverse_values)
    return metrics, arrays


def _posterior_metrics(true_log: np.ndarray, sampled_log: np.ndarray,
                       log_posterior: np.ndarray | None, log_prior: np.ndarray,
                       particles: np.ndarray) -> dict[str, float]:
    """Sample, calibration and information metrics of one posterior (``bgn.metrics``);
    ``particles`` labels the distinct particles (one mass, several frames)."""
    return {**inverse_metrics(true_log, sampled_log),
            **calibration_metrics(true_log, sampled_log, log_posterior, log_prior, particles)}


def _point_metrics(estimate: np.ndarray, true_log: np.ndarray, particles: np.ndarray,
                   edges: np.ndarray, edge_rel: np.ndarray, variance: np.ndarray | None = None,
                   ) -> dict[str, float]:
    """Metrics of per-particle point estimates of log-mass (one per particle and frame):
    ``mass_rel_err`` (median ``|m_hat/m - 1|``), ``relmass_r2_estimate`` (R^2 of the relative
    log-mass ``estimate_i - estimate_j`` on the frames' edges) and ``sim_mass_rel_err``: the
    estimates of one particle pooled over the evaluated frames of its simulation, as masses
    do not change over time (DESIGN section 10): the product of per-frame Gaussians of the
    posterior's mean and ``variance`` (``bgn.metrics.aggregate_gaussian``; sharp frames weigh
    more: spring 1.5 % against 2.7 % for the plain mean in log), a plain mean without it."""
    _, index = np.unique(particles, return_inverse=True)
    _, pooled, _ = aggregate_gaussian(estimate, np.ones_like(estimate) if variance is None
                                      else variance, particles)
    truth = np.bincount(index, true_log) / np.bincount(index)
    return {"mass_rel_err": relative_mass_error(estimate, true_log),
            "relmass_r2_estimate": r2_score(estimate[edges[1]] - estimate[edges[0]], edge_rel),
            "sim_mass_rel_err": relative_mass_error(pooled, truth)}


def window_and_contacts(dataset: FrameDataset, index: int) -> tuple[np.ndarray,
                                                                    np.ndarray | None]:
    """The position window the model sees at dataset ``index`` (k+2, N, D) and, for a contact
    scene, its contacts as rows ``(frame within the window, i, j)``."""
    sim, t = dataset.locate(index)
    first = t - dataset.history - 1
    window = dataset.file.read("positions", (sim, slice(first, t + 1)))
    if dataset.meta.interaction != "contact":
        return window, None
    table = dataset.file.read("contacts", ...)
    rows = table[(table[:, 0] == sim) & (table[:, 1] >= first) & (table[:, 1] < t)]
    return window, np.column_stack([rows[:, 1] - first, rows[:, 2], rows[:, 3]])


def _physical(dataset: FrameDataset, prior: MassPrior,
              views: list[tuple[np.ndarray, np.ndarray | None]]) -> np.ndarray:
    """The force-law estimate (N,) from the windows (and contacts) of one simulation."""
    windows = np.stack([w for w, _ in views])
    contacts = None if views[0][1] is None else [c for _, c in views]
    return physical_log_mass(dataset.scene, prior, windows, dataset.dt, contacts)


def _impact_solve_error(dataset: FrameDataset, prior: MassPrior,
                        per_sim: dict[int, list[tuple[np.ndarray, np.ndarray | None]]],
                        model_contacts: dict[int, list[np.ndarray]], sampled: np.ndarray,
                        particles: np.ndarray) -> float:
    """A contact scene's per-simulation masses the model's way, and their median relative
    error: the momentum exchanged at the impacts its contact head sees in the evaluated
    windows, solved jointly per simulation (``impact_log_mass``), each group of discs linked by
    impacts placed by the flow's pooled posteriors of its members; a disc in no usable impact
    keeps its pooled posterior mean. Per-frame posteriors alone cannot do this: each impact
    says how a disc's mass compares with its partner's, which the flow sees one frame at a
    time."""
    labels, mean, var = aggregate_gaussian(sampled.mean(axis=0), sampled.var(axis=0), particles)
    estimate, truth = [], []
    for sim, views in per_sim.items():
        true_log = np.log(dataset.file.read("masses", sim))
        mine = labels // 1_000_000 == sim
        index = labels[mine] % 1_000_000
        gauge = np.full((2, len(true_log)), np.nan)
        gauge[0, index], gauge[1, index] = mean[mine], var[mine]
        solved = impact_log_mass(prior, np.stack([w for w, _ in views]), dataset.dt,
                                 model_contacts[sim], gauge=(gauge[0], gauge[1]))
        estimate.append(np.where(np.isfinite(solved), solved, gauge[0]))
        truth.append(true_log)
    return relative_mass_error(np.concatenate(estimate), np.concatenate(truth))


@torch.no_grad()
def evaluate_inverse(module: PhysicsModule, dataset: FrameDataset, mass_frames: int = 32,
                     mass_samples: int = 32, batch_size: int = 16, seed: int = 0,
                     ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The inverse model beside its two references (``bgn.inverse_references``) on every
    particle of ``mass_frames`` evenly spaced test frames (they cover every simulation).

    Keys: the model's metrics unprefixed; ``prior/...`` the prior-only sampler's (the same
    number of draws from the scene's mass law, its exact density); ``physical/...`` the
    force-law estimator on each frame's window (NaN where the window says nothing: the prior's
    mean), with ``physical/identified`` the share it could estimate. Per-simulation
    aggregates (``sim_mass_rel_err``): the product of the model's per-frame posteriors (as
    Gaussians) over the evaluated frames of a simulation; the estimator's least squares over
    all those windows at once (``physical/sim_identified``: the share of particles it could
    estimate). Arrays for the figure: true and sampled masses and the coverage curves of the
    model and the prior."""
    model = module.model
    prior = MassPrior.of_scene(dataset.scene)
    rng = np.random.default_rng(seed)
    indices = evenly_spaced(len(dataset), mass_frames)
    true_log, sampled, log_post, physical, particles, edges, edge_rel = ([] for _ in range(7))
    per_sim: dict[int, list[tuple[np.ndarray, np.ndarray | None]]] = {}
    # the contact head's impacts in each window: its per-simulation mass solve
    head = getattr(model, "force_head", None)
    seen_contacts = (head.window_contacts if isinstance(head, ContactImpulseHead) else None)
    model_contacts: dict[int, list[np.ndarray]] = {}
    offset = 0
    for s in range(0, len(indices), batch_size):
        chunk = indices[s:s + batch_size]
        g = collate([dataset[i] for i in chunk])
        samples, density = model.mass_posterior(g, mass_samples)
        sampled.append(samples.double().numpy())
        log_post.append(density.double().numpy())
        true_log.append(torch.log(g.mass.double()).numpy())
        # one key per particle of a simulation, the same in every frame: sim * 1e6 + index
        first_node = torch.cumsum(g.num_nodes, 0) - g.num_nodes
        node_index = torch.arange(len(g.mass)) - first_node[g.batch]
        particles.append((g.sim[g.batch] * 1_000_000 + node_index).numpy())
        edges.append(g.edge_index.numpy() + offset)
        edge_rel.append(g.edge_rel_log_mass.double().numpy())
        offset += len(g.mass)
        rows = None if seen_contacts is None else seen_contacts(g)
        for b, i in enumerate(chunk):
            window, contacts = window_and_contacts(dataset, i)
            sim = dataset.locate(i)[0]
            per_sim.setdefault(sim, []).append((window, contacts))
            physical.append(_physical(dataset, prior, [(window, contacts)]))
            if rows is not None:    # (j, i, k) graph-wide -> (frame in the window, i, k) local
                mine = rows[g.batch[rows[:, 1]] == b]
                model_contacts.setdefault(sim, []).append(torch.stack(
                    [len(window) - 1 - mine[:, 0], mine[:, 1] - first_node[b],
                     mine[:, 2] - first_node[b]], 1).numpy())
    true_log_a, sampled_a = np.concatenate(true_log), np.concatenate(sampled, axis=1)
    particles_a, edges_a = np.concatenate(particles), np.concatenate(edges, axis=1)
    rel_a = np.concatenate(edge_rel)
    log_prior = prior.log_pdf(true_log_a)
    metrics: dict[str, Any] = _posterior_metrics(true_log_a, sampled_a,
                                                 np.concatenate(log_post), log_prior,
                                                 particles_a)
    metrics.update(_point_metrics(sampled_a.mean(axis=0), true_log_a, particles_a, edges_a,
                                  rel_a, sampled_a.var(axis=0)))
    if model_contacts:
        metrics["sim_mass_rel_err_flow"] = metrics["sim_mass_rel_err"]
        metrics["sim_mass_rel_err"] = _impact_solve_error(
            dataset, prior, per_sim, model_contacts, sampled_a, particles_a)
    metrics["mass_particles"] = int(len(true_log_a))
    prior_samples = prior.sample(sampled_a.shape, rng)
    references = {"prior": _posterior_metrics(true_log_a, prior_samples, log_prior, log_prior,
                                              particles_a)}
    estimate = np.concatenate(physical)
    pooled = {sim: _physical(dataset, prior, views) for sim, views in per_sim.items()}
    sim_estimate = np.concatenate(list(pooled.values()))
    sim_true = np.log(np.concatenate([dataset.file.read("masses", sim) for sim in pooled]))
    references["physical"] = {
        **_point_metrics(np.where(np.isfinite(estimate), estimate, prior.mean), true_log_a,
                         particles_a, edges_a, rel_a),
        "identified": float(np.mean(np.isfinite(estimate))),
        # per simulation: one least-squares fit of all its windows, not a mean of estimates
        "sim_mass_rel_err": relative_mass_error(
            np.where(np.isfinite(sim_estimate), sim_estimate, prior.mean), sim_true),
        "sim_identified": float(np.mean(np.isfinite(sim_estimate)))}
    for name, values in references.items():
        metrics.update({f"{name}/{k}": v for k, v in values.items()})
    arrays = {"true_mass": np.exp(true_log_a), "sampled_mass": np.exp(sampled_a),
              "coverage_levels": COVERAGE_LEVELS,
              "coverage": coverage_curve(true_log_a, sampled_a),
              "coverage_prior": coverage_curve(true_log_a, prior_samples)}
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
    """Write the KDE of true vs sampled masses beside the coverage curves of the model and
    the prior-only sampler (``figures.mass_calibration``) as a PNG."""
    from bgn.figures import mass_calibration, save

    return save(mass_calibration(arrays["true_mass"], arrays["sampled_mass"].ravel(),
                                 arrays["coverage_levels"],
                                 {"model": arrays["coverage"],
                                  "prior-only sampler": arrays["coverage_prior"]}), path)
