"""Inverse model (paper section "Inverse model definition and design", Eq. 6-10).

- A conditional normalising flow ``p(z | H̃_V,i)`` over the particle's *normalised* log-mass
  (1-D; context = the node feature width), trained by its negative log-likelihood: the forward
  KL of Eq. 8, with the log-density of Eq. 7. From zuko: ``"nsf"`` (neural spline flow) or
  ``"naf"`` (neural autoregressive flow, the paper's choice, Huang et al. 2018).
- Samples ``Z_K`` (one per particle, reparameterised so the relative-mass loss trains the flow
  and the encoder through them) feed the relative-mass decoder on edges, Eq. 9-10:
  ``h_ij = s(bilinear(z_i, z_j))``, then linear layers -> ``R̂_ij ≈ log m_i - log m_j``
  (normalised by its scale).

Both flows support ``rsample``: NSF inverts its splines in closed form; NAF inverts its monotone
network by bisection (about 25 network evaluations) and zuko differentiates that inverse
implicitly, which is why NAF is much slower to sample
(docs/design.md#departures-from-the-paper).

What the flow is conditioned on (``context``): the paper's ``H̃_V`` alone, or with
``pairs`` (not in the paper) also pair terms of the observed accelerations, the quantities
that carry mass (docs/design.md#identifiability). On spring ``m_i a_i`` is the mass-free spring
force, so ``log m_i`` is a function of the pair geometry seen from ``a_i`` minus ``log |a_i|``;
under gravity ``a_i = sum_j m_j f(s_ij) u_ji`` holds ``m_j`` in the *neighbour's* acceleration, so a
particle needs messages from the edges where it is the sender. GCN layers that average normalised
features do not form such log-ratios of magnitudes from a few hundred training masses; per edge, the
log-distance, the log-magnitudes of both accelerations and their cosines with the pair direction
make them a smooth function an MLP learns.
``fit`` adds to ``pairs`` the log-mass that the structured force head (``model.dynamics=newton``,
``bgn.model.newton``) fits to the window's accelerations with its learned force law: under
gravity a joint least-squares fit of every particle's mass from its neighbours' accelerations,
which a few hundred training masses do not teach an MLP of pair terms. The fit's scale is free
(a constant the flow learns); it enters detached, so the flow does not bend the force law.
Optional dropout on the context during training regularises a flow that sees few masses.

Calibration (``calibration``): a flow trained by maximum likelihood on a few thousand masses
is miscalibrated (its intervals too narrow, or too wide with too heavy tails). At inference a
base draw ``e ~ N(0, 1)`` becomes ``sign(e) m(|e|)`` with ``m`` a monotone piecewise-linear
map of the radius (knots ``(z, r)``, linear past the last): for a 1-D flow the transform is
monotone, so this moves every credible interval's bounds around the same median, in the
flow's own warped coordinates, and the density follows by the change of variables. The map is
fitted on the validation split after training (``bgn.eval.evaluate.calibrate_mass_posterior``,
``bgn.metrics.fit_radius_map``); it is the identity while training and not part of the
checkpoint's weights.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import zuko
from torch import nn
from torch.nn import functional as F

from bgn.graph import Graph
from bgn.model.base import OptionGroup, check_positive_ints
from bgn.model.message_passing import CheckpointEdges, edge_chunks, edge_sums, edge_vector
from bgn.model.ops import Linear, activation, linear

FLOWS = ("nsf", "naf")
CONTEXTS = ("node", "pairs", "fit")
PAIR_FEATURES = 5   # log r, log |a_i|, log |a_j|, cos(a_i, u_ij), cos(a_j, u_ij)
_EPS = 1e-12


@dataclass
class InverseOptions(OptionGroup):
    """The inverse model's options (``InverseModel``, Eq. 6-10; ``bgn.model.bgn.ModelConfig``
    composes them): the flow and what it is conditioned on. ``inverse`` (in ``ModelConfig``)
    switches the model itself."""

    flow: str = "nsf"                  # conditional flow: nsf | naf (the paper's; module doc)
    flow_transforms: int = 3
    flow_hidden: int = 64
    # What the flow is conditioned on (InverseModel.context): "node", H̃_V alone (the paper),
    # or "pairs", also pair terms of the observed accelerations (not in the paper; it raised
    # the relative-mass R^2 and the information gain on spring and collisions:
    # docs/results.md), or "fit", pairs and the log-masses the structured head
    # (dynamics=newton, force scenes; elsewhere fit = pairs) fits to the window.
    # mass_context_dropout: dropout on that context.
    mass_context: str = "pairs"
    mass_context_dropout: float = 0.0
    # mass_context=fit: also the fit's relative standard error, so the flow can tell a window
    # that pins the masses from one that does not (gravity_r2:
    # docs/notes/2026-11-26-results-history.md, "gravity_r2: the fit's own error"); where the
    # context is not a fit (bgn.model.bgn.BGN._conditioning) there is no fit error to read,
    # and it is unused
    mass_fit_error: bool = False
    # frames of the window whose accelerations the pair terms read (1: the newest; at most
    # the history): an impact anywhere in the window carries the pair's mass ratio
    mass_context_frames: int = 1

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_ints(self, ("flow_transforms", "flow_hidden"))
        if self.flow not in FLOWS:
            raise ValueError(f"flow={self.flow!r}; choose one of {FLOWS}")
        if self.mass_context not in CONTEXTS:
            raise ValueError(f"mass_context={self.mass_context!r}; choose one of {CONTEXTS}")
        if self.mass_context_frames < 1:
            raise ValueError(f"mass_context_frames={self.mass_context_frames} must be >= 1")
        if not 0.0 <= self.mass_context_dropout < 1.0:
            raise ValueError(f"mass_context_dropout={self.mass_context_dropout} must be in "
                             "[0, 1)")


def make_flow(kind: str, context: int, transforms: int, hidden: int) -> zuko.flows.Flow:
    """A 1-D conditional flow from zuko with ``transforms`` layers of width ``hidden``."""
    if kind == "nsf":
        return zuko.flows.NSF(1, context, transforms=transforms,
                              hidden_features=(hidden, hidden))
    if kind == "naf":
        return zuko.flows.NAF(1, context, transforms=transforms,
                              hidden_features=(hidden, hidden),
                              network={"hidden_features": (hidden, hidden)})
    raise ValueError(f"flow={kind!r}; choose one of {FLOWS}")


def window_accelerations(g: Graph, frames: int) -> torch.Tensor:
    """(N, F, D) the window's ``frames`` newest finite-difference accelerations
    ``(v[t-f] - v[t-f-1]) / dt``, f = 0 .. F-1, in physical units."""
    if g.dt is None:
        raise ValueError("pair terms need the frame spacing: the graph has no dt")
    return (g.vel[:, :frames] - g.vel[:, 1:frames + 1]) / g.dt[g.batch][:, None, None]


def pair_features(g: Graph, frames: int = 1) -> torch.Tensor:
    """(E, F, 5) per edge j -> i at frames t-1, .., t-F, where the window's finite-difference
    accelerations ``a[t-f-1] = (v[t-f] - v[t-f-1]) / dt`` are exact: ``log r_ij``,
    ``log |a_i|``, ``log |a_j|`` and both accelerations' cosines with the unit vector ``u_ij``
    from j to i. Positions at t-f-1 are ``x[t] - dt (v[t] + .. + v[t-f])`` (the backward
    differences, undone)."""
    snd, rcv = g.edge_index[0], g.edge_index[1]
    acc = window_accelerations(g, frames)
    prev = g.pos[:, None] - g.dt[g.batch][:, None, None] * torch.cumsum(g.vel[:, :frames], 1)
    rel = edge_vector(prev, g)
    r = torch.sqrt((rel * rel).sum(-1) + _EPS)
    a_norm = torch.sqrt((acc * acc).sum(-1) + _EPS)
    unit, a_unit = rel / r[..., None], acc / a_norm[..., None]
    return torch.stack([torch.log(r), torch.log(a_norm[rcv]), torch.log(a_norm[snd]),
                        (a_unit[rcv] * unit).sum(-1), (a_unit[snd] * unit).sum(-1)], -1)


class PairContext(nn.Module):
    """Pair terms for the flow's context: an edge MLP of ``pair_features`` at each of
    ``frames`` frames, summed over them and at the receiver and (a second half) at the
    sender, then a node MLP with the node's own ``log |a|`` at those frames; returns
    (N, hidden). More than the newest frame (``mass_context_frames``): an impact, whose
    momentum exchange gives the pair's mass ratio, shows wherever it falls in the window."""

    def __init__(self, hidden: int, act: str, frames: int = 1) -> None:
        super().__init__()
        self.hidden, self.frames = hidden, frames
        self.edge = nn.Sequential(Linear(PAIR_FEATURES, hidden), activation(act),
                                  nn.Linear(hidden, 2 * hidden))
        self.node = nn.Sequential(nn.Linear(2 * hidden + frames, hidden), activation(act),
                                  nn.Linear(hidden, hidden))
        self.edge_chunk: int | None = None            # set by PhysicsModel (its config)
        self.checkpoint_edges = CheckpointEdges()

    def forward(self, g: Graph) -> torch.Tensor:
        snd, rcv = g.edge_index[0], g.edge_index[1]
        n, h = len(g.vel), self.hidden
        features = pair_features(g, self.frames)                       # (E, F, features)
        # the edge MLP's last layer is linear, so it runs after the sums over frames and
        # at the nodes: sum_j sum_f (W s_ijf + b) = W (sum s) + F deg b; no (E, 2 hidden).
        # On large graphs the sums run in chunks of edges (``edge_chunk``): at 20 000 discs
        # the (E, hidden) activations and their gradients were most of BGN's peak memory
        sums = edge_sums(self._edge_hidden, self.edge[0].parameters(), features, g.edge_index,
                         n, self.edge_chunk, self.checkpoint_edges.above(features))
        w, b = self.edge[2].weight.split(h), self.edge[2].bias.split(h)
        to_rcv, to_snd = (
            F.linear(part, w_half)
            + features.shape[1] * torch.bincount(index, minlength=n).to(part.dtype)[:, None]
            * b_half
            for part, index, w_half, b_half in ((sums[0], rcv, w[0], b[0]),
                                                (sums[1], snd, w[1], b[1])))
        acc = window_accelerations(g, self.frames)
        log_a = 0.5 * torch.log((acc * acc).sum(-1) + _EPS)
        return self.node(torch.cat([to_rcv, to_snd, log_a], -1))

    def _edge_hidden(self, features: torch.Tensor) -> torch.Tensor:
        """(E, hidden): the edge MLP's hidden layer on (E, F, features), summed over frames."""
        return self.edge[1](self.edge[0](features)).sum(1)


class InverseModel(nn.Module):
    """Flow over normalised log-mass given ``H̃_V`` plus the bilinear relative-mass decoder.

    Everything here is in normalised units (``Normalizer.log_mass`` / ``rel_log_mass``).
    """

    def __init__(self, context: int, flow: str = "nsf", transforms: int = 3, hidden: int = 64,
                 act: str = "silu", conditioning: str = "node", dropout: float = 0.0,
                 frames: int = 1, fit_error: bool = False) -> None:
        super().__init__()
        if conditioning not in CONTEXTS:
            raise ValueError(f"mass_context={conditioning!r}; choose one of {CONTEXTS}")
        self.kind = flow
        self.pairs = PairContext(hidden, act, frames) if conditioning in ("pairs", "fit") else None
        self.uses_fit = conditioning == "fit"
        # under fit, also the fit's relative standard error (newton.PairForceHead.least_squares)
        self.fit_error = fit_error and self.uses_fit
        self.dropout = dropout
        fit_width = self.uses_fit + self.fit_error
        self.flow = make_flow(flow, context + (hidden if self.pairs else 0) + fit_width,
                              transforms, hidden)
        self.bilinear = nn.Bilinear(2, 2, hidden)     # Eq. 9 on [z, 1]
        self.act = activation(act)
        self.linear2 = nn.Linear(hidden, hidden)      # Eq. 10: W_Inv-Dec2
        self.linear3 = nn.Linear(hidden, 1)           # Eq. 10: W_Inv-Dec3
        self.edge_chunk: int | None = None            # set by PhysicsModel (its config)
        # knots (z, r) of the radius map, (2, K); none: the identity. Not persistent: fitted
        # after training on the validation split, not learned
        self.register_buffer("calibration", torch.empty(2, 0), persistent=False)
        self.checkpoint_edges = CheckpointEdges()

    def context(self, h_tilde_v: torch.Tensor, g: Graph,
                fitted_log_mass: torch.Tensor | None = None) -> torch.Tensor:
        """What the flow is conditioned on: ``H̃_V`` (Eq. 6), with the pair terms under
        ``pairs`` and ``fit``, and the force head's ``fitted_log_mass`` (N,) under ``fit``
        ((N, 2) with ``fit_error``: with the fit's relative error); dropout on it while
        training."""
        parts = [h_tilde_v] if self.pairs is None else [h_tilde_v, self.pairs(g)]
        if self.uses_fit:
            if fitted_log_mass is None:
                raise ValueError("mass_context=fit needs the structured head's fitted masses")
            parts.append(fitted_log_mass.detach().reshape(len(h_tilde_v), -1))
        return F.dropout(torch.cat(parts, -1), self.dropout, self.training)

    def forward(self, context: torch.Tensor, log_mass: torch.Tensor,
                noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Per particle: NLL of the normalised log-mass (Eq. 7-8) and one sample ``z_K``.

        ``noise`` (N,) is the base-distribution (standard normal) draw; pass it to make the
        sample reproducible (tests), else it is drawn here while training, and is 0 in eval
        mode: the posterior's median, so that Eq. 9-10 decode a point estimate of the relative
        masses (a random draw adds the posterior's width to their error:
        docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs").
        Returns ``(nll (N,), z (N,))``.
        """
        dist = self.flow(context)  # the context network runs once for both uses
        nll = -dist.log_prob(log_mass[:, None])
        if noise is None:
            noise = torch.randn_like(log_mass) if self.training else torch.zeros_like(log_mass)
        z = dist.transform.inv(noise[:, None]).squeeze(-1)  # rsample: differentiable
        return nll, z

    def relative(self, z: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        """Eq. 9-10 on edges: ``R̂_ij`` (E,) for edge j -> i (receiver minus sender); its
        (E, hidden) layers in chunks on very large graphs (``edge_chunk``)."""
        zt = torch.stack([z, torch.ones_like(z)], -1)              # [z, 1]
        return edge_chunks(self._relative, self.edge_chunk, (edge_index[1], edge_index[0]),
                           (zt,), self.checkpoint_edges.above(zt))

    def _relative(self, rcv: torch.Tensor, snd: torch.Tensor, zt: torch.Tensor) -> torch.Tensor:
        # s(Z_Kᵀ W1 Z_K): nn.Bilinear's own kernel is slow for 2 x 2 inputs on CPU; the same
        # map as a linear layer on the 4 products [z_i, 1] ⊗ [z_j, 1]
        outer = (zt.index_select(0, rcv)[:, :, None] * zt.index_select(0, snd)[:, None, :]
                 ).flatten(1)
        h = self.act(linear(outer, self.bilinear.weight.flatten(1), self.bilinear.bias))
        return self.linear3(self.act(self.linear2(h))).squeeze(-1)

    def _radius(self, x: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """The radius map ``m`` (or its inverse) at ``|x|`` with the sign of ``x``, and the
        map's slope there (piecewise linear between the knots, linear past the last)."""
        z, r = self.calibration.to(x.dtype)
        xp, fp = (r, z) if inverse else (z, r)
        a = x.abs()
        i = torch.searchsorted(xp, a.detach().contiguous()).clamp(1, len(xp) - 1)
        slope = (fp[i] - fp[i - 1]) / (xp[i] - xp[i - 1])
        return torch.sign(x) * (fp[i - 1] + slope * (a - xp[i - 1])), slope

    def log_density(self, context: torch.Tensor, log_mass: torch.Tensor) -> torch.Tensor:
        """(N,) log-density of the normalised ``log_mass`` (N,) under the calibrated posterior:
        the flow's, with the base density ``N(0, 1)`` at ``u`` replaced by that of ``u`` under
        the radius map, ``phi(m^-1(u)) / m'``."""
        dist = self.flow(context)
        log_p = dist.log_prob(log_mass[:, None])
        if not self.calibration.numel():
            return log_p
        u = dist.transform(log_mass[:, None]).squeeze(-1)
        e, slope = self._radius(u, inverse=True)
        return log_p + 0.5 * (u * u - e * e) + torch.log(slope)

    def base_value(self, context: torch.Tensor, log_mass: torch.Tensor) -> torch.Tensor:
        """(N,) the normalised log-mass mapped to the flow's base space (uncalibrated): standard
        normal across particles when the flow is calibrated (``bgn.metrics.fit_radius_map``)."""
        return self.flow(context).transform(log_mass[:, None]).squeeze(-1)

    def sample_log_mass(self, context: torch.Tensor, n: int) -> torch.Tensor:
        """``n`` samples of every particle's normalised log-mass under the calibrated
        posterior, shape (n, N)."""
        dist = self.flow(context)
        if not self.calibration.numel():
            return dist.sample((n,)).squeeze(-1)
        e = torch.randn((n, len(context), 1), dtype=context.dtype, device=context.device)
        return dist.transform.inv(self._radius(e, inverse=False)[0]).squeeze(-1)
