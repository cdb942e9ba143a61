"""A pair law tabulated in log distance and fitted by least squares: the piecewise-linear
basis, the normal equations of a fit accumulated over batches, and the fit whose smoothness
is chosen on a check set. Force matching (``bgn.model.force_matching``) fits the pair-force
head's initial law with them; the velocity test (``bgn.data.balance``) fits laws of the
distance, with and without the relative speed, to a dataset's frames."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

# smoothness penalties tried (second differences of the table), relative to the mean
# diagonal of the normal matrix
SMOOTHING = tuple(10.0**-k for k in range(10, -1, -1))
# a law's size near a zero crossing: its change over this fraction of r (``law_size``)
ZERO_CROSSING_WIDTH = 0.1


def law_size(values: np.ndarray, log_r: np.ndarray, width: float = ZERO_CROSSING_WIDTH,
             ) -> np.ndarray:
    """The size a law's relative errors are taken against, at each of the sorted ``log_r``
    (the last axis of ``values``): ``sqrt(f^2 + (width r f')^2)``, within a few % of |f| for a
    power law, and finite where f crosses zero (a spring's law at its rest length, where an
    error relative to |f| is undefined)."""
    slope = np.gradient(values, log_r, axis=-1)
    return np.sqrt(values * values + (width * slope) ** 2)


@dataclass
class NormalEquations:
    """``gram = X^T X``, ``moment = X^T y`` and ``total = y^T y`` of a least-squares problem
    ``X c = y`` (float64), accumulated over batches; ``rows`` counts the rows."""

    gram: torch.Tensor
    moment: torch.Tensor
    total: torch.Tensor
    rows: int

    def __add__(self, other: NormalEquations) -> NormalEquations:
        return NormalEquations(self.gram + other.gram, self.moment + other.moment,
                               self.total + other.total, self.rows + other.rows)

    def relative_error(self, coef: torch.Tensor) -> float:
        """``|X c - y|^2 / |y|^2`` of the coefficients ``coef``."""
        sq = coef @ self.gram @ coef - 2 * self.moment @ coef + self.total
        return float(sq.clamp_min(0) / self.total.clamp_min(torch.finfo(sq.dtype).tiny))


def log_knots(lo: float, hi: float, k: int) -> torch.Tensor:
    """(k,) log distances evenly spaced from ``log lo`` to ``log hi`` (float64)."""
    return torch.linspace(math.log(lo), math.log(hi), k, dtype=torch.float64)


def hat_basis(log_dist: torch.Tensor, knots: torch.Tensor) -> torch.Tensor:
    """(..., K) the piecewise-linear basis at ``log_dist`` (...): each value shared between its
    two neighbouring knots; outside the knots, the end segments extended."""
    step = knots[1] - knots[0]
    x = (log_dist - knots[0]) / step
    i = x.floor().clamp(0, len(knots) - 2)
    w = (x - i)[..., None]
    idx = i.long()[..., None]
    basis = log_dist.new_zeros(*log_dist.shape, len(knots))
    return basis.scatter_add(-1, idx, 1 - w).scatter_add(-1, idx + 1, w)


def fit_table(fit: NormalEquations, check: NormalEquations, n_pairs: int,
              ) -> tuple[torch.Tensor, float]:
    """The table's values (pairs x knots) of least squares on ``fit`` with a penalty on their
    second differences, its weight (``SMOOTHING``) the best on ``check``."""
    k = fit.gram.shape[0] // n_pairs
    second = torch.diff(torch.eye(k, dtype=fit.gram.dtype), n=2, dim=0)
    penalty = torch.block_diag(*[second.T @ second] * n_pairs)
    # pairs of types never seen give zero rows: a small ridge keeps the system regular
    scale = float(fit.gram.diagonal().mean())
    ridge = 1e-12 * scale * torch.eye(len(penalty), dtype=penalty.dtype)
    best = None
    for weight in SMOOTHING:
        coef = torch.linalg.solve(fit.gram + weight * scale * penalty + ridge, fit.moment)
        error = check.relative_error(coef)
        if best is None or error < best[0]:
            best = (error, weight, coef)
    assert best is not None
    return best[2].view(n_pairs, k), best[1]
