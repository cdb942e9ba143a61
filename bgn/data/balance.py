"""What a dataset's motion conserves, read from its positions alone: the evidence that a
structure writing in equal and opposite central pair forces can express the data at all.

Central pair forces ``F_ij = f(s_ij) u_ij = -F_ji``, however the masses enter (the pair-force
head's ``mass_law`` inertial or source), leave the total momentum unchanged, ``sum_i m_i a_i =
0`` at every instant, and, being central, the total angular momentum too, ``sum_i m_i x_i x
a_i = 0``. A field (gravity), walls, drag or friction break the first; forces across the line
between two particles (friction's tangential part) break the second. Both hold exactly for
the frames' second differences as well (``x_{t+1} - 2 x_t + x_{t-1}`` of a momentum-conserving
system sums to zero with the masses' weights, whatever the frame rate), so the test needs no
model and no law.

The masses are unknown: per simulation, the non-negative weights ``w`` (sum 1) that balance
the particles' normalised acceleration columns best, ``min ||A w||^2 / ||w||^2`` (each column
one particle's second differences over the frames, scaled to unit length, so that no particle
balances the others by accelerating little). 0: balanced by some positive masses; near 1: no
mixture of the particles cancels. docs/design.md#choosing-a-structure says how ``auto`` uses it.

    python -m bgn.data.balance data/imported/<name>/train.h5 [...]   # a markdown table
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

# Imbalance above which the data do not conserve momentum (or angular momentum): orders of
# magnitude above the float32 rounding of balanced frames, orders below the imbalance of a
# field or of walls (docs/results.md#what-the-data-conserve-momentum-balance).
IMBALANCE_MAX = 1e-3
SIMS = 8            # simulations of the split read (evenly spaced)
FRAMES = 256        # frames of each simulation read (evenly spaced, consecutive triples)


@dataclass(frozen=True)
class Balance:
    """The median imbalance over the simulations read: ``linear`` (momentum) and
    ``angular`` (momentum and angular momentum with the same weights; None where a dimension
    is periodic or the data are 1-D, where it is not defined). ``None`` for ``linear`` too
    where the test does not apply (``reason``)."""

    linear: float | None
    angular: float | None
    sims: int
    frames: int
    reason: str = ""

    def breaks(self) -> str:
        """Why central pair forces cannot make these data ("" when they can, or untested)."""
        if self.linear is not None and self.linear > IMBALANCE_MAX:
            return (f"the data's total momentum changes (imbalance {self.linear:.2g} > "
                    f"{IMBALANCE_MAX:g}): forces without an equal and opposite partner act "
                    "(a field, walls, drag or friction)")
        if self.angular is not None and self.angular > IMBALANCE_MAX:
            return (f"the data's angular momentum changes (imbalance {self.angular:.2g} > "
                    f"{IMBALANCE_MAX:g}): pair forces across the line between the particles act")
        return ""


def imbalance(columns: np.ndarray) -> float:
    """``min ||A w||^2 / ||w||^2`` over ``w >= 0`` with ``sum w = 1``, the columns of ``A``
    (rows, N) scaled to unit length (a zero column is left out: it balances nothing)."""
    from scipy.optimize import lsq_linear

    norms = np.linalg.norm(columns, axis=0)
    keep = norms > 0
    if keep.sum() < 2:
        return 1.0 if keep.any() else 0.0
    a = columns[:, keep] / norms[keep]
    n = a.shape[1]
    weight = 1e3 * np.sqrt(a.shape[0])             # the sum-to-one row, held tightly
    system = np.vstack([a, np.full((1, n), weight)])
    target = np.zeros(len(system))
    target[-1] = weight
    w = lsq_linear(system, target, bounds=(0.0, np.inf), method="bvls").x
    return float(np.sum((a @ w) ** 2) / max(np.sum(w**2), 1e-300))


def _cross(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``x x a`` per particle: (..., 1) in 2-D, (..., 3) in 3-D."""
    if x.shape[-1] == 2:
        return (x[..., 0] * a[..., 1] - x[..., 1] * a[..., 0])[..., None]
    return np.cross(x, a)


def simulation_columns(positions: np.ndarray, angular: bool) -> np.ndarray:
    """(T, N, D) positions (unwrapped) -> the (rows, N) matrix of each particle's second
    differences at the inner frames, with the angular rows ``x_t x (second difference)``
    beneath when ``angular`` (positions relative to the simulation's mean, in its spread's
    units, so the two kinds of rows weigh alike)."""
    x = np.asarray(positions, dtype=np.float64)
    acc = x[2:] - 2.0 * x[1:-1] + x[:-2]                               # (T-2, N, D)
    rows = [acc.transpose(0, 2, 1).reshape(-1, x.shape[1])]
    if angular:
        centred = x[1:-1] - x.mean(axis=(0, 1))
        spread = max(float(np.sqrt(np.mean(centred**2))), 1e-300)
        torque = _cross(centred / spread, acc)                          # (T-2, N, 1 or 3)
        rows.append(torque.transpose(0, 2, 1).reshape(-1, x.shape[1]))
    return np.vstack(rows)


def momentum_balance(file: Any, meta: Any, sims: int = SIMS, frames: int = FRAMES) -> Balance:
    """The imbalance of ``file`` (a ``bgn.data.files.DatasetFile``, positions unwrapped) with
    the scene record ``meta``: ``sims`` evenly spaced simulations, each read at ``frames``
    consecutive frames from its middle (consecutive: the second differences need them)."""
    from bgn.data.frames import evenly_spaced

    if "kinematic" in file.handle and np.asarray(file.read("kinematic", ...)).any():
        return Balance(None, None, 0, 0, "particles moved by the source push the others "
                       "without being pushed back in the files")
    if file.n_frames < 3:
        return Balance(None, None, 0, 0, "fewer than 3 frames")
    angular = meta.dim in (2, 3) and not meta.periodic
    span = min(frames, file.n_frames)
    first = (file.n_frames - span) // 2
    linear, both, floor = [], [], []
    picked = evenly_spaced(file.n_sims, sims)
    for s in picked:
        x = np.asarray(file.read("positions", (s, slice(first, first + span))))
        floor.append(rounding_share(x))
        n_linear = (span - 2) * meta.dim
        cols = simulation_columns(x, angular)
        linear.append(imbalance(cols[:n_linear]))
        if angular:
            both.append(imbalance(cols))
    if np.median(floor) > IMBALANCE_MAX / 10:
        return Balance(None, None, len(picked), span, "the positions' rounding is "
                       f"{np.median(floor):.2g} of their second differences' size (squared): "
                       "too coarse to tell")
    return Balance(float(np.median(linear)), float(np.median(both)) if both else None,
                   len(picked), span)


def rounding_share(positions: np.ndarray) -> float:
    """The squared size of the rounding in (T, N, D) positions' second differences against
    their own: positions exactly representable in float32 are taken as stored in float32.
    Far from the origin or moving little, a float32 source's frames cannot show a balance."""
    x = np.asarray(positions, dtype=np.float64)
    eps = 2.0**-24 if np.array_equal(x.astype(np.float32).astype(np.float64), x) else 2.0**-53
    acc = x[2:] - 2.0 * x[1:-1] + x[:-2]
    # three roundings of relative size eps, uniform: variance 6 (eps |x|)^2 / 3
    noise = 2.0 * np.mean((eps * x) ** 2)
    size = np.mean(acc**2)
    return float(noise / size) if size > 0 else float("inf")


def _show(value: float | None) -> str:
    return "-" if value is None else f"{value:.2g}"


def main(argv: list[str]) -> str:
    """The markdown table of ``momentum_balance`` for each dataset file in ``argv``."""
    from bgn.data.files import DatasetFile

    if not argv:
        raise SystemExit("usage: python -m bgn.data.balance <dataset .h5 file> [...]")
    lines = ["| file | simulations x frames | momentum | with angular momentum | verdict |",
             "|---|---|---|---|---|"]
    for path in argv:
        f = DatasetFile(path)
        b = momentum_balance(f, f.meta)
        f.close()
        verdict = b.reason or b.breaks() or "balanced: central pair forces can make them"
        lines.append(f"| {path} | {b.sims} x {b.frames} | {_show(b.linear)} | "
                     f"{_show(b.angular)} | {verdict} |")
    return "\n".join(lines)


if __name__ == "__main__":
    print(main(sys.argv[1:]))
