"""Where particles touch, read from positions alone: the contact distance of each pair of
types and of each type to a wall, and the evidence that velocities change only there.

A GNS-layout file gives types, not radii. Hard or stiff contacts leave no pair of particles
closer than their contact distance and many at it, so the distances along pairs (and to the
walls) in the training frames have a sharp lower edge: ``closest_approach`` reads it as a
small quantile (the very lowest are the deepest overlaps of the hardest impacts).

Contacts are a structure only where nothing else moves the particles: a particle that touches
nothing (no partner within its contact distance, no wall, over a frame on either side) flies
freely, up to a uniform field (gravity) and a linear drag. ``free_flight`` fits that field and
drag to the free particles' second differences and returns what they leave unexplained, as a
share of the mean squared second difference of every particle: near the positions' rounding for
contact data, large where forces reach beyond contact (a soft potential, gravity between the
particles, pressure). docs/design.md#granular-media says how ``auto`` uses both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

SIMS = 8            # simulations read (evenly spaced)
FRAMES = 64         # consecutive frames of each, from its middle
# the closest approach: the k-th smallest distance, k this share of the distances (>= MIN_RANK)
REACH_SHARE, REACH_MIN_RANK = 1e-4, 5
# free flight: a frame's motion of both particles of a pair, at this quantile of the speeds
MARGIN_QUANTILE = 0.99
# the share of the second differences that free flight may leave unexplained in contact data:
# orders above float32 rounding, below forces that reach beyond contact (docs/results.md,
# "Granular media")
FREE_RESIDUAL_MAX = 1e-3
# distances along pairs read at most per file (memory: a complete graph of thousands of
# particles has millions of pairs a frame); fewer frames are read where they are many
PAIRS_READ = 1 << 24


@dataclass(frozen=True)
class Approach:
    """Contact distances: ``pair`` (T, T) per pair of types, ``wall`` (T,) per type to a wall
    (NaN: never close, or no walls)."""

    pair: np.ndarray
    wall: np.ndarray

    def as_dict(self) -> dict[str, list]:
        return {"pair": np.round(self.pair, 6).tolist(), "wall": np.round(self.wall, 6).tolist()}


@dataclass(frozen=True)
class FreeFlight:
    """What free particles' motion leaves unexplained by a uniform field and a drag
    (``residual``, a share; None with a ``reason`` where no particle flies free), the fitted
    field (per frame^2, D) and drag (per frame), and how many free samples were read."""

    residual: float | None
    field: tuple[float, ...] = ()
    drag: float = 0.0
    samples: int = 0
    reason: str = ""

    def breaks(self) -> str:
        """Why contacts cannot make these data ("" when they can)."""
        if self.residual is None:
            return self.reason
        if self.residual > FREE_RESIDUAL_MAX:
            return (f"particles that touch nothing still accelerate: a uniform field and drag "
                    f"leave {self.residual:.2g} of the second differences unexplained (> "
                    f"{FREE_RESIDUAL_MAX:g}), so forces reach beyond contact")
        return ""


def contact_cutoff(file: Any) -> float:
    """How far to look for contacts in a ``DatasetFile``: the reach of its radius graph (its
    margin, the connectivity radius, plus the two largest radii: ``bgn.data.edges``), every
    pair on a complete graph."""
    if file.meta.graph != "radius":
        return float(np.inf)
    radii = np.asarray(file.read("radii", ...), dtype=np.float64) if "radii" in file.handle \
        else np.zeros(1)
    return float(file.margin) + 2.0 * float(np.max(radii, initial=0.0))


def _frames(file: Any, sims: int, frames: int, cutoff: float,
            period: tuple[float, ...] | None) -> list[np.ndarray]:
    """(T, N, D) positions of ``sims`` evenly spaced simulations, ``frames`` consecutive each
    (at least 3): fewer where the pairs within ``cutoff`` of a frame are many (``PAIRS_READ``
    in all)."""
    from bgn.data.frames import evenly_spaced

    span = min(frames, file.n_frames)
    first = (file.n_frames - span) // 2
    x = np.asarray(file.read("positions", (0, first)), dtype=np.float64)
    pairs = max(1, len(_pairs(x, cutoff, period)[1]))
    span = min(span, max(3, PAIRS_READ // (pairs * max(1, min(sims, file.n_sims)))))
    first = (file.n_frames - span) // 2
    return [np.asarray(file.read("positions", (s, slice(first, first + span))), dtype=np.float64)
            for s in evenly_spaced(file.n_sims, sims)]


def _types(file: Any, sim_count: int, sims: int) -> list[np.ndarray]:
    from bgn.data.frames import evenly_spaced

    return [np.asarray(file.read("types", (s,)), dtype=np.int64)
            for s in evenly_spaced(sim_count, sims)]


def _pairs(x: np.ndarray, cutoff: float, period: tuple[float, ...] | None,
           ) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (P, 2) of one frame's positions (N, D) within ``cutoff`` and their distances (the
    minimum image where every dimension is periodic; otherwise a mixed box is searched as
    open, missing the pairs across its periodic sides)."""
    from scipy.spatial import cKDTree

    if period is not None and all(p > 0 for p in period):
        box = np.asarray(period, dtype=np.float64)
        tree = cKDTree(np.mod(x, box), boxsize=box)
    else:
        tree = cKDTree(x)
    dist = tree.sparse_distance_matrix(tree, cutoff, output_type="ndarray")
    keep = dist["i"] < dist["j"]
    return np.stack([dist["i"][keep], dist["j"][keep]], 1), dist["v"][keep]


def pairs_within(x: np.ndarray, cutoff: float, period: tuple[float, ...] | None,
                 ) -> np.ndarray:
    """(P, 2) the pairs (i < j) of (T, N, D) positions within ``cutoff`` at any of the T
    frames, each once, sorted."""
    found = [_pairs(frame, cutoff, period)[0] for frame in x]
    pairs = np.unique(np.concatenate(found), axis=0) if found else np.zeros((0, 2), np.int64)
    return pairs.reshape(-1, 2).astype(np.int64)


def _wall_distance(x: np.ndarray, box: Any) -> np.ndarray | None:
    """(..., N) the distance of each particle to its nearest wall of the box [0, box]^D."""
    if box is None:
        return None
    b = np.broadcast_to(np.asarray(box, dtype=np.float64), x.shape[-1:])
    return np.minimum(x, b - x).min(-1)


def _edge(values: list[np.ndarray]) -> float:
    if not values:
        return float("nan")
    v = np.sort(np.concatenate(values))
    if not len(v):
        return float("nan")
    k = max(REACH_MIN_RANK, int(REACH_SHARE * len(v)))
    return float(v[min(k, len(v)) - 1])


def closest_approach(file: Any, meta: Any, cutoff: float, sims: int = SIMS,
                     frames: int = FRAMES) -> Approach:
    """The contact distances of ``file`` (a training ``DatasetFile``) with scene record
    ``meta``: the closest approaches within ``cutoff`` (the graph's connectivity radius)."""
    n_types = max(1, int(meta.n_types))
    pair_d: list[list[np.ndarray]] = [[] for _ in range(n_types * n_types)]
    wall_d: list[list[np.ndarray]] = [[] for _ in range(n_types)]
    positions = _frames(file, sims, frames, cutoff, meta.period)
    for x, types in zip(positions, _types(file, file.n_sims, sims), strict=True):
        walls = _wall_distance(x, meta.box)
        for t, frame in enumerate(x):
            pairs, dist = _pairs(frame, cutoff, meta.period)
            a, b = types[pairs[:, 0]], types[pairs[:, 1]]
            code = np.minimum(a, b) * n_types + np.maximum(a, b)
            for c in np.unique(code):
                pair_d[c].append(dist[code == c])
            if walls is not None:
                for k in range(n_types):
                    wall_d[k].append(walls[t][types == k])
    pair = np.array([_edge(p) for p in pair_d]).reshape(n_types, n_types)
    pair = np.fmin(pair, pair.T)
    return Approach(pair, np.array([_edge(w) for w in wall_d]))


def free_flight(file: Any, meta: Any, approach: Approach, cutoff: float, sims: int = SIMS,
                frames: int = FRAMES) -> FreeFlight:
    """The evidence that velocities change only at contact (module doc): per frame triple,
    the particles that touch nothing at any of its three frames (a margin of a frame's motion
    of both), one uniform field and drag fitted to all of them by least squares, and the
    share of the mean squared second difference (of every particle) they leave."""
    rows, targets, total, count = [], [], 0.0, 0
    positions = _frames(file, sims, frames, cutoff, meta.period)
    dim = positions[0].shape[-1]
    for x, types in zip(positions, _types(file, file.n_sims, sims), strict=True):
        if len(x) < 3:
            continue
        step = np.diff(x, axis=0)
        if meta.period is not None:
            from bgn.data.edges import minimum_image
            step = minimum_image(step, meta.period)
        speed = np.sqrt((step * step).sum(-1))                      # per frame, (T-1, N)
        margin = 2.0 * float(np.quantile(speed, MARGIN_QUANTILE))
        touching = np.zeros(x.shape[:2], dtype=bool)                 # (T, N)
        walls = _wall_distance(x, meta.box)
        for t, frame in enumerate(x):
            pairs, dist = _pairs(frame, cutoff, meta.period)
            reach = approach.pair[types[pairs[:, 0]], types[pairs[:, 1]]]
            close = np.nan_to_num(reach, nan=-np.inf) + margin > dist
            touching[t, pairs[close, 0]] = True
            touching[t, pairs[close, 1]] = True
            if walls is not None:
                touching[t] |= np.nan_to_num(approach.wall[types], nan=-np.inf) + margin > walls[t]
        accel = x[2:] - 2 * x[1:-1] + x[:-2]                        # (T-2, N, D), per frame^2
        if meta.period is not None:
            accel = step[1:] - step[:-1]
        total += float((accel * accel).sum())
        count += accel.shape[0] * accel.shape[1]
        free = ~(touching[2:] | touching[1:-1] | touching[:-2])
        # a = g - gamma v, v the central difference (per frame)
        velocity = 0.5 * (step[1:] + step[:-1])
        t_idx, n_idx = np.nonzero(free)
        for d in range(dim):
            design = np.zeros((len(t_idx), dim + 1))
            design[:, d] = 1.0
            design[:, dim] = -velocity[t_idx, n_idx, d]
            rows.append(design)
            targets.append(accel[t_idx, n_idx, d])
    samples = sum(len(r) for r in rows) // max(dim, 1)
    if samples < dim + 1 or count == 0:
        return FreeFlight(None, samples=samples, reason="no particle flies free of contacts in "
                          "the frames read: no evidence that velocities change only at contact")
    a, y = np.vstack(rows), np.concatenate(targets)
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    residual = float(((a @ coef - y) ** 2).sum() / dim / max(samples, 1))
    scale = total / count / dim
    return FreeFlight(residual / max(scale, 1e-300), tuple(float(c) for c in coef[:dim]),
                      float(coef[dim]), samples)
