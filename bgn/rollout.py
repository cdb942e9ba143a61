"""Rollouts of a model on a dataset's simulations, through the learned simulator.

The bridge between the files (``FrameDataset``) and ``bgn.simulator.LearnedSimulator``: true
windows and particles of chosen simulations in, predicted and true trajectories out.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from bgn.data.dataset import FrameDataset
from bgn.data.frames import evenly_spaced
from bgn.metrics import capped_rollout_error
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
    result = simulator(model, dataset).rollout(torch.as_tensor(truth[:, :k + 2]),
                                               particles(dataset, [sim]), n_steps, start,
                                               driven=torch.as_tensor(truth[:, k + 2:]))
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
                 n_steps: int) -> Trajectories:
    """Every simulation in ``sims`` rolled out from every frame in ``starts`` (batched over
    the simulations of one start)."""
    k, sim_ = dataset.history, simulator(model, dataset)
    parts = particles(dataset, sims)
    predicted, true, bad, seconds = [], [], [], []
    for start in starts:
        truth = true_positions(dataset, sims, start - k - 1, start + n_steps)
        result = sim_.rollout(torch.as_tensor(truth[:, :k + 2]), parts, n_steps, start,
                              driven=torch.as_tensor(truth[:, k + 2:]))
        predicted.append(np.concatenate([truth[:, k:k + 1], result.positions.cpu().numpy()], 1))
        true.append(truth[:, k:])
        bad.append(result.first_non_finite.numpy())
        seconds.append(result.seconds_per_step / len(sims))
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
