"""Per-particle couplings of either sign, fitted to the frames: ``a_i = k_i sum_j c_j X_ij``.

Particles that carry hidden charges ``q`` of either sign and hidden inertial masses ``m`` feel
pair forces ``F_ij = q_i q_j f(s_ij) u_ij``, so ``a_i = (q_i / m_i) sum_j q_j f(s_ij) u_ij``.
With ``X_ij = f(s_ij) u_ij`` (the pair terms, one per edge j -> i and frame), ``k_i = q_i /
m_i`` and ``c_j = q_j`` the model is bilinear. What frames identify
(docs/design.md#identifiability, "Couplings"): ``k`` and ``c`` up to one scale (``k / lam, lam
c``: the learned law's free scale) and one sign (``-k, -c``); the mass ``m_i = c_i / k_i`` up to
the scale alone, and the charges' ratios with their relative signs. The pair-force head fits
them per simulation (``mass_law=coupling``, ``bgn.model.newton``): over every window of a batch
that comes from one simulation, pooled (``simulation_system``), since a single window's few
frames do not pin ``2 n - 1`` unknowns (docs/design.md#identifiability, "Couplings").

A least-squares fit in ``k`` for fixed ``c`` is one unknown per particle, in ``c`` for fixed
``k`` one joint system per simulation; alternating the two is slow and, from charges all of one
sign, stops where the signs are wrong. So the fit is Levenberg-Marquardt on ``(k, c)`` jointly
from several sign patterns of ``c`` (``STARTS``; all of them for a few particles), the start
that ends with the smallest residual kept; it runs without gradients. One alternation from that
optimum (``k`` given ``c``, ``c`` given ``k``, ``k`` given ``c``, each a linear least squares)
then carries the law's gradient into the fit, as the other mass laws' closed-form fits do.

Plain torch, dense per simulation (``n`` particles: a ``(B, n * F * D, 2 n)`` Jacobian), for the
few-body systems the head serves.
"""

from __future__ import annotations

import itertools

import torch

from bgn.graph import Graph

# the most particles a simulation may hold: the fit is dense per simulation, a (n M, 2 n)
# Jacobian per sign pattern, whose cost grows as n^3 (bgn.model.newton.build_head refuses more)
MAX_PARTICLES = 16
STARTS = 16          # sign patterns of c tried per simulation (all 2^(n-1) where fewer)
ITERATIONS = 40      # Levenberg-Marquardt steps per start
DAMPING = 1e-3       # its initial damping, relative to the normal matrix's diagonal
FLOOR = 1e-12        # keeps the solves finite where a particle feels nothing
# Relative errors, then a robust reweighting (Cauchy, scale ROBUST_SCALE, ROBUST_STEPS rounds):
# the frames of a close encounter are the least resolved by the frame rate, and one of them
# would otherwise set every coupling of its simulation (the source law's mass fit,
# bgn.model.newton, weighs its rows the same way)
ROBUST_STEPS, ROBUST_SCALE = 2, 0.01
SIZE_FLOOR = 1e-3    # relative weights 1 / (|a| + SIZE_FLOOR x the simulation's mean |a|)


def sign_patterns(n: int, count: int = STARTS) -> torch.Tensor:
    """(S, n) starts of ``c``: every pattern of signs with the first particle's positive where
    2^(n-1) <= ``count`` (the global sign is free), else ``count`` patterns drawn with a fixed
    seed (the all-positive one first), so that a fit does not depend on the run."""
    if n <= 1:
        return torch.ones(1, max(n, 1), dtype=torch.float64)
    if 2 ** (n - 1) <= count:
        rows = [(1.0, *signs) for signs in itertools.product((1.0, -1.0), repeat=n - 1)]
        return torch.tensor(rows, dtype=torch.float64)
    gen = torch.Generator().manual_seed(0)
    drawn = torch.randint(0, 2, (count - 1, n), generator=gen).double() * 2 - 1
    return torch.cat([torch.ones(1, n, dtype=torch.float64), drawn])


def relative_weights(target: torch.Tensor, real: torch.Tensor) -> torch.Tensor:
    """(B, n, M) weights that make each row's error relative to the acceleration it fits:
    ``1 / (|a| + SIZE_FLOOR x the simulation's mean |a|)``, zero on padded particles.
    ``target``: (B, n, M); ``real``: (B, n) bool."""
    count = (real.sum(1) * target.shape[2]).clamp_min(1)
    size = (target.abs() * real[..., None]).sum((1, 2)) / count                  # (B,)
    return real[..., None] / (target.abs() + SIZE_FLOOR * size[:, None, None] + FLOOR)


def cauchy(weights: torch.Tensor, miss: torch.Tensor) -> torch.Tensor:
    """``weights`` after one round of Cauchy reweighting of the weighted residuals ``miss``."""
    return weights / (1 + (miss / ROBUST_SCALE) ** 2).sqrt()


def fit_k(design: torch.Tensor, target: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """(B, n) the least-squares ``k`` for fixed ``c`` (B, n): one unknown per particle.
    ``design``: (B, n, M, n), the pair terms of particle i's M rows from each j."""
    push = torch.einsum("bimj,bj->bim", design, c)
    return (push * target).sum(-1) / ((push * push).sum(-1) + FLOOR)


def fit_c(design: torch.Tensor, target: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """(B, n) the least-squares ``c`` for fixed ``k`` (B, n): one joint system per simulation,
    ridge-regularised relative to each column (a particle that pulls on no one stays finite)."""
    b, n, m, _ = design.shape
    a = (k[:, :, None, None] * design).reshape(b, n * m, n)
    gram = a.transpose(1, 2) @ a
    ridge = torch.diag_embed(1e-9 * gram.diagonal(dim1=1, dim2=2) + FLOOR)
    return torch.linalg.solve(gram + ridge, a.transpose(1, 2) @ target.reshape(b, n * m, 1))[..., 0]


def normalise(k: torch.Tensor, c: torch.Tensor, real: torch.Tensor,
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """The gauge the fit reports: ``c`` of unit root-mean-square over each simulation's real
    particles (``real``: (B, n) bool) and its largest entry positive, ``k`` scaled and signed to
    keep every product ``k_i c_j``."""
    count = real.sum(1, keepdim=True).clamp_min(1)
    scale = (c.pow(2).sum(1, keepdim=True) / count).sqrt().clamp_min(FLOOR)
    biggest = c.gather(1, c.abs().argmax(1, keepdim=True))
    sign = torch.where(biggest < 0, -1.0, 1.0).to(c.dtype)
    return k * scale * sign, c / scale * sign


def residual(design: torch.Tensor, target: torch.Tensor, k: torch.Tensor, c: torch.Tensor,
             ) -> torch.Tensor:
    """(B, n, M) the prediction's miss ``k_i sum_j c_j X_ij - a_i``."""
    return k[..., None] * torch.einsum("bimj,bj->bim", design, c) - target


@torch.no_grad()
def lifted_start(design: torch.Tensor, target: torch.Tensor, real: torch.Tensor,
                 completions: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
    """A start for ``(k, c)`` (B, n) from the linear problem the bilinear one lifts to: every
    coupling ``G_ij = k_i c_j`` free (one least squares per particle, ``n - 1`` unknowns),
    then the nearest rank-one ``k c^T`` to ``G`` off its diagonal (the diagonal, which no frame
    shows, filled in from the rank-one fit and the fit repeated, ``completions`` times). Exact
    where the frames pin every ``G_ij``: many frames of one simulation (a pooled fit); from one
    window's few frames ``G`` is ill-posed and the sign patterns of ``sign_patterns`` do better."""
    gram = design.transpose(2, 3) @ design                                    # (B, n, n, n)
    ridge = torch.diag_embed(1e-9 * gram.diagonal(dim1=2, dim2=3) + FLOOR)
    couplings = torch.linalg.solve(gram + ridge,
                                   (design.transpose(2, 3) @ target[..., None]))[..., 0]
    mask = real[:, :, None] & real[:, None, :]
    mask = mask & ~torch.eye(real.shape[1], dtype=torch.bool, device=real.device)
    filled = torch.where(mask, couplings, 0.0)
    for _ in range(completions):
        u, sv, vh = torch.linalg.svd(filled)
        rank1 = sv[:, :1, None] * u[:, :, :1] @ vh[:, :1, :]
        filled = torch.where(mask, couplings, rank1)
    k, c = u[:, :, 0] * sv[:, :1], vh[:, 0, :]
    return normalise(k * real, c * real, real)


@torch.no_grad()
def levenberg_marquardt(design: torch.Tensor, target: torch.Tensor, k: torch.Tensor,
                        c: torch.Tensor, real: torch.Tensor, iterations: int = ITERATIONS,
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Levenberg-Marquardt on ``(k, c)`` (B, n) each, from the given start; returns them and
    each simulation's final sum of squared (weighted) residuals (B,). The scale gauge makes the
    normal matrix singular: the damping keeps each step finite and ``normalise`` fixes it."""
    b, n, m, _ = design.shape
    cost = residual(design, target, k, c).pow(2).sum((1, 2))
    damping = torch.full((b,), DAMPING, dtype=design.dtype, device=design.device)
    eye = torch.eye(n, dtype=design.dtype, device=design.device)
    for _ in range(iterations):
        push = torch.einsum("bimj,bj->bim", design, c)                        # d/dk_i
        jk = push[..., None] * eye[None, :, None, :]                          # (B, n, M, n)
        jc = k[:, :, None, None] * design                                     # (B, n, M, n)
        jac = torch.cat([jk, jc], -1).reshape(b, n * m, 2 * n)
        r = residual(design, target, k, c).reshape(b, n * m, 1)
        normal = jac.transpose(1, 2) @ jac
        grad = jac.transpose(1, 2) @ r
        diag = normal.diagonal(dim1=1, dim2=2)
        step = torch.linalg.solve(
            normal + torch.diag_embed(damping[:, None] * diag + FLOOR), -grad)[..., 0]
        k_new, c_new = normalise(k + step[:, :n], c + step[:, n:], real)
        new = residual(design, target, k_new, c_new).pow(2).sum((1, 2))
        better = new < cost
        k = torch.where(better[:, None], k_new, k)
        c = torch.where(better[:, None], c_new, c)
        cost = torch.where(better, new, cost)
        damping = torch.where(better, damping / 3, damping * 3).clamp(1e-12, 1e12)
    return k, c, cost


def fit_couplings(design: torch.Tensor, target: torch.Tensor, real: torch.Tensor,
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """``k`` and ``c`` (B, n) of ``a_i = k_i sum_j c_j X_ij`` fitted to the accelerations
    ``target`` (B, n, M) with the pair terms ``design`` (B, n, M, n) (zero where there is no
    edge, and on padded particles, ``real`` false), by least squares weighted per particle
    (``relative_weights``, then ``cauchy``), in the gauge of ``normalise``; differentiable in
    ``design`` through the final alternation (the module doc). Computed in float64; returned
    in the design's dtype."""
    dtype = design.dtype
    w = relative_weights(target.double(), real)
    d64, t64 = design.double() * w[..., None], target.double() * w
    b, n = real.shape
    # every sign pattern of c, and the lifted start: s starts per simulation, in a row
    lifted = lifted_start(d64.detach(), t64.detach(), real)[1]
    starts = torch.cat([sign_patterns(n).to(d64.device)[None].expand(b, -1, -1),
                        lifted[:, None]], 1)                                  # (B, s, n)
    s = starts.shape[1]
    rep_d = d64.detach().repeat_interleave(s, 0)
    rep_t = t64.detach().repeat_interleave(s, 0)
    rep_real = real.repeat_interleave(s, 0)
    c0 = starts.reshape(b * s, n) * rep_real
    k, c, cost = levenberg_marquardt(rep_d, rep_t, *normalise(fit_k(rep_d, rep_t, c0), c0,
                                                              rep_real), rep_real)
    best = cost.reshape(b, s).argmin(1) + torch.arange(b, device=d64.device) * s
    k, c = k[best], c[best]
    for _ in range(ROBUST_STEPS):
        w = cauchy(w, residual(d64, t64, k, c).detach())
        d64, t64 = design.double() * w[..., None], target.double() * w
        k, c, _ = levenberg_marquardt(d64.detach(), t64.detach(), k, c, real)
    # one alternation from the optimum carries the law's gradient
    k = fit_k(d64, t64, c)
    c = fit_c(d64, t64, k)
    k = fit_k(d64, t64, c)
    k, c = normalise(k, c * real, real)
    return k.to(dtype), c.to(dtype)


def coupling_errors(design: torch.Tensor, target: torch.Tensor, real: torch.Tensor,
                    k: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, n) standard errors of ``k`` and ``c``, each given the other (the residuals' variance
    through the conditional normal matrices): small where the frames pin a particle's
    coupling, large where they do not. Weighted as ``fit_couplings``."""
    w = relative_weights(target.double(), real)
    d64, t64 = design.double() * w[..., None], target.double() * w
    k64, c64 = k.double(), c.double()
    for _ in range(ROBUST_STEPS):
        w = cauchy(w, residual(d64, t64, k64, c64))
        d64, t64 = design.double() * w[..., None], target.double() * w
    b, n, m, _ = d64.shape
    miss = residual(d64, t64, k64, c64)
    dof = (real.sum(1) * m - (2 * real.sum(1) - 1)).clamp_min(1)
    variance = miss.pow(2).sum((1, 2)) / dof                                  # (B,)
    push = torch.einsum("bimj,bj->bim", d64, c64)
    k_err = (variance[:, None] / ((push * push).sum(-1) + FLOOR)).sqrt()
    a = (k64[:, :, None, None] * d64).reshape(b, n * m, n)
    gram = a.transpose(1, 2) @ a
    ridge = torch.diag_embed(1e-9 * gram.diagonal(dim1=1, dim2=2) + FLOOR)
    c_err = (variance[:, None] * torch.linalg.inv(gram + ridge).diagonal(dim1=1, dim2=2)).sqrt()
    return k_err.to(k.dtype), c_err.to(c.dtype)


def simulation_system(g: Graph, past: torch.Tensor, seen: torch.Tensor) -> tuple[
        torch.Tensor, torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """The windows of ``g`` grouped by simulation (``g.sim``) and stacked along the rows:
    ``design`` (S, n, M, n), ``target`` (S, n, M) and ``real`` (S, n) as ``fit_couplings``
    reads them, one system per simulation of the batch, and ``where``: each node's (system,
    particle) index, to read the fit back per node. ``past``: (E, F, D) pair terms at the F
    frames of ``seen`` (N, F, D). Every graph of one simulation holds the same particles in
    the same order (a window of it); a simulation with fewer windows than the batch's most is
    padded with rows that are zero on both sides, which fit nothing."""
    n_graphs = g.num_graphs
    device = g.batch.device
    groups, group = torch.unique(g.sim.to(device), return_inverse=True)       # (G,)
    order = torch.argsort(group, stable=True)
    per_group = torch.bincount(group, minlength=len(groups))
    first = torch.cumsum(per_group, 0) - per_group
    slot = torch.empty(n_graphs, dtype=torch.long, device=device)
    slot[order] = torch.arange(n_graphs, device=device) - first[group[order]]
    counts = g.num_nodes.to(device)
    local = g.local_index
    n, windows = int(counts.max()), int(per_group.max())
    frames, dim = seen.shape[1], seen.shape[2]
    snd, rcv = g.edge_index
    node_group, node_slot = group[g.batch], slot[g.batch]
    design = past.new_zeros(len(groups), n, windows, frames, dim, n)
    design[node_group[rcv], local[rcv], node_slot[rcv], :, :, local[snd]] = past
    target = seen.new_zeros(len(groups), n, windows, frames, dim)
    target[node_group, local, node_slot] = seen
    real = torch.zeros(len(groups), n, dtype=torch.bool, device=device)
    real[node_group, local] = True
    rows = windows * frames * dim
    return (design.reshape(len(groups), n, rows, n), target.reshape(len(groups), n, rows), real,
            (node_group, local))
