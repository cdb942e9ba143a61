"""The masses of each simulation inferred through the model's own contact head: the momentum
exchanged at the impacts it sees, over all the evaluated frames of a simulation, and a
Gaussian posterior on log-mass (docs/design.md#inverse-metrics).

The per-frame flow sees one window at a time, and a window rarely holds an impact; a
simulation's masses do not change, and over its frames most discs meet another. Per
simulation:

- ``simulation_impacts``: the windows of its frames (``simulation_frames``: the evaluated ones
  and, with ``law_frames``, that many more spread over it), the impacts the model's contact
  head resolves in each (``ContactImpulseHead.window_contacts``: where free flight meets and
  its gate is open; never the recorded contacts), and the equations they give,
  ``log m_i - log m_j = log |dv_j| - log |dv_i|`` at each isolated impact
  (``impact_equations``, the physical estimator's, which reads the recorded contacts instead).
- ``impact_posterior``: the equations, each with one noise standard deviation, times the
  prior of each disc's own type (the scene's mass law per type: a type is seen, its radius
  shows it), a linear Gaussian model in closed form: the posterior's mean and each disc's
  marginal standard deviation. Kinematics alone fixes ratios only; the types' laws place each
  group of linked discs. A disc in no equation keeps its type's law.
- ``choose_noise``: the noise and a share of the type's law mixed into each posterior (a false
  impact costs the type's density, not a Gaussian's tail), the pair under which the
  validation split's recorded masses are most probable (mean log-density: a proper score).
  With no validation masses (a model trained on the frames alone), the noise is the
  equations' own residual scatter (no truth read) and nothing is mixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from bgn.data.dataset import FrameDataset
from bgn.eval.law_posterior import CONTAMINATION, KEY, LawPosterior, simulation_frames
from bgn.eval.mass_baselines import MassPrior, impact_equations, impact_matrix
from bgn.graph import Graph, collate
from bgn.model.impulse import ContactImpulseHead

# candidate standard deviations of one impact's log-ratio (``choose_noise``): from the
# float round-off of an exact exchange to a factor of e
NOISE = tuple(float(s) for s in np.geomspace(1e-4, 1.0, 17))


def position_window(dataset: FrameDataset, index: int) -> np.ndarray:
    """The position window the model sees at dataset ``index`` (k+2, N, D)."""
    sim, t = dataset.locate(index)
    return dataset.file.read("positions", (sim, slice(t - dataset.history - 1, t + 1)))


def window_and_contacts(dataset: FrameDataset, index: int) -> tuple[np.ndarray,
                                                                    np.ndarray | None]:
    """``position_window`` and, for a contact scene, its recorded contacts as rows ``(frame
    within the window, i, j)``."""
    window = position_window(dataset, index)
    if dataset.meta.interaction != "contact":
        return window, None
    sim, t = dataset.locate(index)
    first = t - dataset.history - 1
    table = dataset.file.read("contacts", ...)
    rows = table[(table[:, 0] == sim) & (table[:, 1] >= first) & (table[:, 1] < t)]
    return window, np.column_stack([rows[:, 1] - first, rows[:, 2], rows[:, 3]])


@torch.no_grad()
def contact_rows(head: ContactImpulseHead, g: Graph, frames: int) -> list[np.ndarray]:
    """The impacts the contact ``head`` sees in each window of the batch ``g`` (windows of
    ``frames`` frames), per graph as rows ``(frame in its window, i, k)`` with the graph's own
    node indices: ``ContactImpulseHead.window_contacts``' rows ``(j, i, k)`` split by graph."""
    rows = head.window_contacts(g).cpu()
    batch = g.batch.cpu()
    first = (torch.cumsum(g.num_nodes, 0) - g.num_nodes).cpu()
    out = []
    for b in range(len(first)):
        mine = rows[batch[rows[:, 1]] == b]
        out.append(torch.stack([frames - 1 - mine[:, 0], mine[:, 1] - first[b],
                                mine[:, 2] - first[b]], 1).numpy())
    return out


@dataclass
class SimulationImpacts:
    """One simulation's impact equations (``impact_equations``) and its discs."""

    sim: int
    pairs: np.ndarray       # (M, 2)
    ratios: np.ndarray      # (M,)
    types: np.ndarray       # (N,)
    true_log: np.ndarray    # (N,) recorded log-masses (NaN where none are recorded)
    windows: int

    @property
    def keys(self) -> np.ndarray:
        """(N,) simulation * KEY + index, as the other inverse metrics key particles."""
        return self.sim * KEY + np.arange(len(self.types))

    def residual_sum(self) -> tuple[float, int]:
        """The least-squares residual sum of squares of the equations and its degrees of
        freedom (equations less the rank): what their scatter says of their noise."""
        if not len(self.pairs):
            return 0.0, 0
        a = impact_matrix(self.pairs, len(self.types))
        solution, _, rank, _ = np.linalg.lstsq(a, self.ratios, rcond=None)
        return float(np.sum((a @ solution - self.ratios) ** 2)), len(self.pairs) - int(rank)


@torch.no_grad()
def simulation_impacts(head: ContactImpulseHead, dataset: FrameDataset, indices: list[int],
                       law_frames: int = 0, batch_size: int = 16) -> list[SimulationImpacts]:
    """Per simulation of ``indices`` (and ``law_frames`` more of its frames), the impacts the
    contact ``head`` sees in each window, as equations on log-mass."""
    known = getattr(dataset.meta, "masses_known", True)
    out = []
    for sim, frames in simulation_frames(dataset, indices, law_frames).items():
        windows = np.stack([position_window(dataset, i) for i in frames])
        contacts = []
        for s in range(0, len(frames), batch_size):
            g = collate([dataset[i] for i in frames[s:s + batch_size]])
            contacts += contact_rows(head, g, windows.shape[1])
        pairs, ratios = impact_equations(windows, dataset.dt, contacts)
        types = dataset.file.read("types", sim)
        masses = (dataset.file.read("masses", sim) if known
                  else np.full(len(types), np.nan))
        out.append(SimulationImpacts(sim, pairs, ratios, np.asarray(types, np.int64),
                                     np.log(np.asarray(masses, dtype=np.float64)),
                                     len(frames)))
    return out


def type_prior(prior: MassPrior, types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per disc the mean and std of log-mass its prior gives: its type's component where the
    mass law has one per type, the law itself where it has one."""
    if prior.typed:
        return prior.type_law(types)
    return (np.full(len(types), prior.means[0]), np.full(len(types), prior.stds[0]))


def impact_posterior(sim: SimulationImpacts, prior: MassPrior, noise: float,
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The Gaussian posterior of one simulation's log-masses: each equation
    ``log m_i - log m_j = ratio`` with noise std ``noise``, each disc's prior its type's law
    (``type_prior``). Returns each disc's posterior mean and marginal std (N,)."""
    mean0, std0 = type_prior(prior, sim.types)
    a = impact_matrix(sim.pairs, len(sim.types))
    precision = np.diag(1.0 / std0 ** 2) + a.T @ a / noise ** 2
    covariance = np.linalg.inv(precision)
    mean = covariance @ (mean0 / std0 ** 2 + a.T @ sim.ratios / noise ** 2)
    return mean, np.sqrt(np.diag(covariance))


def posterior_of(impacts: list[SimulationImpacts], prior: MassPrior, noise: float,
                 ) -> LawPosterior:
    """Every disc of ``impacts``' Gaussian posterior (``impact_posterior``), one component."""
    fits = [impact_posterior(sim, prior, noise) for sim in impacts]
    return LawPosterior(np.concatenate([m for m, _ in fits])[:, None],
                        np.concatenate([s for _, s in fits])[:, None],
                        np.zeros((sum(len(sim.types) for sim in impacts), 1)))


def mixed_with_types(posterior: LawPosterior, impacts: list[SimulationImpacts],
                     prior: MassPrior, share: float) -> LawPosterior:
    """``(1 - share)`` of ``posterior`` and ``share`` of each disc's type's law
    (``type_prior``): a false impact costs the type's density, not a Gaussian's tail."""
    laws = [type_prior(prior, sim.types) for sim in impacts]
    means = np.concatenate([m for m, _ in laws])[:, None]
    stds = np.concatenate([s for _, s in laws])[:, None]
    return posterior.mixed_with(LawPosterior(means, stds, np.zeros_like(means)), share)


def residual_noise(impacts: list[SimulationImpacts]) -> float:
    """The equations' noise std from their own residual scatter (pooled over simulations;
    no recorded mass read); the smallest of ``NOISE`` where they have no redundancy."""
    sums = [sim.residual_sum() for sim in impacts]
    dof = sum(d for _, d in sums)
    if dof == 0:
        return NOISE[0]
    return max(float(np.sqrt(sum(s for s, _ in sums) / dof)), NOISE[0])


def choose_noise(impacts: list[SimulationImpacts], validation: list[SimulationImpacts] | None,
                 prior: MassPrior) -> tuple[float, float, str]:
    """The noise std of one equation, the share of the type's law mixed in
    (``mixed_with_types``), and where they came from ("validation" or "residuals"): of
    ``NOISE`` x ``CONTAMINATION``, the pair under which the validation discs' recorded
    log-masses are most probable (their mean log-density); without validation masses,
    ``residual_noise`` of ``impacts`` and no share."""
    truth = None if validation is None else np.concatenate([s.true_log for s in validation])
    if truth is None or not np.isfinite(truth).any():
        return residual_noise(impacts), 0.0, "residuals"
    seen = np.isfinite(truth)
    best, choice = -np.inf, (NOISE[0], 0.0)
    for noise in NOISE:
        posterior = posterior_of(validation, prior, noise)
        for share in CONTAMINATION:
            score = float(np.mean(mixed_with_types(posterior, validation, prior, share)
                                  .log_pdf(np.where(seen, truth, 0.0))[seen]))
            if score > best:
                best, choice = score, (noise, share)
    return choice[0], choice[1], "validation"
