"""Elastic hard discs (or spheres, any ``dim``) in a reflecting box, integrated exactly.

Event-driven: particles move ballistically between events; an event is either a disc-disc
time of impact (elastic impulse along the line of centres) or a wall hit (that velocity
component flips sign). Nothing is time-stepped, so the physical trajectory is independent of
the frame times: frames are read off the piecewise-ballistic motion, and kinetic energy and
momentum (between wall hits) are conserved to round-off.

Each particle keeps its own reference time ``t0`` and position ``x0`` at its last event, so a
particle's state only changes when it takes part in an event. A per-particle table holds the
next predicted event (time, partner); after an event only the rows of the particles involved,
and of particles that had predicted an event with them, are recomputed (O(N) numpy work).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from bgn.coerce import as_float, as_int
from bgn.sim.scene import SceneMeta, State, Trajectory

# Safety net: a correct run never gets near this, an endless zero-time loop would.
_MAX_EVENTS = 50_000_000
# Pair-distance table up to this N; rows of the initial prediction per chunk.
_SIG2_TABLE_MAX = 2048
_PREDICT_CHUNK = 256
# Placement: at most this many candidates per disc and round, and this many rounds.
_PLACE_BATCH = 32
_PLACE_ROUNDS = 2_000
# Largest allowed fraction of the box volume covered by discs.
_MAX_PACKING = 0.5


@dataclass(frozen=True)
class ParticleType:
    """One particle species: radius, log-normal mass around ``mass_mode``, share of particles."""

    radius: float
    mass_mode: float
    mass_log_std: float = 0.0
    fraction: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            object.__setattr__(self, f.name,
                               as_float(getattr(self, f.name), f"ParticleType.{f.name}"))
        if self.radius <= 0:
            raise ValueError(f"ParticleType.radius must be > 0 (got {self.radius}); "
                             "set a positive radius")
        if self.mass_mode <= 0:
            raise ValueError(f"ParticleType.mass_mode must be > 0 (got {self.mass_mode}); "
                             "set a positive mass")
        if self.mass_log_std < 0:
            raise ValueError(f"ParticleType.mass_log_std must be >= 0 (got "
                             f"{self.mass_log_std}); use 0 for a fixed mass")
        if not 0 <= self.fraction <= 1:
            raise ValueError(f"ParticleType.fraction must lie in [0, 1] (got {self.fraction})")

    @classmethod
    def coerce(cls, value: Any) -> ParticleType:
        """Build from a ParticleType, a mapping (config dict) or a positional sequence."""
        if isinstance(value, ParticleType):
            return value
        if isinstance(value, Mapping):
            unknown = set(value) - {f.name for f in fields(cls)}
            if unknown:
                raise ValueError(f"unknown ParticleType keys {sorted(map(str, unknown))}; "
                                 "use radius, mass_mode, mass_log_std, fraction")
            return cls(**{str(k): v for k, v in value.items()})
        if isinstance(value, Sequence) and not isinstance(value, str):
            if not 2 <= len(value) <= 4:
                raise ValueError("a ParticleType sequence must be (radius, mass_mode"
                                 f"[, mass_log_std[, fraction]]), got {value!r}")
            return cls(*value)
        raise ValueError(f"cannot build a ParticleType from {value!r}; give a dict with keys "
                         "radius, mass_mode, mass_log_std, fraction")


def _ball_volume(radius: np.ndarray | float, dim: int) -> np.ndarray | float:
    return math.pi ** (dim / 2) / math.gamma(dim / 2 + 1) * np.asarray(radius) ** dim


@dataclass
class EventLog:
    """Every event of a run, in order: time, particle ``i`` and ``j``.

    ``j >= 0`` is a disc-disc impact (``i < j``); ``j = -1 - axis`` is a wall hit of ``i``.
    """

    times: np.ndarray
    i: np.ndarray
    j: np.ndarray


def _check_initial_state(pos: np.ndarray, vel: np.ndarray, m: np.ndarray, r: np.ndarray,
                         box: float) -> None:
    """Reject states the event loop cannot handle: it assumes no overlaps at the start."""
    if not (np.isfinite(pos).all() and np.isfinite(vel).all()):
        raise ValueError("positions and velocities must be finite")
    if np.any(m <= 0) or np.any(r <= 0) or not box > 0:
        raise ValueError("masses, radii and box must be positive")
    tol = 1e-12 * box
    if np.any(pos < r[:, None] - tol) or np.any(pos > box - r[:, None] + tol):
        raise ValueError("every disc must lie inside the box [0, box]^dim at the start")
    if pos.shape[0] > 1:
        # Only pairs closer than the largest contact distance can overlap (no N^2 matrix).
        pairs = cKDTree(pos).query_pairs(2 * float(r.max()), output_type="ndarray")
        if pairs.size:
            i, j = pairs.T
            dist = np.linalg.norm(pos[i] - pos[j], axis=1)
            if np.any(dist < (r[i] + r[j]) * (1 - 1e-12)):
                raise ValueError("discs overlap at the start; place them at least r_i + r_j "
                                 "apart")


def _checked_times(times: np.ndarray) -> np.ndarray:
    """``times`` as float64, refused unless a non-empty, strictly increasing 1-D array."""
    times = np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or times.size == 0:
        raise ValueError("times must be a non-empty 1-D array")
    if np.any(np.diff(times) <= 0):
        raise ValueError("times must be strictly increasing")
    return times


def _initial_state(positions: np.ndarray, velocities: np.ndarray, masses: np.ndarray,
                   radii: np.ndarray, box: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The start as float64 arrays (N, D), (N, D), (N,), (N,), checked for the event loop."""
    pos = np.asarray(positions, dtype=np.float64)
    vel = np.asarray(velocities, dtype=np.float64)
    m = np.asarray(masses, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    if pos.ndim != 2 or vel.shape != pos.shape or m.shape != pos.shape[:1] \
            or r.shape != pos.shape[:1]:
        raise ValueError("positions/velocities must be (N, D), masses and radii (N,)")
    _check_initial_state(pos, vel, m, r, box)
    return pos, vel, m, r


def _flown(x: list[float], v: list[float], dt: float) -> list[float]:
    """Position after ``dt`` of free flight from ``x`` at velocity ``v``."""
    return [a + u * dt for a, u in zip(x, v, strict=True)]


def _elastic_impact(xi: list[float], xj: list[float], vi: list[float], vj: list[float],
                    mi: float, mj: float) -> tuple[list[float], list[float]] | None:
    """Velocities of two touching discs after an elastic impulse along their line of centres
    (docs/design.md#collisions-scene); None when they do not approach (a grazing pair that
    round-off turned separating gets no impulse)."""
    d = [b - a for a, b in zip(xi, xj, strict=True)]
    dist = math.sqrt(math.fsum(e * e for e in d))
    nrm = [e / dist for e in d]
    vn = sum((b - a) * e for a, b, e in zip(vi, vj, nrm, strict=True))
    if not vn < 0:   # also a NaN normal (coincident centres): no impulse
        return None
    jimp = 2.0 * mi * mj / (mi + mj) * vn
    ci, cj = jimp / mi, jimp / mj
    return ([u + ci * e for u, e in zip(vi, nrm, strict=True)],
            [u - cj * e for u, e in zip(vj, nrm, strict=True)])


class _EventLoop:
    """The state of one event-driven run: each particle's motion since its last event, its
    next predicted event (time, partner) and the events so far.

    (D, N) layout: per-component rows are contiguous, which makes the small vector ops of the
    prediction cheaper; per-event arithmetic is done on Python floats.
    """

    def __init__(self, pos: np.ndarray, vel: np.ndarray, m: np.ndarray, r: np.ndarray,
                 box: float, t_start: float) -> None:
        n, dim = pos.shape
        self.n, self.dim, self.r = n, dim, r
        self.xT = np.ascontiguousarray(pos.T)   # position of each particle at its own t0
        self.vT = np.ascontiguousarray(vel.T)
        self.t0 = np.full(n, t_start)            # each particle's time of its last event
        # Contact distances squared: a table for moderate N, per row on the fly beyond (memory).
        self.sig2 = (r[:, None] + r[None, :]) ** 2 if n <= _SIG2_TABLE_MAX else None
        self.m_list = m.tolist()
        self.lo_list = r.tolist()                # wall contact coordinates per particle
        self.hi_list = (box - r).tolist()
        # last[i]: partner of i's last event (-1 - axis for a wall, n for none). The pair of a
        # collision is not rescheduled until one of the two has another event: in exact
        # arithmetic they separate, and round-off must not make them collide again at once.
        self.last = [n] * n
        self.t_next = np.full(n, np.inf)         # next event of each particle (absolute time)
        self.partner = np.full(n, n, dtype=np.int64)
        self.t_wall = np.full(n, np.inf)         # next wall hit, from the particle's motion only
        self.wall_code = np.full(n, -1, dtype=np.int64)
        self.ev_t: list[float] = []
        self.ev_i: list[int] = []
        self.ev_j: list[int] = []
        for k, (xk, vk) in enumerate(zip(pos.tolist(), vel.tolist(), strict=True)):
            self.predict_wall(k, t_start, xk, vk)

    def predict_wall(self, k: int, tk: float, xk: list[float], vk: list[float]) -> None:
        """Next wall hit of ``k``; only changes when k's velocity changes."""
        best, axis = math.inf, 0
        for a in range(self.dim):
            va = vk[a]
            if va > 0:
                t = (self.hi_list[k] - xk[a]) / va
            elif va < 0:
                t = (self.lo_list[k] - xk[a]) / va
            else:
                continue
            if t < best:
                best, axis = t, a
        # A disc a hair past its wall (round-off) and moving out bounces now.
        self.t_wall[k] = tk + max(best, 0.0)
        self.wall_code[k] = -1 - axis

    def predict(self, rows: np.ndarray, now: float) -> None:
        """Recompute the next event of ``rows`` given every particle's motion at ``now``."""
        vT, sig2, r, n, last, inf = self.vT, self.sig2, self.r, self.n, self.last, math.inf
        xs = vT * (now - self.t0)
        xs += self.xT
        dx = xs[:, None, :] - xs[:, rows, None]       # (D, R, N)
        dv = vT[:, None, :] - vT[:, rows, None]
        b = dx[0] * dv[0]
        dvv = dv[0] * dv[0]
        c = dx[0] * dx[0]
        for a in range(1, self.dim):
            b += dx[a] * dv[a]
            dvv += dv[a] * dv[a]
            c += dx[a] * dx[a]
        c -= sig2.take(rows, axis=0) if sig2 is not None else (r[rows, None] + r) ** 2
        disc = b * b
        disc -= dvv * c
        # Only approaching pairs (b < 0) that meet (disc >= 0) are scheduled; this also
        # excludes i itself (b = 0).
        ok = b < 0
        ok &= disc >= 0
        # Cancellation-free root c / (-b + sqrt(disc)) (-b > 0 where ok). A slightly
        # negative c (round-off overlap) gives tau < 0: collide now, since they approach.
        tau = np.sqrt(disc)
        tau -= b
        np.divide(c, tau, out=tau)
        tau = np.where(ok, tau, inf)
        np.maximum(tau, 0.0, out=tau)
        for a, i in enumerate(rows.tolist()):
            j = last[i]
            if j < n and j >= 0 and last[j] == i:
                tau[a, j] = inf
        jp = tau.argmin(axis=1)
        tp = tau[np.arange(rows.size), jp]
        tp += now
        tw = self.t_wall[rows]
        wall = tw < tp
        self.t_next[rows] = np.where(wall, tw, tp)
        self.partner[rows] = np.where(wall, self.wall_code[rows], jp)

    def flight(self, k: int, te: float) -> tuple[list[float], list[float]]:
        """Position of ``k`` at ``te`` and its velocity, as Python floats."""
        vk = self.vT[:, k].tolist()
        return _flown(self.xT[:, k].tolist(), vk, te - float(self.t0[k])), vk

    def moved(self, k: int, te: float, xk: list[float], vk: list[float], other: int) -> None:
        """Record an event of ``k`` with ``other`` at ``te``: its new reference point and
        its next wall hit (its velocity ``vk`` is already stored)."""
        self.xT[:, k] = xk
        self.t0[k] = te
        self.last[k] = other
        self.predict_wall(k, te, xk, vk)

    def affected(self, *ks: int) -> np.ndarray:
        """Mask of ``ks`` and of the particles whose predicted event was with one of them."""
        mask = self.partner == ks[0]
        for k in ks[1:]:
            mask |= self.partner == k
        for k in ks:
            mask[k] = True
        return mask

    def collide(self, i: int, j: int, te: float) -> np.ndarray:
        """Disc-disc event of ``i < j`` at ``te``; returns the particles to predict again."""
        xi, vi = self.flight(i, te)
        xj, vj = self.flight(j, te)
        after = _elastic_impact(xi, xj, vi, vj, self.m_list[i], self.m_list[j])
        if after is not None:
            vi, vj = after
            self.vT[:, i] = vi
            self.vT[:, j] = vj
        self.moved(i, te, xi, vi, j)
        self.moved(j, te, xj, vj, i)
        self.log(te, i, j)
        return self.affected(i, j)

    def bounce(self, k: int, code: int, te: float) -> np.ndarray:
        """Wall hit ``code`` (-1 - axis) of ``k`` at ``te``: that velocity component flips
        sign (exact); returns the particles to predict again."""
        axis = -1 - code
        xk, vk = self.flight(k, te)
        vk[axis] = -vk[axis]
        self.vT[axis, k] = vk[axis]
        self.moved(k, te, xk, vk, code)
        self.log(te, k, code)
        return self.affected(k)

    def log(self, te: float, i: int, j: int) -> None:
        """Append an event to the log (``EventLog``'s convention for ``j``)."""
        self.ev_t.append(te)
        self.ev_i.append(i)
        self.ev_j.append(j)

    def event_log(self) -> EventLog:
        """The events so far, in order."""
        return EventLog(np.asarray(self.ev_t, dtype=np.float64),
                        np.asarray(self.ev_i, dtype=np.int64),
                        np.asarray(self.ev_j, dtype=np.int64))

    def sample(self, frame: int, until: float, frame_times: list[float], out_x: np.ndarray,
               out_v: np.ndarray) -> int:
        """Write the frames from ``frame`` on that come strictly before ``until`` (the next
        event); returns the first frame not written."""
        while frame < len(frame_times) and frame_times[frame] < until:
            xs = self.vT * (frame_times[frame] - self.t0)
            xs += self.xT
            out_x[frame] = xs.T
            out_v[frame] = self.vT.T
            frame += 1
        return frame

    def run(self, frame_times: list[float]) -> tuple[np.ndarray, np.ndarray]:
        """Apply events in time order until the last frame time; the frames (T, N, D)."""
        n_frames = len(frame_times)
        out_x = np.empty((n_frames, self.n, self.dim))
        out_v = np.empty((n_frames, self.n, self.dim))
        t_next, partner = self.t_next, self.partner
        with np.errstate(divide="ignore", invalid="ignore"):
            for start in range(0, self.n, _PREDICT_CHUNK):  # chunks: (D, rows, N) temporaries
                self.predict(np.arange(start, min(start + _PREDICT_CHUNK, self.n)),
                             frame_times[0])
            frame = 0
            for _ in range(_MAX_EVENTS):
                k = int(t_next.argmin())
                te = float(t_next[k])
                # Frames strictly before the event see the old motion; an event at exactly a
                # frame time is shown in that frame (contacts use the interval (t_f, t_f+1]).
                if frame_times[frame] < te:   # frame < n_frames here
                    frame = self.sample(frame, te, frame_times, out_x, out_v)
                    if frame == n_frames:
                        break
                p = int(partner[k])
                if p >= 0:
                    mask = self.collide(min(k, p), max(k, p), te)
                else:
                    mask = self.bounce(k, p, te)
                self.predict(np.flatnonzero(mask), te)
            else:  # pragma: no cover - only an integrator bug gets here
                raise RuntimeError(f"more than {_MAX_EVENTS} events; the event loop is stuck")
        return out_x, out_v


def _frame_contacts(log: EventLog, times: np.ndarray) -> np.ndarray:
    """Rows ``(frame, i, j)`` (M, 3) int64, one per pair that collides in ``(times[frame],
    times[frame + 1]]``, sorted and unique."""
    disc_ev = log.j >= 0
    frame_of = np.searchsorted(times, log.times[disc_ev], side="left") - 1
    c_arr = np.stack([frame_of, log.i[disc_ev], log.j[disc_ev]], axis=1).astype(np.int64)
    c_arr = c_arr[frame_of >= 0]   # an impact at exactly times[0] precedes every interval
    return np.unique(c_arr, axis=0) if c_arr.size else np.zeros((0, 3), dtype=np.int64)


def integrate(positions: np.ndarray, velocities: np.ndarray, masses: np.ndarray,
              radii: np.ndarray, box: float, times: np.ndarray, *,
              return_events: bool = False
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, EventLog | None]:
    """Evolve hard discs from ``times[0]`` exactly; sample the state at ``times``.

    positions, velocities: (N, D) at ``times[0]``; discs must not overlap and must lie inside
    ``[0, box]^D``. Returns positions (T, N, D), velocities (T, N, D), contacts (M, 3) int64
    rows ``(frame, i, j)``, ``i < j``, one per pair that collides in ``(times[frame],
    times[frame + 1]]``, and the event log if ``return_events``. A frame at time t shows the
    state after every event at time <= t. The events never depend on ``times`` beyond where
    the run stops, so any two time grids agree bit for bit at the times they share.
    """
    times = _checked_times(times)
    box = float(box)
    pos, vel, m, r = _initial_state(positions, velocities, masses, radii, box)
    loop = _EventLoop(pos, vel, m, r, box, float(times[0]))
    out_x, out_v = loop.run(times.tolist())
    log = loop.event_log()
    return out_x, out_v, _frame_contacts(log, times), log if return_events else None


@dataclass
class CollisionScene:
    """Elastic hard discs of several types in the reflecting box ``[0, box]^dim``."""

    n_particles: int = 200
    dim: int = 2
    box: float = 10.0
    # Velocity spread of the heaviest mass mode. With ``thermal`` every particle starts with
    # the same mean kinetic energy (std ~ 1/sqrt(m)): the gas is in equipartition from frame 0,
    # so the data are stationary; otherwise light discs heat up ~20x over the first frames.
    velocity_std: float = 0.05
    thermal: bool = True
    # Two species by default: light small discs and heavy large ones (bimodal masses).
    types: tuple = (ParticleType(radius=0.1, mass_mode=0.001, mass_log_std=0.1, fraction=0.5),
                    ParticleType(radius=0.2, mass_mode=0.4, mass_log_std=0.1, fraction=0.5))

    def __post_init__(self) -> None:
        for name in ("n_particles", "dim"):
            setattr(self, name, as_int(getattr(self, name), f"CollisionScene.{name}", 1))
        for name in ("box", "velocity_std"):
            setattr(self, name, as_float(getattr(self, name), f"CollisionScene.{name}", 0.0,
                                         strict=True))
        raw = self.types
        if isinstance(raw, (Mapping, ParticleType)) or not isinstance(raw, Sequence) \
                or len(raw) == 0:
            raise ValueError("CollisionScene.types must be a non-empty list of particle types "
                             "(dicts with radius, mass_mode, mass_log_std, fraction)")
        converted = []
        for idx, t in enumerate(raw):
            try:
                converted.append(ParticleType.coerce(t))
            except (TypeError, ValueError) as err:
                raise ValueError(f"CollisionScene.types[{idx}]: {err}") from err
        self.types = tuple(converted)
        total = sum(t.fraction for t in self.types)
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"CollisionScene.types fractions must sum to 1, got {total:.6g}; "
                             "rescale the fraction values")
        counts = self.type_counts()
        if counts.min() < 0:
            raise ValueError("CollisionScene.types fractions round to more particles than "
                             f"n_particles={self.n_particles}; adjust the fractions")
        for idx, t in enumerate(self.types):
            if 2 * t.radius >= self.box:
                raise ValueError(f"CollisionScene.types[{idx}].radius={t.radius} does not fit "
                                 f"in box={self.box}; use radius < box / 2")
        radii = np.array([t.radius for t in self.types])
        covered = float(np.sum(counts * _ball_volume(radii, self.dim)))
        if covered > _MAX_PACKING * self.box ** self.dim:
            raise ValueError(
                f"CollisionScene: the discs cover {covered / self.box ** self.dim:.0%} of the "
                f"box volume (limit {_MAX_PACKING:.0%}); lower n_particles or the radii, or "
                "increase box")

    def type_counts(self) -> np.ndarray:
        """Particles per type: round(fraction * n) (Python's round, half to even), the
        remainder to the last type."""
        counts = [int(round(t.fraction * self.n_particles)) for t in self.types[:-1]]
        counts.append(self.n_particles - sum(counts))
        return np.asarray(counts, dtype=np.int64)

    @property
    def meta(self) -> SceneMeta:
        return SceneMeta(name="collisions", dim=self.dim, n_particles=self.n_particles,
                         n_types=len(self.types), interaction="contact", target="velocity",
                         graph="radius", box=self.box)

    def energy(self, positions: np.ndarray, velocities: np.ndarray,
               masses: np.ndarray) -> np.ndarray:
        """Kinetic energy per frame (T,) for (T, N, D) velocities; no potential energy."""
        vel = np.asarray(velocities, dtype=np.float64)
        return 0.5 * np.einsum("n,...nd,...nd->...", np.asarray(masses, np.float64), vel, vel)

    def draw_initial(self, rng: np.random.Generator
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Draw types, masses, radii, positions, velocities (in this order from ``rng``)."""
        n, dim = self.n_particles, self.dim
        layout = np.repeat(np.arange(len(self.types), dtype=np.int64), self.type_counts())
        types = rng.permutation(layout)
        mode = np.array([t.mass_mode for t in self.types])[types]
        log_std = np.array([t.mass_log_std for t in self.types])[types]
        masses = mode * np.exp(log_std * rng.standard_normal(n))
        radii = np.array([t.radius for t in self.types])[types]
        std = np.full(n, self.velocity_std)
        if self.thermal:
            std = std * np.sqrt(max(t.mass_mode for t in self.types) / masses)
        velocities = rng.normal(0.0, 1.0, size=(n, dim)) * std[:, None]
        positions = self._place(rng, radii)
        return types, masses, radii, positions, velocities

    def _place(self, rng: np.random.Generator, radii: np.ndarray) -> np.ndarray:
        """Uniform non-overlapping positions, each disc inside the box (rejection sampling).

        Rounds of random sequential addition, vectorised: every disc not yet placed draws a
        few candidates; a candidate is kept unless it overlaps a placed disc or an earlier
        candidate (largest discs first, as they are the hardest to fit), and each disc takes
        its first kept candidate. A k-d tree finds the close pairs, so there is no N^2 matrix.
        The order of the draws is fixed, so ``rng`` makes it reproducible.
        """
        n, dim, box = radii.size, self.dim, self.box
        reach = 2.0 * float(radii.max())
        pos = np.empty((n, dim))
        remaining = np.argsort(-radii, kind="stable")
        placed = np.zeros(0, dtype=np.int64)
        for _ in range(_PLACE_ROUNDS):
            if remaining.size == 0:
                return pos
            # More candidates per disc once few are left (the dense tail), bounded work.
            per = int(min(_PLACE_BATCH, max(1, n // remaining.size)))
            who = np.repeat(remaining, per)
            r_c = radii[who][:, None]
            cand = rng.uniform(r_c, box - r_c, size=(who.size, dim))
            allpos = np.concatenate([pos[placed], cand])
            all_r = np.concatenate([radii[placed], radii[who]])
            pairs = cKDTree(allpos).query_pairs(reach, output_type="ndarray")
            bad = np.zeros(who.size, dtype=bool)
            if pairs.size:
                a, b = pairs.min(axis=1), pairs.max(axis=1)
                hit = np.linalg.norm(allpos[a] - allpos[b], axis=1) < all_r[a] + all_r[b]
                # b > a always: b is a candidate that overlaps a placed disc or an earlier one
                bad[b[hit] - placed.size] = True
            good = ~bad.reshape(-1, per)
            ok = good.any(axis=1)
            first = np.argmax(good, axis=1)
            chosen = remaining[ok]
            pos[chosen] = cand.reshape(-1, per, dim)[ok, first[ok]]
            placed = np.concatenate([placed, chosen])
            remaining = remaining[~ok]
        if remaining.size == 0:
            return pos
        raise ValueError(
            f"CollisionScene: random placement jammed after {n - remaining.size} of {n} discs "
            f"in box={box} (random sequential addition stops near 40-50% coverage in 2D, less "
            "in 3D and in small boxes); lower n_particles or the radii, or increase box")

    def draw_state(self, rng: np.random.Generator) -> State:
        """The start ``simulate`` draws from ``rng`` (``draw_initial``) as a ``State``."""
        types, masses, radii, positions, velocities = self.draw_initial(rng)
        return State(positions, velocities, masses, radii, types)

    def simulate(self, rng: np.random.Generator, times: np.ndarray) -> Trajectory:
        """Draw a start from ``rng`` and sample the exact motion at ``times`` (increasing)."""
        traj, _ = self.simulate_events(rng, times, return_events=False)
        return traj

    def simulate_events(self, rng: np.random.Generator, times: np.ndarray, *,
                        return_events: bool = True) -> tuple[Trajectory, EventLog | None]:
        """``simulate`` plus the full event log (for checks and debugging)."""
        return self.simulate_events_from(self.draw_state(rng), times,
                                         return_events=return_events)

    def simulate_from(self, state: State, times: np.ndarray) -> Trajectory:
        """The exact motion from ``state`` (at ``times[0]``, discs inside this scene's box and
        not overlapping; any number of discs) sampled at ``times`` (increasing)."""
        return self.simulate_events_from(state, times, return_events=False)[0]

    def simulate_events_from(self, state: State, times: np.ndarray, *,
                             return_events: bool = True) -> tuple[Trajectory, EventLog | None]:
        """``simulate_from`` plus the full event log."""
        times = np.asarray(times, dtype=np.float64)
        pos, vel, contacts, log = integrate(state.positions, state.velocities, state.masses,
                                            state.radii, self.box, times,
                                            return_events=return_events)
        traj = Trajectory(times=times.copy(), positions=pos, velocities=vel,
                          masses=state.masses, types=state.types, radii=state.radii,
                          accelerations=None, contacts=contacts)
        return traj, log


__all__ = ["CollisionScene", "EventLog", "ParticleType", "integrate"]
