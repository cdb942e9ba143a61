"""The masses of each simulation inferred through the model's own learned pair law: one least
squares over all its frames, and a Laplace posterior on log-mass
(docs/design.md#inverse-metrics).

A pair law the model learned is a likelihood: it says which masses make the observed
accelerations. ``learned_law/...`` (``bgn.eval.evaluate``) fits each window of a few frames on
its own; a simulation's masses do not change, and under gravity a few frames do not pin them
where a whole trajectory does. Here, per simulation:

- ``pooled_system``: the windows of its frames stacked along the frame axis on one graph (the
  union of their edges; a pair without an edge in a frame contributes nothing there), fitted
  by the head's own least squares (``PairForceHead.fit_observed``: under the source law the
  masses jointly, with its robust weights; under the inertial law ``1 / m`` per particle),
  after ``screened`` leaves out the accelerations the law cannot explain at a robust start
  (the median of the windows' own fits): the physical estimator likewise drops the
  accelerations the frame rate does not resolve. The simulator's true law is never used.
- ``fit_simulation``: the fit's standard errors (residual variance through the inverse normal
  matrix) turned into a standard deviation of log-mass by the delta method,
  ``sd(log m) = se(m) / m`` (``se(w) / w`` for ``w = 1 / m``). A particle whose fitted mass is
  not positive is not identified and keeps the prior (under the inertial law the sign of a
  free law is free as well: the fit is turned by the sign of its median over particles).
- ``place_scale``: the law's scale. Trained with the law loss (the head's prediction with the
  recorded masses, ``bgn.model.newton.law_loss``) it is physical and the masses absolute;
  otherwise the masses are known up to one common factor, a log-shift set on the validation
  split (the median of true minus fitted log-mass over its particles) or, with no validation
  masses, by the scene's mass law (``place_by_prior``). Never on the split scored. With
  validation masses the likelihood about the fit is calibrated there (``spread_calibration``,
  ``Spread``): the fit's standard deviations shrunk by one factor or widened by a floor, so
  that half the validation particles lie within the central 50 % interval (the likelihood's
  errors ignore the learned law's own error), and a heavy tail, a share of the likelihood
  widened, where it brings the validation coverage nearer every level.
- ``laplace_posterior``: that likelihood (a Gaussian, or two with a tail) times the scene's
  mass law (the prior), in closed form per pair of components: the posterior's mean,
  density and draws, for the same metrics as the flow's. Each particle's marginal: the
  fit's correlations between particles are not carried into the draws.
- ``contamination``: a share of the prior mixed into every posterior, chosen on the
  validation split (the share under which its recorded masses are most probable): a fit
  that goes wrong costs the prior's density, not a Gaussian's tail.

A head with one learned mass per type (``mass_law=type``) fits nothing to the frames: it has
no per-simulation posterior (``fit_simulation`` returns None).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy.optimize import brentq
from scipy.special import logsumexp
from scipy.stats import norm

from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.eval.mass_baselines import MassPrior, place_by_prior
from bgn.graph import Graph, collate
from bgn.metrics import COVERAGE_LEVELS
from bgn.model.newton import FIT_EPS, ROBUST_SCALE, PairForceHead

SCALES = ("physical", "validation", "prior")  # where the law's scale comes from
# |z| at the central 50 % interval of a standard normal: the median of |z| when calibrated
HALF_WIDTH = float(norm.ppf(0.75))
KEY = 1_000_000  # a particle's key: simulation * KEY + its index (as evaluate_inverse's)
# an acceleration the law misses by more than this (relative) at the robust start is left out:
# three of the head's Cauchy scales, where its weights would already cut it to a tenth
SCREEN = 3 * ROBUST_SCALE
# shares of the prior mixed into each particle's posterior, the one that makes the validation
# masses most probable kept (``contamination``)
CONTAMINATION = (0.0, 0.001, 0.003, 0.01, 0.03, 0.1, 0.3)
# the likelihood's heavy tails, (share, width): a share of it widened by the width, the pair
# that calibrates the validation particles best kept (``spread_calibration``); (0, 1) is the
# Gaussian alone
TAILS = ((0.0, 1.0),) + tuple((share, width) for share in (0.05, 0.1, 0.2, 0.3)
                              for width in (2.0, 4.0, 8.0))


def law_scale_pinned(model: torch.nn.Module) -> bool:
    """Whether the head's law is in physical units: its training read the recorded masses
    through the law loss (the model's ``law`` head, as ``bgn.laws.compare.read_law`` asks)."""
    return "law" in getattr(model, "heads", ())


def simulation_frames(dataset: FrameDataset, indices: list[int], law_frames: int = 0,
                      ) -> dict[int, list[int]]:
    """Per simulation, the dataset indices of its frames among ``indices`` and, with
    ``law_frames``, that many more of its frames evenly spaced over it: at most one per
    ``history`` frames, so that the added windows share no acceleration (a shared one would
    count twice and shrink the errors)."""
    out: dict[int, set[int]] = {}
    for i in indices:
        out.setdefault(dataset.locate(i)[0], set()).add(int(i))
    if law_frames > 0:
        per = dataset.frames_per_sim
        extra = evenly_spaced(per, min(law_frames, max(per // max(dataset.history, 1), 1)))
        for sim in out:
            first = dataset.sims.index(sim) * per
            out[sim].update(first + e for e in extra)
    return {sim: sorted(frames) for sim, frames in out.items()}


def pooled_system(head: PairForceHead, graphs: list[Graph],
                  ) -> tuple[Graph, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One simulation's windows (single-frame graphs of the same particles) as one
    least-squares system: a graph of its particles with the union of the windows' edges, the
    pair terms (E, W F, D) and the accelerations (N, W F, D) of every window's F fitted frames
    (``PairForceHead.observed_system``), window after window; and a robust start (N,), each
    particle's median over the windows of their own fits (``PairForceHead.fit_observed``);
    under the coupling law, whose fit pools a simulation's windows anyway, that fit (N, 2)."""
    n = int(graphs[0].num_nodes[0])
    g = collate(graphs)
    past, seen = head.observed_system(g, head.window(g)[1])
    fits = head.fit_observed(g, past, seen)[0]
    start = fits[-n:] if head.mass_law == "coupling" else \
        fits.reshape(len(graphs), n).median(0).values
    n_windows, n_frames, dim = len(graphs), past.shape[1], past.shape[2]
    snd, rcv = g.edge_index
    window = g.batch[rcv]                                   # each edge's window
    local = g.local_index                                   # index within its window
    pair = local[snd] * n + local[rcv]
    union, slot = torch.unique(pair, return_inverse=True)
    pooled_past = past.new_zeros(len(union), n_windows, n_frames, dim)
    pooled_past[slot, window] = past
    pooled_seen = seen.new_zeros(n, n_windows, n_frames, dim)
    pooled_seen[local, g.batch] = seen
    edges = torch.stack([union // n, union % n])
    return (replace(graphs[0], edge_index=edges), pooled_past.reshape(len(union), -1, dim),
            pooled_seen.reshape(n, -1, dim), start)


def screened(head: PairForceHead, g: Graph, past: torch.Tensor, seen: torch.Tensor,
             start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The system ``past``, ``seen`` (``pooled_system``) without the accelerations (a
    particle at a frame) the law with the robust ``start`` misses by more than ``SCREEN``
    relative to their size (floored as the head's weights are): set to zero with every pair
    term that reaches them, so they weigh nothing. A close encounter the frame rate does not
    resolve gives a few such rows; the head's reweighting starts from the plain fit, which
    over a whole trajectory they can drag far off (measured: docs/results.md)."""
    size = seen.norm(dim=-1)
    miss = (head.observed_prediction(g, past, start) - seen).norm(dim=-1) \
        / (size + 1e-3 * size.mean() + FIT_EPS)
    drop = miss > SCREEN                                                   # (N, F)
    return (past.masked_fill(drop[g.edge_index[1]][..., None], 0.0),
            seen.masked_fill(drop[..., None], 0.0))


@torch.no_grad()
def fit_simulation(head: PairForceHead, graphs: list[Graph],
                   ) -> tuple[np.ndarray, np.ndarray] | None:
    """Log-mass (N,) of each particle of one simulation from its windows ``graphs``, up to the
    law's free scale, and its standard deviation (N,) (the delta method); NaN where the fitted
    mass is not positive, the fit turned by its median's sign first (a law learned without
    recorded masses may have either). None under ``mass_law=type`` (nothing to fit). Under the
    coupling law the mass is ``c_i / k_i`` (``q_i / (q_i / m_i)``), turned by its median's
    sign likewise, its relative error the two couplings' added in quadrature."""
    if head.mass_law == "type":
        return None
    g, past, seen, start = pooled_system(head, graphs)
    fit, error = head.fit_observed(g, *screened(head, g, past, seen, start), with_error=True)
    fit, error = fit.double().numpy(), error.double().numpy()
    if head.mass_law == "coupling":
        k, c = fit[:, 0], fit[:, 1]
        rel = np.sqrt((error[:, 0] / (np.abs(k) + FIT_EPS)) ** 2
                      + (error[:, 1] / (np.abs(c) + FIT_EPS)) ** 2)
        mass = c / np.where(k == 0, FIT_EPS, k)
        # the law's sign is free as well (f -> -f, c -> -c makes the same accelerations): the
        # masses are turned by the sign of their median, as the inertial fit is
        mass = mass * (np.sign(np.median(mass)) or 1.0)
        positive = mass > 0
        return (np.where(positive, np.log(np.where(positive, mass, 1.0)), np.nan),
                np.where(positive, rel, np.nan))
    # a free law's sign is free too (f -> -f with 1 / m -> -1 / m, or m -> -m at the source,
    # makes the same accelerations): the fit is turned by the sign of its median
    fit = fit * (np.sign(np.median(fit)) or 1.0)
    positive = fit > 0
    safe = np.where(positive, fit, 1.0)
    log_mass = np.log(safe) if head.mass_law == "source" else -np.log(safe)
    return np.where(positive, log_mass, np.nan), np.where(positive, error / safe, np.nan)


@dataclass
class SimulationFits:
    """The per-simulation fits of a split, one row per particle of each simulation."""

    keys: np.ndarray        # (P,) simulation * KEY + index
    true_log: np.ndarray    # (P,) recorded log-masses (NaN where none are recorded)
    log_mass: np.ndarray    # (P,) fitted, up to the law's free scale; NaN: not identified
    log_std: np.ndarray     # (P,)
    windows: float          # mean windows per simulation


def fit_simulations(head: PairForceHead, dataset: FrameDataset, indices: list[int],
                    law_frames: int = 0) -> SimulationFits | None:
    """``fit_simulation`` on every simulation of ``indices`` (``simulation_frames``); None
    under ``mass_law=type``."""
    keys, true_log, log_mass, log_std, windows = [], [], [], [], []
    for sim, frames in simulation_frames(dataset, indices, law_frames).items():
        fit = fit_simulation(head, [dataset[i] for i in frames])
        if fit is None:
            return None
        n = len(fit[0])
        keys.append(sim * KEY + np.arange(n))
        masses = (dataset.file.read("masses", sim)
                  if getattr(dataset.meta, "masses_known", True) else np.full(n, np.nan))
        true_log.append(np.log(np.asarray(masses, dtype=np.float64)))
        log_mass.append(fit[0])
        log_std.append(fit[1])
        windows.append(len(frames))
    return SimulationFits(np.concatenate(keys), np.concatenate(true_log),
                          np.concatenate(log_mass), np.concatenate(log_std),
                          float(np.mean(windows)))


def place_scale(fits: SimulationFits, prior: MassPrior, pinned: bool,
                validation: SimulationFits | None) -> tuple[float, Spread, str]:
    """The log-shift for the law's scale, the likelihood about the fit (``Spread``: a factor
    on the fit's standard deviations, a floor added to them in quadrature, a heavy tail) and
    where the shift came from (``SCALES``). The shift: 0 where the law is physical
    (``pinned``); else the validation split's median of true minus fitted log-mass, or, with
    no validation masses, the shift that puts ``fits``' log-masses where the prior makes them
    most probable. The spread is chosen on the validation particles (``spread_calibration``):
    a factor below 1 where the fit's errors are too wide; a floor where they are too narrow,
    the learned law's own error, which the least squares does not see and which does not
    shrink with more frames; a tail where they are heavier than a Gaussian's (the stated
    Gaussian, ``Spread()``, without validation masses)."""
    known = (None if validation is None else
             np.isfinite(validation.true_log) & np.isfinite(validation.log_mass))
    has_validation = known is not None and bool(known.any())
    if pinned:
        shift, scale = 0.0, "physical"
    elif has_validation:
        shift = float(np.median(validation.true_log[known] - validation.log_mass[known]))
        scale = "validation"
    else:
        seen = np.isfinite(fits.log_mass)
        placed = place_by_prior(fits.log_mass, prior)
        shift = float(np.mean(placed[seen] - fits.log_mass[seen])) if seen.any() else 0.0
        scale = "prior"
    if not has_validation:
        return shift, Spread(), scale
    return shift, spread_calibration(
        validation.true_log[known] - validation.log_mass[known] - shift,
        validation.log_std[known]), scale


@dataclass(frozen=True)
class Spread:
    """The calibrated likelihood of a miss about a fit whose stated standard deviation is
    ``sd``: ``(1 - tail_share) N(0, s^2) + tail_share N(0, (tail_width s)^2)``, with
    ``s^2 = (sd factor)^2 + floor^2`` (``spread_calibration``). The tail, a share of the
    likelihood widened, is a scale mixture about the fit: a fit's errors are heavier-tailed
    than its least squares says (a window the law barely explains, a particle read only
    through a far pull), which a Gaussian of any one width cannot cover at 50 % and 90 %
    alike. ``Spread()``: the stated Gaussian itself."""

    factor: float = 1.0
    floor: float = 0.0
    tail_share: float = 0.0
    tail_width: float = 1.0

    def sd(self, sd: np.ndarray) -> np.ndarray:
        """The Gaussian core's standard deviation for stated ``sd``."""
        return np.sqrt((np.asarray(sd, dtype=np.float64) * self.factor) ** 2 + self.floor ** 2)

    def components(self) -> list[tuple[float, float]]:
        """(share, width) of each Gaussian of the mixture, the core first."""
        if self.tail_share <= 0:
            return [(1.0, 1.0)]
        return [(1.0 - self.tail_share, 1.0), (self.tail_share, self.tail_width)]

    def central(self, miss: np.ndarray, sd: np.ndarray) -> np.ndarray:
        """The smallest central credibility level whose interval holds ``miss``: uniform on
        [0, 1] over particles when calibrated (the mixture's two-sided PIT, closed form)."""
        a, s = np.abs(np.asarray(miss, dtype=np.float64)), np.maximum(self.sd(sd), 1e-300)
        return sum(share * (2 * norm.cdf(a / (s * width)) - 1)
                   for share, width in self.components())

    def covered(self, miss: np.ndarray, sd: np.ndarray, level: float) -> np.ndarray:
        """Whether each ``miss`` lies in the central ``level`` interval."""
        return self.central(miss, sd) <= level

    def log_pdf(self, miss: np.ndarray, sd: np.ndarray) -> np.ndarray:
        """The density of each ``miss`` under the calibrated likelihood."""
        s = np.maximum(self.sd(sd), 1e-300)
        return logsumexp([np.log(share) + norm.logpdf(miss, 0.0, s * width)
                          for share, width in self.components()], axis=0)


def spread_calibration(miss: np.ndarray, sd: np.ndarray) -> Spread:
    """The likelihood about the fit (``Spread``) chosen on the validation particles' misses
    ``miss`` from the truth and stated standard deviations ``sd``: for each tail of ``TAILS``
    a factor below 1 where the stated errors are too wide, else a floor added in quadrature
    (the error the least squares does not see, ``place_scale``), so that half the particles
    lie in the central 50 % interval; of those, the one whose coverage is nearest the level
    at every level of ``COVERAGE_LEVELS`` (the largest deviation, what recalibration is
    judged by), ties broken by the misses' mean log-density. With no tail this is the median
    |z| of a calibrated normal."""
    miss = np.abs(np.asarray(miss, dtype=np.float64))
    sd = np.maximum(np.asarray(sd, dtype=np.float64), 1e-12)
    finite = np.isfinite(miss) & np.isfinite(sd)  # a failed fit's particle says nothing here
    miss, sd = miss[finite], sd[finite]
    if not len(miss):
        return Spread()

    def rank(spread: Spread) -> tuple[float, float]:
        held = spread.central(miss, sd)
        deviation = max(abs(float(np.mean(held <= level)) - level)
                        for level in COVERAGE_LEVELS)
        return -round(deviation, 9), float(np.mean(spread.log_pdf(miss, sd)))

    return max((_half_covered(miss, sd, share, width) for share, width in TAILS), key=rank)


def _half_covered(miss: np.ndarray, sd: np.ndarray, share: float, width: float) -> Spread:
    """The factor (below 1) or floor under which the tail ``(share, width)`` holds half the
    misses in its central 50 % interval."""
    def excess(factor: float, floor: float) -> float:  # the median level held, less 1/2
        return float(np.median(Spread(factor, floor, share, width).central(miss, sd))) - 0.5

    if excess(1.0, 0.0) <= 0:
        if excess(1e-9, 0.0) <= 0:  # half the misses are exactly 0: no factor moves the
            return Spread(1.0, 0.0, share, width)  # median, so the stated errors are kept
        return Spread(brentq(lambda f: excess(f, 0.0), 1e-9, 1.0), 0.0, share, width)
    top = 2 * width * miss.max() / HALF_WIDTH + 1e-12
    return Spread(1.0, brentq(lambda f: excess(1.0, f), 0.0, top), share, width)


@dataclass
class LawPosterior:
    """Per particle a mixture of Gaussians over log-mass (one component per component of the
    prior): (P, K) means, standard deviations and log-weights (each row's sum to 1)."""

    means: np.ndarray
    stds: np.ndarray
    log_weights: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        """(P,) the posterior mean of log-mass."""
        return np.sum(np.exp(self.log_weights) * self.means, axis=1)

    def log_pdf(self, log_mass: np.ndarray) -> np.ndarray:
        """(P,) the density of each particle's posterior at ``log_mass`` (P,)."""
        z = (np.asarray(log_mass)[:, None] - self.means) / self.stds
        return logsumexp(self.log_weights - 0.5 * z ** 2
                         - np.log(self.stds * np.sqrt(2 * np.pi)), axis=1)

    def widened(self, std: float) -> LawPosterior:
        """Every component's spread widened by ``std`` in quadrature: an error common to all
        particles (the shift the prior placed), not a per-particle one to weigh against the
        prior, which would shrink every mass towards the prior's mean alike."""
        return LawPosterior(self.means, np.hypot(self.stds, std), self.log_weights)

    def mixed_with(self, other: LawPosterior, share: float) -> LawPosterior:
        """``(1 - share)`` of this posterior and ``share`` of ``other`` (per particle too), as
        one mixture per particle (``other``'s components appended)."""
        if share <= 0:
            return self
        return LawPosterior(np.concatenate([self.means, other.means], 1),
                            np.concatenate([self.stds, other.stds], 1),
                            np.concatenate([self.log_weights + np.log1p(-share),
                                            other.log_weights + np.log(share)], 1))

    def mixed(self, prior: MassPrior, share: float) -> LawPosterior:
        """``(1 - share)`` of this posterior and ``share`` of the prior (``mixed_with``)."""
        p = len(self.means)
        prior_w = np.log(prior.weights / prior.weights.sum())[None].repeat(p, 0)
        return self.mixed_with(LawPosterior(np.repeat(prior.means[None], p, 0),
                                            np.repeat(prior.stds[None], p, 0), prior_w), share)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """(n, P) independent draws of each particle's log-mass."""
        cdf = np.cumsum(np.exp(self.log_weights), axis=1)
        k = np.minimum((rng.random((n, len(cdf), 1)) > cdf[None]).sum(-1), cdf.shape[1] - 1)
        rows = np.arange(len(cdf))[None]
        return self.means[rows, k] + self.stds[rows, k] * rng.standard_normal(k.shape)


def laplace_posterior(log_mass: np.ndarray, log_std: np.ndarray, prior: MassPrior,
                      spread: Spread | None = None) -> LawPosterior:
    """The likelihood of the fit ``log_mass`` (P,) of stated standard deviations ``log_std``
    (``spread``'s mixture of Gaussians about it; the stated Gaussian by default) times the
    prior, component by component (a product of Gaussians for each pair of a likelihood's and
    a prior's component, weighted by its share and how well it predicts the fit); the prior
    itself where ``log_mass`` is NaN (the fit said nothing)."""
    spread = Spread() if spread is None else spread
    seen = np.isfinite(log_mass) & np.isfinite(log_std)
    mu = np.where(seen, log_mass, 0.0)[:, None]
    core = np.maximum(spread.sd(np.where(seen, log_std, 1.0)), 1e-12)[:, None]
    m0, v0 = prior.means[None], prior.stds[None] ** 2
    means, stds, log_ws = [], [], []
    for share, width in spread.components():
        var = np.where(seen[:, None], (core * width) ** 2, np.inf)
        precision = 1 / var + 1 / v0
        means.append((mu / var + m0 / v0) / precision)
        stds.append(np.sqrt(1 / precision))
        evidence = np.where(seen[:, None], norm.logpdf(mu, m0, np.sqrt(np.where(
            seen[:, None], var, 1.0) + v0)), 0.0)
        log_ws.append(np.log(share) + np.log(prior.weights / prior.weights.sum())[None]
                      + evidence)
    log_w = np.concatenate(log_ws, 1)
    return LawPosterior(np.concatenate(means, 1), np.concatenate(stds, 1),
                        log_w - logsumexp(log_w, axis=1, keepdims=True))


def contamination(validation: SimulationFits | None, prior: MassPrior, shift: float,
                  spread: Spread) -> float:
    """The share of the prior mixed into each particle's posterior (``LawPosterior.mixed``):
    of ``CONTAMINATION``, the one under which the validation particles' recorded log-masses
    are most probable (their mean log-density; 0 without validation masses). The Gaussian
    likelihood of a least squares says nothing of the fits that go wrong (a simulation whose
    encounters the frames barely resolve): one such particle, many of its standard
    deviations off, costs the information gain hundreds of nats, which the median's
    calibration (``place_scale``) does not see. The mixture bounds that cost at the prior's."""
    known = (None if validation is None else
             np.isfinite(validation.true_log) & np.isfinite(validation.log_mass))
    if known is None or not known.any():
        return 0.0
    base = laplace_posterior(validation.log_mass + shift, validation.log_std, prior, spread)
    scores = [float(np.mean(base.mixed(prior, share).log_pdf(validation.true_log)[known]))
              for share in CONTAMINATION]
    return CONTAMINATION[int(np.argmax(scores))]
