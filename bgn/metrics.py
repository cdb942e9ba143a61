"""Metrics of predictions and mass samples on plain arrays: one definition each, shared by
the evaluation of checkpoints (``bgn.eval.evaluate``), the benchmarks and the tests.

R^2; inverse metrics of mass samples (Welch t-test, Wasserstein-1, recovered KDE modes) and
the calibration and information checks of simulation-based inference (expected coverage at
every level, SBC ranks, TARP, information gain over the prior: docs/design.md#inverse-metrics);
type-classification accuracy and AUROC; rollout errors, energy and momentum drift and failures.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from scipy.signal import find_peaks
from scipy.stats import chisquare, gaussian_kde, kstest, norm, ttest_ind, wasserstein_distance


def r2_score(pred: np.ndarray, true: np.ndarray) -> float:
    """Coefficient of determination (nan when the truth has no variance)."""
    pred, true = np.ravel(pred), np.ravel(true)
    total = float(np.sum((true - true.mean()) ** 2))
    if len(true) < 2 or total == 0.0:
        return float("nan")
    return 1.0 - float(np.sum((pred - true) ** 2)) / total


def binary_f1(pred: np.ndarray, true: np.ndarray) -> float:
    """F1 of boolean predictions (nan when there is nothing to find and nothing found)."""
    pred, true = np.ravel(pred).astype(bool), np.ravel(true).astype(bool)
    tp = np.sum(pred & true)
    denominator = 2 * tp + np.sum(pred & ~true) + np.sum(~pred & true)
    return float(2 * tp / denominator) if denominator else float("nan")


KDE_MAX_VALUES = 20_000


def kde_modes(values: np.ndarray, grid: np.ndarray, min_prominence: float = 0.05) -> np.ndarray:
    """Locations of the peaks of a Gaussian KDE of ``values`` on ``grid``; a peak counts when
    its prominence is at least ``min_prominence`` x the highest density (ignores wiggles)."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    # a KDE costs len(values) x len(grid): every 1/k-th of millions of samples finds the
    # same peaks, far faster
    # (docs/notes/2026-11-26-results-history.md, "Measurements behind the defaults")
    values = values[::max(1, len(values) // KDE_MAX_VALUES)]
    if len(values) < 2 or np.ptp(values) == 0:
        return values[:1].copy()
    density = gaussian_kde(values)(grid)
    # pad with zeros so a peak on the edge of the grid is still a peak
    padded = np.concatenate([[0.0], density, [0.0]])
    peaks, _ = find_peaks(padded, prominence=min_prominence * density.max())
    return grid[peaks - 1]


def recovered_modes(true_log: np.ndarray, sampled_log: np.ndarray,
                    tolerance: float = 0.5) -> tuple[int, int]:
    """(number of KDE modes of the true log-masses, how many of them have a mode of the
    sampled log-masses within ``tolerance``)."""
    true_log = np.ravel(true_log)
    sampled_log = np.ravel(sampled_log)
    sampled_log = sampled_log[np.isfinite(sampled_log)]
    lo = min(true_log.min(), np.percentile(sampled_log, 0.5)) - 1.0
    hi = max(true_log.max(), np.percentile(sampled_log, 99.5)) + 1.0
    grid = np.linspace(lo, hi, 512)
    true_modes, sampled_modes = kde_modes(true_log, grid), kde_modes(sampled_log, grid)
    if len(sampled_modes) == 0:
        return len(true_modes), 0
    matched = sum(bool(np.min(np.abs(sampled_modes - m)) <= tolerance) for m in true_modes)
    return len(true_modes), int(matched)


def _check_samples(true_log: np.ndarray, sampled_log: np.ndarray,
                   ) -> tuple[np.ndarray, np.ndarray]:
    true_log = np.asarray(true_log, dtype=np.float64)
    sampled_log = np.asarray(sampled_log, dtype=np.float64)
    if sampled_log.ndim != 2 or sampled_log.shape[1] != true_log.shape[0]:
        raise ValueError(f"samples {sampled_log.shape} must be (n_samples, {len(true_log)})")
    return true_log, sampled_log


COVERAGE_LEVELS = np.round(np.linspace(0.05, 0.95, 19), 2)  # 0.05, 0.10, ..., 0.95


def coverage_curve(true_log: np.ndarray, sampled_log: np.ndarray,
                   levels: np.ndarray = COVERAGE_LEVELS, seed: int = 0) -> np.ndarray:
    """Expected coverage at each credibility level: the fraction of particles whose true value
    lies inside the central ``level`` interval of its own posterior (``true_log`` (N,),
    ``sampled_log`` (S, N) samples of it). A calibrated posterior gives the diagonal,
    coverage = level; below it the posterior is overconfident (too narrow or biased), above it
    too wide.

    The posterior's CDF at the truth is read from the samples as a randomised rank,
    ``(rank + U) / (S + 1)`` with ``U`` uniform (``sbc_ranks``): exactly uniform on [0, 1] for
    a calibrated posterior whatever S, and the truth is inside the central ``level`` interval
    when it lies within ``level / 2`` of 0.5. The interval between the samples' own
    quantiles is narrower than the posterior's by about (S - 1) / (S + 1), so it undercovers
    (docs/notes/2026-11-26-results-history.md,
    "Recalibration, pooling over frames and the fitted masses")."""
    true_log, sampled_log = _check_samples(true_log, sampled_log)
    rng = np.random.default_rng(seed)
    pit = (sbc_ranks(true_log, sampled_log, rng) + rng.random(len(true_log))) \
        / (len(sampled_log) + 1)
    return np.mean(np.abs(pit[None, :] - 0.5) <= np.asarray(levels)[:, None] / 2, axis=1)


def sbc_ranks(true_log: np.ndarray, sampled_log: np.ndarray,
              rng: np.random.Generator | None = None) -> np.ndarray:
    """Simulation-based calibration (Talts et al. 2018): the rank of each true value among its
    S samples, 0..S, ties broken at random. Truths drawn from the prior and a calibrated
    posterior give ranks uniform on 0..S."""
    true_log, sampled_log = _check_samples(true_log, sampled_log)
    rng = np.random.default_rng(0) if rng is None else rng
    below = np.sum(sampled_log < true_log, axis=0)
    ties = np.sum(sampled_log == true_log, axis=0)
    return below + np.floor(rng.random(len(true_log)) * (ties + 1)).astype(int)


def sbc_uniformity_p(ranks: np.ndarray, n_samples: int, n_bins: int = 8) -> float:
    """p-value of a chi-square test that SBC ranks (0..``n_samples``) are uniform, on
    ``n_bins`` bins of equal width in rank (a few bins so each holds enough particles)."""
    edges = np.linspace(0, n_samples + 1, n_bins + 1)
    counts, _ = np.histogram(ranks, bins=edges)
    expected = len(ranks) * np.diff(edges) / (n_samples + 1)
    return float(chisquare(counts, expected).pvalue)


def tarp(true_log: np.ndarray, sampled_log: np.ndarray, rng: np.random.Generator | None = None,
         n_bins: int = 20) -> dict[str, float | np.ndarray]:
    """TARP (Lemos et al. 2023, "Sampling-based accuracy testing of posterior estimators"),
    as sbi's diagnostics run it. For each particle a reference point r is drawn uniformly over
    the range of the true values; f = the share of samples closer to r than the truth is.
    f is uniform on [0, 1] exactly when the posterior is accurate (for random references), so
    the expected coverage ``ecp(alpha)`` = P(f < alpha) is the diagonal. Returns the curve on
    ``n_bins`` levels, ``atc`` (area between the curve and the diagonal above alpha = 0.5,
    sbi's check_tarp: < 0 overconfident, > 0 too wide) and ``ks_p``, a one-sample
    Kolmogorov-Smirnov test of f against uniform (sbi compares the two curves instead)."""
    true_log, sampled_log = _check_samples(true_log, sampled_log)
    rng = np.random.default_rng(0) if rng is None else rng
    reference = rng.uniform(true_log.min(), true_log.max(), size=len(true_log))
    f = np.mean(np.abs(sampled_log - reference) < np.abs(true_log - reference), axis=0)
    alpha = np.linspace(0.0, 1.0, n_bins + 1)
    ecp = np.mean(f[None, :] < alpha[:, None], axis=1)
    ecp[-1] = 1.0                                     # f < 1 or f = 1: all covered at alpha 1
    upper = alpha >= 0.5
    atc = float(np.sum(ecp[upper] - alpha[upper]) / n_bins)
    return {"alpha": alpha, "ecp": ecp, "atc": atc, "ks_p": float(kstest(f, "uniform").pvalue)}


def kde_log_density(true_log: np.ndarray, sampled_log: np.ndarray) -> np.ndarray:
    """log q(true) per particle, q a Gaussian KDE of that particle's own samples (for a
    posterior known only by samples; a flow gives its density exactly)."""
    true_log, sampled_log = _check_samples(true_log, sampled_log)
    out = np.full(len(true_log), -np.inf)
    for i, (x, s) in enumerate(zip(true_log, sampled_log.T)):
        s = s[np.isfinite(s)]
        if len(s) > 1 and np.ptp(s) > 0:
            out[i] = gaussian_kde(s).logpdf(x)[0]
    return out


def information_gain(log_posterior: np.ndarray, log_prior: np.ndarray) -> float:
    """What the posterior adds over the prior, in nats per particle: the mean of
    ``log q(theta | x) - log p(theta)`` at the true values (an estimate of the expected KL
    from the prior to the posterior). 0 for a sampler that ignores the data; negative when
    the posterior puts less density on the truth than the prior does. A -inf density (the
    truth outside the samples' support) makes it -inf: that posterior excluded the truth."""
    return float(np.mean(np.asarray(log_posterior) - np.asarray(log_prior)))


def calibration_metrics(true_log: np.ndarray, sampled_log: np.ndarray,
                        log_posterior: np.ndarray | None = None,
                        log_prior: np.ndarray | None = None,
                        groups: np.ndarray | None = None, seed: int = 0) -> dict[str, float]:
    """The calibration and information checks of one posterior (docs/design.md#inverse-metrics):
    ``coverage_max_dev`` (the largest |coverage - level| over ``COVERAGE_LEVELS``), ``sbc_p``,
    ``tarp_atc``, ``tarp_ks_p`` and, given the log prior at the truths, ``info_gain`` with
    ``log_posterior`` (exact) or a KDE of the samples. Coverage at 50 % and 90 % is in
    ``inverse_metrics``.

    ``groups`` (N,): one label per distinct true value (a particle seen in several frames).
    The curves and means use every row; the two tests (``sbc_p``, ``tarp_ks_p``) assume
    independent truths, so they take the first row of each group only."""
    rng = np.random.default_rng(seed)
    true_log, sampled_log = _check_samples(true_log, sampled_log)
    first = (np.arange(len(true_log)) if groups is None
             else np.unique(groups, return_index=True)[1])
    curve = coverage_curve(true_log, sampled_log)
    t = tarp(true_log, sampled_log, rng)
    ranks = sbc_ranks(true_log[first], sampled_log[:, first], rng)
    out = {"coverage_max_dev": float(np.max(np.abs(curve - COVERAGE_LEVELS))),
           "sbc_p": sbc_uniformity_p(ranks, len(sampled_log)),
           "tarp_atc": float(t["atc"]),
           "tarp_ks_p": float(tarp(true_log[first], sampled_log[:, first], rng)["ks_p"])}
    if log_prior is not None:
        if log_posterior is None:
            log_posterior = kde_log_density(true_log, sampled_log)
        out["info_gain"] = information_gain(log_posterior, log_prior)
    return out


def inverse_metrics(true_log: np.ndarray, sampled_log: np.ndarray,
                    mode_tolerance: float = 0.5) -> dict[str, float]:
    """Metrics of mass samples. ``true_log`` (N,) true log-masses, ``sampled_log`` (S, N):
    S samples for each particle (natural log).

    Coverage: the fraction of particles whose true log-mass lies inside the central 50% / 90%
    interval of its posterior, read from the truth's randomised rank among the samples (0.5 /
    0.9 when calibrated; ``coverage_curve``). Welch p and
    W1 compare the pooled distributions (all true values against all samples).
    """
    true_log, sampled_log = _check_samples(true_log, sampled_log)
    pooled = sampled_log[np.isfinite(sampled_log)]
    out: dict[str, float] = {}
    out["welch_p"] = float(ttest_ind(true_log, pooled, equal_var=False).pvalue)
    out["wasserstein1"] = float(wasserstein_distance(true_log, pooled))
    out["coverage50"], out["coverage90"] = map(
        float, coverage_curve(true_log, sampled_log, np.array([0.5, 0.9])))
    n_true, n_matched = recovered_modes(true_log, pooled, mode_tolerance)
    out["modes_true"], out["modes_recovered"] = float(n_true), float(n_matched)
    return out


RECALIBRATION_LEVELS = np.linspace(0.0, 0.99, 100)  # knots of the monotone radius map


def fit_radius_map(base_values: np.ndarray, levels: np.ndarray = RECALIBRATION_LEVELS,
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Knots ``(z, r)`` of the monotone map ``r = m(z)`` that recalibrates a 1-D flow
    (Kuleshov et al. 2018, "Accurate uncertainties for deep learning using calibrated
    regression", in the flow's base space). ``base_values``: true values mapped to the base
    space of their own posteriors, N(0, 1) across cases when calibrated. A base draw ``e``
    becomes ``sign(e) m(|e|)``: the central ``level`` interval then reaches ``|u| <= r_level``,
    the ``level`` quantile of ``|base_values|``, and holds the truth at its level on these
    cases whatever the shape of the miscalibration (a scale alone, ``m(z) = tau z``, fixes
    only a too-narrow or too-wide Gaussian). ``z_k = Phi^-1((1 + level_k) / 2)``, ``r_k``
    strictly increasing from ``m(0) = 0``; non-finite values are dropped."""
    u = np.abs(np.asarray(base_values, dtype=np.float64))
    u = u[np.isfinite(u)]
    z = norm.ppf((1.0 + np.asarray(levels)) / 2)
    r = np.quantile(u, levels)
    if levels[0] == 0:
        r[0] = 0.0
    # strictly increasing (ties in |u| would make the inverse map undefined)
    r = np.maximum.accumulate(r) + 1e-9 * np.arange(len(r))
    return z, r


def aggregate_gaussian(mean: np.ndarray, var: np.ndarray, groups: np.ndarray,
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pool per-frame Gaussian posteriors ``N(mean, var)`` of one constant quantity (a
    particle's log-mass seen in several frames, labelled by ``groups``) into their product:
    precision ``sum 1/var``, mean the precision-weighted mean. Frames whose window says more
    (a sharp posterior: an impact, a close pass) weigh more than a plain average lets them.
    Returns ``(labels, mean, var)`` per group, labels sorted (``np.unique``)."""
    labels, index = np.unique(groups, return_inverse=True)
    precision = 1.0 / np.maximum(np.asarray(var, dtype=np.float64), 1e-12)
    total = np.bincount(index, precision)
    return labels, np.bincount(index, precision * mean) / total, 1.0 / total


def relative_mass_error(estimate_log: np.ndarray, true_log: np.ndarray) -> float:
    """Median over particles of ``|m_hat / m - 1|`` for log-mass estimates (natural log)."""
    return float(np.median(np.abs(np.expm1(np.asarray(estimate_log) - np.asarray(true_log)))))


def type_metrics(logits: np.ndarray, types: np.ndarray) -> dict[str, float]:
    """Accuracy and one-vs-rest macro AUROC (as the LightningModule's MulticlassAUROC)."""
    from torchmetrics.functional.classification import multiclass_auroc

    logits_t, types_t = torch.as_tensor(logits), torch.as_tensor(types).long()
    n = logits_t.shape[1]
    auroc = multiclass_auroc(logits_t.softmax(-1), types_t, num_classes=n)
    return {"type_accuracy": float((logits_t.argmax(-1) == types_t).float().mean()),
            "type_auroc": float(auroc)}


# ----------------------------------------------------------------------------- rollouts
ROLLOUT_HORIZONS = (1, 10, 50, 100)
ESCAPE_FACTOR = 10.0  # a rollout fails when a particle goes this many scene scales astray


def scene_scale(true: np.ndarray, box: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Centre and size of the scene of each of R true trajectories (R, T, N, D): the box's
    centre and half side, or the trajectory's mean position and largest distance from it."""
    if box is not None:
        return np.full(true.shape[-1], box / 2), np.full(len(true), box / 2)
    centre = true.mean(axis=(1, 2))[:, None, None, :]
    return centre, np.linalg.norm(true - centre, axis=-1).max(axis=(1, 2))


def capped_rollout_error(predicted: np.ndarray, true: np.ndarray, box: float | None) -> float:
    """One number for a training monitor: the mean position error per particle over every
    step of R rollouts (R, T+2, N, D), each step's error capped at ``ESCAPE_FACTOR`` scene
    scales (where a rollout counts as failed), and a non-finite step counted at that cap, so
    the value stays finite and a failed rollout is the worst case."""
    return float(capped_step_errors(predicted, true, box).mean())


def capped_step_errors(predicted: np.ndarray, true: np.ndarray, box: float | None,
                       ) -> np.ndarray:
    """(R, T) the mean position error per particle after each step of R rollouts (R, T+2, N,
    D), capped at ``ESCAPE_FACTOR`` scene scales, a non-finite step counted at that cap."""
    cap = ESCAPE_FACTOR * scene_scale(true, box)[1][:, None]
    err = np.linalg.norm(predicted[:, 2:] - true[:, 2:], axis=-1).mean(axis=-1)
    return np.where(np.isfinite(err), np.minimum(err, cap), cap)


def rollout_failures(predicted: np.ndarray, true: np.ndarray, box: float | None,
                     first_non_finite: np.ndarray) -> np.ndarray:
    """(R,) the first step (index into the frames after the start) at which a rollout failed,
    -1 if it did not: a non-finite value, or a particle further than ``ESCAPE_FACTOR`` scene
    scales from the scene (the box, or the true trajectory's extent about its centre)."""
    steps = predicted[:, 2:]                                    # frames after the start
    centre, scale = scene_scale(true, box)
    with np.errstate(invalid="ignore"):
        far = np.linalg.norm(steps - centre, axis=-1).max(axis=-1) \
            > ESCAPE_FACTOR * np.reshape(scale, (-1, 1))
    escaped = np.where(far.any(axis=1), far.argmax(axis=1) + 1, -1)
    both = np.stack([np.where(first_non_finite < 0, np.inf, first_non_finite),
                     np.where(escaped < 0, np.inf, escaped)])
    first = both.min(axis=0)
    return np.where(np.isfinite(first), first, -1).astype(int)


def rollout_cap(true: np.ndarray, box: float | None) -> np.ndarray:
    """(R,) the position error a failed rollout counts at: ``ESCAPE_FACTOR`` scene scales
    (``scene_scale``), the distance at which a rollout counts as failed."""
    return ESCAPE_FACTOR * scene_scale(true, box)[1]


def survived(failed_at: np.ndarray, length: int) -> np.ndarray:
    """(R, length) whether each rollout is still alive at each step from the start (False
    from the step it failed on, ``rollout_failures``)."""
    return np.arange(length)[None, :] < np.where(failed_at < 0, length, failed_at)[:, None]


def capped_errors(predicted: np.ndarray, true: np.ndarray, box: float | None,
                  failed_at: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per rollout and step from the start (R, T+1): the mean position error per particle and
    the mean squared error per coordinate, each counted at the cap (``rollout_cap``: error
    ``cap``, squared error ``cap^2 / D``, as if every particle were ``cap`` off) from the step
    a rollout failed on (``failed_at``, ``rollout_failures``) and wherever it exceeds the cap.
    Returns ``(error, squared error, cap (R,))``: means over them count every rollout, and a
    failed one as the worst case, where the survivors alone would hide it."""
    cap = rollout_cap(true, box)
    dim = predicted.shape[-1]
    with np.errstate(invalid="ignore", over="ignore"):
        err = np.linalg.norm(predicted - true, axis=-1).mean(axis=-1)[:, 1:]
        sq = ((predicted - true) ** 2).mean(axis=(-1, -2))[:, 1:]
    failed = ~survived(failed_at, err.shape[1]) | ~np.isfinite(err) | ~np.isfinite(sq)
    err = np.where(failed, cap[:, None], np.minimum(err, cap[:, None]))
    sq = np.where(failed, (cap**2 / dim)[:, None], np.minimum(sq, (cap**2 / dim)[:, None]))
    return err, sq, cap


def energy_errors(predicted: np.ndarray, true: np.ndarray, masses: np.ndarray, dt: float,
                  energy: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per rollout and step from the start (R, T+1): ``|E_t - E_0| / |E_0|`` of the prediction
    and of the truth (its finite-difference floor); velocities are backward differences and
    E_0 is the true start's energy."""
    v_pred, v_true = np.diff(predicted, axis=1) / dt, np.diff(true, axis=1) / dt
    e_pred, e_true = [], []
    for r in range(len(predicted)):
        e_true.append(energy(true[r, 1:], v_true[r], masses[r]))
        with np.errstate(invalid="ignore", over="ignore"):
            e_pred.append(energy(predicted[r, 1:], v_pred[r], masses[r]))
    e_true_a = np.asarray(e_true)
    e0 = np.abs(e_true_a[:, :1])
    with np.errstate(invalid="ignore", over="ignore"):
        e_err = np.abs(np.asarray(e_pred) - e_true_a[:, :1]) / e0
    return e_err, np.abs(e_true_a - e_true_a[:, :1]) / e0


def rollout_metrics(predicted: np.ndarray, true: np.ndarray, masses: np.ndarray, dt: float,
                    energy: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray],
                    first_non_finite: np.ndarray, box: float | None = None,
                    momentum: bool = False, horizons: tuple[int, ...] = ROLLOUT_HORIZONS,
                    contacts: tuple[np.ndarray, np.ndarray] | None = None,
                    ) -> dict[str, float]:
    """Rollout metrics (docs/design.md#rollouts) of R rollouts: ``predicted``, ``true`` (R, T+2, N,
    D) hold the frame before the start, the start and T steps; ``energy(x, v, m)`` is the scene's
    energy of (T, N, D) arrays.

    Every rollout counts, a failed one at a stated cap (``capped_errors``: 10 scene scales,
    ``rollout_cap`` its mean over the rollouts). Per horizon h: ``pos_err_mean@h`` the mean
    over all rollouts of the mean position error per particle, ``pos_err_median@h`` their
    median (beside the mean: up to half the rollouts can fail without moving a median),
    ``pos_mse_mean@h`` the mean squared error per coordinate over all rollouts; the same over
    the whole rollout (``@all``: the mean over its steps). Energy error
    ``|E_t - E_0| / |E_0|`` (velocities are backward differences, E_0 from the true start):
    the median over rollouts, a failed one infinite, at each horizon and at the end, beside
    the truth's own (its finite-difference floor); momentum error likewise when the scene
    conserves momentum; ``failed_share``, the share of failed rollouts
    (``rollout_failures``). ``contacts`` = (radii, types), each (R, N), for a disc gas adds
    ``contact_rollout_metrics``.
    """
    failed_at = rollout_failures(predicted, true, box, first_non_finite)
    n_steps = predicted.shape[1] - 2
    err, sq, cap = capped_errors(predicted, true, box, failed_at)
    alive = survived(failed_at, n_steps + 1)
    out: dict[str, float] = {"rollouts": float(len(predicted)), "rollout_steps": float(n_steps),
                             "failed_share": float(np.mean(failed_at >= 0)),
                             "rollout_cap": float(np.mean(cap))}
    chosen = [h for h in horizons if h <= n_steps] + ["all"]
    e_err, e_floor = energy_errors(predicted, true, masses, dt, energy)
    v_pred, v_true = np.diff(predicted, axis=1) / dt, np.diff(true, axis=1) / dt
    if momentum:
        with np.errstate(invalid="ignore", over="ignore"):
            p_pred = np.einsum("rn,rtnd->rtd", masses, v_pred)
        p_true = np.einsum("rn,rtnd->rtd", masses, v_true)
        p_scale = np.einsum("rn,rnd->r", masses, np.abs(v_true[:, 0]))[:, None]
        p_err = np.linalg.norm(p_pred - p_true[:, :1], axis=-1) / p_scale
    for h in chosen:
        if h == "all":
            at, e_h, sq_h = n_steps, err[:, 1:].mean(axis=1), sq[:, 1:].mean(axis=1)
        else:
            at, e_h, sq_h = h, err[:, h], sq[:, h]
        out[f"pos_err_mean@{h}"] = float(e_h.mean())
        out[f"pos_err_median@{h}"] = float(np.median(e_h))
        out[f"pos_mse_mean@{h}"] = float(sq_h.mean())
        out[f"energy_err@{h}"] = float(np.median(np.where(alive[:, at], e_err[:, at], np.inf)))
        out[f"energy_err_truth@{h}"] = float(np.median(e_floor[:, at]))
        if momentum:
            out[f"momentum_err@{h}"] = float(
                np.median(np.where(alive[:, at], p_err[:, at], np.inf)))
    if contacts is not None:
        out.update(contact_rollout_metrics(predicted, true, *contacts, dt, failed_at))
    return out


def collisions_per_frame(positions: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """(T-2,) impacts per frame interval of one trajectory (T, N, D): pairs that, moving on
    with their incoming displacement (frame t-1 to t), would touch before frame t+1 (the
    time-of-impact rule), and whose relative displacement then changes (by more than 10 %):
    they bounced. The same detector scores the truth and a rollout, so their rates compare;
    pairs that merely pass each other, or touch without a change, do not count."""
    from scipy.spatial import cKDTree

    counts = np.zeros(max(len(positions) - 2, 0), dtype=int)
    reach_max = 2 * float(radii.max())
    for t in range(1, len(positions) - 1):
        before, now, after = positions[t - 1], positions[t], positions[t + 1]
        if not (np.isfinite(before).all() and np.isfinite(now).all()
                and np.isfinite(after).all()):
            counts[t - 1:] = -1
            break
        step_in, step_out = now - before, after - now
        reach = reach_max + 2 * float(np.linalg.norm(step_in, axis=-1).max())
        pairs = cKDTree(now).query_pairs(reach, output_type="ndarray")
        if len(pairs) == 0:
            continue
        i, j = pairs[:, 0], pairs[:, 1]
        dx, dv_in = now[i] - now[j], step_in[i] - step_in[j]
        tau = np.clip(-(dx * dv_in).sum(-1) / np.maximum((dv_in * dv_in).sum(-1), 1e-300),
                      0.0, 1.0)
        touch = np.linalg.norm(dx + dv_in * tau[:, None], axis=-1) <= radii[i] + radii[j]
        change = np.linalg.norm((step_out[i] - step_out[j]) - dv_in, axis=-1)
        bounced = change > 0.1 * np.linalg.norm(dv_in, axis=-1) + 1e-300
        counts[t - 1] = int(np.sum(touch & bounced))
    return counts


def contact_rollout_metrics(predicted: np.ndarray, true: np.ndarray, radii: np.ndarray,
                            types: np.ndarray, dt: float, failed_at: np.ndarray,
                            ) -> dict[str, float]:
    """What stays predictable in a chaotic disc gas, for R rollouts (R, T+2, N, D), over all
    of them. ``speed_w1_type<k>``: type k's speed distribution at the last step against the
    truth's (Wasserstein-1 over the true mean speed of that type), pooled over every rollout;
    a predicted speed counts at most ``ESCAPE_FACTOR`` times that mean speed, and the discs of
    a failed rollout count at that cap (as if they had flown off). ``collision_rate_ratio``:
    the impacts of the rollouts against the truth's over the same rollouts
    (``collisions_per_frame``); a failed rollout's impacts count up to its failure and none
    after it, while its truth counts to the end."""
    failed = failed_at >= 0
    out: dict[str, float] = {}
    with np.errstate(invalid="ignore", over="ignore"):
        v_pred = np.linalg.norm(predicted[:, -1] - predicted[:, -2], axis=-1) / dt
    v_true = np.linalg.norm(true[:, -1] - true[:, -2], axis=-1) / dt
    for k in np.unique(types):
        mask = types == k
        mean = float(v_true[mask].mean())
        if mean <= 0:
            out[f"speed_w1_type{k}"] = float("nan")
            continue
        cap = ESCAPE_FACTOR * mean
        capped = np.where(failed[:, None] | ~np.isfinite(v_pred), cap, np.minimum(v_pred, cap))
        out[f"speed_w1_type{k}"] = float(wasserstein_distance(capped[mask], v_true[mask]) / mean)
    hits_pred = hits_true = 0
    for r in range(len(predicted)):
        last = failed_at[r] + 1 if failed[r] else predicted.shape[1]  # frames before failure
        hits_pred += int(collisions_per_frame(predicted[r, 1:last], radii[r]).clip(0).sum())
        hits_true += int(collisions_per_frame(true[r, 1:], radii[r]).sum())
    out["collision_rate_ratio"] = float(hits_pred / hits_true) if hits_true else float("nan")
    return out


# ----------------------------------------------------------------------------- LagrangeBench
# LagrangeBench's rollout metrics (Toshev et al. 2023; lagrangebench/evaluate/metrics.py), so
# that results on imported data compare with published numbers: position MSE averaged over
# the first 5 / 10 / 20 / 50 / 100 steps and over the whole rollout, the Sinkhorn divergence
# between the predicted and true particle clouds and the kinetic-energy MSE.
LB_HORIZONS = (5, 10, 20, 50, 100)
LB_EPSILON = 0.05  # ott-jax's default entropic regularisation, relative to the mean cost


def minimum_image(d: Any, period: Any) -> Any:
    """Differences ``d`` (..., D) moved by whole box lengths to their nearest image in each
    periodic dimension; ``period`` broadcasts against ``d`` (a box's side where periodic; 0
    or inf where not; None: ``d`` unchanged). numpy arrays or torch tensors, the result of the
    same kind: the one implementation of the package (data, models and metrics use it). The
    shift is piecewise constant, so a tensor's gradient in ``d`` is the identity."""
    if period is None:
        return d
    if isinstance(d, torch.Tensor):
        where, period = torch.where, torch.as_tensor(period, device=d.device).to(d.dtype)
    else:
        where, d, period = np.where, np.asarray(d), np.asarray(period, dtype=np.float64)
    periodic = (period > 0) & (period < math.inf)
    side = where(periodic, period, 1.0)
    return where(periodic, d - side * (d / side).round(), d)


def _entropic_cost(cost: np.ndarray, eps: float, max_iter: int, threshold: float) -> float:
    """ott-jax's ``reg_ot_cost`` between uniform weights: ``<P, C> + eps KL(P | a b^T)`` of
    the entropic plan P (POT's Sinkhorn; the log-domain solver where the kernel underflows)."""
    import ot
    from scipy.special import xlogy

    a, b = np.full(cost.shape[0], 1 / cost.shape[0]), np.full(cost.shape[1], 1 / cost.shape[1])
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # underflow: the log-domain solver takes over below
        plan = ot.sinkhorn(a, b, cost, eps, method="sinkhorn", numItermax=max_iter,
                           stopThr=threshold)
    if not np.isfinite(plan).all() or abs(plan.sum() - 1) > 1e-6:
        plan = ot.sinkhorn(a, b, cost, eps, method="sinkhorn_log", numItermax=max_iter,
                           stopThr=threshold)
    entropy = xlogy(plan, plan).sum() - plan.sum(1) @ np.log(a) - plan.sum(0) @ np.log(b)
    return float((plan * cost).sum() + eps * entropy)


def sinkhorn_divergence(x: np.ndarray, y: np.ndarray, period: np.ndarray | None = None,
                        max_iter: int = 2000, threshold: float | None = None) -> float:
    """The Sinkhorn divergence between the particle clouds ``x`` (N, D) and ``y`` (M, D) with
    uniform weights, as LagrangeBench computes it with ott-jax's defaults: squared Euclidean
    cost (minimum image along periodic dimensions), entropic regularisation
    ``eps = 0.05 * mean(C_xy)`` shared by the three terms,
    ``S = OT_eps(x, y) - (OT_eps(x, x) + OT_eps(y, y)) / 2`` with ``OT_eps`` the regularised
    cost ``<P, C> + eps KL(P | a b^T)``. Solved by POT in float64, at most ``max_iter``
    iterations (ott-jax's default), to a marginal error (2-norm) ``threshold``, by default
    ``1e-4 / sqrt(N)``: at most ott-jax's 1e-4 in its 1-norm (LagrangeBench: ott-jax in
    float32). 0 for one cloud and any permutation of it; a cloud translated by c gives
    ``|c|^2`` (the cross term of the cost is separable, so the plan is the unshifted one's)."""
    def cost(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        out = np.zeros((len(p), len(q)))
        for k in range(p.shape[-1]):  # one coordinate at a time: no (N, M, D) array
            d = minimum_image(p[:, None, k:k + 1] - q[None, :, k:k + 1],
                              None if period is None else np.asarray(period)[k:k + 1])
            out += d[..., 0] ** 2
        return out

    c_xy = cost(x, y)
    eps = LB_EPSILON * float(c_xy.mean())
    if eps <= 0:  # every particle in one point, in both clouds
        return 0.0
    threshold = 1e-4 / np.sqrt(max(len(x), len(y))) if threshold is None else threshold
    terms = [_entropic_cost(c, eps, max_iter, threshold) for c in (c_xy, cost(x, x), cost(y, y))]
    return max(terms[0] - (terms[1] + terms[2]) / 2, 0.0)


def kinetic_energy(x: np.ndarray, masses: np.ndarray, dt: float,
                   period: np.ndarray | None = None) -> np.ndarray:
    """LagrangeBench's kinetic energy of each frame interval of trajectories (..., T, N, D):
    ``sum_i m_i |v_i|^2`` (no 1/2; their m_i = dx^dim, unit density) with finite-difference
    velocities ``v = (x_{t+1} - x_t) / dt`` (minimum image where periodic); (..., T-1)."""
    v = minimum_image(np.diff(x, axis=-3), period) / dt
    return np.einsum("...n,...tn->...t", masses, (v**2).sum(-1))


def lagrangebench_metrics(predicted: np.ndarray, true: np.ndarray, masses: np.ndarray,
                          dt: float, failed_at: np.ndarray, box: float | None = None,
                          period: np.ndarray | None = None,
                          horizons: tuple[int, ...] = LB_HORIZONS, sinkhorn_stride: int = 10,
                          sinkhorn_rollouts: int | None = None) -> dict[str, float]:
    """LagrangeBench's rollout metrics of R rollouts (R, T+2, N, D: the frame before the
    start, the start and T steps, as ``rollout_metrics``), each per rollout then averaged over
    the rollouts, as their ``averaged_metrics``; ``<name>_std`` the standard deviation over
    the rollouts beside each. Every particle counts, kinematic ones too (LagrangeBench sets
    them to the truth, as bgn's rollouts do, and averages over all particles).

    - ``mse@h``: the per-step MSE (mean over particles and coordinates of the squared position
      error, minimum image along ``period``) averaged over steps 1..h (LagrangeBench's
      ``mse{h}``); ``mse@all`` over the whole rollout (their ``loss``). The MSE at step h
      alone is ``rollout_metrics``' ``pos_mse_mean@h``.
    - ``sinkhorn``: ``sinkhorn_divergence`` of the clouds at steps 1, 1 + s, ... < T
      (LagrangeBench's frames ``[0:-1:s]``, s = ``sinkhorn_stride``: theirs is 1 at
      inference, 10 in training validation), on ``sinkhorn_rollouts`` evenly spaced rollouts
      (None: all), the divergence the costly one.
    - ``e_kin_mse``: the MSE over the rollout of ``kinetic_energy`` per frame interval
      (steps 1..T, stride 1 as LagrangeBench's inference).

    Failed rollouts (``failed_at``, ``rollout_failures``) count at the cap of
    ``capped_errors`` (``rollout_cap``: 10 scene scales) from the step they failed on: a step's
    MSE at ``cap^2 / D`` and the Sinkhorn divergence at ``cap^2`` (a cloud ``cap`` off), each
    also capped there; the predicted kinetic energy at 10^2 times the true mean over the
    rollout (speeds 10 times the truth's, as ``contact_rollout_metrics``' speed cap);
    ``failed_share`` beside."""
    n_rollouts, n_steps, dim = len(predicted), predicted.shape[1] - 2, predicted.shape[-1]
    cap = rollout_cap(true, box)
    alive = survived(failed_at, n_steps + 1)[:, 1:]                           # steps 1..T
    with np.errstate(invalid="ignore", over="ignore"):
        sq = (minimum_image(predicted[:, 2:] - true[:, 2:], period) ** 2).mean(axis=(-1, -2))
    sq_cap = (cap**2 / dim)[:, None]
    sq = np.where(alive & np.isfinite(sq), np.minimum(sq, sq_cap), sq_cap)
    out: dict[str, float] = {"rollouts": float(n_rollouts),
                             "failed_share": float(np.mean(failed_at >= 0))}

    def put(name: str, per_rollout: np.ndarray, at: str = "") -> None:
        out[f"{name}{at}"] = float(np.mean(per_rollout))
        out[f"{name}_std{at}"] = float(np.std(per_rollout))

    for h in [h for h in horizons if h <= n_steps] + ["all"]:
        put("mse", sq[:, :n_steps if h == "all" else h].mean(axis=1), f"@{h}")
    if n_steps >= 2:
        e_true = kinetic_energy(true[:, 2:], masses, dt, period)
        with np.errstate(invalid="ignore", over="ignore"):
            e_pred = kinetic_energy(predicted[:, 2:], masses, dt, period)
        e_cap = ESCAPE_FACTOR**2 * e_true.mean(axis=1, keepdims=True)
        e_pred = np.where(alive[:, 1:] & np.isfinite(e_pred), np.minimum(e_pred, e_cap), e_cap)
        put("e_kin_mse", ((e_pred - e_true) ** 2).mean(axis=1))
    frames = np.arange(1, max(n_steps, 2), sinkhorn_stride)
    chosen = np.unique(np.linspace(0, n_rollouts - 1, min(sinkhorn_rollouts or n_rollouts,
                                                         n_rollouts)).round().astype(int))
    divergences = np.empty((len(chosen), len(frames)))
    for k, r in enumerate(chosen):
        for j, step in enumerate(frames):
            x = predicted[r, step + 1]
            if alive[r, step - 1] and np.isfinite(x).all():
                value = sinkhorn_divergence(x, true[r, step + 1], period)
                divergences[k, j] = min(value, cap[r] ** 2)
            else:
                divergences[k, j] = cap[r] ** 2
    put("sinkhorn", divergences.mean(axis=1))
    out["sinkhorn_rollouts"], out["sinkhorn_frames"] = float(len(chosen)), float(len(frames))
    out["sinkhorn_stride"] = float(sinkhorn_stride)
    return out


SHORT_HORIZON = 10  # the short-horizon error reported beside a rollout score's horizon


def rollout_scores(predicted: np.ndarray, true: np.ndarray, first_non_finite: np.ndarray,
                   box: float | None, horizons: Sequence[int],
                   ) -> tuple[dict[int, float], float, np.ndarray]:
    """Errors after each horizon (the mean over R rollouts (R, T+2, N, D) of the capped
    position error, ``bgn.metrics.capped_step_errors``, a failed rollout at the cap from the
    step it failed), the share of rollouts that failed, and the mean error per step (T,)."""
    errors, failed = failure_capped_errors(predicted, true, first_non_finite, box)
    n_steps = errors.shape[1]
    scores = {int(h): float(errors[:, h - 1].mean()) for h in horizons if 1 <= h <= n_steps}
    return scores, float(np.mean(failed >= 0)), errors.mean(axis=0)


def failure_capped_errors(predicted: np.ndarray, true: np.ndarray, first_non_finite: np.ndarray,
                          box: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) each rollout's capped position error per step (``capped_step_errors``), at the
    cap from the step it failed on, and (R,) that step (-1: it did not fail)."""
    errors = capped_step_errors(predicted, true, box)
    cap = ESCAPE_FACTOR * scene_scale(true, box)[1]
    failed = rollout_failures(predicted, true, box, first_non_finite)
    for r, step in enumerate(failed):
        if step >= 1:
            errors[r, step - 1:] = cap[r]
    return errors, failed
