"""Softened n-body scenes of Cranmer et al. 2020: spring, gravity_r1 (log) and gravity_r2 (1/r).

The physics and its choices: docs/design.md#n-body-scenes. Every pair potential is a function
of the
additively softened distance ``s = r + softening``; forces point along the unsoftened difference
``x_i - x_j``. numpy and scipy only.

Charges: where a state carries per-particle ``charges`` (``State.charges``), the r1 and r2
potentials couple them in place of the masses, ``q_i q_j`` with the opposite sign (like
charges repel: ``phi = q_i q_j / s`` for r2), and the masses stay inertial, ``a_i = F_i / m_i``
(docs/design.md#n-body-scenes, "Charges"). The spring ignores both.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from bgn.coerce import as_float, as_int
from bgn.sim.scene import SceneMeta, State, Trajectory

POTENTIALS = ("spring", "r1", "r2")
_SCENE_NAMES = {"spring": "spring", "r1": "gravity_r1", "r2": "gravity_r2"}


def _pair_indices(n: int) -> tuple[np.ndarray, np.ndarray]:
    i, j = np.triu_indices(n, k=1)
    return i.astype(np.intp), j.astype(np.intp)


def _unit(diff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance and unit vector of ``diff`` (..., D); the direction is 0 where ``r == 0``.

    Coincident particles have no direction (the reference gives NaN); a zero direction keeps
    every value finite and makes the pair exert no force, which is also what symmetry demands.
    """
    r = np.sqrt(np.einsum("...d,...d->...", diff, diff))
    safe = np.where(r > 0.0, r, 1.0)
    u = diff / safe[..., None]
    u = np.where((r > 0.0)[..., None], u, 0.0)
    return r, u


NYQUIST_TURN = 0.5  # revolutions per frame above which frames alias a pair's rotation


def pair_turns(positions: np.ndarray, velocities: np.ndarray, dt: float) -> np.ndarray:
    """(T,) the fastest rotation of any pair at each of T frames, in revolutions per frame
    interval ``dt``: a pair's angular rate ``|v_ij, perpendicular| / r_ij`` (any dimension)
    times ``dt / 2 pi``, at the frame times. Above ``NYQUIST_TURN`` the frames alias the
    motion: positions sampled once per frame cannot tell such a turn from a slower one the
    other way round, so no model fed those frames can follow it. ``positions``,
    ``velocities``: (T, N, D)."""
    i, j = _pair_indices(positions.shape[1])
    if len(i) == 0:
        return np.zeros(positions.shape[0])
    rel, vel = positions[:, i] - positions[:, j], velocities[:, i] - velocities[:, j]
    r2 = np.maximum(np.einsum("tpd,tpd->tp", rel, rel), 1e-300)
    radial = np.einsum("tpd,tpd->tp", rel, vel)
    # |v_perp|^2 = |v|^2 - (r.v)^2 / r^2, clipped at 0 against round-off
    perp2 = np.maximum(np.einsum("tpd,tpd->tp", vel, vel) - radial**2 / r2, 0.0)
    return np.sqrt(perp2 / r2).max(axis=1) * dt / (2 * np.pi)


@dataclass
class NBodyScene:
    """Softened pairwise-potential n-body scene; all fields are config values."""

    potential: str
    n_particles: int = 4
    dim: int = 2
    softening: float = 0.01
    mass_log_mean: float = 0.0
    mass_log_std: float = 1.0
    position_std: float = 1.0
    velocity_std: float = 1.0
    rtol: float = 1e-10
    atol: float = 1e-10
    segment: float = 1.0

    def __post_init__(self) -> None:
        if self.potential not in POTENTIALS:
            raise ValueError(f"potential={self.potential!r} is unknown; set potential to one of "
                             f"{list(POTENTIALS)}")
        for name, low in (("n_particles", 2), ("dim", 1)):
            setattr(self, name, as_int(getattr(self, name), name, low))
        # per field: True -> must be > 0, False -> must be >= 0, None -> any finite value;
        # softening may be 0 only for the spring, whose force stays finite at r = 0
        checks = (("softening", self.potential != "spring"), ("mass_log_mean", None),
                  ("mass_log_std", False), ("position_std", True), ("velocity_std", False),
                  ("rtol", True), ("atol", True), ("segment", True))
        for name, strict in checks:
            try:
                value = as_float(getattr(self, name), name,
                                 None if strict is None else 0.0, strict=bool(strict))
            except ValueError as err:
                why = (" (gravity diverges at r = 0 without softening)"
                       if name == "softening" else "")
                raise ValueError(f"{err}{why}") from None
            setattr(self, name, value)

    @property
    def meta(self) -> SceneMeta:
        return SceneMeta(name=_SCENE_NAMES[self.potential], dim=self.dim,
                         n_particles=self.n_particles, n_types=1, interaction="pairwise",
                         target="acceleration", graph="full", box=None)

    # ----------------------------------------------------------------- force law

    def _dphi_ds(self, s: np.ndarray, mm: np.ndarray) -> np.ndarray:
        """dphi/ds of the pair potential at softened distance ``s``, ``mm`` the pair's
        coupling (``pair_coupling``)."""
        if self.potential == "spring":
            return 2.0 * (s - 1.0)
        if self.potential == "r1":
            return mm / s
        return mm / (s * s)

    def _phi(self, s: np.ndarray, mm: np.ndarray) -> np.ndarray:
        if self.potential == "spring":
            return (s - 1.0) ** 2
        if self.potential == "r1":
            return mm * np.log(s)
        return -mm / s

    @staticmethod
    def pair_coupling(masses: np.ndarray, charges: np.ndarray | None, i: np.ndarray,
                      j: np.ndarray) -> np.ndarray:
        """The coupling of each pair (i, j) in the gravity potentials: ``m_i m_j``, or with
        charges ``-q_i q_j`` (like charges repel)."""
        if charges is None:
            return masses[i] * masses[j]
        return -charges[i] * charges[j]

    def _check(self, positions: np.ndarray, masses: np.ndarray,
               charges: np.ndarray | None = None,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        x = np.asarray(positions, dtype=np.float64)
        m = np.asarray(masses, dtype=np.float64)
        if x.ndim < 2 or m.ndim != 1 or x.shape[-2] != m.shape[0]:
            raise ValueError(f"positions must be (..., N, D) and masses (N,); got "
                             f"{x.shape} and {m.shape}")
        if charges is None:
            return x, m, None
        q = np.asarray(charges, dtype=np.float64)
        if q.shape != m.shape:
            raise ValueError(f"charges must be (N,) = {m.shape}; got {q.shape}")
        return x, m, q

    def accelerations(self, positions: np.ndarray, masses: np.ndarray,
                      charges: np.ndarray | None = None) -> np.ndarray:
        """Accelerations (..., N, D) from positions (..., N, D), masses (N,) and, where the
        particles carry them, charges (N,); float64."""
        x, m, q = self._check(positions, masses, charges)
        n = x.shape[-2]
        i, j = _pair_indices(n)
        r, u = _unit(x[..., i, :] - x[..., j, :])
        mm = self.pair_coupling(m, q, i, j)
        g = self._dphi_ds(r + self.softening, mm)[..., None] * u  # = -force on i
        # antisymmetric pair table, then a fixed-order sum over partners: a BLAS contraction
        # could round differently for different numbers of frames, and recorded accelerations
        # must be bit-identical whatever frames are asked for
        table = np.zeros(x.shape[:-2] + (n, n, x.shape[-1]))
        table[..., i, j, :] = -g
        table[..., j, i, :] = g
        force = np.zeros_like(x)
        for k in range(n):
            force += table[..., :, k, :]
        return force / m[:, None]

    def pair_force_magnitude(self, positions: np.ndarray, masses: np.ndarray,
                             senders: np.ndarray, receivers: np.ndarray,
                             charges: np.ndarray | None = None) -> np.ndarray:
        """|force on receiver from sender| = |dphi/ds| per directed edge, shape (..., E).

        Zero where the two particles coincide (or the edge is a self-loop), matching the zero
        force that ``accelerations`` applies there.
        """
        x, m, q = self._check(positions, masses, charges)
        snd = np.asarray(senders, dtype=np.intp)
        rcv = np.asarray(receivers, dtype=np.intp)
        diff = x[..., rcv, :] - x[..., snd, :]
        r = np.sqrt(np.einsum("...d,...d->...", diff, diff))
        mag = np.abs(self._dphi_ds(r + self.softening, self.pair_coupling(m, q, rcv, snd)))
        return np.where(r > 0.0, mag, 0.0)

    def potential_energy(self, positions: np.ndarray, masses: np.ndarray,
                         charges: np.ndarray | None = None) -> np.ndarray:
        """Sum over pairs i < j of phi, shape (...)."""
        x, m, q = self._check(positions, masses, charges)
        i, j = _pair_indices(x.shape[-2])
        diff = x[..., i, :] - x[..., j, :]
        r = np.sqrt(np.einsum("...d,...d->...", diff, diff))
        return self._phi(r + self.softening, self.pair_coupling(m, q, i, j)).sum(axis=-1)

    def energy(self, positions: np.ndarray, velocities: np.ndarray,
               masses: np.ndarray, charges: np.ndarray | None = None) -> np.ndarray:
        """Total (kinetic + potential) energy per frame for (T, N, D) arrays, shape (T,)."""
        x, m, q = self._check(positions, masses, charges)
        v = np.asarray(velocities, dtype=np.float64)
        kinetic = 0.5 * np.einsum("n,...nd,...nd->...", m, v, v)
        return kinetic + self.potential_energy(x, m, q)

    # ----------------------------------------------------------------- integration

    def _rhs(self, masses: np.ndarray, charges: np.ndarray | None = None,
             ) -> Callable[[float, np.ndarray], np.ndarray]:
        """State derivative for solve_ivp, specialised to one mass (and charge) vector.

        solve_ivp calls this ~12 times per DOP853 step, so everything that depends only on the
        masses is precomputed and the body is a handful of small array operations.
        """
        n, d = self.n_particles, self.dim
        nd = n * d
        i, j = _pair_indices(n)
        npair = i.size
        # diff = inc_x @ x gives x_i - x_j per pair; acc = inc_a @ (w * diff) scatters -F/m
        inc_x = np.zeros((npair, n))
        inc_x[np.arange(npair), i] = 1.0
        inc_x[np.arange(npair), j] = -1.0
        inc_a = -inc_x.T / masses[:, None]
        mm = self.pair_coupling(masses, charges, i, j)
        eps = self.softening
        ones = np.ones(d)
        # Added to r^2: exact no-op unless r^2 < ~1e-284, and it keeps coincident particles
        # finite (w * diff = huge * 0 = 0) without a branch in the hot loop.
        tiny = 1e-300

        # w = (dphi/ds) / r, so that w * diff = dphi/ds * unit vector
        if self.potential == "spring":
            def weight(r: np.ndarray) -> np.ndarray:
                return 2.0 * (r + (eps - 1.0)) / r
        elif self.potential == "r1":
            def weight(r: np.ndarray) -> np.ndarray:
                return mm / ((r + eps) * r)
        else:
            def weight(r: np.ndarray) -> np.ndarray:
                s = r + eps
                return mm / (s * s * r)

        def rhs(_t: float, y: np.ndarray) -> np.ndarray:
            diff = inc_x @ y[:nd].reshape(n, d)
            r = np.sqrt((diff * diff) @ ones + tiny)
            res = np.empty(2 * nd)
            res[:nd] = y[nd:]
            np.matmul(inc_a * weight(r), diff, out=res[nd:].reshape(n, d))
            return res

        return rhs

    def draw_state(self, rng: np.random.Generator) -> State:
        """Draw masses, positions, velocities from ``rng`` (in that order)."""
        n, d = self.n_particles, self.dim
        masses = np.exp(self.mass_log_mean + self.mass_log_std * rng.standard_normal(n))
        x0 = self.position_std * rng.standard_normal((n, d))
        v0 = self.velocity_std * rng.standard_normal((n, d))
        return State(x0, v0, masses)

    def simulate(self, rng: np.random.Generator, times: np.ndarray) -> Trajectory:
        """Draw a state from ``rng`` (``draw_state``) and sample its motion at ``times``."""
        return self.simulate_from(self.draw_state(rng), times)

    def simulate_from(self, state: State, times: np.ndarray) -> Trajectory:
        """Sample at ``times`` (non-decreasing, >= 0) the motion from ``state`` at time 0.

        The state must have ``n_particles`` bodies in ``dim`` dimensions (radii and types are
        ignored; charges, where it carries them, couple in place of the masses: the module
        doc). The integration restarts at every multiple of ``segment`` so that the state
        at a time depends only on that physical time, never on which other times were asked for.
        """
        t = np.asarray(times, dtype=np.float64)
        if t.ndim != 1 or t.size == 0 or not np.all(np.isfinite(t)) or t[0] < 0.0 \
                or np.any(np.diff(t) < 0.0):
            raise ValueError("times must be a non-empty, finite, non-decreasing 1-D array "
                             "starting at >= 0")
        n, d = self.n_particles, self.dim
        if state.positions.shape != (n, d):
            raise ValueError(f"the state has {state.positions.shape} positions; this scene has "
                             f"(n_particles, dim) = ({n}, {d}): set them in the scene's config")
        if not (np.isfinite(state.positions).all() and np.isfinite(state.velocities).all()
                and np.all(state.masses > 0)):
            raise ValueError("the state needs finite positions and velocities and positive "
                             "masses")
        if state.charges is not None and not np.isfinite(state.charges).all():
            raise ValueError("the state's charges must be finite")
        masses, x0, v0 = state.masses, state.positions, state.velocities

        rhs = self._rhs(masses, state.charges)
        states = np.empty((t.size, 2 * n * d))
        y = np.concatenate([x0.ravel(), v0.ravel()])
        # piece k covers [k*segment, (k+1)*segment); the boundary itself takes the state there
        piece = np.floor(t / self.segment).astype(np.int64)
        start = piece * self.segment
        # floor of the division can disagree with the product by one ulp: fix it up
        piece = np.where(start > t, piece - 1, piece)
        piece = np.where((piece + 1) * self.segment <= t, piece + 1, piece)
        last = int(piece[-1])
        for k in range(last + 1):
            lo, hi = k * self.segment, (k + 1) * self.segment
            sel = np.flatnonzero(piece == k)
            at_lo = sel[t[sel] == lo]
            states[at_lo] = y
            inside = sel[t[sel] != lo]
            if inside.size == 0 and k == last:
                break
            sol = solve_ivp(rhs, (lo, hi), y, method="DOP853", rtol=self.rtol, atol=self.atol,
                            dense_output=True)
            if sol.status != 0:
                raise RuntimeError(f"{self.meta.name}: integration failed on [{lo}, {hi}]: "
                                   f"{sol.message}")
            if inside.size:
                states[inside] = sol.sol(t[inside]).T
            y = sol.y[:, -1].copy()

        nd = n * d
        positions = states[:, :nd].reshape(t.size, n, d)
        velocities = states[:, nd:].reshape(t.size, n, d)
        return Trajectory(times=t, positions=positions, velocities=velocities, masses=masses,
                          types=np.zeros(n, dtype=np.int64), radii=np.zeros(n),
                          accelerations=self.accelerations(positions, masses, state.charges),
                          contacts=None, charges=state.charges)
