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
implicitly, which is why NAF is much slower to sample (DESIGN section 9).

What the flow is conditioned on (``context``): the paper's ``H̃_V`` alone, or with
``pairs`` (not in the paper) also pair terms of the observed accelerations, the quantities
that carry mass (DESIGN section 10). On spring ``m_i a_i`` is the mass-free spring force, so
``log m_i`` is a function of the pair geometry seen from ``a_i`` minus ``log |a_i|``; under
gravity ``a_i = sum_j m_j f(s_ij) u_ji`` holds ``m_j`` in the *neighbour's* acceleration, so a
particle needs messages from the edges where it is the sender. GCN layers that average
normalised features do not form such log-ratios of magnitudes from a few hundred training
masses; per edge, the log-distance, the log-magnitudes of both accelerations and their
cosines with the pair direction make them a smooth function an MLP learns.
Optional dropout on the context during training regularises a flow that sees few masses.

The bilinear map acts on ``[z, 1]``: with 1-D ``z`` alone, ``z_i W z_j`` is symmetric in (i, j)
and cannot represent the antisymmetric ``z_i - z_j``; the constant channel adds the linear terms
``z_i`` and ``z_j`` (homogeneous coordinates) at no other cost.
"""

from __future__ import annotations

import torch
import zuko
from torch import nn
from torch.nn import functional as F

from bgn.graph import Graph
from bgn.model.message_passing import edge_chunks
from bgn.model.ops import Linear, activation, linear

FLOWS = ("nsf", "naf")
CONTEXTS = ("node", "pairs")
PAIR_FEATURES = 5   # log r, log |a_i|, log |a_j|, cos(a_i, u_ij), cos(a_j, u_ij)
_EPS = 1e-12


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


def newest_acceleration(g: Graph) -> torch.Tensor:
    """(N, D) the window's newest finite-difference acceleration ``(v[t] - v[t-1]) / dt``, in
    physical units (the pair terms take its log-magnitude: no scale to learn)."""
    if g.dt is None:
        raise ValueError("pair terms need the frame spacing: the graph has no dt")
    return (g.vel[:, 0] - g.vel[:, 1]) / g.dt[g.batch][:, None]


def pair_features(g: Graph) -> torch.Tensor:
    """(E, 5) per edge j -> i at frame t-1, where the window's newest finite-difference
    acceleration ``a = (v[t] - v[t-1]) / dt`` is exact: ``log r_ij``, ``log |a_i|``,
    ``log |a_j|`` and both accelerations' cosines with the unit vector ``u_ij`` from j to i.
    Positions at t-1 are ``x[t] - dt v[t]`` (the backward difference, undone)."""
    snd, rcv = g.edge_index[0], g.edge_index[1]
    acc = newest_acceleration(g)
    prev = g.pos - g.dt[g.batch][:, None] * g.vel[:, 0]
    rel = prev[rcv] - prev[snd]
    r = torch.sqrt((rel * rel).sum(-1) + _EPS)
    a_norm = torch.sqrt((acc * acc).sum(-1) + _EPS)
    unit, a_unit = rel / r[:, None], acc / a_norm[:, None]
    return torch.stack([torch.log(r), torch.log(a_norm[rcv]), torch.log(a_norm[snd]),
                        (a_unit[rcv] * unit).sum(-1), (a_unit[snd] * unit).sum(-1)], -1)


class PairContext(nn.Module):
    """Pair terms for the flow's context: an edge MLP of ``pair_features``, summed at the
    receiver and (a second half) at the sender, then a node MLP with the node's own
    ``log |a|``; returns (N, hidden)."""

    def __init__(self, hidden: int, act: str) -> None:
        super().__init__()
        self.hidden = hidden
        self.edge = nn.Sequential(Linear(PAIR_FEATURES, hidden), activation(act),
                                  nn.Linear(hidden, 2 * hidden))
        self.node = nn.Sequential(nn.Linear(2 * hidden + 1, hidden), activation(act),
                                  nn.Linear(hidden, hidden))

    def forward(self, g: Graph) -> torch.Tensor:
        snd, rcv = g.edge_index[0], g.edge_index[1]
        n, h = len(g.vel), self.hidden
        first, act, last = self.edge
        s = act(first(pair_features(g)))                                # (E, hidden)
        # the edge MLP's last layer is linear, so it runs after the sums, per node:
        # sum_j (W s_ij + b) = W (sum_j s_ij) + deg b; no (E, 2 hidden) messages
        w, b = last.weight.split(h), last.bias.split(h)
        to_rcv, to_snd = (
            F.linear(s.new_zeros(n, h).index_add_(0, index, s), w_half)
            + torch.bincount(index, minlength=n).to(s.dtype)[:, None] * b_half
            for index, w_half, b_half in ((rcv, w[0], b[0]), (snd, w[1], b[1])))
        acc = newest_acceleration(g)
        log_a = 0.5 * torch.log((acc * acc).sum(-1, keepdim=True) + _EPS)
        return self.node(torch.cat([to_rcv, to_snd, log_a], -1))


class InverseModel(nn.Module):
    """Flow over normalised log-mass given ``H̃_V`` plus the bilinear relative-mass decoder.

    Everything here is in normalised units (``Normalizer.log_mass`` / ``rel_log_mass``).
    """

    def __init__(self, context: int, flow: str = "nsf", transforms: int = 3, hidden: int = 64,
                 act: str = "silu", conditioning: str = "node", dropout: float = 0.0) -> None:
        super().__init__()
        if conditioning not in CONTEXTS:
            raise ValueError(f"mass_context={conditioning!r}; choose one of {CONTEXTS}")
        self.kind = flow
        self.pairs = PairContext(hidden, act) if conditioning == "pairs" else None
        self.dropout = dropout
        self.flow = make_flow(flow, context + (hidden if self.pairs else 0), transforms, hidden)
        self.bilinear = nn.Bilinear(2, 2, hidden)     # Eq. 9 on [z, 1]
        self.act = activation(act)
        self.linear2 = nn.Linear(hidden, hidden)      # Eq. 10: W_Inv-Dec2
        self.linear3 = nn.Linear(hidden, 1)           # Eq. 10: W_Inv-Dec3
        self.edge_chunk: int | None = None            # set by PhysicsModel (its config)
        self.checkpoint_edges: int | None = None

    def context(self, h_tilde_v: torch.Tensor, g: Graph) -> torch.Tensor:
        """What the flow is conditioned on: ``H̃_V`` (Eq. 6), with the pair terms under
        ``pairs``; dropout on it while training."""
        c = h_tilde_v if self.pairs is None else torch.cat([h_tilde_v, self.pairs(g)], -1)
        return F.dropout(c, self.dropout, self.training)

    def forward(self, context: torch.Tensor, log_mass: torch.Tensor,
                noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Per particle: NLL of the normalised log-mass (Eq. 7-8) and one sample ``z_K``.

        ``noise`` (N,) is the base-distribution (standard normal) draw; pass it to make the
        sample reproducible (tests), else it is drawn here. Returns ``(nll (N,), z (N,))``.
        """
        dist = self.flow(context)  # the context network runs once for both uses
        nll = -dist.log_prob(log_mass[:, None])
        if noise is None:
            noise = torch.randn_like(log_mass)
        z = dist.transform.inv(noise[:, None]).squeeze(-1)  # rsample: differentiable
        return nll, z

    def relative(self, z: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        """Eq. 9-10 on edges: ``R̂_ij`` (E,) for edge j -> i (receiver minus sender); its
        (E, hidden) layers in chunks on very large graphs (``edge_chunk``)."""
        zt = torch.stack([z, torch.ones_like(z)], -1)              # [z, 1]
        return edge_chunks(self._relative, self.edge_chunk, (edge_index[1], edge_index[0]),
                           (zt,), self.checkpoint_edges)

    def _relative(self, rcv: torch.Tensor, snd: torch.Tensor, zt: torch.Tensor) -> torch.Tensor:
        # s(Z_Kᵀ W1 Z_K): nn.Bilinear's own kernel is slow for 2 x 2 inputs on CPU; the same
        # map as a linear layer on the 4 products [z_i, 1] ⊗ [z_j, 1]
        outer = (zt.index_select(0, rcv)[:, :, None] * zt.index_select(0, snd)[:, None, :]
                 ).flatten(1)
        h = self.act(linear(outer, self.bilinear.weight.flatten(1), self.bilinear.bias))
        return self.linear3(self.act(self.linear2(h))).squeeze(-1)

    def sample_log_mass(self, context: torch.Tensor, n: int) -> torch.Tensor:
        """``n`` samples of every particle's normalised log-mass, shape (n, N)."""
        return self.flow(context).sample((n,)).squeeze(-1)
