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

Central forces that depend on velocity (drag or damping along the line between two
particles) keep both, so the balance cannot see them. ``velocity_dependence`` asks the frames
directly: the best central law of the distance alone, ``F_ij = f(r_ij) u_ij``, against the
best law of the distance and the relative speed along the pair, ``(f(r_ij) + g(r_ij) w_ij)
u_ij``, each a table in log r fitted by least squares to the training split's second
differences and scored on the validation split's. Where the second explains the frames many
times better, the forces depend on velocity, and no pair-force head (a law of the distance)
can make the data.

    python -m bgn.data.balance data/imported/<name>/train.h5 [...]   # a markdown table
    python -m bgn.data.balance <files> results_md=docs/results.md    # and into its block

(the command: ``bgn.train.balance``, ``conf/balance.yaml``; ``--help`` lists its keys).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

# Imbalance above which the data do not conserve momentum (or angular momentum): orders of
# magnitude above the float32 rounding of balanced frames, orders below the imbalance of a
# field or of walls (docs/results.md, "What the data conserve").
IMBALANCE_MAX = 1e-3
SIMS = 8            # simulations of the split read (evenly spaced)
FRAMES = 256        # frames of each simulation read (evenly spaced, consecutive triples)
# Velocity dependence: the share of the validation accelerations a law of the distance leaves
# unexplained must exceed UNEXPLAINED_MIN (a law of distance explaining the rest is a usable
# structure) and be VELOCITY_GAIN times what a law of distance and relative speed leaves
VELOCITY_GAIN = 10.0
UNEXPLAINED_MIN = 0.01
LAW_KNOTS = 24      # table knots per law and pair of types, evenly spaced in log r
PAIRS_MAX = 1 << 17  # particle pairs of one simulation the all-pairs test reads at most
PAIR_FRAMES = 1 << 18  # pairs x frames of one simulation read at most (memory)


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


@dataclass(frozen=True)
class VelocityDependence:
    """The share of the validation split's accelerations left unexplained by the best central
    law of the distance (``distance``) and of the distance and the relative speed along the
    pair (``velocity``); None with a ``reason`` where the test does not apply."""

    distance: float | None
    velocity: float | None
    sims: int
    frames: int
    reason: str = ""

    def breaks(self) -> str:
        """Why a law of the distance cannot make these data ("" when it can, or untested)."""
        if self.distance is None or self.velocity is None:
            return ""
        if self.distance > UNEXPLAINED_MIN and self.distance > VELOCITY_GAIN * self.velocity:
            return (f"the forces depend on velocity: a central law of the distance leaves "
                    f"{self.distance:.2g} of the validation accelerations unexplained, one of "
                    f"the distance and the relative speed along the pair {self.velocity:.2g} "
                    "(drag or damping between particles, which a law of the distance cannot "
                    "express)")
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


def pair_separations(x: np.ndarray, period: Any, cutoff: float,
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pairs (i < j) of (T, N, D) positions within ``cutoff`` at any of the frames (every
    pair where it is infinite): i, j, the separations (T, pairs, D) by the minimum image and
    the distances (T, pairs), zero where a pair is beyond ``cutoff``."""
    from bgn.data.contacts import pairs_within
    from bgn.data.edges import minimum_image

    if np.isfinite(cutoff):
        i, j = pairs_within(x, cutoff, period).T
    else:
        i, j = np.triu_indices(x.shape[1], k=1)
    d = minimum_image(x[:, i] - x[:, j], period)
    r = np.sqrt((d**2).sum(-1))
    return i, j, d, np.where(r <= cutoff, r, 0.0)


def law_columns(x: np.ndarray, types: np.ndarray, n_types: int, period: Any, cutoff: float,
                knots: np.ndarray, moving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One simulation's least-squares rows: (rows, 2 P K) the pair terms of a central law of
    the distance (first P K columns: one table of ``knots`` per pair of types) and of the
    distance times the relative speed along the pair (the rest), each particle's sum
    Numerov-weighted as its second difference sees it (``(F_{t-1} + 10 F_t + F_{t+1}) / 12``),
    and (rows,) the second differences; rows of particles the source moves left out."""
    import torch
    from scipy.sparse import csr_matrix

    from bgn.law_table import hat_basis

    x = np.asarray(x, dtype=np.float64)
    n, dim, k = x.shape[1], x.shape[2], len(knots)
    acc, vel = x[2:] - 2 * x[1:-1] + x[:-2], 0.5 * (x[2:] - x[:-2])   # frames 1 .. T-2
    i, j, d, r = pair_separations(x[1:-1], period, cutoff)
    near = r > 0
    u = d / np.where(near, r, 1.0)[..., None]
    speed = ((vel[:, i] - vel[:, j]) * u).sum(-1)
    basis = hat_basis(torch.from_numpy(np.log(np.where(near, r, 1.0))),
                      torch.from_numpy(knots)).numpy() * near[..., None]
    blocks = n_types * n_types
    pair = np.minimum(types[i], types[j]) * n_types + np.maximum(types[i], types[j])
    forces = np.zeros((n, len(r), dim, 2 * blocks * k))                # (N, F, D, 2 P K)
    for b in np.unique(pair):
        on = np.flatnonzero(pair == b)
        m = len(on)                # each pair pushes i along u and j against it
        incidence = csr_matrix((np.r_[np.ones(m), -np.ones(m)],
                                (np.r_[i[on], j[on]], np.r_[np.arange(m), np.arange(m)])),
                               shape=(n, m))
        for half, weight in enumerate((basis[:, on], basis[:, on] * speed[:, on, None])):
            terms = u[:, on, :, None] * weight[:, :, None, :]           # (F, m, D, K)
            summed = incidence @ terms.transpose(1, 0, 2, 3).reshape(m, -1)
            start = (half * blocks + b) * k
            forces[..., start:start + k] = summed.reshape(n, len(r), dim, k)
    numerov = (forces[:, :-2] + 10 * forces[:, 1:-1] + forces[:, 2:]) / 12  # frames 2 .. T-3
    rows, target = numerov[moving], acc[1:-1, moving].transpose(1, 0, 2)
    return rows.reshape(-1, rows.shape[-1]), target.reshape(-1)


def smoothed_error(fit: tuple[np.ndarray, np.ndarray, float],
                   check: tuple[np.ndarray, np.ndarray, float], k: int) -> float:
    """The relative squared error on ``check`` of the tables fitted to ``fit`` (each normal
    equations ``(X^T X, X^T y, y^T y)``, blocks of ``k`` knots), their smoothness chosen on
    ``check`` (``bgn.law_table.fit_table``)."""
    import torch

    from bgn.law_table import NormalEquations, fit_table

    fit_eq, check_eq = (NormalEquations(*(torch.as_tensor(v, dtype=torch.float64)
                                          for v in eq), 0) for eq in (fit, check))
    values, _ = fit_table(fit_eq, check_eq, len(fit[0]) // k)
    return check_eq.relative_error(values.reshape(-1))


def velocity_dependence(train: Any, val: Any, meta: Any, sims: int = SIMS,
                        frames: int = FRAMES) -> VelocityDependence:
    """``VelocityDependence`` of the ``train`` and ``val`` files (``DatasetFile``, scene record
    ``meta``): ``sims`` evenly spaced simulations of each, consecutive frames from their
    middle (``frames``, fewer where the pairs are many), every pair of particles within the
    radius graph's reach (all pairs on a full graph); one table per pair of types."""
    from bgn.data.contacts import contact_cutoff, pairs_within
    from bgn.data.frames import evenly_spaced
    from bgn.law_table import log_knots

    n = meta.n_particles
    cutoff = contact_cutoff(train)
    pairs = n * (n - 1) // 2                      # within reach of a radius graph: counted
    if np.isfinite(cutoff):                       # at the middle frame of the first simulation
        pairs = len(pairs_within(np.asarray(train.read("positions", (0, train.n_frames // 2)),
                                            dtype=np.float64)[None], cutoff, meta.period))
    if pairs > PAIRS_MAX:
        return VelocityDependence(None, None, 0, 0, f"{n} particles, {pairs} pairs within "
                                  f"reach: more than the pair-law test reads ({PAIRS_MAX})")
    span = min(frames, max(5, PAIR_FRAMES // max(pairs, 1)), train.n_frames, val.n_frames)
    if span < 5:
        return VelocityDependence(None, None, 0, 0, "fewer than 5 frames")
    files = {"train": train, "val": val}
    reads = {name: [(s, np.asarray(f.read("positions", (s, slice(
        (f.n_frames - span) // 2, (f.n_frames - span) // 2 + span))), dtype=np.float64))
        for s in evenly_spaced(f.n_sims, sims)] for name, f in files.items()}
    seen = np.concatenate([pair_separations(x, meta.period, cutoff)[3].ravel()
                           for runs in reads.values() for _, x in runs])
    seen = seen[seen > 0]
    if seen.size == 0 or not seen.max() > seen.min():
        return VelocityDependence(None, None, 0, span, "no pairs of particles within reach")
    knots = log_knots(float(seen.min()), float(seen.max()), LAW_KNOTS).numpy()
    n_types = max(int(meta.n_types), 1)
    sums = {}
    for name, f in files.items():
        gram, moment, total = 0.0, 0.0, 0.0
        for s, x in reads[name]:
            types = (np.asarray(f.read("types", s)) if n_types > 1
                     else np.zeros(n, dtype=np.int64))
            moving = (~np.asarray(f.read("kinematic", s), dtype=bool)
                      if "kinematic" in f.handle else np.ones(n, dtype=bool))
            rows, y = law_columns(x, types, n_types, meta.period, cutoff, knots, moving)
            gram, moment, total = gram + rows.T @ rows, moment + rows.T @ y, total + y @ y
        sums[name] = (gram, moment, float(total))
    half = n_types * n_types * LAW_KNOTS   # the law of the distance alone: its columns

    def distance_only(eq: tuple[np.ndarray, np.ndarray, float]) -> tuple[Any, ...]:
        return eq[0][:half, :half], eq[1][:half], eq[2]

    return VelocityDependence(
        smoothed_error(distance_only(sums["train"]), distance_only(sums["val"]), LAW_KNOTS),
        smoothed_error(sums["train"], sums["val"], LAW_KNOTS), len(reads["train"]), span)


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


def validation_file(path: str | Path) -> Path | None:
    """The validation split beside a training file (``train.h5`` -> ``val.h5``,
    ``<scene>_train.h5`` -> ``<scene>_val.h5``), where there is one."""
    path = Path(path)
    if "train" not in path.name:
        return None
    val = path.with_name("val".join(path.name.rsplit("train", 1)))
    return val if val.exists() else None


BLOCK = "balance"  # the generated block --results-md rewrites


def table(files: list[str | Path], results_md: str | Path | None = None,
          command: str = "") -> str:
    """The markdown table of ``momentum_balance`` for each dataset file in ``files``, and of
    ``velocity_dependence`` where a training file has its validation split beside it;
    with ``results_md`` also written, with ``command`` (as typed) and the commit, into that
    file's block ``<!-- generated:balance:... -->`` (docs/results.md, "What the data
    conserve")."""
    import platform
    import time

    from bgn.data.contacts import closest_approach, contact_cutoff, free_flight
    from bgn.data.files import DatasetFile

    lines = ["| file | simulations x frames | momentum | with angular momentum | law of the "
             "distance / with velocity | verdict | free flight beside contacts | seconds |",
             "|---|---|---|---|---|---|---|---|"]
    for path in files:
        start = time.perf_counter()
        f = DatasetFile(path)
        b = momentum_balance(f, f.meta)
        verdict = b.reason or b.breaks()
        speed = "-"
        if (val_path := validation_file(path)) is not None:
            val = DatasetFile(val_path)
            v = velocity_dependence(f, val, f.meta)
            val.close()
            speed = v.reason or f"{_show(v.distance)} / {_show(v.velocity)}"
            verdict = verdict or v.breaks()
        # soft contacts' evidence (bgn.data.contacts): what particles touching nothing leave
        # unexplained by a uniform field and drag
        cutoff = contact_cutoff(f)
        flight = free_flight(f, f.meta, closest_approach(f, f.meta, cutoff), cutoff)
        contacts = (flight.reason if flight.residual is None else
                    f"{_show(flight.residual)}: "
                    + ("velocities change only at contact" if not flight.breaks()
                       else "forces reach beyond contact"))
        f.close()
        verdict = verdict or "balanced: central pair forces can make them"
        lines.append(f"| {path} | {b.sims} x {b.frames} | {_show(b.linear)} | "
                     f"{_show(b.angular)} | {speed} | {verdict} | {contacts} | "
                     f"{time.perf_counter() - start:.2g} |")
    text = "\n".join(lines)
    if results_md:
        import torch

        from bgn.provenance import git_commit, write_block

        write_block(results_md, BLOCK, "\n".join([
            "_Written by the command below; do not edit by hand._", "",
            f"Regenerated by `{command}` (commit {git_commit()[:10]}; {platform.platform()}, "
            f"{torch.get_num_threads()} torch thread(s); `seconds`: the file's wall time).",
            "", text]))
    return text


if __name__ == "__main__":  # the command is bgn.train.balance's (it reads a Hydra config)
    import runpy

    runpy.run_module("bgn.train.balance", run_name="__main__", alter_sys=True)
