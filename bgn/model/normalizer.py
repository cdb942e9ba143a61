"""Normalisation of inputs and targets from the training-split statistics (``bgn.data.stats``).

Statistics are held as buffers, so a checkpoint carries them and ``model.double()`` / ``.to()``
move them with the weights.

Choices (docs/design.md#frames-and-targets: targets of force scenes are heavy-tailed):

- Kinematic quantities (velocity, target, relative position/velocity, force magnitude) use a
  robust scale (1.4826 x MAD), falling back to the standard deviation where it is zero (e.g.
  more than half the values equal), then to 1. Centres are medians. A few extreme frames then
  do not shrink every ordinary value towards zero, which a standard deviation would.
- Vectors get one isotropic scale (mean of the per-component scales): directions are kept,
  which matters for relative positions (force directions), and an MSE in normalised units stays
  proportional to the physical MSE.
- Relative quantities on edges are only scaled, never centred, so ``x_i - x_j`` stays
  antisymmetric; positions enter only as differences (translation invariance).
- Log-masses are not heavy-tailed: mean and standard deviation (what a flow with a standard
  normal base prefers). Relative log-masses ``log m_i - log m_j`` are only scaled.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import nn

STAT_NAMES = ("velocity", "target", "log_mass", "rel_position", "rel_velocity", "contact",
              "rel_log_mass")
TINY = 1e-12  # a scale at or below this is treated as zero


def _column(stats: Mapping[str, Any], name: str, key: str) -> np.ndarray:
    try:
        entry = stats[name]
    except KeyError:
        raise KeyError(f"statistics have no entry {name!r}; expected {STAT_NAMES}") from None
    try:
        return np.atleast_1d(np.asarray(entry[key], dtype=np.float64))
    except KeyError:
        raise KeyError(f"statistics {name!r} have no key {key!r}") from None


def robust_scale(stats: Mapping[str, Any], name: str) -> np.ndarray:
    """Per-column scale: robust_scale, else std where that is zero, else 1."""
    robust = _column(stats, name, "robust_scale")
    std = _column(stats, name, "std")
    scale = np.where(robust > TINY, robust, std)
    return np.where(np.isfinite(scale) & (scale > TINY), scale, 1.0)


def std_scale(stats: Mapping[str, Any], name: str) -> np.ndarray:
    """Per-column standard deviation, else 1 where it is zero."""
    std = _column(stats, name, "std")
    return np.where(np.isfinite(std) & (std > TINY), std, 1.0)


class Normalizer(nn.Module):
    """Maps physical quantities to the model's units and the target back.

    ``stats[name][key]`` are numpy arrays for the names in ``STAT_NAMES`` and the keys
    ``mean``, ``std``, ``median``, ``robust_scale``.
    """

    def __init__(self, stats: Mapping[str, Any], dim: int) -> None:
        super().__init__()
        self.dim = dim

        def buf(name: str, value: np.ndarray) -> None:
            value = np.array(value, dtype=np.float64)  # a writable copy
            self.register_buffer(name, torch.tensor(value, dtype=torch.float32))

        buf("velocity_center", np.broadcast_to(_column(stats, "velocity", "median"), (dim,)))
        buf("velocity_scale", robust_scale(stats, "velocity").mean())
        buf("target_center", np.broadcast_to(_column(stats, "target", "median"), (dim,)))
        buf("target_scale", robust_scale(stats, "target").mean())
        # older statistics lack increments: fall back to the velocity scale
        buf("increment_scale", robust_scale(stats, "velocity_increment").mean()
            if "velocity_increment" in stats else robust_scale(stats, "velocity").mean())
        buf("rel_position_scale", robust_scale(stats, "rel_position").mean())
        buf("rel_velocity_scale", robust_scale(stats, "rel_velocity").mean())
        buf("contact_scale", robust_scale(stats, "contact").mean())
        buf("log_mass_center", _column(stats, "log_mass", "mean").mean())
        buf("log_mass_scale", std_scale(stats, "log_mass").mean())
        buf("rel_log_mass_scale", std_scale(stats, "rel_log_mass").mean())

    # Node inputs and targets.
    def velocity(self, v: torch.Tensor) -> torch.Tensor:
        """(..., D) velocities -> normalised."""
        return (v - self.velocity_center) / self.velocity_scale

    def velocity_increment(self, dv: torch.Tensor) -> torch.Tensor:
        """v[t] - v[t-1] in units of its own scale: the window's finite-difference
        accelerations, well conditioned (differences of normalised velocities are tiny at
        high fps)."""
        return dv / self.increment_scale

    def target(self, y: torch.Tensor) -> torch.Tensor:
        """(N, D) physical target -> normalised."""
        return (y - self.target_center) / self.target_scale

    def denormalize_target(self, y: torch.Tensor) -> torch.Tensor:
        """(N, D) normalised target -> physical."""
        return y * self.target_scale + self.target_center

    # Edge inputs and targets (scaled only: antisymmetry and zero are kept).
    def rel_position(self, d: torch.Tensor) -> torch.Tensor:
        return d / self.rel_position_scale

    def rel_velocity(self, d: torch.Tensor) -> torch.Tensor:
        return d / self.rel_velocity_scale

    def contact(self, c: torch.Tensor) -> torch.Tensor:
        """Pairwise force magnitude -> units of its robust scale (contact scenes: unused)."""
        return c / self.contact_scale

    def rel_log_mass(self, r: torch.Tensor) -> torch.Tensor:
        return r / self.rel_log_mass_scale

    def denormalize_rel_log_mass(self, r: torch.Tensor) -> torch.Tensor:
        return r * self.rel_log_mass_scale

    # Inverse model.
    def log_mass(self, log_m: torch.Tensor) -> torch.Tensor:
        return (log_m - self.log_mass_center) / self.log_mass_scale

    def denormalize_log_mass(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.log_mass_scale + self.log_mass_center
