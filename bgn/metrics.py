"""Metrics of predictions and mass samples on plain arrays: one definition each, shared by
the evaluation of checkpoints (``bgn.evaluate``), the benchmarks and the tests.

R^2; inverse metrics of mass samples (Welch t-test, Wasserstein-1, recovered KDE modes,
interval coverage); type-classification accuracy and AUROC.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.signal import find_peaks
from scipy.stats import gaussian_kde, ttest_ind, wasserstein_distance


def r2_score(pred: np.ndarray, true: np.ndarray) -> float:
    """Coefficient of determination (nan when the truth has no variance)."""
    pred, true = np.ravel(pred), np.ravel(true)
    total = float(np.sum((true - true.mean()) ** 2))
    if len(true) < 2 or total == 0.0:
        return float("nan")
    return 1.0 - float(np.sum((pred - true) ** 2)) / total


def kde_modes(values: np.ndarray, grid: np.ndarray, min_prominence: float = 0.05) -> np.ndarray:
    """Locations of the peaks of a Gaussian KDE of ``values`` on ``grid``; a peak counts when
    its prominence is at least ``min_prominence`` x the highest density (ignores wiggles)."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
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


def inverse_metrics(true_log: np.ndarray, sampled_log: np.ndarray,
                    mode_tolerance: float = 0.5) -> dict[str, float]:
    """Metrics of mass samples. ``true_log`` (N,) true log-masses, ``sampled_log`` (S, N):
    S samples for each particle (natural log).

    Coverage: the fraction of particles whose true log-mass lies inside the central 50% / 90%
    interval of its own samples (0.5 / 0.9 when calibrated). Welch p and W1 compare the pooled
    distributions (all true values against all samples).
    """
    true_log = np.asarray(true_log, dtype=np.float64)
    sampled_log = np.asarray(sampled_log, dtype=np.float64)
    if sampled_log.ndim != 2 or sampled_log.shape[1] != true_log.shape[0]:
        raise ValueError(f"samples {sampled_log.shape} must be (n_samples, {len(true_log)})")
    pooled = sampled_log[np.isfinite(sampled_log)]
    out: dict[str, float] = {}
    out["welch_p"] = float(ttest_ind(true_log, pooled, equal_var=False).pvalue)
    out["wasserstein1"] = float(wasserstein_distance(true_log, pooled))
    for level in (50, 90):
        tail = (100 - level) / 2
        lo, hi = np.nanpercentile(sampled_log, [tail, 100 - tail], axis=0)
        out[f"coverage{level}"] = float(np.mean((true_log >= lo) & (true_log <= hi)))
    n_true, n_matched = recovered_modes(true_log, pooled, mode_tolerance)
    out["modes_true"], out["modes_recovered"] = float(n_true), float(n_matched)
    return out


def type_metrics(logits: np.ndarray, types: np.ndarray) -> dict[str, float]:
    """Accuracy and one-vs-rest macro AUROC (as the LightningModule's MulticlassAUROC)."""
    from torchmetrics.functional.classification import multiclass_auroc

    logits_t, types_t = torch.as_tensor(logits), torch.as_tensor(types).long()
    n = logits_t.shape[1]
    auroc = multiclass_auroc(logits_t.softmax(-1), types_t, num_classes=n)
    return {"type_accuracy": float((logits_t.argmax(-1) == types_t).float().mean()),
            "type_auroc": float(auroc)}
