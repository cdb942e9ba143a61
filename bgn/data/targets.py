"""Finite-difference inputs and targets, and the step that turns a target back into a frame.

docs/design.md#frames-and-targets: the input velocities are backward differences ``v[t] = (x[t] -
x[t-1]) / dt`` and the targets are defined so that a rollout reproduces the recorded frames:

- velocity scenes (collisions): target ``v[t+1] = (x[t+1] - x[t]) / dt``;
- acceleration scenes (forces): target ``a[t] = (v[t+1] - v[t]) / dt``.

``step`` inverts both, so ``step(x[t], v[t], target[t])`` gives ``x[t+1]`` up to round-off.
"""

from __future__ import annotations

import numpy as np

from bgn.sim.scene import TargetKind


def backward_velocities(positions: np.ndarray, dt: float) -> np.ndarray:
    """(T, ...) positions -> (T-1, ...) velocities; entry j is the input velocity of frame j+1."""
    return np.diff(positions, axis=0) / dt


def targets(positions: np.ndarray, dt: float, kind: TargetKind) -> np.ndarray:
    """Targets of frames 1 .. T-2 from (T, ...) positions: entry j belongs to frame j+1."""
    v = backward_velocities(positions, dt)
    if kind == "velocity":
        return v[1:]
    if kind == "acceleration":
        return np.diff(v, axis=0) / dt
    raise ValueError(f"unknown target kind {kind!r}")


def step(position, velocity, target, dt: float, kind: TargetKind):
    """One rollout step (numpy or torch): frame t -> (x[t+1], v[t+1]) from a target.

    Semi-implicit Euler for accelerations, which is exactly the inverse of the finite
    differences above.
    """
    if kind == "velocity":
        new_velocity = target
    elif kind == "acceleration":
        new_velocity = velocity + dt * target
    else:
        raise ValueError(f"unknown target kind {kind!r}")
    return position + dt * new_velocity, new_velocity
