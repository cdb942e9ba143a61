"""Figures for TensorBoard and reports (matplotlib, no display needed)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from scipy.stats import gaussian_kde  # noqa: E402


def predicted_vs_true(pred: np.ndarray, true: np.ndarray, label: str) -> Figure:
    """One panel per dimension: predicted against true target, with the identity line."""
    d = true.shape[1]
    fig, axes = plt.subplots(1, d, figsize=(3.2 * d, 3.2), squeeze=False)
    for i, ax in enumerate(axes[0]):
        ax.scatter(true[:, i], pred[:, i], s=4, alpha=0.5)
        lo, hi = np.percentile(true[:, i], [0.5, 99.5])
        ax.plot([lo, hi], [lo, hi], "k--", lw=1)
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_xlabel(f"true {label} [{i}]")
        ax.set_ylabel("predicted")
    fig.tight_layout()
    return fig


def _draw_mass_density(ax: Any, true: np.ndarray, sampled: np.ndarray) -> None:
    log_true, log_sampled = np.log10(true), np.log10(sampled[np.isfinite(sampled)
                                                             & (sampled > 0)])
    lo = min(log_true.min(), np.percentile(log_sampled, 0.5)) - 0.3
    hi = max(log_true.max(), np.percentile(log_sampled, 99.5)) + 0.3
    grid = np.linspace(lo, hi, 300)
    edges = np.linspace(lo, hi, 41)
    series = ((log_true, "true"), (log_sampled, "sampled"))
    spread = [v for v, _ in series if len(v) > 1 and np.ptp(v) > 0]
    # Scott's bandwidth in log10-mass units: std * n^(-1/5)
    width = min((np.std(v, ddof=1) * len(v) ** -0.2 for v in spread), default=None)
    for values, name in series:
        if len(values) > 1 and np.ptp(values) > 0:
            kde = gaussian_kde(values, bw_method=width / np.std(values, ddof=1))
            line, = ax.plot(grid, kde(grid), label=f"{name} (KDE)")
            ax.hist(values, bins=edges, density=True, alpha=0.25, color=line.get_color())
        else:
            ax.axvline(values[0] if len(values) else lo, label=name)
    ax.set_xlabel("log10 mass")
    ax.set_ylabel("density")
    ax.legend()


def mass_density(true: np.ndarray, sampled: np.ndarray) -> Figure:
    """Kernel density of true and sampled masses on a log axis (paper figures 2-3), over
    shaded histograms on shared bins. Both curves use one kernel width, the narrower of the
    two series' Scott bandwidths: Scott's rule alone would blur the series with fewer values
    more (32 samples per particle against one true value), so equal laws would look unequal.
    Narrow modes of a multi-modal law are still blurred; the histograms show them."""
    fig, ax = plt.subplots(figsize=(4.5, 3.2))
    _draw_mass_density(ax, true, sampled)
    fig.tight_layout()
    return fig


def mass_calibration(true: np.ndarray, sampled: np.ndarray, levels: np.ndarray,
                     coverage: dict[str, np.ndarray]) -> Figure:
    """The mass densities (``mass_density``) beside expected-coverage curves: for each
    credibility level, the share of true log-masses inside the central interval of their
    posterior samples (``bgn.metrics.coverage_curve``), one line per posterior. Matching
    densities do not show inference (a sampler of the prior matches them too); a curve on the
    diagonal is calibrated, below it overconfident."""
    fig, (ax, ax_cov) = plt.subplots(1, 2, figsize=(8.5, 3.4))
    _draw_mass_density(ax, true, sampled)
    ax_cov.plot([0, 1], [0, 1], "k--", lw=1, label="calibrated")
    for name, curve in coverage.items():
        ax_cov.plot(levels, curve, "o-", ms=3, label=name)
    ax_cov.set_xlim(0, 1)
    ax_cov.set_ylim(0, 1)
    ax_cov.set_xlabel("credibility level")
    ax_cov.set_ylabel("expected coverage")
    ax_cov.legend(fontsize=8)
    fig.tight_layout()
    return fig


def pair_law(r: np.ndarray, laws: dict[str, np.ndarray], distances: np.ndarray) -> Figure:
    """A learned pair law against r (one curve per pair of types, ``laws``: label -> f on the
    grid ``r``) above the histogram of the distances it was read at (log r). A law of one sign
    over more than two decades is drawn as ``|f|`` on a log axis, else linearly."""
    from matplotlib.ticker import NullFormatter

    fig, (ax, ax_hist) = plt.subplots(2, 1, figsize=(5, 4.5), sharex=True,
                                      gridspec_kw={"height_ratios": [3, 1]})
    values = np.concatenate(list(laws.values()))
    finite = values[np.isfinite(values)]
    one_sign = finite.size > 0 and (np.all(finite > 0) or np.all(finite < 0))
    log = one_sign and np.abs(finite).max() > 100 * np.abs(finite).min()
    for label, f in laws.items():
        ax.plot(r, np.abs(f) if log else f, lw=1.5, label=label)
    if log:
        ax.set_yscale("log")
    else:
        ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xscale("log")
    ax.set_ylabel("|f(r)|" if log else "f(r)")
    ax.set_title("learned pair law")
    if len(laws) > 1:
        ax.legend(fontsize=8)
    ax_hist.hist(distances, bins=np.geomspace(r[0], r[-1], 40), color="0.5")
    ax_hist.xaxis.set_minor_formatter(NullFormatter())
    ax_hist.set_xlabel("r")
    ax_hist.set_ylabel("pairs")
    fig.tight_layout()
    return fig


def rollout(result: dict[str, np.ndarray]) -> Figure:
    """Trajectories (truth solid, prediction dashed) and position error over time."""
    true, pred = result["true"], result["predicted"]
    fig, (ax, ax_err) = plt.subplots(1, 2, figsize=(8, 3.5))
    n_show = min(true.shape[1], 8)
    for i in range(n_show):
        line, = ax.plot(true[:, i, 0], true[:, i, 1], lw=1)
        ax.plot(pred[:, i, 0], pred[:, i, 1], "--", lw=1, color=line.get_color())
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("rollout (solid: truth, dashed: model)")
    err = np.linalg.norm(pred - true, axis=-1).mean(axis=-1)
    ax_err.semilogy(np.arange(len(err)), np.maximum(err, 1e-12))
    ax_err.set_xlabel("step")
    ax_err.set_ylabel("mean position error")
    fig.tight_layout()
    return fig


def sample_efficiency(rows: Sequence[dict[str, Any]], split: str = "test") -> Figure:
    """NMSE on ``split`` (the study's scored split) against the number of training
    simulations, one line per (scene, fps, model), log-log; ``rows`` hold scene, fps, model,
    train_sims and nmse."""
    fig, ax = plt.subplots(figsize=(4.8, 3.4))
    for key in dict.fromkeys((r["scene"], r["fps"], r["model"]) for r in rows):
        pts = sorted((r["train_sims"], r["nmse"]) for r in rows
                     if (r["scene"], r["fps"], r["model"]) == key)
        ax.plot(*zip(*pts), "o-", label=f"{key[2]} ({key[0]}, fps {key[1]})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training simulations")
    ax.set_ylabel(f"{split} NMSE")
    if rows:
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def pareto(points: Sequence[dict[str, Any]], fronts: dict[str, Sequence[dict[str, Any]]],
           costs: dict[str, str], label: Callable[[dict[str, Any]], str],
           simulator: dict[float, float], title: str) -> Figure:
    """Error against each cost of ``costs`` (key in the points -> axis label), log-log, one
    panel per cost: every point labelled (``label``), its Pareto front (``fronts[cost]``)
    drawn as a step line, and the exact simulator's time per fps (``simulator``) as vertical
    lines on the panel of ``seconds_per_time_unit`` (its error is zero: off a log axis)."""
    fig, axes = plt.subplots(1, len(costs), figsize=(6.5 * len(costs), 5.2))
    markers = {"bgn": "o", "gns": "s", "cranmer_gn": "^"}
    for ax, (cost, name) in zip(np.atleast_1d(axes), costs.items()):
        shown = [p for p in points if np.isfinite(p["rollout_error"]) and p[cost] > 0]
        for model in dict.fromkeys(p["model"] for p in shown):
            pts = [p for p in shown if p["model"] == model]
            ax.scatter([p[cost] for p in pts], [p["rollout_error"] for p in pts],
                       marker=markers.get(model, "x"), label=model, alpha=0.8)
        for p in shown:
            ax.annotate(label(p), (p[cost], p["rollout_error"]), fontsize=5,
                        xytext=(2, 2), textcoords="offset points")
        front = [p for p in fronts[cost] if p[cost] > 0]
        if front:
            ax.step([p[cost] for p in front], [p["rollout_error"] for p in front], "k--",
                    where="post", lw=1, label="Pareto front")
        if cost == "seconds_per_time_unit":
            for fps, seconds in simulator.items():
                ax.axvline(seconds, color="grey", lw=1, ls=":")
                ax.annotate(f"exact simulator fps{fps:g}", (seconds, 1), fontsize=6,
                            xycoords=("data", "axes fraction"), rotation=90, va="top")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(name)
        ax.set_ylabel("rollout position error after 1 time unit")
        ax.legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=7, wrap=True)
    fig.tight_layout()
    return fig


def save(fig: Figure, path: str | Path, dpi: int = 110) -> Path:
    """Write ``fig`` as an image (folders created) and close it; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def rollout_animation(result: dict[str, np.ndarray], path: str | Path, fps: int = 20,
                      max_frames: int = 200, dpi: int = 80) -> Path:
    """An animation of a predicted against a true rollout (``bgn.rollout.rollout``'s result):
    true particles filled, predicted ones hollow in the same colour, a short trail behind
    each, the mean position error in the title. ``.gif`` (Pillow, always available) or
    ``.mp4`` (needs ffmpeg on the PATH)."""
    import logging

    from matplotlib.animation import FFMpegWriter, FuncAnimation, PillowWriter

    logging.getLogger("matplotlib.animation").setLevel(logging.WARNING)  # no line per save
    path = Path(path)
    if path.suffix not in (".gif", ".mp4"):
        raise ValueError(f"{path}: write a .gif or an .mp4")
    if path.suffix == ".mp4" and not FFMpegWriter.isAvailable():
        raise RuntimeError(f"{path}: an .mp4 needs ffmpeg on the PATH; write a .gif instead")
    true, pred = result["true"][..., :2], result["predicted"][..., :2]
    frames = np.unique(np.linspace(0, len(pred) - 1, min(max_frames, len(pred))).astype(int))
    err = np.linalg.norm(result["predicted"] - result["true"][:len(pred)], axis=-1).mean(-1)
    box = float(result["box"]) if np.isfinite(result["box"]) else None
    both = np.concatenate([true.reshape(-1, 2), pred.reshape(-1, 2)])
    lo, hi = (np.zeros(2), np.full(2, box)) if box else (both.min(0), both.max(0))
    pad = 0.05 * float(np.max(hi - lo))
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    colours = plt.cm.tab10(np.arange(true.shape[1]) % 10)
    size = 300.0 / max(true.shape[1], 10) ** 0.5
    truth = ax.scatter(true[0, :, 0], true[0, :, 1], s=size, c=colours)
    model = ax.scatter(pred[0, :, 0], pred[0, :, 1], s=size, facecolors="none",
                       edgecolors=colours, linewidths=1.2)
    trails = [ax.plot([], [], lw=0.6, color=c)[0] for c in colours[:min(len(colours), 20)]]

    def draw(i: int) -> list:
        truth.set_offsets(true[i])
        model.set_offsets(pred[i])
        for p, line in enumerate(trails):
            line.set_data(pred[max(0, i - 20):i + 1, p, 0], pred[max(0, i - 20):i + 1, p, 1])
        ax.set_title(f"step {i}: mean position error {err[i]:.3g}\n"
                     "filled: truth, hollow: model", fontsize=9)
        return [truth, model, *trails]

    animation = FuncAnimation(fig, draw, frames=frames, blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = PillowWriter(fps=fps) if path.suffix == ".gif" else FFMpegWriter(fps=fps)
    animation.save(path, writer=writer, dpi=dpi)
    plt.close(fig)
    return path


def rollout_errors(curves: dict[str, dict[str, np.ndarray]], cap: float | None = None,
                   ) -> Figure:
    """Position error against steps, one line per source (the model, the no-learning
    references, the predictability limit): the mean over all rollouts with a failed one at
    the cap (solid) and the median (dashed); ``curves[source]`` holds ``pos_err_mean`` and
    ``pos_err_median`` per step from the start (``bgn.rollout.evaluate_rollouts``)."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, c in curves.items():
        steps = np.arange(len(c["pos_err_mean"]))[1:]
        line, = ax.semilogy(steps, np.maximum(c["pos_err_mean"][1:], 1e-12), label=name)
        ax.semilogy(steps, np.maximum(c["pos_err_median"][1:], 1e-12), "--", lw=1,
                    color=line.get_color())
    if cap is not None:
        ax.axhline(cap, color="grey", lw=0.8, ls=":", label="cap (failed rollout)")
    ax.set_xlabel("step")
    ax.set_ylabel("mean position error per particle")
    ax.set_title("rollout error (solid: mean, failures at the cap; dashed: median)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def energy_drift(curves: dict[str, dict[str, np.ndarray]]) -> Figure:
    """Relative energy error ``|E_t - E_0| / |E_0|`` against steps (median over rollouts),
    one line per source, and the truth's own (its finite-difference floor)."""
    fig, ax = plt.subplots(figsize=(6, 4))
    floor = None
    for name, c in curves.items():
        steps = np.arange(len(c["energy_err"]))[1:]
        ax.semilogy(steps, np.clip(c["energy_err"][1:], 1e-16, 1e16), label=name)
        floor = c["energy_err_truth"] if floor is None else floor
    if floor is not None:
        ax.semilogy(np.arange(len(floor))[1:], np.maximum(floor[1:], 1e-16), "k:", lw=1,
                    label="truth (finite differences)")
    ax.set_xlabel("step")
    ax.set_ylabel("|E_t - E_0| / |E_0| (median)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
