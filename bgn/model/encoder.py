"""Encoders (paper section "Encoder definition and design", Eq. 1).

- Node encoder ``E_V``: raw-residual GCN layers over the particles' own state.
- Edge (relation) encoder ``E_E``: a shared linear map of per-edge relative features (the paper's
  1x1 convolution over the ``N x (k+1) x |V| x |V|`` relative tensor) gives one weight per edge;
  weighted raw-residual GCN layers then give ``H_E``.

Positions enter only as differences ``x_i - x_j`` (receiver minus sender; by the minimum image
in a periodic scene, ``message_passing.edge_vector``), so both encoders are translation
invariant (on the torus too) unless ``use_absolute_position`` is set.
"""

from __future__ import annotations

from itertools import pairwise

import torch
from torch import nn

from bgn.graph import Graph
from bgn.model.message_passing import edge_difference, edge_vector
from bgn.model.normalizer import Normalizer
from bgn.model.ops import activation, gcn_aggregate, pad_features

WALL_CLIP = 5.0  # wall distances beyond this many interaction lengths carry no information
DIRECTION_EPS = 1e-6  # in normalised length units: coincident particles get direction 0, not NaN


def node_input_dim(dim: int, history: int, walls: bool, absolute_position: bool,
                   increments: bool = False) -> int:
    """Width of ``node_features``: velocity window, increments, wall distances, position."""
    return ((history + 1) * dim + (history * dim if increments else 0)
            + (2 * dim if walls else 0) + (dim if absolute_position else 0))


def edge_input_dim(dim: int, history: int) -> int:
    """Width of ``edge_features``: relative position, distance, direction, velocity window."""
    return dim + 1 + dim + (history + 1) * dim


def node_features(g: Graph, norm: Normalizer, walls: bool, absolute_position: bool = False,
                  box: float | None = None, increments: bool = False) -> torch.Tensor:
    """``H_V^0`` (N, F0): normalised velocity window flattened (newest first), optionally its
    increments v[t-l] - v[t-l-1] in their own scale, then the distances to the walls in
    interaction lengths (clipped), then optionally the position."""
    feats = [norm.velocity(g.vel).flatten(1)]
    if increments:
        feats.append(norm.velocity_increment(g.vel[:, :-1] - g.vel[:, 1:]).flatten(1))
    if walls:
        if g.wall is None:
            raise ValueError("the scene has walls but the graph carries no wall distances")
        feats.append(torch.clamp(norm.rel_position(g.wall), max=WALL_CLIP))
    if absolute_position:
        if g.period is not None:  # a torus has no origin: a coordinate jumps at the seam
            raise ValueError("model.use_absolute_position=true is undefined on a scene with "
                             "periodic boundaries; set model.use_absolute_position=false")
        feats.append(g.pos / box if box is not None else norm.rel_position(g.pos))
    return torch.cat(feats, dim=1)


def edge_geometry(g: Graph, norm: Normalizer) -> torch.Tensor:
    """(E, D+1): ``[x_i - x_j, |x_i - x_j|]`` (receiver minus sender) in relative-position
    units; the distance is ``sqrt(r^2 + eps^2)``: no NaN (value or gradient) for coincident
    particles. The first columns of ``edge_features``, and the baselines' edge features."""
    rel = norm.rel_position(edge_vector(g.pos, g))
    return torch.cat([rel, torch.sqrt((rel * rel).sum(-1, keepdim=True) + DIRECTION_EPS**2)],
                     dim=1)


def edge_features(g: Graph, norm: Normalizer) -> torch.Tensor:
    """Per-edge relative features (E, Fe), receiver minus sender: the paper's ``P_i - P_j``.

    ``[x_i - x_j, |x_i - x_j|, unit direction, v_i - v_j for each of the k+1 window steps]``,
    lengths in units of the relative-position scale, velocities in the relative-velocity scale.
    The unit direction is given explicitly so that a message linear in these features can carry
    a force direction (processor).
    """
    geometry = edge_geometry(g, norm)
    d = g.pos.shape[1]
    rel_vel = norm.rel_velocity(edge_difference(g.vel, g.edge_index)).flatten(1)
    return torch.cat([geometry, geometry[:, :d] / geometry[:, d:], rel_vel], dim=1)


def approach_gap(g: Graph) -> torch.Tensor:
    """(E,) how close each pair comes before the next frame if both keep their newest window
    velocity, as a fraction of their contact distance: ``min over tau in [0, dt] of
    |dx + dv tau| / (r_i + r_j) - 1`` (<= 0: they touch). The time-of-impact rule of the window
    alone (free flight; walls and other impacts ignored). Swap-symmetric; contact scenes only
    (it needs radii and the frame spacing ``g.dt``)."""
    if g.dt is None:
        raise ValueError("the approach gap needs the frame spacing: the graph has no dt")
    snd, rcv = g.edge_index[0], g.edge_index[1]
    dx = edge_vector(g.pos, g)
    dv = edge_difference(g.vel[:, 0], g.edge_index)
    dt = g.dt.to(dx.dtype)[g.batch[rcv]]
    speed2 = (dv * dv).sum(-1)
    tau = torch.minimum((-(dx * dv).sum(-1) / speed2.clamp_min(1e-30)).clamp_min(0.0), dt)
    closest = dx + dv * tau[:, None]
    reach = (g.radius[rcv] + g.radius[snd]).clamp_min(1e-12)
    return torch.sqrt((closest * closest).sum(-1) + DIRECTION_EPS**2) / reach - 1.0


def gap_features(gap: torch.Tensor) -> torch.Tensor:
    """(E, 2): the approach gap, clipped to [-1, 3], and the time-of-impact rule (gap <= 0)."""
    return torch.stack([gap.clamp(-1.0, 3.0), (gap <= 0).to(gap.dtype)], dim=1)


def symmetric_edge_width(history: int) -> int:
    """Width of ``symmetric_edge_features``."""
    return 1 + 2 * (history + 1)


def symmetric_edge_features(e: torch.Tensor, dim: int) -> torch.Tensor:
    """From ``edge_features``: the channels that do not change when i and j swap (E, 1+2(k+1)):
    distance, radial relative velocity ``u_ij . (v_i - v_j)`` and relative speed per window
    step. A contact label is symmetric, so these are what an edge term of it may use."""
    dist = e[:, dim:dim + 1]
    direction = e[:, dim + 1:2 * dim + 1]
    rel_vel = e[:, 2 * dim + 1:].unflatten(1, (-1, dim))            # (E, k+1, D)
    radial = (rel_vel * direction[:, None]).sum(-1)
    speed = torch.sqrt((rel_vel * rel_vel).sum(-1) + DIRECTION_EPS**2)
    return torch.cat([dist, radial, speed], 1)


class RawResidualGCN(nn.Module):
    """One raw-residual graph convolution, Eq. 1: ``H' = s(Â H W + Â H)``, ``Â = A + I``.

    When the width changes (first layer) the raw path ``Â H`` is zero-padded or truncated to the
    output width (``ops.pad_features``): a fixed linear projection. A learned one would merge
    with ``W`` and the raw features would no longer pass through.

    ``self_weight=True`` (not in the paper) adds ``H W_self``: on a complete graph ``Â`` is the
    all-ones matrix, so Eq. 1 alone gives every node of a graph the same features.
    """

    def __init__(self, in_features: int, out_features: int, act: str = "silu",
                 normalize: bool = False, self_weight: bool = False) -> None:
        super().__init__()
        self.out_features = out_features
        self.normalize = normalize
        self.linear = nn.Linear(in_features, out_features)  # W^l (with a bias)
        self.self_linear = (nn.Linear(in_features, out_features, bias=False)
                            if self_weight else None)
        self.act = activation(act)

    def forward(self, h: torch.Tensor, edge_index: torch.Tensor,
                edge_weight: torch.Tensor | None = None) -> torch.Tensor:
        ah = gcn_aggregate(h, edge_index, edge_weight, self.normalize)  # Â H
        z = self.linear(ah) + pad_features(ah, self.out_features)      # Eq. 1
        if self.self_linear is not None:
            z = z + self.self_linear(h)
        return self.act(z)


class NodeEncoder(nn.Module):
    """``E_V: [A, P] -> H_V``: ``layers`` raw-residual GCN layers on the unweighted graph."""

    def __init__(self, in_features: int, hidden: int, layers: int, act: str = "silu",
                 normalize: bool = False, self_weight: bool = False) -> None:
        super().__init__()
        widths = [in_features] + [hidden] * layers
        self.layers = nn.ModuleList(RawResidualGCN(a, b, act, normalize, self_weight)
                                    for a, b in pairwise(widths))

    def forward(self, x: torch.Tensor, edge_index: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = layer(x, edge_index)
        return x


class EdgeEncoder(nn.Module):
    """``E_E: [A, P_i - P_j] -> H_E``.

    The 1x1 convolution over the channels of the relative tensor is a linear map shared by all
    edges, ``w_ij = sigmoid(a . e_ij + b)``. The sigmoid keeps the learned adjacency a soft
    0/1 mask like the paper's ``A`` (contact or not): bounded weights keep the sums of the GCN
    bounded by the degree, even for the close encounters of the gravity scenes, where an
    unbounded squashing (softplus, exp) could explode.
    """

    def __init__(self, node_features: int, edge_features: int, hidden: int, layers: int,
                 act: str = "silu", normalize: bool = False, self_weight: bool = False) -> None:
        super().__init__()
        self.conv1x1 = nn.Linear(edge_features, 1)
        widths = [node_features] + [hidden] * layers
        self.layers = nn.ModuleList(RawResidualGCN(a, b, act, normalize, self_weight)
                                    for a, b in pairwise(widths))

    def edge_weight(self, e: torch.Tensor) -> torch.Tensor:
        """(E, Fe) relative features -> (E,) weights in (0, 1): the learned ``A``."""
        return torch.sigmoid(self.conv1x1(e)).squeeze(-1)

    def forward(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Node (N, F0) and edge (E, Fe) features -> (``H_E`` (N, hidden), weights (E,))."""
        w = self.edge_weight(e)
        h = x
        for layer in self.layers:
            h = layer(h, edge_index, w)  # Eq. 1 with Â = A_w + I
        return h, w
