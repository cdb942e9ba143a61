"""Processor (paper section "Processor definition and design", Eq. 2-4).

- Particle-type classifier, Eq. 2: ``Ŷ = softmax(H_V W)``, ``H̃_V = H_V ‖ Ŷ``; built only when
  the scene has more than one particle type.
- Contact decoder, Eq. 3: ``ĉ_ij = <h_E,i, h_E,j> / sqrt(F)`` per edge. The ``1/sqrt(F)`` (a
  constant) keeps initial logits O(1) so the sigmoid does not start saturated.
- ``H̃_CV``: the paper concatenates row i of the N x N matrix ``Ĉ`` to ``H̃_V``, which ties the
  model to one N. Here (``contact_mode="aggregate"``) a contact-weighted sum of edge messages,
  ``sum_j ĉ_ij m_ij``, is concatenated instead; ``contact_mode="dense"`` keeps the literal rows
  as an ablation for full graphs with a fixed N.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from bgn.graph import Graph
from bgn.model.base import OptionGroup
from bgn.model.encoder import (
    approach_gap,
    gap_features,
    symmetric_edge_features,
    symmetric_edge_width,
)
from bgn.model.message_passing import edge_dot
from bgn.model.ops import EdgeMLP, scatter_sum

CONTACT_MODES = ("aggregate", "dense")
MESSAGES = ("linear", "mlp", "vector")
FORCE_TRANSFORMS = ("log1p", "linear")


@dataclass
class ContactOptions(OptionGroup):
    """The contact decoder's options (``ContactHead``, Eq. 3-4; ``bgn.model.bgn.ModelConfig``
    composes them): how its logits are formed, what its weighted sum carries, its target and
    its loss. ``contact`` (in ``ModelConfig``) switches the head itself."""

    # aggregate (sparse, any N) | dense (the paper's literal C || H_V; fixed-N full graphs)
    contact_mode: str = "aggregate"
    # Not in the paper: add a linear term of the swap-symmetric edge features (distance, radial
    # and total relative speed) to the contact logit <h_E,i, h_E,j>. Node embeddings that do
    # not know positions cannot say from an inner product alone whether two particles touch.
    contact_edge_term: bool = True
    # Not in the paper, contact scenes: + the window's time-of-impact features in that edge
    # term (how close each pair comes within the next frame in free flight, against the sum
    # of the radii, and the rule "they touch"): encoder.approach_gap.
    contact_gap: bool = False
    # What the contact-weighted aggregation sums (ContactHead): "linear", a linear map of the
    # edge features (our reading of the paper), or "mlp", an edge MLP that also reads both
    # particles' H̃_V and can express an elastic impulse, or "vector", an edge MLP whose
    # outputs weigh the edge's own vectors (direction, relative velocities): a D-vector
    # impulse added to the decoded target (docs/design.md#departures-from-the-paper).
    # collisions defaults to "vector" (conf/dataset_model/collisions_bgn.yaml).
    contact_message: str = "linear"
    # Force scenes: the contact target is |F_ij| / robust scale, compressed by log1p so that
    # the heavy tail of close encounters does not dominate; "linear" = paper MSE
    # (docs/design.md#departures-from-the-paper).
    force_transform: str = "log1p"     # "log1p" | "linear"
    # Contact scenes: weight of the positive class in the contact BCE. 1 = the paper's plain
    # BCE, chosen on validation against "balanced" (docs/results.md, "The paper decoder's
    # contact class weight re-checked on validation"); "balanced" = (1 - p) / p with p the
    # training split's contact fraction (base.contact_pos_weight); a number sets it. Typed Any
    # for Hydra (OmegaConf's Union[str, float] refuses the int that
    # `model.contact_pos_weight=1` parses to); __post_init__ checks it.
    contact_pos_weight: Any = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.contact_mode not in CONTACT_MODES:
            raise ValueError(f"contact_mode={self.contact_mode!r}; choose one of "
                             f"{CONTACT_MODES}")
        if self.contact_message not in MESSAGES:
            raise ValueError(f"contact_message={self.contact_message!r}; choose one of "
                             f"{MESSAGES}")
        if self.force_transform not in FORCE_TRANSFORMS:
            raise ValueError(f"force_transform={self.force_transform!r}; use log1p or linear")
        if self.contact_pos_weight != "balanced" and not float(self.contact_pos_weight) > 0:
            raise ValueError(f"contact_pos_weight={self.contact_pos_weight!r}; use 'balanced' "
                             "or a positive number")


class TypeClassifier(nn.Module):
    """Eq. 2: type logits ``H_V W`` (softmax / cross-entropy applied by the loss)."""

    def __init__(self, hidden: int, n_types: int) -> None:
        super().__init__()
        self.linear = nn.Linear(hidden, n_types)

    def forward(self, h_v: torch.Tensor) -> torch.Tensor:
        return self.linear(h_v)


def check_full_graph(g: Graph, n: int) -> None:
    """Raise a clear error unless every graph in the batch is complete with exactly n nodes."""
    counts = g.num_nodes.tolist()
    n_edges = int(g.edge_index.shape[1])
    if any(c != n for c in counts) or n_edges != len(counts) * n * (n - 1):
        raise ValueError(
            f"contact_mode='dense' concatenates rows of the N x N contact matrix and needs "
            f"complete graphs of exactly N={n} particles; got graphs of {sorted(set(counts))} "
            f"nodes with {n_edges} edges in all. Use contact_mode='aggregate' for radius "
            f"graphs or a varying number of particles.")


class ContactHead(nn.Module):
    """Contact decoder (Eq. 3) and the contact-weighted aggregation that replaces ``Ĉ ‖ H_V``.

    Message ``m_ij = W_m e_ij + b_m``: a linear map of the edge's relative features (relative
    position, distance, unit direction, relative velocities). It is linear on purpose: then

        sum_j ĉ_ij m_ij = W_m (sum_j ĉ_ij e_ij) + b_m sum_j ĉ_ij,

    so only the narrow ``e_ij`` (about 16 channels) is gathered and scattered per edge and the
    wide map is applied per node (O(E Fe + N Fe M) instead of O(E M)). With ``ĉ_ij`` a force
    magnitude and the unit direction in ``e_ij``, ``sum_j ĉ_ij u_ij`` is a net force.

    ``message="mlp"`` (not in the paper) makes ``m_ij = MLP(e_ij, h̃_V,i, h̃_V,j)`` instead, one
    hidden layer. An elastic impulse, ``-2 m_j / (m_i + m_j) ((v_i - v_j) . u_ij) u_ij``, is a
    product of edge features and of both particles' masses (their types): a linear message
    cannot carry it, and the decoder sees only the sum over contacts. Costs one edge MLP,
    O(E M), where the linear message costs O(E Fe).

    ``message="vector"`` (not in the paper) builds the impulse itself: an edge MLP of
    ``(e_ij, h̃_V,i, h̃_V,j)`` gives scalar coefficients ``a_ijb`` on the edge's own vectors
    ``g_ijb`` (relative position, unit direction, relative velocity at each window step), and
    ``m_ij = sum_b a_ijb g_ijb`` is a D-vector. An elastic impulse has this form exactly:
    ``-2 m_j / (m_i + m_j) ((v_i - v_j) . n) n`` with the contact normal ``n`` at the impact,
    which within a frame lies in the span of ``x_i - x_j`` and ``v_i - v_j``; and so does a
    pairwise force ``f(r) u_ij``. The MLP then learns scalars of scalars (distance, speeds,
    types) instead of a product with a direction. ``sum_j ĉ_ij m_ij`` (N, D) is added to the
    decoded target (``ProcessorOutput.impulse``) and fed to the decoder. Costs one edge MLP.
    """

    def __init__(self, h_e_features: int, edge_features: int, message_features: int | None,
                 probability: bool, edge_term: int | None = None,
                 message: str = "linear", node_features: int = 0, act: str = "silu",
                 dim: int = 0, gap: bool = False) -> None:
        super().__init__()
        if message not in MESSAGES:
            raise ValueError(f"contact message={message!r}; choose one of {MESSAGES}")
        if (message == "vector" or edge_term is not None) and dim < 1:
            raise ValueError("a vector contact message and the contact edge term need the "
                             "spatial dimension (dim >= 1)")
        self.inv_sqrt_f = 1.0 / math.sqrt(h_e_features)
        self.probability = probability  # contact scenes: sigmoid of the logits
        self.kind, self.dim = message, dim
        self.message: nn.Module | None = None
        if message_features is not None:
            if message == "linear":
                self.message = nn.Linear(edge_features, message_features)
            elif message == "mlp":
                self.message = EdgeMLP(edge_features, node_features,
                                       [message_features, message_features], act)
            else:  # one coefficient per edge vector (edge_vectors)
                n_vectors = (edge_features - 1) // dim
                self.message = EdgeMLP(edge_features, node_features,
                                       [message_features, message_features, n_vectors], act)
        # Optional (not in the paper): + a . s_ij, s_ij the swap-symmetric edge features
        # (distance, radial and total relative speed). ``edge_term`` = the history k when enabled.
        # ``gap`` (not in the paper, contact scenes): + the time-of-impact features of the
        # window (encoder.approach_gap), which the inner product and the linear edge term
        # cannot form (a closest approach within the frame, against the sum of the radii).
        if gap and edge_term is None:
            raise ValueError("the approach-gap features enter through the contact edge term: "
                             "set contact_edge_term=true with contact_gap=true")
        self.gap = gap
        self.edge_term = None
        if edge_term is not None:
            self.edge_term = nn.Linear(symmetric_edge_width(edge_term) + (2 if gap else 0), 1)

    def logits(self, h_e: torch.Tensor, edge_index: torch.Tensor,
               e: torch.Tensor | None = None, gap: torch.Tensor | None = None) -> torch.Tensor:
        """Eq. 3 on edges: ``ĉ_ij = <h_E,i, h_E,j> / sqrt(F)`` (E,) [+ the edge term of the
        symmetric edge features and, with ``gap``, the approach-gap features]."""
        # a sampled product: no (E, F) gathers forward or backward (message_passing)
        c = edge_dot(h_e, h_e, edge_index) * self.inv_sqrt_f
        if self.edge_term is not None:
            assert e is not None
            s = symmetric_edge_features(e, self.dim)
            if self.gap:
                assert gap is not None
                s = torch.cat([s, gap_features(gap).to(s.dtype)], dim=1)
            c = c + self.edge_term(s).squeeze(-1)
        return c

    def weights(self, c: torch.Tensor) -> torch.Tensor:
        """Contact estimate used downstream: probability (contact scenes) or magnitude."""
        return torch.sigmoid(c) if self.probability else c

    def aggregate(self, c: torch.Tensor, e: torch.Tensor, edge_index: torch.Tensor,
                  h: torch.Tensor) -> torch.Tensor:
        """``sum over edges j -> i of weights(ĉ_ij) m_ij`` (N, M); a linear message goes via
        linearity (class doc). ``h``: node features (N, F) that an MLP message also reads."""
        assert self.message is not None
        rcv, n = edge_index[1], h.shape[0]
        w = self.weights(c)
        if self.kind == "vector":
            coef = self.message(e, h, edge_index)                       # (E, B)
            vec = (coef[:, :, None] * edge_vectors(e, self.dim)).sum(1)  # (E, D)
            return scatter_sum(w[:, None] * vec, rcv, n)
        if self.kind == "mlp":
            return scatter_sum(w[:, None] * self.message(e, h, edge_index), rcv, n)
        weighted = scatter_sum(w[:, None] * e, rcv, n)        # sum_j ĉ_ij e_ij
        total = scatter_sum(w, rcv, n)                        # sum_j ĉ_ij
        return nn.functional.linear(weighted, self.message.weight) \
            + total[:, None] * self.message.bias

    def dense_rows(self, c: torch.Tensor, h_e: torch.Tensor, g: Graph, n: int) -> torch.Tensor:
        """Rows of the literal N x N matrix ``Ĉ = H_E H_Eᵀ`` (N_total, n), ablation only.

        Row i, column j (j local to i's graph) is ``weights(ĉ_ij)``; the diagonal is
        ``weights(<h_E,i, h_E,i> / sqrt(F))``, as in the paper's full matrix product (no edge
        term there: a particle is no edge of itself).
        """
        check_full_graph(g, n)
        snd, rcv = g.edge_index[0], g.edge_index[1]
        local = g.local_index
        rows = h_e.new_zeros(h_e.shape[0], n)
        rows[rcv, local[snd]] = self.weights(c)
        diag = (h_e * h_e).sum(-1) * self.inv_sqrt_f
        rows[torch.arange(h_e.shape[0], device=h_e.device), local] = self.weights(diag)
        return rows


def edge_vectors(e: torch.Tensor, dim: int) -> torch.Tensor:
    """The D-vectors among ``encoder.edge_features`` (E, B, D): relative position, unit
    direction and the relative velocity of each window step (all but the distance)."""
    return torch.cat([e[:, :dim], e[:, dim + 1:]], 1).unflatten(1, (-1, dim))


@dataclass
class ProcessorOutput:
    h_tilde_v: torch.Tensor            # (N, F_V)  H_V ‖ Ŷ: context of the inverse model
    h_cv: torch.Tensor                 # (N, F_CV) input of the forward decoder
    type_logits: torch.Tensor | None   # (N, n_types)
    contact: torch.Tensor | None       # (E,) contact logits (contact scenes) or magnitudes
    impulse: torch.Tensor | None = None  # (N, D) sum_j ĉ_ij m_ij of a vector message


class Processor(nn.Module):
    """Classifier (if several types), contact decoder (if ``contact``) and ``H̃_CV``.

    Without the contact head the decoder sees ``H̃_V ‖ H_E``, so relative information still
    reaches it through the edge encoder.
    """

    def __init__(self, hidden: int, edge_features: int, n_types: int, n_particles: int,
                 contact_scene: bool, classifier: bool = True, contact: bool = True,
                 contact_mode: str = "aggregate", contact_edge_term: int | None = None,
                 message: str = "linear", act: str = "silu", dim: int = 0,
                 contact_gap: bool = False, decode: bool = True) -> None:
        super().__init__()
        if contact_mode not in CONTACT_MODES:
            raise ValueError(f"contact_mode={contact_mode!r}; choose one of {CONTACT_MODES}")
        self.contact_mode = contact_mode
        self.n_particles = n_particles
        self.classifier = TypeClassifier(hidden, n_types) if classifier and n_types > 1 else None
        self.tilde_v_features = hidden + (n_types if self.classifier is not None else 0)
        # decode=False: no forward decoder reads H̃_CV (BGN's structured dynamics head), so
        # the contact-weighted messages are not built (unused weights would also stop DDP)
        self.decode = decode
        self.contact = None
        if contact:
            width = hidden if contact_mode == "aggregate" and decode else None
            self.contact = ContactHead(hidden, edge_features, width, contact_scene,
                                       contact_edge_term, message, self.tilde_v_features, act,
                                       dim, contact_gap)
        if self.contact is None:
            extra = hidden                                     # H_E
        elif contact_mode == "dense":
            extra = n_particles                                # row of Ĉ
        elif message == "vector":
            extra = dim                                        # sum_j ĉ_ij m_ij, a D-vector
        else:
            extra = hidden                                     # sum_j ĉ_ij m_ij
        self.out_features = self.tilde_v_features + extra

    def forward(self, h_v: torch.Tensor, h_e: torch.Tensor | None, e: torch.Tensor | None,
                g: Graph) -> ProcessorOutput:
        type_logits = None
        h_tilde_v = h_v
        if self.classifier is not None:
            type_logits = self.classifier(h_v)
            h_tilde_v = torch.cat([h_v, torch.softmax(type_logits, -1)], -1)  # H_V ‖ Ŷ
        contact = impulse = None
        if self.contact is not None:
            assert h_e is not None and e is not None
            gap = approach_gap(g) if self.contact.gap else None
            contact = self.contact.logits(h_e, g.edge_index, e, gap)
        if not self.decode:
            h_cv = h_tilde_v
        elif self.contact is None:
            assert h_e is not None
            h_cv = torch.cat([h_tilde_v, h_e], -1)
        elif self.contact_mode == "dense":  # literal Ĉ_i ‖ H̃_V
            assert h_e is not None and contact is not None
            rows = self.contact.dense_rows(contact, h_e, g, self.n_particles)
            h_cv = torch.cat([rows, h_tilde_v], -1)
        else:
            assert contact is not None and e is not None
            agg = self.contact.aggregate(contact, e, g.edge_index, h_tilde_v)
            h_cv = torch.cat([h_tilde_v, agg], -1)
            if self.contact.kind == "vector":
                impulse = agg
        return ProcessorOutput(h_tilde_v, h_cv, type_logits, contact, impulse)
