"""Evaluation of a trained checkpoint on the test split (used by ``bgn.studies.grid``).

Forward metrics (MSE in physical units, NMSE = MSE / training target variance as the
LightningModule logs it, median relative error, the no-learning references), the inverse
metrics of ``bgn.metrics`` on the flow's posterior beside the prior-only sampler and the
force-law estimator (``evaluate_inverse``, ``bgn.eval.mass_baselines``), type metrics, and
rollout metrics of the model and the no-learning references through the learned simulator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from scipy.stats import norm

from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.eval.impact_posterior import (
    choose_noise,
    contact_rows,
    mixed_with_types,
    posterior_of,
    simulation_impacts,
    window_and_contacts,
)
from bgn.eval.law_posterior import (
    KEY,
    LawPosterior,
    contamination,
    fit_simulations,
    laplace_posterior,
    law_scale_pinned,
    place_scale,
    simulation_frames,
)
from bgn.eval.mass_baselines import (
    MassPrior,
    impact_log_mass,
    physical_log_mass,
    place_by_prior,
    prior_shift_error,
)
from bgn.graph import Graph, collate
from bgn.metrics import (
    COVERAGE_LEVELS,
    aggregate_gaussian,
    binary_f1,
    calibration_metrics,
    coverage_curve,
    fit_radius_map,
    information_gain,
    inverse_metrics,
    kde_modes,
    r2_score,
    recovered_modes,
    relative_mass_error,
    type_metrics,
)
from bgn.model.encoder import approach_gap
from bgn.model.impulse import ContactImpulseHead
from bgn.model.newton import ROLLOUT_MASSES, pair_force_head_of
from bgn.model.target_coder import extrapolate, observed_targets
from bgn.provenance import git_commit, library_versions, processor
from bgn.rollout import evaluate_rollouts, lb_prefix
from bgn.training.checkpoints import CheckpointError, read
from bgn.training.module import PhysicsModule, load_model
from bgn.training.validate import (
    ARGV,
    DATA_EXIT,
    MAX_SEED,
    ConfigError,
    cli,
    fail,
    need_int,
    reported,
)

# the metric functions live in bgn.metrics; imports of them from here keep working
__all__ = ["batches", "calibrate_mass_posterior", "evaluate_model", "evaluate_rollouts",
           "inverse_metrics", "kde_modes", "load_model", "mass_figure", "r2_score",
           "recovered_modes", "type_metrics"]


# ----------------------------------------------------------------------------- loading
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
                   calibration: FrameDataset | None = None, relmass_decode: str = "median",
                   law_frames: int = 0,
                   ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Metrics of one model on a test dataset, and the arrays behind the mass figure
    (``evaluate_inverse``; empty without an inverse head, or with ``inverse=False``: the
    forward error alone, as ``bgn.studies.pareto`` needs it per checkpoint). ``calibration``:
    the split the mass flow's calibration is fitted on first (``calibrate_mass_posterior``, on
    ``mass_frames`` of its frames; ``mass_calibration_scale50/90`` in the metrics); None keeps
    the model's own (none after training); it also places the learned law's free scale of the
    per-simulation posterior (``evaluate_inverse``, which ``law_frames`` goes to).
    ``relmass_decode``: the flow's point behind ``relmass_r2`` (``RELMASS_DECODES``)."""
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
            draw = relmass_decode == "draw" and "relmass" in heads
            out = model(g, noise=torch.randn(len(g.mass)) if draw else None)
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
    masses_known = getattr(module.meta, "masses_known", True)
    if rel_pred and masses_known:
        metrics["relmass_r2"] = r2_score(torch.cat(rel_pred).numpy(), torch.cat(rel_true).numpy())
    arrays: dict[str, np.ndarray] = {}
    if model.has_inverse and inverse and not masses_known:  # nothing to score it against
        metrics.update(posterior_summary(module, dataset, mass_frames, mass_samples,
                                         batch_size, seed))
    elif model.has_inverse and inverse:
        if calibration is not None:
            metrics.update(calibrate_mass_posterior(module, calibration, mass_frames,
                                                    batch_size))
        inverse_values, arrays = evaluate_inverse(module, dataset, mass_frames, mass_samples,
                                                  batch_size, seed, calibration, law_frames)
        metrics.update(inverse_values)
    elif inverse and masses_known and (pair_force_head_of(model) is not None or isinstance(
            getattr(model, "force_head", None), ContactImpulseHead)):
        metrics.update(evaluate_law_inverse(module, dataset, mass_frames, mass_samples, seed,
                                            calibration, law_frames, batch_size))
    return metrics, arrays


def matched_frames(dataset: FrameDataset, validation: FrameDataset,
                   indices: list[int]) -> list[int]:
    """Evenly spaced frames of ``validation``, as many per simulation as ``indices`` hold of
    ``dataset``: a per-simulation posterior's noise is chosen on as much evidence per
    simulation as it is scored with, whatever the two splits' sizes (``sims=``,
    ``calibration_sims=``)."""
    per_sim = len(indices) / len(dataset.sims)
    return evenly_spaced(len(validation), max(1, round(per_sim * len(validation.sims))))


def evaluate_law_inverse(module: PhysicsModule, dataset: FrameDataset, mass_frames: int = 32,
                         mass_samples: int = 32, seed: int = 0,
                         validation: FrameDataset | None = None, law_frames: int = 0,
                         batch_size: int = 16) -> dict[str, Any]:
    """A model with a pair-force head or an impulse head and no inverse flow
    (``ablation=unsupervised`` or ``no_inverse``), on data that record masses: the masses read
    per simulation through its learned law (``law_posterior/...``) or through the impacts its
    contact head sees (``impact_posterior/...``), as ``evaluate_inverse`` computes them beside
    the flow, scored against the recorded masses. A model trained without recorded masses
    (none in ``trained_with``) never reads any: ``validation`` is then ignored, the law's free
    scale is placed by the scene's mass law and the impacts' noise is their own residual
    scatter, as for a user whose data record none (docs/design.md#inverse-metrics, "Without
    recorded masses")."""
    if "masses" not in module.model.trained_with:
        validation = None
    prior = MassPrior.of_scene(dataset.scene, module.hparams.stats.get("log_mass"))
    rng = np.random.default_rng(seed)
    indices = evenly_spaced(len(dataset), mass_frames)
    if pair_force_head_of(module.model) is None:
        values = _impact_posterior_reference(module, dataset, validation, prior, indices,
                                             law_frames, mass_samples, batch_size, rng)
        return {f"impact_posterior/{k}": v for k, v in values.items()}
    values = _law_posterior_reference(module, dataset, validation, prior, indices, law_frames,
                                      mass_samples, rng)
    return {f"law_posterior/{k}": v for k, v in values.items()}


def posterior_summary(module: PhysicsModule, dataset: FrameDataset, mass_frames: int = 32,
                      mass_samples: int = 32, batch_size: int = 16, seed: int = 0,
                      ) -> dict[str, float]:
    """Data without recorded masses (imported): the inverse model's posterior reported, not
    scored. Per particle of ``mass_frames`` evenly spaced frames, the median and the central
    90 % interval of its sampled log-mass; keys ``posterior/...``: particles, the spread (std)
    of the medians over particles, and the mean interval width (nats)."""
    torch.manual_seed(seed)
    indices = evenly_spaced(len(dataset), mass_frames)
    medians, widths = [], []
    for s in range(0, len(indices), batch_size):
        g = collate([dataset[i] for i in indices[s:s + batch_size]])
        samples, _ = module.model.mass_posterior(g, mass_samples)      # (samples, particles)
        low, mid, high = np.quantile(samples.double().numpy(), [0.05, 0.5, 0.95], axis=0)
        medians.append(mid)
        widths.append(high - low)
    mid, width = np.concatenate(medians), np.concatenate(widths)
    return {"posterior/particles": float(len(mid)),
            "posterior/log_mass_median_std": float(mid.std()),
            "posterior/interval90_width": float(width.mean())}


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
    do not change over time (docs/design.md#identifiability): the product of per-frame Gaussians of
    the posterior's mean and ``variance`` (``bgn.metrics.aggregate_gaussian``; sharp frames weigh
    more, docs/notes/2026-11-26-results-history.md,
    "Recalibration, pooling over frames and the fitted masses"), a plain mean without it."""
    _, index = np.unique(particles, return_inverse=True)
    _, pooled, _ = aggregate_gaussian(estimate, np.ones_like(estimate) if variance is None
                                      else variance, particles)
    truth = np.bincount(index, true_log) / np.bincount(index)
    return {"mass_rel_err": relative_mass_error(estimate, true_log),
            "relmass_r2_estimate": r2_score(estimate[edges[1]] - estimate[edges[0]], edge_rel),
            "sim_mass_rel_err": relative_mass_error(pooled, truth)}


def _physical(dataset: FrameDataset, prior: MassPrior,
              views: list[tuple[np.ndarray, np.ndarray | None]],
              types: np.ndarray) -> np.ndarray:
    """The force-law estimate (N,) from the windows (and contacts) of one simulation, whose
    particles have ``types`` (N,): read where the mass law has one component per type."""
    windows = np.stack([w for w, _ in views])
    contacts = None if views[0][1] is None else [c for _, c in views]
    return physical_log_mass(dataset.scene, prior, windows, dataset.dt, contacts,
                             types if prior.typed else None)


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


class _MassArrays(NamedTuple):
    """``_MassDraws`` concatenated: per particle and frame the true log-mass (P,), the draws
    (S, P) and their log-density, the particle's key and type, the force-law estimate (P,);
    the frames' edges (2, E) and their true relative log-masses (E,)."""

    true_log: np.ndarray
    sampled: np.ndarray
    log_post: np.ndarray
    particles: np.ndarray
    types: np.ndarray
    physical: np.ndarray
    edges: np.ndarray
    edge_rel: np.ndarray


@dataclass
class _MassDraws:
    """What ``evaluate_inverse`` gathers batch by batch (``_MassArrays``' lists), and per
    simulation its windows (and contacts) and the contact head's impacts in them."""

    true_log: list[np.ndarray] = field(default_factory=list)
    sampled: list[np.ndarray] = field(default_factory=list)
    log_post: list[np.ndarray] = field(default_factory=list)
    particles: list[np.ndarray] = field(default_factory=list)
    types: list[np.ndarray] = field(default_factory=list)
    physical: list[np.ndarray] = field(default_factory=list)
    edges: list[np.ndarray] = field(default_factory=list)
    edge_rel: list[np.ndarray] = field(default_factory=list)
    per_sim: dict[int, list[tuple[np.ndarray, np.ndarray | None]]] = field(default_factory=dict)
    sim_types: dict[int, np.ndarray] = field(default_factory=dict)   # each simulation's (N,)
    model_contacts: dict[int, list[np.ndarray]] = field(default_factory=dict)
    law_fit: list[np.ndarray] = field(default_factory=list)  # (P, 2) per batch: see add_law_fit
    offset: int = 0     # particles gathered so far: where the next batch's edges start

    def add_posterior(self, model: Any, g: Graph, mass_samples: int) -> torch.Tensor:
        """The flow's draws on batch ``g`` and their log-density (Eq. 7), the true masses,
        the particles' keys and the edges; returns the first node of each graph of the batch."""
        samples, density = model.mass_posterior(g, mass_samples)
        self.sampled.append(samples.double().numpy())
        self.log_post.append(density.double().numpy())
        self.true_log.append(torch.log(g.mass.double()).numpy())
        # one key per particle of a simulation, the same in every frame: sim * 1e6 + index
        self.particles.append((g.sim[g.batch] * 1_000_000 + g.local_index).numpy())
        self.types.append(g.types.numpy())
        self.edges.append(g.edge_index.numpy() + self.offset)
        self.edge_rel.append(g.edge_rel_log_mass.double().numpy())
        self.offset += len(g.mass)
        return torch.cumsum(g.num_nodes, 0) - g.num_nodes

    def add_law_fit(self, head: Any, g: Graph) -> None:
        """The masses the pair-force head's learned law fits to each window of batch ``g``
        (its own least squares, ``PairForceHead.least_squares``), as log-mass up to the law's
        free scale and the log of the fit's relative standard error (P, 2)."""
        fit, error = head.least_squares(g, head.window(g)[1], with_error=True)
        self.law_fit.append(head.fitted_log_mass(g, fit, error).double().numpy())

    def add_windows(self, dataset: FrameDataset, prior: MassPrior, chunk: np.ndarray,
                    g: Graph, first_node: torch.Tensor, rows: list[np.ndarray] | None,
                    ) -> None:
        """Each frame of ``chunk`` (the batch ``g``): its window and contacts, the force-law
        estimate on it and the contact head's impacts in it (``rows``: ``contact_rows`` of
        the batch, None without that head)."""
        for b, i in enumerate(chunk):
            window, contacts = window_and_contacts(dataset, i)
            sim = dataset.locate(i)[0]
            self.per_sim.setdefault(sim, []).append((window, contacts))
            # the graph's own types: the same in every frame of a simulation
            types = self.sim_types.setdefault(
                sim, g.types[first_node[b]:first_node[b] + g.num_nodes[b]].numpy())
            self.physical.append(_physical(dataset, prior, [(window, contacts)], types))
            if rows is not None:
                self.model_contacts.setdefault(sim, []).append(rows[b])

    def arrays(self) -> _MassArrays:
        """The batches concatenated."""
        return _MassArrays(np.concatenate(self.true_log), np.concatenate(self.sampled, axis=1),
                           np.concatenate(self.log_post), np.concatenate(self.particles),
                           np.concatenate(self.types), np.concatenate(self.physical),
                           np.concatenate(self.edges, axis=1), np.concatenate(self.edge_rel))


def _gather_draws(model: Any, dataset: FrameDataset, prior: MassPrior, indices: np.ndarray,
                  mass_samples: int, batch_size: int) -> _MassDraws:
    """The posterior's draws and the windows of the frames ``indices``, a batch at a time."""
    # the contact head's impacts in each window: its per-simulation mass solve
    head = getattr(model, "force_head", None)
    contact_head = head if isinstance(head, ContactImpulseHead) else None
    law_head = pair_force_head_of(model)
    draws = _MassDraws()
    for s in range(0, len(indices), batch_size):
        chunk = indices[s:s + batch_size]
        g = collate([dataset[i] for i in chunk])
        first_node = draws.add_posterior(model, g, mass_samples)
        if law_head is not None:
            draws.add_law_fit(law_head, g)
        draws.add_windows(dataset, prior, chunk, g, first_node, None if contact_head is None
                          else contact_rows(contact_head, g, dataset.history + 2))
    return draws


def _model_mass_metrics(dataset: FrameDataset, prior: MassPrior, draws: _MassDraws,
                        a: _MassArrays, log_prior: np.ndarray) -> dict[str, Any]:
    """The model's inverse metrics: its posterior's and its posterior means'; with a contact
    head, ``sim_mass_rel_err`` from the per-simulation impact solve (the flow's pooled one as
    ``sim_mass_rel_err_flow``); where the mass law has one component per type,
    ``info_gain_over_type``: its information beyond the type's (the type-only reference's
    density in place of the prior's; below 0, the posterior tells less than the type)."""
    metrics: dict[str, Any] = _posterior_metrics(a.true_log, a.sampled, a.log_post, log_prior,
                                                 a.particles)
    if prior.typed:
        metrics["info_gain_over_type"] = information_gain(
            a.log_post, prior.type_log_pdf(a.true_log, a.types))
    metrics.update(_point_metrics(a.sampled.mean(axis=0), a.true_log, a.particles, a.edges,
                                  a.edge_rel, a.sampled.var(axis=0)))
    if draws.model_contacts:
        metrics["sim_mass_rel_err_flow"] = metrics["sim_mass_rel_err"]
        metrics["sim_mass_rel_err"] = _impact_solve_error(
            dataset, prior, draws.per_sim, draws.model_contacts, a.sampled, a.particles)
    metrics["mass_particles"] = int(len(a.true_log))
    return metrics


def _physical_reference(dataset: FrameDataset, prior: MassPrior, draws: _MassDraws,
                        a: _MassArrays) -> dict[str, float]:
    """The force-law estimator's metrics: on each frame's window and per simulation, one
    least-squares fit of all its windows. Where the frames say nothing of a particle it falls
    back to the mean log-mass of the particle's type (of the whole law where it has one
    component); ``identified`` and ``sim_identified``: the shares it estimated, the rest
    fell back."""
    pooled = {sim: _physical(dataset, prior, views, draws.sim_types[sim])
              for sim, views in draws.per_sim.items()}
    sim_estimate = np.concatenate(list(pooled.values()))
    sim_true = np.log(np.concatenate([dataset.file.read("masses", sim) for sim in pooled]))
    sim_types = np.concatenate([draws.sim_types[sim] for sim in pooled])
    return {
        **_point_metrics(np.where(np.isfinite(a.physical), a.physical,
                                  prior.type_mean(a.types)),
                         a.true_log, a.particles, a.edges, a.edge_rel),
        "identified": float(np.mean(np.isfinite(a.physical))),
        # per simulation: one least-squares fit of all its windows, not a mean of estimates
        "sim_mass_rel_err": relative_mass_error(
            np.where(np.isfinite(sim_estimate), sim_estimate, prior.type_mean(sim_types)),
            sim_true),
        "sim_identified": float(np.mean(np.isfinite(sim_estimate)))}


def _learned_law_reference(prior: MassPrior, draws: _MassDraws, a: _MassArrays,
                           ) -> dict[str, float]:
    """The estimator through the model's own learned pair law (no truth, no learning of its
    own): each window's least-squares masses under that law (the head's fit), one common
    shift for the law's free scale placed by the scene's mass law (``place_by_prior``), and
    per simulation the windows' estimates pooled with the fit's own errors as variances (a
    sharp window weighs more)."""
    fit = np.concatenate(draws.law_fit)
    estimate = place_by_prior(fit[:, 0], prior)
    variance = np.exp(2 * fit[:, 1])  # the relative error of m is the std of log m
    return _point_metrics(estimate, a.true_log, a.particles, a.edges, a.edge_rel, variance)


def _law_posterior_reference(module: PhysicsModule, dataset: FrameDataset,
                             validation: FrameDataset | None, prior: MassPrior,
                             indices: list[int], law_frames: int, mass_samples: int,
                             rng: np.random.Generator) -> dict[str, Any]:
    """The per-simulation posterior through the model's own learned pair law
    (``bgn.eval.law_posterior``): per simulation of ``indices``, one least squares over the
    windows of its evaluated frames (and ``law_frames`` more of its frames), a Laplace
    posterior on log-mass with the scene's mass law as prior, the law's free scale placed on
    ``validation`` (the validation split: never the split scored), scored as the flow's
    posterior is, one row per particle. ``scale``: physical, validation or prior (where the
    shift came from); ``shift``, ``std_scale``, ``std_floor``, ``tail_share`` and
    ``tail_width``: the shift, the factor on the fit's standard deviations, the floor added to
    them and the likelihood's heavy tail (``place_scale``, ``Spread``);
    ``contamination``: the share of the prior mixed in, chosen on ``validation`` too;
    ``windows``:
    windows per simulation; ``physical_sim_mass_rel_err`` and
    ``physical_relmass_r2_estimate``: the physical estimator on the same windows
    (``_physical_on_frames``). Empty for a
    model without a pair-force head; under ``mass_law=type`` only ``fit`` saying there is
    nothing to fit."""
    head = pair_force_head_of(module.model)
    if head is None:
        return {}
    fits = fit_simulations(head, dataset, indices, law_frames)
    if fits is None:
        return {"fit": "none: mass_law=type, one learned mass per type, nothing to fit"}
    checked = None
    if validation is not None and getattr(validation.meta, "masses_known", True):
        checked = fit_simulations(head, validation, matched_frames(dataset, validation, indices),
                                  law_frames)
    shift, spread, scale = place_scale(fits, prior, law_scale_pinned(module.model), checked)
    share = contamination(checked, prior, shift, spread)
    laplace = laplace_posterior(fits.log_mass + shift, fits.log_std, prior, spread)
    # a scale placed by the prior is known only as well as the particles' scatter under the
    # prior pins it: an error of every particle at once, added outside the product
    shift_std = prior_shift_error(fits.log_mass + shift, prior) if scale == "prior" else 0.0
    laplace = laplace.widened(shift_std)
    posterior = laplace.mixed(prior, share)
    metrics: dict[str, Any] = {
        # the point estimate is the Laplace posterior's mean: the prior's share stands for the
        # fits that went wrong, in the tails (coverage, density), and would pull every
        # estimate towards the prior's mean by the share
        **_simulation_posterior_metrics(posterior, laplace.mean, fits.true_log, fits.keys,
                                        prior, mass_samples, rng),
        "identified": float(np.mean(np.isfinite(fits.log_mass))),
        "scale": scale, "shift": shift, "shift_std": shift_std, "std_scale": spread.factor,
        "std_floor": spread.floor, "tail_share": spread.tail_share,
        "tail_width": spread.tail_width,
        "contamination": share,
        "windows": fits.windows}
    # the estimator that knows the law, on the same windows
    metrics.update(_physical_on_frames(dataset, prior, indices, law_frames))
    return metrics


def _pairs_within(sims: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair (sender, receiver) of distinct rows with the same simulation
    ``sims`` (P,): the pairs a relative-mass R^2 is scored over."""
    return np.nonzero((sims[:, None] == sims[None, :]) & ~np.eye(len(sims), dtype=bool))


def _simulation_posterior_metrics(posterior: LawPosterior, estimate: np.ndarray,
                                  true_log: np.ndarray, keys: np.ndarray, prior: MassPrior,
                                  mass_samples: int, rng: np.random.Generator,
                                  ) -> dict[str, Any]:
    """A per-simulation posterior (one row per particle, ``keys``) scored as the flow's is:
    its draws and density, and the point ``estimate`` (P,), with the relative masses' R^2 over
    every ordered pair of particles of a simulation."""
    snd, rcv = _pairs_within(keys // KEY)
    return {**_posterior_metrics(true_log, posterior.sample(mass_samples, rng),
                                 posterior.log_pdf(true_log), prior.log_pdf(true_log), keys),
            **_point_metrics(estimate, true_log, keys, np.stack([snd, rcv]),
                             true_log[rcv] - true_log[snd])}


def _physical_on_frames(dataset: FrameDataset, prior: MassPrior, indices: list[int],
                        law_frames: int) -> dict[str, float]:
    """The physical estimator on the windows a per-simulation posterior read
    (``simulation_frames``): the estimator that knows the law, given as much. Its
    per-simulation error (``physical_sim_mass_rel_err``) and its relative masses' R^2 over
    every ordered pair of particles of a simulation (``physical_relmass_r2_estimate``, as the
    posterior's); a particle it cannot estimate keeps its type's mean. Empty where the data
    have no law written down (imported): it estimates nothing there."""
    pooled, truth, keys, seen = [], [], [], False
    for sim, frames in simulation_frames(dataset, indices, law_frames).items():
        views = [window_and_contacts(dataset, i) for i in frames]
        types = dataset.file.read("types", sim)
        estimate = _physical(dataset, prior, views, types)
        seen = seen or bool(np.isfinite(estimate).any())
        pooled.append(np.where(np.isfinite(estimate), estimate, prior.type_mean(types)))
        truth.append(np.log(dataset.file.read("masses", sim)))
        keys.append(np.full(len(estimate), sim))
    if not seen:
        return {}
    estimate, true_log, sims = (np.concatenate(a) for a in (pooled, truth, keys))
    snd, rcv = _pairs_within(sims)
    return {"physical_sim_mass_rel_err": relative_mass_error(estimate, true_log),
            "physical_relmass_r2_estimate": r2_score(estimate[rcv] - estimate[snd],
                                                     true_log[rcv] - true_log[snd])}


def _impact_posterior_reference(module: PhysicsModule, dataset: FrameDataset,
                                validation: FrameDataset | None, prior: MassPrior,
                                indices: list[int], law_frames: int, mass_samples: int,
                                batch_size: int, rng: np.random.Generator) -> dict[str, Any]:
    """The per-simulation posterior through the model's own contact head
    (``bgn.eval.impact_posterior``): per simulation of ``indices``, the momentum exchanged at
    the impacts the head sees in the windows of its evaluated frames (and ``law_frames`` more
    of its frames), a Gaussian posterior with each disc's type's law as prior, its noise and
    the share of the type's law mixed in chosen on ``validation`` (never the split scored),
    scored as the flow's posterior is, one row per disc. ``noise`` and ``noise_from`` (where
    it was chosen: validation, or the equations' own residuals without validation masses),
    ``contamination``, ``identified`` (the share of discs in at least one equation),
    ``impacts`` and ``windows`` per simulation, and the physical estimator on the same
    windows (``_physical_on_frames``). Empty for a model without a contact head."""
    head = getattr(module.model, "force_head", None)
    if not isinstance(head, ContactImpulseHead):
        return {}
    impacts = simulation_impacts(head, dataset, indices, law_frames, batch_size)
    checked = None
    if validation is not None and getattr(validation.meta, "masses_known", True):
        checked = simulation_impacts(head, validation,
                                     matched_frames(dataset, validation, indices), law_frames,
                                     batch_size)
    noise, share, source = choose_noise(impacts, checked, prior)
    gaussian = posterior_of(impacts, prior, noise)
    posterior = mixed_with_types(gaussian, impacts, prior, share)
    true_log = np.concatenate([sim.true_log for sim in impacts])
    keys = np.concatenate([sim.keys for sim in impacts])
    metrics = _simulation_posterior_metrics(posterior, gaussian.mean, true_log, keys, prior,
                                            mass_samples, rng)
    if prior.typed:
        types = np.concatenate([sim.types for sim in impacts])
        metrics["info_gain_over_type"] = information_gain(
            posterior.log_pdf(true_log), prior.type_log_pdf(true_log, types))
    seen = np.concatenate([np.isin(np.arange(len(sim.types)), sim.pairs)
                           for sim in impacts])
    metrics.update({"identified": float(np.mean(seen)), "noise": noise, "noise_from": source,
                    "contamination": share,
                    "impacts": float(np.mean([len(sim.pairs) for sim in impacts])),
                    "windows": float(np.mean([sim.windows for sim in impacts])),
                    **_physical_on_frames(dataset, prior, indices, law_frames)})
    return metrics


def _type_reference(prior: MassPrior, a: _MassArrays, log_prior: np.ndarray,
                    rng: np.random.Generator) -> tuple[dict[str, float], np.ndarray]:
    """The type-only sampler's metrics (draws from each particle's own type's mass law, its
    exact density: all that knowing the type tells) and its draws."""
    samples = prior.type_sample(a.types, a.sampled.shape, rng)
    metrics = {**_posterior_metrics(a.true_log, samples,
                                    prior.type_log_pdf(a.true_log, a.types), log_prior,
                                    a.particles),
               **_point_metrics(prior.type_mean(a.types), a.true_log, a.particles, a.edges,
                                a.edge_rel)}
    return metrics, samples


@torch.no_grad()
def evaluate_inverse(module: PhysicsModule, dataset: FrameDataset, mass_frames: int = 32,
                     mass_samples: int = 32, batch_size: int = 16, seed: int = 0,
                     validation: FrameDataset | None = None, law_frames: int = 0,
                     ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The inverse model beside its two references (``bgn.eval.mass_baselines``) on every
    particle of ``mass_frames`` evenly spaced test frames (they cover every simulation).

    Keys: the model's metrics unprefixed; ``prior/...`` the prior-only sampler's (the same
    number of draws from the scene's mass law, its exact density); ``physical/...`` the
    force-law estimator on each frame's window (NaN where the window says nothing: the prior's
    mean), with ``physical/identified`` the share it could estimate. Per-simulation
    aggregates (``sim_mass_rel_err``): the product of the model's per-frame posteriors (as
    Gaussians) over the evaluated frames of a simulation; the estimator's least squares over
    all those windows at once (``physical/sim_identified``: the share of particles it could
    estimate). ``learned_law/...`` (a model with a pair-force head): the masses its learned law
    fits to each window, placed by the scene's mass law (``_learned_law_reference``): what the
    law alone tells, beside what the flow makes of it. ``law_posterior/...`` (the same
    models): per simulation, one fit of the learned law to all its evaluated windows (and
    ``law_frames`` more of its frames), a Laplace posterior, its free scale placed on
    ``validation`` (``_law_posterior_reference``). Arrays for the figure: true and sampled
    masses and the coverage curves of the model and the prior."""
    prior = MassPrior.of_scene(dataset.scene, module.hparams.stats.get("log_mass"))
    rng = np.random.default_rng(seed)
    indices = evenly_spaced(len(dataset), mass_frames)
    draws = _gather_draws(module.model, dataset, prior, indices, mass_samples, batch_size)
    a = draws.arrays()
    log_prior = prior.log_pdf(a.true_log)
    metrics = _model_mass_metrics(dataset, prior, draws, a, log_prior)
    prior_samples = prior.sample(a.sampled.shape, rng)
    references = {"prior": _posterior_metrics(a.true_log, prior_samples, log_prior, log_prior,
                                              a.particles),
                  "physical": _physical_reference(dataset, prior, draws, a)}
    if draws.law_fit:
        references["learned_law"] = _learned_law_reference(prior, draws, a)
        references["law_posterior"] = _law_posterior_reference(
            module, dataset, validation, prior, indices, law_frames, mass_samples, rng)
    if draws.model_contacts:
        references["impact_posterior"] = _impact_posterior_reference(
            module, dataset, validation, prior, indices, law_frames, mass_samples, batch_size,
            rng)
    arrays = {"true_mass": np.exp(a.true_log), "sampled_mass": np.exp(a.sampled),
              "coverage_levels": COVERAGE_LEVELS,
              "coverage": coverage_curve(a.true_log, a.sampled),
              "coverage_prior": coverage_curve(a.true_log, prior_samples)}
    if prior.typed:
        references["type_prior"], type_samples = _type_reference(prior, a, log_prior, rng)
        arrays["coverage_type"] = coverage_curve(a.true_log, type_samples)
    for name, values in references.items():
        metrics.update({f"{name}/{k}": v for k, v in values.items()})
    return metrics, arrays


def evaluate_split(module: PhysicsModule, dataset: FrameDataset,
                   calibration: FrameDataset | None, max_frames: int | None = 256,
                   mass_frames: int = 32, mass_samples: int = 32, batch_size: int = 16,
                   seed: int = 0, rollout_steps: int = 100, rollout_starts: int = 1,
                   rollout_sims: int | None = None,
                   curves: dict[str, dict[str, np.ndarray]] | None = None,
                   step: Callable[[str], None] | None = None, lagrangebench: bool = True,
                   sinkhorn_stride: int = 10, sinkhorn_rollouts: int | None = 4,
                   positions: dict[str, np.ndarray] | None = None,
                   relmass_decode: str = "median", law_frames: int = 0,
                   ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Everything ``python -m bgn.evaluate`` and the study (``bgn.studies.grid``) score on one
    split: one-step, type and contact metrics and the inverse metrics with the flow
    recalibrated on ``calibration`` (``evaluate_model``), then the rollouts of the model, the
    references and the predictability limit (``evaluate_rollouts``), in LagrangeBench's
    metrics as well with ``lagrangebench``. Returns the metrics and the mass figure's
    arrays."""
    if step is not None:
        step("one-step, type, contact and inverse metrics")
    metrics, arrays = evaluate_model(module, dataset, max_frames=max_frames,
                                     mass_frames=mass_frames, mass_samples=mass_samples,
                                     batch_size=batch_size, seed=seed, calibration=calibration,
                                     relmass_decode=relmass_decode, law_frames=law_frames)
    metrics.update(evaluate_rollouts(module.model, dataset, n_steps=rollout_steps,
                                     starts_per_sim=rollout_starts, max_sims=rollout_sims,
                                     curves=curves, step=step, lagrangebench=lagrangebench,
                                     sinkhorn_stride=sinkhorn_stride,
                                     sinkhorn_rollouts=sinkhorn_rollouts,
                                     positions=positions))
    return metrics, arrays


def mass_plot(arrays: dict[str, np.ndarray]) -> Any:
    """The KDE of true vs sampled masses beside the coverage curves of the model, the
    prior-only sampler and, where there is one, the type-only sampler
    (``figures.mass_calibration``)."""
    from bgn.figures import mass_calibration

    curves = {"model": arrays["coverage"], "prior-only sampler": arrays["coverage_prior"]}
    if "coverage_type" in arrays:
        curves["type-only sampler"] = arrays["coverage_type"]
    return mass_calibration(arrays["true_mass"], arrays["sampled_mass"].ravel(),
                            arrays["coverage_levels"], curves)


def mass_figure(arrays: dict[str, np.ndarray], path: str | Path) -> Path:
    """Write ``mass_plot`` as a PNG."""
    from bgn.figures import save

    return save(mass_plot(arrays), path)


# ----------------------------------------------------------------------------- the command
SPLITS = ("train", "val", "test")
RELMASS_DECODES = ("median", "draw")  # evaluate_model's relmass_decode


def validate_evaluate(cfg: Any) -> tuple[Path, Path, Path]:
    """Everything ``python -m bgn.evaluate`` is given, before any data or model is read;
    returns ``resolve_run``'s paths."""
    if not cfg.get("ckpt"):
        raise ConfigError("ckpt", None, "give a run folder or checkpoint: python -m "
                          "bgn.evaluate outputs/train/runs/<run> [split=test]")
    for key in ("split", "calibration_split"):
        if cfg[key] not in SPLITS:
            raise ConfigError(key, cfg[key], f"choose one of {list(SPLITS)}")
    if cfg.calibration_split == cfg.split:
        raise ConfigError("calibration_split", cfg.calibration_split, (
            "the mass flow would be recalibrated on the split it is scored on; set "
            "calibration_split to another split (val for split=test, train for split=val)"))
    need_int(cfg.max_frames, "max_frames", 1, optional=True,
             why=" (null: the run's own count, dataset.<split>_samples)")
    for key in ("mass_frames", "mass_samples", "batch_size"):
        need_int(cfg[key], key, 1)
    need_int(cfg.law_frames, "law_frames", 0)
    for key in ("sims", "calibration_sims"):
        need_int(cfg[key], key, 1, optional=True, why=" (null: the run's own simulations)")
    need_int(cfg.seed, "seed", 0, MAX_SEED)
    if cfg.relmass_decode not in RELMASS_DECODES:
        raise ConfigError("relmass_decode", cfg.relmass_decode,
                          f"choose one of {list(RELMASS_DECODES)}")
    need_int(cfg.rollout.steps, "rollout.steps", 1)
    need_int(cfg.rollout.starts_per_sim, "rollout.starts_per_sim", 1)
    need_int(cfg.rollout.max_sims, "rollout.max_sims", 1, optional=True,
             why=" (null: every simulation of the split)")
    need_int(cfg.rollout.sinkhorn_stride, "rollout.sinkhorn_stride", 1)
    need_int(cfg.rollout.sinkhorn_rollouts, "rollout.sinkhorn_rollouts", 1, optional=True,
             why=" (null: every rollout)")
    if cfg.rollout.masses is not None and cfg.rollout.masses not in ROLLOUT_MASSES:
        raise ConfigError("rollout.masses", cfg.rollout.masses,
                          f"choose one of {list(ROLLOUT_MASSES)}, or null (the checkpoint's own)")
    from bgn.training.checkpoints import resolve_run

    return resolve_run(str(cfg.ckpt), cfg.get("run_config"))


def load_checked(ckpt: Path, run_cfg: Any, datamodule: Any) -> PhysicsModule:
    """The checkpoint's module, refused in one line when its model is unknown to this bgn or
    it was trained on another scene or model than its run config says."""
    from bgn.model.registry import MODELS
    from bgn.training.checkpoints import check_compatible
    from bgn.training.run import run_provenance

    record = read(ckpt)
    name = ((record.get("hyper_parameters") or {}).get("model_config") or {}).get("name")
    if name not in MODELS:
        raise CheckpointError(f"checkpoint {ckpt} holds a model {name!r} that this bgn does not "
                              f"know (models: {sorted(MODELS)}): evaluate it with the bgn that "
                              "trained it")
    check_compatible(ckpt, run_provenance(run_cfg, datamodule), ckpt=record)
    return load_model(ckpt)


def set_rollout_masses(model: Any, masses: str) -> None:
    """``rollout.masses``: the mass fit the model's pair-force head holds along a rollout
    (``model.rollout_masses``), refused in one line for a model without that head."""
    head = pair_force_head_of(model)
    if head is None:
        raise ConfigError("rollout.masses", masses,
                          f"{model.label} has no pair-force head, whose mass fit this sets; "
                          "leave it null")
    head.rollout_masses = masses


def provenance_record(cfg: Any, ckpt: Path, config: Path, run_cfg: Any) -> dict[str, Any]:
    """The report's header: what was evaluated, by which code, where, with which seeds."""
    import hashlib
    import os
    import platform
    import shlex
    import sys

    return {"checkpoint": str(ckpt.resolve()), "run_config": str(config.resolve()),
            "run_config_hash": hashlib.sha256(config.read_bytes()).hexdigest()[:10],
            "git_commit": git_commit(),
            "machine": f"{platform.platform()}, {platform.processor() or platform.machine()}",
            "processor": processor(), "libraries": library_versions(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "seeds": {"evaluation": int(cfg.seed), "training": run_cfg.get("seed"),
                      "data": run_cfg.dataset.get("seed")},
            "split": str(cfg.split), "calibration_split": str(cfg.calibration_split),
            "command": " ".join([ARGV[0] if ARGV else "python -m bgn.evaluate",
                                 *(shlex.quote(a) for a in (ARGV or sys.argv)[1:])])}


def sims_text(record: dict[str, Any]) -> str:
    """The simulations scored and calibrated on, as the report's provenance says them (an
    older record has none)."""
    sims = record.get("sims")
    return (f" ({sims['split']} simulations scored, {sims['calibration']} calibrated on)"
            if sims else "")


class Stages:
    """A rich progress bar over the named stages of the evaluation (nothing when off)."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.progress = None
        if enabled:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self.progress = Progress(TextColumn("{task.description:<48}"), BarColumn(),
                                     TextColumn("{task.completed}/{task.total}"),
                                     TimeElapsedColumn())
            self.progress.start()
            self.task = self.progress.add_task("evaluation", total=total)
        self.started = False

    def __call__(self, name: str) -> None:
        if self.progress is not None:
            self.progress.update(self.task, advance=1 if self.started else 0, description=name)
            self.started = True

    def close(self) -> None:
        if self.progress is not None:
            self.progress.update(self.task, completed=self.progress.tasks[0].total,
                                 description="done")
            self.progress.stop()


ROLLOUT_SOURCES = {"rollout": "model", "rollout_last": "repeat last (no learning)",
                   "rollout_linear": "linear extrapolation (no learning)",
                   "predictability": "predictability limit (simulator, 1e-6 off)"}
ONE_STEP_KEYS = ["mse", "nmse", "nmse_last_extrapolation", "nmse_linear_extrapolation",
                 "median_relative_error", "n_frames", "type_accuracy", "type_auroc",
                 "contact_rate", "contact_f1_head", "contact_f1_toi_rule", "relmass_r2"]


LB_COLUMNS = ["mse@5", "mse@10", "mse@20", "mse@50", "mse@100", "mse@all", "sinkhorn",
              "e_kin_mse", "failed_share"]
LAW_FIGURE = "law.png"


def lagrangebench_text(metrics: dict[str, Any]) -> list[str]:
    """The report's "LagrangeBench metrics" section: one row per rollout source."""
    from bgn.tables import markdown_table

    rows = [{"source": label, **{c: metrics.get(f"{lb_prefix(key)}/{c}") for c in LB_COLUMNS}}
            for key, label in ROLLOUT_SOURCES.items() if f"{lb_prefix(key)}/rollouts" in metrics]
    if not rows:
        return []
    columns = [c for c in LB_COLUMNS if any(r[c] is not None for r in rows)]
    return ["## LagrangeBench metrics", "",
            "The same rollouts in LagrangeBench's metrics (Toshev et al. 2023, "
            "lagrangebench/evaluate/metrics.py; bgn.metrics.lagrangebench_metrics), each per "
            "rollout then averaged over the rollouts as theirs (the standard deviations over "
            "the rollouts: metrics.json, <name>_std). mse@h: the per-step position MSE (mean "
            "over particles and coordinates of the squared error) averaged over steps 1..h, "
            "their mse{h}; mse@all over the whole rollout (their loss); the MSE at step h alone "
            "is pos_mse_mean@h (metrics.json). sinkhorn: the Sinkhorn divergence between the "
            "predicted and true particle clouds, uniform weights, squared Euclidean cost, "
            "entropic regularisation 0.05 x the mean cost (ott-jax's default, which "
            "LagrangeBench uses), solved with POT in float64 instead of ott-jax in float32; "
            f"on every {int(metrics.get('lb/sinkhorn_stride', 10))}-th step "
            f"({int(metrics.get('lb/sinkhorn_frames', 0))} steps) of "
            f"{int(metrics.get('lb/sinkhorn_rollouts', 0))} of the "
            f"{int(metrics.get('lb/rollouts', 0))} rollouts, evenly spaced (LagrangeBench: "
            "every step at inference). e_kin_mse: the MSE over the rollout of the kinetic "
            "energy per frame, sum_i m_i |v_i|^2 with finite-difference velocities, no 1/2 "
            "(LagrangeBench's, with m_i = dx^dim: where the source gave no masses bgn's unit "
            "masses stand in, so multiply by dx^(2 dim) to compare). Every particle counts, "
            "kinematic ones too (set to the truth in the rollout, as LagrangeBench does); "
            "periodic dimensions by the minimum image. A failed rollout counts at the cap from "
            "the step it failed on: MSE rollout_cap^2 / D, Sinkhorn rollout_cap^2, kinetic "
            "energy 100 x the true mean (speeds 10 x the truth's); failed_share beside.", "",
            markdown_table(["source", *columns], rows)]


def law_text(module: PhysicsModule, dataset: FrameDataset, figure: str | None,
             ) -> tuple[str, Any]:
    """The report's section on the learned pair law (``bgn.laws``: its formula, constants
    and errors over ``dataset``'s distances, the training split) and its figure (None
    without ``figure``); a model without a pair-force head says it has no pair law."""
    from bgn.laws.compare import read_law
    from bgn.laws.report import law_figure, markdown
    from bgn.laws.sample import pair_force_head

    try:
        pair_force_head(module)
    except ValueError:
        name = getattr(module.model, "name", type(module.model).__name__)
        return (f"## The learned pair law\n\nThe {name} model has no pair-force head, so it "
                "has no pair law to read (model=newton, or model=bgn model.dynamics=newton, "
                "on a force or imported scene has one).\n", None)
    report = read_law(module, dataset)
    return markdown(report, figure, level=2), None if figure is None else law_figure(report)


def report_text(record: dict[str, Any], metrics: dict[str, Any], figures: list[str],
                law: str | None = None) -> str:
    """report.md: the provenance header, then one-step, rollout (bgn's and LagrangeBench's)
    and inverse tables, and ``law``, the section on the learned pair law (``law_text``)."""
    from bgn.eval.columns import (
        INVERSE_COLUMNS,
        INVERSE_REFERENCES,
        ROLLOUT_COLUMNS,
        supervision_text,
    )
    from bgn.tables import markdown_table

    seeds = ", ".join(f"{k} {v}" for k, v in record["seeds"].items())
    about = record.get("model") or {}
    lines = [f"# Evaluation on the {record['split']} split", "",
             *([f"- model: {about['label']}; trained with: "
                f"{supervision_text(about)} (beyond the frames); given at inference: "
                f"{', '.join(about['given']) or 'nothing'} beyond the position window; "
                f"physics written in: {about['physics']}"] if about else []),
             f"- command: `{record['command']}`",
             f"- checkpoint: `{record['checkpoint']}`",
             f"- run config: `{record['run_config']}` (hash {record['run_config_hash']})",
             f"- git commit: {record['git_commit']}",
             f"- machine: {record['machine']}; {record.get('processor', 'unknown')}; "
             f"{record['cpu_count']} CPUs, {record['torch_threads']} torch threads",
             f"- libraries: {record.get('libraries', 'unknown')}",
             f"- seeds: {seeds}; mass flow recalibrated on the {record['calibration_split']} "
             f"split{sims_text(record)}; wall time {record['wall_time_s']:.1f} s", "",
             "## One step", "",
             markdown_table(["metric", "value"], [{"metric": k, "value": metrics[k]}
                                                  for k in ONE_STEP_KEYS if k in metrics]),
             "## Rollouts", "",
             "From frame 100 of every simulation of the split (when the files are that long). "
             "Every rollout counts: a failed one (a non-finite value, or a particle more than "
             "10 scene scales astray) counts at the cap (rollout_cap: 10 scene scales) in "
             "pos_err_mean and pos_mse_mean; pos_err_median beside the mean would hide up to "
             "half the rollouts failing. energy_err: median |E_t - E_0| / |E_0|, a failed "
             "rollout infinite. See bgn.metrics.rollout_metrics.", ""]
    rows = [{"source": label, **{c: metrics.get(f"{key}/{c}") for c in ROLLOUT_COLUMNS}}
            for key, label in ROLLOUT_SOURCES.items() if f"{key}/rollouts" in metrics]
    columns = [c for c in ROLLOUT_COLUMNS if any(r[c] is not None for r in rows)]  # the scene's
    lines += [markdown_table(["source", *columns], rows)]
    lines += lagrangebench_text(metrics)
    if "coverage50" in metrics:
        rows = [{"source": "model", **{c: metrics.get(c) for c in INVERSE_COLUMNS}}]
        rows += [{"source": label, **{c: metrics.get(f"{key}/{c}") for c in INVERSE_COLUMNS}}
                 for key, label in INVERSE_REFERENCES.items()
                 if any(f"{key}/{c}" in metrics for c in INVERSE_COLUMNS)]
        columns = [c for c in INVERSE_COLUMNS if any(r[c] is not None for r in rows)]
        lines += ["## Inverse model", "",
                  f"{metrics.get('mass_particles')} particle masses in evenly spaced frames "
                  f"(bgn.eval.evaluate.evaluate_inverse); the flow recalibrated on the "
                  f"{record['calibration_split']} split first (scale at 50 % / 90 %: "
                  f"{metrics.get('mass_calibration_scale50', float('nan')):.3g} / "
                  f"{metrics.get('mass_calibration_scale90', float('nan')):.3g}).", "",
                  markdown_table(["source", *columns], rows)]
    elif "law_posterior/scale" in metrics:  # no flow: the masses through the law alone
        row = {"source": INVERSE_REFERENCES["law_posterior"],
               **{c: metrics.get(f"law_posterior/{c}") for c in INVERSE_COLUMNS}}
        columns = [c for c in INVERSE_COLUMNS if row[c] is not None]
        lines += ["## Inverse model (through the learned law)", "",
                  "No inverse flow: each simulation's masses read through the learned pair law "
                  "(bgn.eval.evaluate.evaluate_law_inverse), its free scale "
                  f"{metrics['law_posterior/scale']}, scored against the recorded masses.", "",
                  markdown_table(["source", *columns], [row])]
    elif "impact_posterior/noise_from" in metrics:  # no flow: the masses through impacts
        row = {"source": INVERSE_REFERENCES["impact_posterior"],
               **{c: metrics.get(f"impact_posterior/{c}") for c in INVERSE_COLUMNS}}
        columns = [c for c in INVERSE_COLUMNS if row[c] is not None]
        lines += ["## Inverse model (through the impacts)", "",
                  "No inverse flow: each simulation's masses read from the momentum exchanged "
                  "at the impacts the model's contact head sees, each type's mass law as prior "
                  "(bgn.eval.evaluate.evaluate_law_inverse), the impacts' noise from "
                  f"{metrics['impact_posterior/noise_from']}, scored against the recorded "
                  "masses.", "", markdown_table(["source", *columns], [row])]
    if "posterior/particles" in metrics:
        lines += ["## Inverse model (no recorded masses)", "",
                  "The data carry no masses, so the posterior is reported, not scored "
                  f"(bgn.eval.evaluate.posterior_summary): over "
                  f"{int(metrics['posterior/particles'])} particles of evenly spaced frames, "
                  "the medians of the sampled log-masses spread by "
                  f"{metrics['posterior/log_mass_median_std']:.3g} (std), and the central 90 % "
                  f"intervals are {metrics['posterior/interval90_width']:.3g} wide on average "
                  "(nats).", ""]
    if law is not None:
        lines += [law]
    figures = [f for f in figures if f != LAW_FIGURE or law is None or f not in law]
    if figures:
        lines += ["## Figures", ""] + [f"![{Path(f).stem}]({f})" for f in figures] + [""]
    lines += ["Every value: metrics.json (and metrics.csv, one row per key).", ""]
    return "\n".join(lines)


def write_outputs(out_dir: Path, record: dict[str, Any], metrics: dict[str, Any],
                  figures: dict[str, Any], law: str | None = None) -> None:
    """Write report.md, metrics.csv, metrics.json and the figures into ``out_dir``, each
    through a temporary file and a rename (nothing half-written)."""
    import csv
    import io
    import json
    import os

    from bgn.figures import save
    from bgn.training.checkpoints import write_atomic

    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for name, fig in figures.items():
        tmp = out_dir / f".{name}.tmp{os.getpid()}.png"
        try:
            save(fig, tmp)
            os.replace(tmp, out_dir / f"{name}.png")
        finally:
            tmp.unlink(missing_ok=True)
        names.append(f"{name}.png")
    values = {k: (v.item() if isinstance(v, np.generic) else v) for k, v in metrics.items()}
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(["metric", "value"])
    writer.writerows(sorted(values.items()))
    write_atomic(out_dir / "metrics.csv", text.getvalue())
    write_atomic(out_dir / "metrics.json", json.dumps(
        {"provenance": record, "metrics": values}, indent=2, sort_keys=True))
    write_atomic(out_dir / "report.md", report_text(record, values, names, law))


def one_step_frames(cfg: Any, datamodule: Any) -> int | None:
    """How many frames the one-step metrics average: ``max_frames``, or where that is null
    the frames the training run's own test (validation) phase scores, its dataset's
    ``test_samples`` (``val_samples``; the latter for the train split too), so that the
    report's NMSE is the one the run printed. NMSE is heavy-tailed: a few hundred frames
    give a different figure from ten thousand (docs/design.md#metrics-and-protocols)."""
    if cfg.max_frames is not None:
        return int(cfg.max_frames)
    return datamodule.samples.get(cfg.split, datamodule.samples["val"])


def evaluate_run(cfg: Any, paths: tuple[Path, Path, Path]) -> Path:
    """The command's work: the run's data and checkpoint, every metric, the files; returns
    the output folder."""
    import time

    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.figures import energy_drift, rollout_errors

    start = time.perf_counter()
    ckpt, run_dir, config = paths
    run_cfg = OmegaConf.load(config)
    data_dir = cfg.paths.data_dir or run_cfg.paths.data_dir
    datamodule = ParticleDataModule(run_cfg.dataset, run_cfg.fps, data_dir,
                                    generate_workers=run_cfg.dataset.get("generate_workers"),
                                    show_progress=bool(cfg.progress))
    module = load_checked(ckpt, run_cfg, datamodule)  # before any data are generated
    if cfg.rollout.masses is not None:
        with reported():  # a model without the head: one line
            set_rollout_masses(module.model, str(cfg.rollout.masses))
    datamodule.prepare_data()  # the run's data, generated again where they are missing
    datamodule.setup()
    dataset = datamodule.datasets[cfg.split]
    if cfg.sims is not None:
        with reported():  # imported data: one line
            dataset = datamodule.larger_split(cfg.split, cfg.sims)
    calibration = datamodule.datasets[cfg.calibration_split]
    if cfg.calibration_sims is not None:
        with reported():  # imported data: one line
            calibration = datamodule.larger_split(cfg.calibration_split, cfg.calibration_sims)
    references = 2 if dataset.meta.target == "velocity" else 3
    stages = Stages(3 + references + bool(cfg.figures), bool(cfg.progress))
    curves: dict[str, dict[str, np.ndarray]] = {}
    positions: dict[str, np.ndarray] = {}  # the model's rollouts, written as rollouts.npz
    try:
        metrics, arrays = evaluate_split(
            module, dataset, calibration,
            one_step_frames(cfg, datamodule),
            cfg.mass_frames, cfg.mass_samples, cfg.batch_size, int(cfg.seed),
            int(cfg.rollout.steps), int(cfg.rollout.starts_per_sim), cfg.rollout.max_sims,
            curves=curves, step=stages, sinkhorn_stride=int(cfg.rollout.sinkhorn_stride),
            sinkhorn_rollouts=cfg.rollout.sinkhorn_rollouts, positions=positions,
            relmass_decode=str(cfg.relmass_decode),
            law_frames=int(cfg.law_frames))  # law_posterior's extra frames per simulation
        figures: dict[str, Any] = {}
        stages("the learned pair law")
        law, figures["law"] = law_text(module, datamodule.datasets["train"],
                                       LAW_FIGURE if cfg.figures else None)
        if figures["law"] is None:
            del figures["law"]
        if cfg.figures:
            stages("figures")
            labelled = {ROLLOUT_SOURCES[k]: c for k, c in curves.items()}
            figures["rollout_error"] = rollout_errors(labelled, metrics.get("rollout/rollout_cap"))
            figures["energy_drift"] = energy_drift(labelled)
            if arrays:
                figures["mass"] = mass_plot(arrays)
    finally:
        stages.close()
    out_dir = Path(cfg.out_dir) if cfg.out_dir else run_dir / "eval" / str(cfg.split)
    record = provenance_record(cfg, ckpt, config, run_cfg)
    record["wall_time_s"] = time.perf_counter() - start
    record["sims"] = {"split": len(dataset.sims), "calibration": len(calibration.sims)}
    record["model"] = module.model.describe()  # the variant, given, physics written in
    write_outputs(out_dir, record, metrics, figures, law)
    write_rollouts(out_dir / "rollouts.npz", positions, dataset.dt)
    return out_dir


def write_rollouts(path: Path, positions: dict[str, np.ndarray], dt: float) -> None:
    """The model's rollouts (``predicted``, ``true`` (R, steps + 2, N, D): the frame before the
    start, the start, the steps; ``sims``, ``starts`` (R,); ``dt``), written whole through a
    temporary file, so an engine's own energy can be computed on them
    (examples/engines/engine_energy.py --positions)."""
    import os

    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.npz")
    try:
        np.savez_compressed(tmp, dt=np.asarray(dt), **positions)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@cli("evaluate", positional="ckpt")  # bad input: one line, exit 2 (bgn.training.validate)
def main(cfg: Any) -> Path:
    """``python -m bgn.evaluate <run folder or checkpoint> [split=test] ...``."""
    with reported():
        paths = validate_evaluate(cfg)
    try:
        out_dir = evaluate_run(cfg, paths)
    except CheckpointError as err:  # an unreadable or foreign checkpoint: one line
        fail(err, DATA_EXIT)
    print(f"report: {out_dir / 'report.md'}")
    return out_dir
