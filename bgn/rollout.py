"""Rollouts of a model on a dataset's simulations, through the learned simulator, and their
scores.

The bridge between the files (``FrameDataset``) and ``bgn.simulator.LearnedSimulator``: true
windows and particles of chosen simulations in, predicted and true trajectories out;
``evaluate_rollouts`` scores them beside the no-learning references (``bgn.metrics``), and
``test_rollouts`` is the training's test phase (``bgn.training.run``) and the evaluation's
(``bgn.eval.evaluate``) common part.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import torch

from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.metrics import (
    capped_errors,
    capped_rollout_error,
    energy_errors,
    lagrangebench_metrics,
    rollout_failures,
    rollout_metrics,
    survived,
)
from bgn.model.references import REFERENCES, Extrapolation
from bgn.sim.scene import State
from bgn.simulator import LearnedSimulator, Particles, Predictor

# frame 100 of every test simulation: the reference protocol (docs/design.md#rollouts)
REFERENCE_START = 100


def simulator(model: Predictor, dataset: FrameDataset) -> LearnedSimulator:
    """The learned simulator of ``model`` at the dataset's frame spacing and graph margin."""
    if model.history != dataset.history:
        raise ValueError(f"the model reads {model.history + 1} velocities, the dataset's window "
                         f"has {dataset.history + 1}: build the dataset with history="
                         f"{model.history}")
    return LearnedSimulator(model, dataset.dt, dataset.margin)


def particles(dataset: FrameDataset, sims: list[int]) -> Particles:
    """Masses, radii and types of the dataset's simulations ``sims``, (B, N) each."""
    def read(name: str) -> torch.Tensor:
        return torch.as_tensor(np.stack([dataset.file.read(name, s) for s in sims]))

    return Particles(read("masses"), read("radii"), read("types"), torch.as_tensor(sims),
                     read("kinematic") if dataset.has_kinematic else None)


def true_positions(dataset: FrameDataset, sims: list[int], first: int, last: int) -> np.ndarray:
    """Recorded positions of frames ``first .. last`` (inclusive), (B, T, N, D) float64."""
    return np.stack([dataset.file.read("positions", (s, slice(first, last + 1))) for s in sims])


@torch.no_grad()
def rollout(model: Predictor, dataset: FrameDataset, sim: int, start: int | None = None,
            n_steps: int = 100) -> dict[str, np.ndarray]:
    """Roll ``model`` out for ``n_steps`` from frame ``start`` of simulation ``sim``.

    The first window (k+2 frames) is true; every later frame is predicted. Returns true and
    predicted positions (n_steps+1, N, D), the true and predicted energy per frame, and the
    first step with a non-finite value (-1 if none); the arrays stop before that step, so
    every array returned is finite.
    """
    k = dataset.history
    start = k + 1 if start is None else start
    n_steps = min(n_steps, dataset.file.n_frames - 1 - start)
    if n_steps < 1:
        raise ValueError(f"rollout from frame {start} needs at least one later frame")
    truth = true_positions(dataset, [sim], start - k - 1, start + n_steps)
    result = simulator(model, dataset).rollout(
        torch.as_tensor(truth[:, :k + 2]), particles(dataset, [sim]), n_steps, start,
        driven=torch.as_tensor(truth[:, k + 2:]),
        context=recorded_context(model, dataset, [sim], start))
    first_bad = int(result.first_non_finite[0])
    predicted = result.positions[0].cpu().numpy()
    if first_bad >= 0:
        predicted = predicted[:first_bad]
    true = truth[0, k + 1:k + 1 + len(predicted)]
    masses = dataset.file.read("masses", sim)

    def energy(x: np.ndarray) -> np.ndarray:
        v = np.diff(x, axis=0) / dataset.dt
        return dataset.scene.energy(x[1:], v, masses)

    return {"true": true, "predicted": predicted, "dt": np.array(dataset.dt),
            "energy_true": energy(true), "energy_predicted": energy(predicted),
            "first_non_finite": np.array(first_bad),
            "box": np.array(np.nan if dataset.meta.box is None else dataset.meta.box)}


def recorded_context(model: Predictor, dataset: FrameDataset, sims: list[int], start: int,
                     ) -> torch.Tensor | None:
    """(B, C, N, D) the recorded frames 0 .. ``start`` of ``sims``: the context a held fit
    reads (``LearnedSimulator.rollout``) for a model whose fit reads the frames before the
    start (``held_fit_windows`` > 1); None for the others, and where those frames are only the
    window."""
    if int(getattr(model, "held_fit_windows", 1)) <= 1 or start + 1 <= dataset.history + 2:
        return None
    return torch.as_tensor(true_positions(dataset, sims, 0, start))


def rollout_starts(dataset: FrameDataset, n_steps: int, per_sim: int = 1) -> list[int]:
    """Start frames shared by every simulation: frame 100 first (the reference protocol)
    when the file is long enough, then evenly spaced frames that leave ``n_steps`` after them.
    """
    first, last = dataset.history + 1, dataset.file.n_frames - 1 - n_steps
    if last < first:
        raise ValueError(f"{dataset.file.path}: {dataset.file.n_frames} frames leave no start "
                         f"for {n_steps}-step rollouts with history {dataset.history}")
    starts = [REFERENCE_START] if first <= REFERENCE_START <= last else []
    spread = [first + i for i in evenly_spaced(last - first + 1, per_sim)]
    return sorted((starts + [t for t in spread if t not in starts])[:per_sim])


def scoring_starts(dataset: FrameDataset, n_steps: int, n_sims: int,
                   min_rollouts: int) -> list[int]:
    """The start frames of a validation score (``model.dynamics=auto``'s and the formula
    stage's): as many per simulation (``rollout_starts``, frame 100 among them) as ``n_sims``
    simulations need to give at least ``min_rollouts`` rollouts, fewer where the files are
    short. One start on a split of 10 simulations lets a single close encounter decide a
    mean, and a law that fails only at encounters the 10 miss is never seen failing
    (docs/design.md, "Choosing on validation rollouts")."""
    return rollout_starts(dataset, n_steps, max(1, -(-min_rollouts // max(1, n_sims))))


@dataclass
class Trajectories:
    """Rollouts of one predictor from several (simulation, start) pairs, all ``n_steps`` long.
    ``predicted``/``true`` (R, n_steps + 2, N, D) hold the frame before the start, the start
    and the steps (NaN from a failed step on); ``first_non_finite`` (R,); masses and types
    (R, N); ``seconds_per_step``: wall time of one step of one rollout."""

    predicted: np.ndarray
    true: np.ndarray
    first_non_finite: np.ndarray
    masses: np.ndarray
    types: np.ndarray
    radii: np.ndarray
    seconds_per_step: float


@torch.no_grad()
def rollout_many(model: Predictor, dataset: FrameDataset, sims: list[int], starts: list[int],
                 n_steps: int, chunk: int | None = None,
                 between: Callable[[], None] | None = None) -> Trajectories:
    """Every simulation in ``sims`` rolled out from every frame in ``starts`` (batched over
    the simulations of one start; with ``chunk``, in batches of whole simulations of at most
    ``chunk`` particles, at least one simulation each). ``between``: called before each
    batch (a caller's deadline or signal check: one batch of a large scene can take minutes)."""
    k, sim_ = dataset.history, simulator(model, dataset)
    parts = particles(dataset, sims)
    size = len(sims) if chunk is None else max(1, chunk // max(1, parts.masses.shape[1]))
    groups = [list(range(i, min(i + size, len(sims)))) for i in range(0, len(sims), size)]
    batches = [[sims[i] for i in group] for group in groups]
    # the particles read once for every batch and start: each batch's rows of ``parts``
    group_parts = [parts if len(g) == len(sims) else parts.select(torch.as_tensor(g))
                   for g in groups]
    predicted, true, bad, seconds = [], [], [], []
    for start in starts:
        for batch, part in zip(batches, group_parts):
            if between is not None:
                between()
            truth = true_positions(dataset, batch, start - k - 1, start + n_steps)
            result = sim_.rollout(torch.as_tensor(truth[:, :k + 2]), part, n_steps, start,
                                  driven=torch.as_tensor(truth[:, k + 2:]),
                                  context=recorded_context(model, dataset, batch, start))
            predicted.append(np.concatenate([truth[:, k:k + 1],
                                             result.positions.cpu().numpy()], 1))
            true.append(truth[:, k:])
            bad.append(result.first_non_finite.numpy())
            seconds.append(result.seconds_per_step / len(batch))
    reps = len(starts)
    return Trajectories(np.concatenate(predicted), np.concatenate(true), np.concatenate(bad),
                        np.tile(parts.masses.numpy(), (reps, 1)),
                        np.tile(parts.types.numpy(), (reps, 1)),
                        np.tile(parts.radii.numpy(), (reps, 1)), float(np.median(seconds)))


def predictability(dataset: FrameDataset, sims: list[int], starts: list[int], n_steps: int,
                   eps: float = 1e-6, seed: int = 0) -> Trajectories:
    """The scene's predictability limit on the rollouts' protocol (docs/design.md#rollouts): the
    exact simulator run twice from the recorded state one frame before each start, once as recorded
    and once with every position moved by ``eps`` in a random direction. ``true`` is the
    first, ``predicted`` the second: their distance is what chaos alone does to an error of
    ``eps``; a model's rollout error above it is the model's."""
    rng = np.random.default_rng(seed)
    times = np.arange(n_steps + 2) * dataset.dt
    predicted, true = [], []
    for start in starts:
        for sim in sims:
            frame = (sim, start - 1)
            state = State(dataset.file.read("positions", frame),
                          dataset.file.read("velocities", frame),
                          dataset.file.read("masses", sim), dataset.file.read("radii", sim),
                          dataset.file.read("types", sim))
            kick = rng.standard_normal(state.positions.shape)
            kick *= eps / np.linalg.norm(kick, axis=-1, keepdims=True)
            moved = replace(state, positions=state.positions + kick)
            true.append(dataset.scene.simulate_from(state, times).positions)
            predicted.append(dataset.scene.simulate_from(moved, times).positions)
    parts = particles(dataset, sims)
    reps = len(starts)
    return Trajectories(np.stack(predicted), np.stack(true), np.full(len(true), -1),
                        np.tile(parts.masses.numpy(), (reps, 1)),
                        np.tile(parts.types.numpy(), (reps, 1)),
                        np.tile(parts.radii.numpy(), (reps, 1)), float("nan"))


def rollout_error(model: Predictor, dataset: FrameDataset, n_sims: int = 2,
                  n_steps: int = 50) -> float:
    """A cheap rollout score for training (``val/rollout_error``): ``n_steps`` from one fixed
    start in ``n_sims`` evenly spaced simulations of ``dataset``, scored by
    ``bgn.metrics.capped_rollout_error``."""
    n_steps = min(n_steps, dataset.file.n_frames - dataset.history - 2)
    t = rollout_many(model, dataset, evenly_spaced(dataset.file.n_sims, n_sims),
                     rollout_starts(dataset, n_steps), n_steps)
    return capped_rollout_error(t.predicted, t.true, dataset.meta.box)


def position_error(result: dict[str, np.ndarray], horizons: tuple[int, ...] = (10, 100, 1000),
                   ) -> dict[int, float]:
    """Mean position error after each horizon that the rollout reaches."""
    err = np.linalg.norm(result["predicted"] - result["true"], axis=-1).mean(axis=-1)
    return {h: float(err[h]) for h in horizons if h < len(err)}


# ----------------------------------------------------------------------------- scores
def scene_period(dataset: FrameDataset) -> np.ndarray | None:
    """(D,) the side of the source's periodic box along each periodic dimension, inf along
    the others; None where nothing is periodic (imported data record it: ``ImportedScene``)."""
    periodic = getattr(dataset.scene, "periodic", ()) or ()
    bounds = getattr(dataset.scene, "bounds", ()) or ()
    if not any(periodic) or len(bounds) != len(periodic):
        return None
    return np.array([hi - lo if p else np.inf for p, (lo, hi) in zip(periodic, bounds)])


def discs(dataset: FrameDataset, radii: np.ndarray) -> bool:
    """Whether rollouts get the discs' contact metrics (``contact_rollout_metrics``): a
    contact scene, or imported particles whose radii are given (``radii_by_type``)."""
    return dataset.meta.interaction == "contact" or bool(radii.size and np.all(radii > 0))


def lb_prefix(key: str) -> str:
    """The key prefix of a rollout source's LagrangeBench metrics: ``lb`` for the model,
    ``lb_last``, ``lb_linear``, ``lb_predictability`` for the references."""
    return "lb" if key == "rollout" else "lb_" + key.removeprefix("rollout_")


def evaluate_rollouts(model: Predictor, dataset: FrameDataset, n_steps: int = 100,
                      starts_per_sim: int = 1, max_sims: int | None = None,
                      references: bool = True, predictability_limit: bool = True,
                      curves: dict[str, dict[str, np.ndarray]] | None = None,
                      step: Callable[[str], None] | None = None,
                      lagrangebench: bool = False, sinkhorn_stride: int = 10,
                      sinkhorn_rollouts: int | None = 4,
                      positions: dict[str, np.ndarray] | None = None) -> dict[str, float]:
    """Rollout metrics (``bgn.metrics.rollout_metrics``) of ``model`` from the same start
    frames of every test simulation (frame 100 first), keyed ``rollout/<metric>``, and of the
    no-learning references beside it (``rollout_last/...``, ``rollout_linear/...``) and, with
    ``predictability_limit``, the scene's predictability limit (``predictability/...``: the
    exact simulator from positions 1e-6 off, ``bgn.rollout.predictability``). Steps are capped
    by the file's length. Momentum is scored where the scene conserves it (no walls).
    ``curves``, when given, receives per source the per-step curves behind the figures
    (``pos_err_mean``, ``pos_err_median``, ``energy_err``, ``energy_err_truth``); ``step(name)``
    is called before each source is rolled out (a progress bar). ``lagrangebench``: the
    same rollouts in LagrangeBench's metrics as well (``bgn.metrics.lagrangebench_metrics``,
    keyed ``lb/<metric>`` for the model, ``lb_last/...`` etc. for the references), the
    Sinkhorn divergence on every ``sinkhorn_stride``-th step of ``sinkhorn_rollouts`` evenly
    spaced rollouts (None: all). ``positions``, when given, receives the model's rollouts:
    ``predicted`` and ``true`` (R, n_steps + 2, N, D), ``sims`` and ``starts`` (R,), so that
    quantities bgn cannot compute (an engine's own energy) can be measured on them."""
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
    # the true simulator 1e-6 off: the chaos floor (imported data have no simulator to rerun)
    if references and predictability_limit and getattr(dataset.scene, "has_simulator", True):
        runs["predictability"] = partial(predictability, dataset, sims, starts, n_steps)
    metrics: dict[str, float] = {}
    for key, run in runs.items():
        if step is not None:
            step(f"rollouts: {key}")
        t = run()
        if positions is not None and key == "rollout":
            positions.update(predicted=t.predicted, true=t.true,
                             sims=np.tile(np.asarray(sims), len(starts)),
                             starts=np.repeat(np.asarray(starts), len(sims)))
        values = rollout_metrics(t.predicted, t.true, t.masses, dataset.dt, dataset.scene.energy,
                                 t.first_non_finite, dataset.meta.box,
                                 momentum=dataset.meta.box is None,
                                 contacts=((t.radii, t.types)
                                           if discs(dataset, t.radii) else None))
        values["seconds_per_step"] = t.seconds_per_step
        metrics.update({f"{key}/{name}": value for name, value in values.items()})
        failed_at = rollout_failures(t.predicted, t.true, dataset.meta.box, t.first_non_finite)
        if lagrangebench:
            lb = lagrangebench_metrics(t.predicted, t.true, t.masses, dataset.dt, failed_at,
                                       dataset.meta.box, scene_period(dataset),
                                       sinkhorn_stride=sinkhorn_stride,
                                       sinkhorn_rollouts=sinkhorn_rollouts)
            metrics.update({f"{lb_prefix(key)}/{name}": value for name, value in lb.items()})
        if curves is not None:
            err, _, _ = capped_errors(t.predicted, t.true, dataset.meta.box, failed_at)
            e_err, e_floor = energy_errors(t.predicted, t.true, t.masses, dataset.dt,
                                           dataset.scene.energy)
            alive = survived(failed_at, err.shape[1])
            curves[key] = {"pos_err_mean": err.mean(axis=0),
                           "pos_err_median": np.median(err, axis=0),
                           "energy_err": np.median(np.where(alive, e_err, np.inf), axis=0),
                           "energy_err_truth": np.median(e_floor, axis=0)}
    return metrics


# the test phase's rollout figures (bgn.train), short keys: reference source -> suffix
SUMMARY_HORIZONS = (10, 50, 100)
SUMMARY_SOURCES = {"rollout_last": "last", "rollout_linear": "linear",
                   "predictability": "predictability"}


def rollout_summary(metrics: dict[str, float], prefix: str = "test/") -> dict[str, float]:
    """The headline rollout figures of ``evaluate_rollouts``' metrics under short keys:
    ``<prefix>rollout_error@h`` (mean over all rollouts, a failed one at the cap) at the
    horizons reached of 10, 50 and 100 steps; at the longest of them H the median beside it
    (``rollout_error_median@H``), the MSE over all rollouts (``rollout_mse@H``), the energy
    error (``energy_error@H``), each reference's ``rollout_error@H_<reference>``; and
    ``rollout_failed_share``."""
    reached = [h for h in SUMMARY_HORIZONS if f"rollout/pos_err_mean@{h}" in metrics]
    out = {f"{prefix}rollout_failed_share": metrics["rollout/failed_share"]}
    for h in reached:
        out[f"{prefix}rollout_error@{h}"] = metrics[f"rollout/pos_err_mean@{h}"]
    if reached:
        h = reached[-1]
        out[f"{prefix}rollout_error_median@{h}"] = metrics[f"rollout/pos_err_median@{h}"]
        out[f"{prefix}rollout_mse@{h}"] = metrics[f"rollout/pos_mse_mean@{h}"]
        out[f"{prefix}energy_error@{h}"] = metrics[f"rollout/energy_err@{h}"]
        for source, name in SUMMARY_SOURCES.items():
            if f"{source}/pos_err_mean@{h}" in metrics:
                out[f"{prefix}rollout_error@{h}_{name}"] = metrics[f"{source}/pos_err_mean@{h}"]
    return out


@torch.no_grad()
def test_rollouts(model: Predictor, dataset: FrameDataset, n_steps: int = 100,
                  predictability_limit: bool = False) -> dict[str, float]:
    """``bgn.train``'s test phase: ``evaluate_rollouts`` of ``model`` and the no-learning
    references on every simulation of ``dataset`` (batched), as ``rollout_summary``'s
    ``test/...`` keys. The predictability limit is off by default: it runs the exact simulator
    twice per simulation, one at a time, far slower than the batched rollouts (``python -m
    bgn.eval.evaluate`` reports it). The model is rolled out in eval mode and left in the mode it
    was in."""
    training = getattr(model, "training", False)
    if isinstance(model, torch.nn.Module):
        model.eval()
    try:
        metrics = evaluate_rollouts(model, dataset, n_steps,
                                    predictability_limit=predictability_limit)
    finally:
        if isinstance(model, torch.nn.Module):
            model.train(training)
    return rollout_summary(metrics)
