"""The two references the inverse model is judged against (docs/design.md#inverse-metrics,
docs/design.md#identifiability).

- ``MassPrior``: the scene's own law of log-masses (what training draws from). Sampling it
  ignores the data: calibrated by construction, zero information gain. A posterior that does
  no better than it has learned nothing about the particles it sees.
- ``physical_log_mass``: a no-learning estimator from the known force law and the observed
  frames, the upper anchor of what the data reveal about mass:
  - spring: the pair force ``2 (s - 1)`` does not involve the masses, so ``F_i = m_i a_i``
    with ``F_i`` from the positions: ``m_i`` by least squares over the window;
  - gravity: ``a_i = sum_j m_j f(s_ij) (x_j - x_i) / r_ij`` is linear in the *other*
    masses, so all masses follow from the accelerations by least squares;
  - collisions: at an isolated impact ``m_i dv_i = -m_j dv_j``, so
    ``log m_i - log m_j = log |dv_j| - log |dv_i|``; the impacts of a simulation fix the
    log-masses of each group of particles linked by impacts up to one shift (kinematics
    alone cannot give an absolute mass scale without a force constant), chosen as the most
    probable under the prior.

- ``place_by_prior``: log-masses known up to one shift (an impact group's ratios, or the
  masses a model's learned pair law fits to each window: its scale is free) placed where the
  prior makes them most probable together (``bgn.eval.evaluate``'s learned-law reference).

Accelerations are second differences of the frames, ``(x[t+1] - 2 x[t] + x[t-1]) / dt^2``:
the force scenes' targets (``bgn.data.targets``), exact for frames stepped by the matching
rule (Stormer-Verlet), and O(dt^2) off the adaptive integrator's frames. Velocities are the
backward differences the model sees. numpy only; a particle the window says nothing about
gets NaN (the caller falls back to the prior).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.sparse.csgraph import connected_components
from scipy.special import logsumexp

from bgn.sim import Scene
from bgn.sim.collisions import CollisionScene

# Stored float64 frames: a window whose accelerations are all below this (in the scene's
# units) carries no information about mass.
_TINY = 1e-12
SMOOTH = 0.5


@dataclass(frozen=True)
class MassPrior:
    """A mixture of Gaussians over natural log-mass (one component per particle type)."""

    weights: np.ndarray
    means: np.ndarray
    stds: np.ndarray

    @classmethod
    def of_scene(cls, scene: Scene, log_mass: dict[str, Any] | None = None) -> MassPrior:
        """The law a scene draws masses from: log-normal per type (collisions) or one
        log-normal (n-body). A scene without a mass law (imported data) takes the log-normal
        of its training split's masses, ``log_mass`` (the statistics' mean and std). A fixed
        mass (std 0) gets a narrow 1e-3 so it has a density."""
        if isinstance(scene, CollisionScene):
            weights = [t.fraction for t in scene.types]
            means = [np.log(t.mass_mode) for t in scene.types]
            stds = [t.mass_log_std for t in scene.types]
        elif hasattr(scene, "mass_log_mean"):
            weights, means, stds = [1.0], [scene.mass_log_mean], [scene.mass_log_std]
        elif log_mass is not None:
            weights = [1.0]
            means = [float(np.ravel(log_mass["mean"])[0])]
            stds = [float(np.ravel(log_mass["std"])[0])]
        else:
            raise ValueError(f"{type(scene).__name__} has no mass law: pass the training "
                             "split's log-mass statistics")
        return cls(np.asarray(weights, float), np.asarray(means, float),
                   np.maximum(np.asarray(stds, float), 1e-3))

    def log_pdf(self, log_mass: np.ndarray) -> np.ndarray:
        """Log-density of natural log-masses (any shape)."""
        x = np.asarray(log_mass, dtype=np.float64)[..., None]
        z = (x - self.means) / self.stds
        terms = np.log(self.weights) - 0.5 * z ** 2 - np.log(self.stds * np.sqrt(2 * np.pi))
        return logsumexp(terms, axis=-1)

    def sample(self, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """Independent draws of log-mass, ignoring any data (the prior-only sampler)."""
        k = rng.choice(len(self.weights), size=shape, p=self.weights / self.weights.sum())
        return self.means[k] + self.stds[k] * rng.standard_normal(shape)

    @property
    def mean(self) -> float:
        return float(np.sum(self.weights * self.means) / self.weights.sum())

    @property
    def typed(self) -> bool:
        """One component per particle type (collisions): a particle's type, which its radius
        shows, says which component its mass was drawn from."""
        return len(self.weights) > 1

    def type_law(self, types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per particle, the mean and std of log-mass of its type's component."""
        if not self.typed:
            raise ValueError("a mass law of one component has no per-type law")
        k = np.asarray(types, dtype=np.int64)
        return self.means[k], self.stds[k]

    def type_log_pdf(self, log_mass: np.ndarray, types: np.ndarray) -> np.ndarray:
        """Log-density of log-masses under each particle's own type's component (the
        type-only reference: what knowing the type alone tells of the mass)."""
        mean, std = self.type_law(types)
        z = (np.asarray(log_mass, dtype=np.float64) - mean) / std
        return -0.5 * z ** 2 - np.log(std * np.sqrt(2 * np.pi))

    def type_sample(self, types: np.ndarray, shape: tuple[int, ...],
                    rng: np.random.Generator) -> np.ndarray:
        """Draws (shape: (..., P)) of log-mass from each particle's own type's component,
        ignoring everything else (the type-only sampler)."""
        mean, std = self.type_law(types)
        return mean + std * rng.standard_normal(shape)

    def type_mean(self, types: np.ndarray) -> np.ndarray:
        """Per particle, the mean log-mass of its type's component, or of the whole law
        where it has one component: the guess of an estimator the frames tell nothing."""
        if not self.typed:
            return np.full(np.shape(types), self.mean)
        return self.type_law(types)[0]


def _second_differences(windows: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions (W, F, N, D) -> (the interior frames (W, F-2, N, D), their accelerations)."""
    acc = (windows[:, 2:] - 2 * windows[:, 1:-1] + windows[:, :-2]) / dt ** 2
    return windows[:, 1:-1], acc


def _resolved(acc: np.ndarray) -> np.ndarray:
    """(W, T, N) which finite-difference accelerations (W, T, N, D) to trust. One is off by
    about ``(omega dt)^2``, and a close encounter (omega ~ 1/dt) makes it useless: it shows as
    a jump to a neighbouring frame larger than ``SMOOTH`` x the particle's RMS acceleration
    over the window (RMS, not the local size, which passes through zero harmlessly)."""
    size = np.sqrt(np.mean(np.sum(acc ** 2, axis=-1), axis=1, keepdims=True))    # (W, 1, N)
    if acc.shape[1] == 1:                       # one acceleration: nothing to compare with
        return np.ones(acc.shape[:-1], dtype=bool)
    jump = np.linalg.norm(np.diff(acc, axis=1), axis=-1)               # (W, T-1, N)
    zero = np.zeros_like(jump[:, :1])           # the larger jump to either neighbour
    worst = np.maximum(np.concatenate([zero, jump], 1), np.concatenate([jump, zero], 1))
    return worst <= SMOOTH * size


def spring_log_mass(scene: Scene, windows: np.ndarray, dt: float) -> np.ndarray:
    """Spring: ``F_i = m_i a_i`` with the mass-free spring force (``accelerations`` at unit
    mass), least squares over every interior frame of the windows (W, F, N, D)."""
    x, acc = _second_differences(windows, dt)
    force = scene.accelerations(x, np.ones(x.shape[-2]))
    num = np.einsum("wtnd,wtnd->n", force, acc)
    den = np.einsum("wtnd,wtnd->n", acc, acc)
    with np.errstate(divide="ignore", invalid="ignore"):
        m = num / den
    return np.where((den > _TINY) & (m > 0), np.log(np.abs(m)), np.nan)


def gravity_log_mass(scene: Scene, windows: np.ndarray, dt: float) -> np.ndarray:
    """Gravity: ``a_i = sum_j m_j f(s_ij) (x_j - x_i) / r_ij`` with ``f = |dphi/ds|`` at unit
    masses (``pair_force_magnitude``), linear in the masses: least squares over all particles,
    dimensions and interior frames of the windows (W, F, N, D). A particle's own mass is absent
    from its own acceleration; it is read from its neighbours'."""
    x, acc = _second_differences(windows, dt)
    ok = _resolved(acc)
    n = x.shape[-2]
    rcv, snd = np.nonzero(~np.eye(n, dtype=bool))              # edge j -> i: i = rcv
    f = scene.pair_force_magnitude(x, np.ones(n), snd, rcv)      # (W, T, E)
    diff = x[..., snd, :] - x[..., rcv, :]                       # x_j - x_i
    r = np.linalg.norm(diff, axis=-1, keepdims=True)
    unit = np.divide(diff, r, out=np.zeros_like(diff), where=r > 0)
    design = np.zeros(x.shape[:2] + (n, x.shape[-1], n))         # (W, T, N_i, D, N_j)
    design[:, :, rcv, :, snd] = np.moveaxis(f[..., None] * unit, 2, 0)
    keep = np.repeat(ok[..., None], x.shape[-1], -1).reshape(-1)     # resolved rows only
    rows, rhs = design.reshape(-1, n)[keep], acc.reshape(-1)[keep]
    if not np.any(np.abs(rhs) > _TINY) or np.linalg.matrix_rank(rows) < n:
        return np.full(n, np.nan)
    m = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    return np.where(m > 0, np.log(np.abs(m)), np.nan)


def impact_equations(windows: np.ndarray, dt: float, contacts: list[np.ndarray],
                     ) -> tuple[np.ndarray, np.ndarray]:
    """The momentum exchanged at the isolated impacts of one simulation's windows, as
    equations on log-mass: pairs (M, 2) ``(i, j)`` and ratios (M,), one per impact,
    ``log m_i - log m_j = ratio``.

    ``contacts[w]`` (K, 3) rows ``(frame, i, j)``: i and j touch between frames ``frame`` and
    ``frame + 1`` of window w (the dataset's contacts table made relative to the window, or
    the impacts a model's contact head sees in it). An impact is used when the frames before
    and after it are in the window, neither disc has another event in the impact's interval
    or the two beside it (so the backward-difference velocities before and after are free
    flight), and the two velocity changes are antiparallel (no wall bounce in between): then
    ``m_i dv_i = -m_j dv_j``, so ``log m_i - log m_j = log |dv_j| - log |dv_i|``."""
    pairs, ratios = [], []
    for x, table in zip(windows, contacts):
        v = np.diff(x, axis=0) / dt                 # v[s] = (x[s+1] - x[s]) / dt
        events: dict[tuple[int, int], int] = {}
        for f, i, j in table:
            events[(f, i)] = events.get((f, i), 0) + 1
            events[(f, j)] = events.get((f, j), 0) + 1
        for f, i, j in table:
            if f < 1 or f + 2 >= len(x):
                continue                            # free flight before/after not in view
            if any(events.get((g, p), 0) != (g == f) for p in (i, j) for g in (f - 1, f, f + 1)):
                continue                            # another impact muddles the velocities
            dv_i, dv_j = v[f + 1, i] - v[f - 1, i], v[f + 1, j] - v[f - 1, j]
            ni, nj = np.linalg.norm(dv_i), np.linalg.norm(dv_j)
            if ni < _TINY or nj < _TINY or np.dot(dv_i, dv_j) > -(1 - 1e-6) * ni * nj:
                continue                            # a wall bounce too: not a pair exchange
            pairs.append((int(i), int(j)))
            ratios.append(np.log(nj) - np.log(ni))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2), np.asarray(ratios, float)


def impact_matrix(pairs: np.ndarray, n: int) -> np.ndarray:
    """The equations' matrix (M, n) of ``impact_equations``' pairs: +1 at i, -1 at j."""
    a = np.zeros((len(pairs), n))
    rows = np.arange(len(pairs))
    a[rows, pairs[:, 0]] += 1.0
    a[rows, pairs[:, 1]] -= 1.0
    return a


def impact_log_mass(prior: MassPrior, windows: np.ndarray, dt: float,
                    contacts: list[np.ndarray],
                    gauge: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Collisions: log-masses from the momentum exchanged at isolated impacts
    (``impact_equations``). The equations of a simulation are solved by least squares; each
    group of discs linked by impacts is shifted to the most probable place under ``prior``
    (only ratios are observable), or, given a ``gauge`` (per-disc mean and variance (N,) of
    log-mass: a model's own posteriors, or each disc's type's law), to the precision-weighted
    agreement with it."""
    n = windows.shape[2]
    pairs, ratios = impact_equations(windows, dt, contacts)
    out = np.full(n, np.nan)
    if not len(pairs):
        return out
    a = impact_matrix(pairs, n)
    seen = np.flatnonzero(np.abs(a).sum(axis=0) > 0)
    # minimum-norm least squares, then one shift per linked group (the gauge)
    out[seen] = np.linalg.lstsq(a[:, seen], ratios, rcond=None)[0]
    adjacency = (np.abs(a[:, seen]).T @ np.abs(a[:, seen])) > 0
    _, labels = connected_components(adjacency, directed=False)
    for group in np.unique(labels):
        members = seen[labels == group]
        if gauge is not None:       # the shift of most probability under Gaussians: closed form
            weight = 1.0 / np.maximum(gauge[1][members], 1e-12)
            out[members] += np.sum(weight * (gauge[0][members] - out[members])) / weight.sum()
            continue
        out[members] = place_by_prior(out[members], prior)
    return out


def place_by_prior(log_mass: np.ndarray, prior: MassPrior) -> np.ndarray:
    """Log-masses known up to one common shift (only their ratios observed), shifted to
    where they are most probable together under ``prior``: a grid of shifts over the law's
    range around their mean. NaN entries stay NaN and do not vote."""
    log_mass = np.asarray(log_mass, dtype=np.float64)
    known = np.isfinite(log_mass)
    if not known.any():
        return log_mass.copy()
    centred = log_mass - log_mass[known].mean()
    shifts = np.linspace(prior.means.min() - 3 * prior.stds.max(),
                         prior.means.max() + 3 * prior.stds.max(), 2001)
    score = prior.log_pdf(centred[known][None, :] + shifts[:, None]).sum(axis=1)
    return centred + shifts[np.argmax(score)]


def prior_shift_error(placed: np.ndarray, prior: MassPrior) -> float:
    """The standard error of the common log-shift ``place_by_prior`` chose for ``placed`` (its
    output; NaN entries ignored): one over the square root of the curvature of their summed
    prior log-density along the shift (the shift's Fisher information: ``std / sqrt(n)`` for
    one Gaussian law and n particles); the prior's widest std where nothing is known or the
    density is flat."""
    known = np.asarray(placed, dtype=np.float64)
    known = known[np.isfinite(known)]
    if known.size == 0:
        return float(prior.stds.max())
    h = 1e-3 * float(prior.stds.min())

    def total(d: float) -> float:
        return float(prior.log_pdf(known + d).sum())

    curvature = -(total(h) - 2.0 * total(0.0) + total(-h)) / (h * h)
    return float(1.0 / np.sqrt(curvature)) if curvature > 0 else float(prior.stds.max())


def physical_log_mass(scene: Scene, prior: MassPrior, windows: np.ndarray, dt: float,
                      contacts: list[np.ndarray] | None = None,
                      types: np.ndarray | None = None) -> np.ndarray:
    """Natural log-mass (N,) of every particle from position windows (W, F, N, D) of one
    simulation (W = 1: one frame's window, as the model sees it; more: pooled over frames),
    by the scene's force law; NaN where the windows say nothing about a particle.

    ``types`` (N,), where the mass law has one component per type: the impacts' groups of
    discs are placed by their members' own types' laws (as the radius shows them), not by
    the mixture, so the estimator uses all it is given, as the models with radii do."""
    windows = np.asarray(windows, dtype=np.float64)
    if isinstance(scene, CollisionScene):
        if contacts is None:
            raise ValueError("collisions: the estimator needs the windows' contacts")
        gauge = None
        if types is not None and prior.typed:
            mean, std = prior.type_law(types)
            gauge = (mean, std ** 2)
        return impact_log_mass(prior, windows, dt, contacts, gauge=gauge)
    potential = getattr(scene, "potential", None)
    if potential is None:  # no force law written down (imported data): nothing to estimate
        return np.full(windows.shape[2], np.nan)
    if potential == "spring":
        return spring_log_mass(scene, windows, dt)
    return gravity_log_mass(scene, windows, dt)
