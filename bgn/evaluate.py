"""Evaluation of a trained checkpoint on the test split (used by ``bgn.experiments``).

Forward metrics (MSE in physical units, NMSE = MSE / training target variance as the
LightningModule logs it, median relative error), inverse metrics from mass samples (Welch
t-test, Wasserstein-1, recovered KDE modes, relative-mass R^2, interval coverage) and type
classification metrics. The metric functions take plain arrays so they are testable alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.signal import find_peaks
from scipy.stats import gaussian_kde, ttest_ind, wasserstein_distance

from bgn.data.dataset import FrameDataset
from bgn.graph import Graph, collate
from bgn.model.target import extrapolate, observed_targets
from bgn.module import PhysicsModule


# ----------------------------------------------------------------------------- loading
def load_model(ckpt: str | Path) -> PhysicsModule:
    """The LightningModule of a checkpoint, on the CPU, in eval mode."""
    return PhysicsModule.load_from_checkpoint(ckpt, map_location="cpu").eval()


def frame_indices(dataset: FrameDataset, max_frames: int | None) -> np.ndarray:
    """Evenly spaced test frames (all when ``max_frames`` is None): a fixed, reproducible
    subset that still covers every test simulation."""
    n = len(dataset)
    if max_frames is None or max_frames >= n:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, int(max_frames)).round().astype(int))


def batches(dataset: FrameDataset, indices: np.ndarray, batch_size: int) -> list[Graph]:
    return [collate([dataset[int(i)] for i in indices[s:s + batch_size]])
            for s in range(0, len(indices), batch_size)]


# ----------------------------------------------------------------------------- metrics
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
    indices = frame_indices(dataset, max_frames)
    sq_err, rel_err = [], []
    # references without learning: repeat the last observed target, extrapolate the last two
    ref_err: dict[str, list[torch.Tensor]] = {"last": [], "linear": []}
    logits, types, rel_pred, rel_true = [], [], [], []
    for g in batches(dataset, indices, batch_size):
        pred = model.predict(g)
        sq_err.append(((pred - g.target) ** 2).flatten())
        seen = observed_targets(g, module.meta.target)
        for name in ref_err if seen.shape[1] > 1 else ("last",):
            ref_err[name].append(((extrapolate(seen, name) - g.target) ** 2).flatten())
        rel_err.append((pred - g.target).norm(dim=-1)
                       / g.target.norm(dim=-1).clamp_min(1e-12))
        if heads & {"type", "relmass"}:
            out = model(g)
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
    if rel_pred:
        metrics["relmass_r2"] = r2_score(torch.cat(rel_pred).numpy(), torch.cat(rel_true).numpy())
    arrays: dict[str, np.ndarray] = {}
    if model.has_inverse:
        # every particle of a subset of test frames, each sampled mass_samples times
        true_mass, sampled = [], []
        for g in batches(dataset, frame_indices(dataset, mass_frames), batch_size):
            sampled.append(model.sample_mass(g, mass_samples))
            true_mass.append(g.mass)
        arrays = {"true_mass": torch.cat(true_mass).double().numpy(),
                  "sampled_mass": torch.cat(sampled, dim=1).double().numpy()}
        with np.errstate(divide="ignore", invalid="ignore"):
            metrics.update(inverse_metrics(np.log(arrays["true_mass"]),
                                           np.log(arrays["sampled_mass"])))
        metrics["mass_particles"] = int(arrays["true_mass"].shape[0])
    return metrics, arrays


def mass_figure(arrays: dict[str, np.ndarray], path: str | Path) -> Path:
    """Write the KDE of true vs sampled masses (``figures.mass_density``) as a PNG."""
    import matplotlib.pyplot as plt

    from bgn.figures import mass_density

    fig = mass_density(arrays["true_mass"], arrays["sampled_mass"].ravel())
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
