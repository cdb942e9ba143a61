"""Rollouts: feed a model its own predictions, frame after frame, and compare with the truth."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from bgn.data.dataset import FrameDataset
from bgn.data.targets import step


@torch.no_grad()
def rollout(model: nn.Module, dataset: FrameDataset, sim: int, start: int | None = None,
            n_steps: int = 100) -> dict[str, np.ndarray]:
    """Roll ``model`` out for ``n_steps`` from frame ``start`` of simulation ``sim``.

    The first window (k+2 frames) is true; every later frame is predicted. Returns true and
    predicted positions (n_steps+1, N, D), the true and predicted energy per frame, and the
    first step with a non-finite value (-1 if none); a rollout stops before that step, so
    every array it returns is finite.
    """
    k = dataset.history
    start = k + 1 if start is None else start
    last = dataset.file.n_frames - 1
    n_steps = min(n_steps, last - start)
    if n_steps < 1:
        raise ValueError(f"rollout from frame {start} needs at least one later frame")
    device = next(model.parameters()).device
    truth = dataset.file.read("positions", (sim, slice(start - k - 1, start + n_steps + 1)))
    window = truth[: k + 2].copy()
    predicted = [window[-1]]
    first_bad = -1
    kind = dataset.meta.target
    for i in range(n_steps):
        g = dataset.graph(window, sim, start + i).to(device)
        target = model.predict(g).double().cpu().numpy()
        velocity = (window[-1] - window[-2]) / dataset.dt
        position, _ = step(window[-1], velocity, target, dataset.dt, kind)
        if not np.isfinite(position).all():
            first_bad = i + 1  # stop here: nothing after a non-finite frame means anything
            break
        window = np.concatenate([window[1:], position[None]])
        predicted.append(position)
    predicted = np.stack(predicted)
    true = truth[k + 1:k + 1 + len(predicted)]
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
