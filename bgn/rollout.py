"""Rollouts of a model on a dataset's simulations, through the learned simulator.

The bridge between the files (``FrameDataset``) and ``bgn.simulator.LearnedSimulator``: true
windows and particles of chosen simulations in, predicted and true trajectories out.
"""

from __future__ import annotations

import numpy as np
import torch

from bgn.data.dataset import FrameDataset
from bgn.model.base import PhysicsModel
from bgn.simulator import LearnedSimulator, Particles


def simulator(model: PhysicsModel, dataset: FrameDataset) -> LearnedSimulator:
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

    return Particles(read("masses"), read("radii"), read("types"), torch.as_tensor(sims))


def true_positions(dataset: FrameDataset, sims: list[int], first: int, last: int) -> np.ndarray:
    """Recorded positions of frames ``first .. last`` (inclusive), (B, T, N, D) float64."""
    return np.stack([dataset.file.read("positions", (s, slice(first, last + 1))) for s in sims])


@torch.no_grad()
def rollout(model: PhysicsModel, dataset: FrameDataset, sim: int, start: int | None = None,
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
                                               particles(dataset, [sim]), n_steps, start)
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


def position_error(result: dict[str, np.ndarray], horizons: tuple[int, ...] = (10, 100, 1000),
                   ) -> dict[int, float]:
    """Mean position error after each horizon that the rollout reaches."""
    err = np.linalg.norm(result["predicted"] - result["true"], axis=-1).mean(axis=-1)
    return {h: float(err[h]) for h in horizons if h < len(err)}
