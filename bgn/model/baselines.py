"""The two baselines of Table 1 (docs/design.md#baselines), built like BGN from
``(meta, stats, history)``.

- BS1 ``CranmerGN``: the graph network of Cranmer et al. 2020, "Discovering symbolic models from
  deep learning with inductive biases" (NeurIPS): an edge (message) MLP on both endpoints'
  features, sum aggregation at the receiver, a node MLP on ``[node features, summed messages]``
  predicting the target. Hidden width 300, message width 100, three hidden layers per MLP, ReLU.
- BS2 ``GNS``: the Graph Network-based Simulator of Sanchez-Gonzalez et al. 2020, "Learning to
  simulate complex physics with graph networks" (ICML): encode-process-decode with 2x128 MLPs
  and LayerNorm, 10 unshared interaction networks with residual node and edge updates, an MLP
  decoder without LayerNorm, random-walk Gaussian noise on the input velocities in training.

Both see what BGN sees (``encoder.node_features``: the normalised velocity window and, where the
scene has walls, the clipped wall distances; on edges the relative position and distance), never
masses, radii or types by default (the published GNS embeds particle types; this one reads them
only when asked). ``node_inputs`` gives them what BGN's structured heads read, as extra node
columns: "radius" (in the units of the relative positions on the edges, so that ``r_i + r_j``
compares with the edge's distance) and "type" (one-hot over the scene's types, where it has
several): "GNS + radii/types" beside "BGN + impulse head (radii)". ``oracle=True`` appends the
true normalised log-mass (and the one-hot type when the scene has several) and labels the model
"... (oracle)".
Positions enter only as differences (translation invariance); every graph operation is a gather
or an ``index_add_`` over the edge list (O(E)), run in blocks of edges on a CPU (``edge_block``:
``EdgeMLP.fused``, with the backward written out, for ReLU; ``EdgeMLP.blocks`` otherwise).
Targets are normalised by the same ``Normalizer`` methods as BGN's, so the ``dynamics`` losses
of all three models are in the same units.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F
from torch.utils.checkpoint import checkpoint

from bgn.graph import Graph
from bgn.model.base import DynamicsConfig, ModelOutput, PhysicsModel, check_positive_ints
from bgn.model.encoder import edge_geometry, node_features, node_input_dim
from bgn.model.message_passing import checkpointed
from bgn.model.noise import random_walk
from bgn.model.ops import EdgeMLP, activation, mlp

NODE_INPUTS = ("radius", "type")  # BaselineConfig.node_inputs
LABELS = {"cranmer_gn": "Cranmer GN", "gns": "GNS"}


# ----------------------------------------------------------------------------- configs
@dataclass
class BaselineConfig(DynamicsConfig):
    """Options both baselines share (see ``CranmerGNConfig``, ``GNSConfig``)."""

    # also feed the true log-mass (and one-hot type) to the nodes -> "<label> (oracle)"
    oracle: bool = False
    # what the structured heads read, as node features: "radius" (divided by the training
    # split's relative-position scale, the edges' unit) and/or "type" (one-hot; none on a
    # one-type scene, where it says nothing): -> "GNS + radii/types". Never masses (oracle).
    node_inputs: list[str] = field(default_factory=list)
    # the edge MLPs are most of a step: no recompute below a million edges (DynamicsConfig)
    checkpoint_edges: int | None = 1_000_000
    # On a CPU the edges run in blocks of this many (ops.EdgeMLP.fused with ReLU, else
    # EdgeMLP.blocks): no per-edge tensor of the whole graph. 8 192 was the fastest block size
    # for GNS's training step on large scenes (docs/notes/2026-11-26-results-history.md,
    # "The baselines' edge MLPs with their backward written out" and "Edge blocks for the
    # baselines").
    # null: one block.
    edge_block: int | None = 8192

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.edge_block is not None and not self.edge_block >= 1:
            raise ValueError(f"edge_block={self.edge_block} must be >= 1 (or null: one block)")
        unknown = [k for k in self.node_inputs if k not in NODE_INPUTS]
        if unknown or len(set(self.node_inputs)) != len(self.node_inputs):
            raise ValueError(f"node_inputs={list(self.node_inputs)}: each of {NODE_INPUTS} at "
                             "most once (masses: oracle=true)")
        self.node_inputs = [str(k) for k in self.node_inputs]


@dataclass
class CranmerGNConfig(BaselineConfig):
    """BS1 options (the schema of ``conf/model/cranmer_gn.yaml``); defaults are the published
    ones (Cranmer et al. 2020, their ``GN``). ``target_prior``, ``dynamics_loss``,
    ``huber_delta``: as BGN's (equal terms); ``target_prior=none dynamics_loss=mse`` is the
    published parameterisation."""

    hidden: int = 300          # width of every hidden layer (their `hidden`)
    message_dim: int = 100     # width of the messages, the edge MLP output (their `msg_dim`)
    hidden_layers: int = 3     # hidden layers per MLP, edge and node (their Seq of 4 Linear)
    activation: str = "relu"   # relu (theirs) | silu | gelu | tanh | softplus

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_ints(self, ("hidden", "message_dim", "hidden_layers"))
        activation(self.activation)  # raises ValueError on an unknown name


@dataclass
class GNSConfig(BaselineConfig):
    """BS2 options (the schema of ``conf/model/gns.yaml``); defaults follow Sanchez-Gonzalez
    et al. 2020 (section 3 and appendix). ``target_prior``, ``dynamics_loss``,
    ``huber_delta``: as BGN's (equal terms); ``target_prior=none dynamics_loss=mse`` is the
    published parameterisation.

    ``noise_std`` is the std of the training-only random-walk noise on the input velocity
    window, at the newest velocity, in *normalised* velocity units (as in their
    ``noise_utils``). Their default is 6.7e-4 in position units per step, against a per-step
    velocity std of about 1.35e-3 on their WaterDrop data (``metadata.json``): a ratio of 0.5,
    hence 0.5 here. Noise is on velocities only and the target is not shifted (BGN's loss,
    comparable): for next-velocity targets (collisions) this sets a floor of about
    ``noise_std**2 / (history + 1)`` (~0.04) on the normalised training MSE; lower it (e.g.
    0.05) or set 0 for one-step comparisons. Off in eval mode and in ``predict()``.
    """

    latent: int = 128                  # width of the node and edge latents
    mlp_hidden: int = 128              # width of the hidden layers of every MLP
    mlp_layers: int = 2                # hidden layers per MLP
    message_passing_steps: int = 10    # unshared interaction networks (their M = 10)
    activation: str = "relu"           # relu (theirs) | silu | gelu | tanh | softplus
    noise_std: float = 0.5

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_ints(self, ("latent", "mlp_hidden", "mlp_layers",
                                   "message_passing_steps"))
        if not self.noise_std >= 0.0:
            raise ValueError(f"noise_std={self.noise_std} must be >= 0")
        activation(self.activation)


# ----------------------------------------------------------------------------- building blocks
class Baseline(PhysicsModel):
    """What both baselines share: BGN's node inputs (plus oracle columns), edge geometry, and
    one dynamics head. Subclasses implement ``_target(x, e, edge_index)``: normalised node
    inputs (N, F) and edge inputs (E, D+1) -> normalised target (N, D)."""

    def build(self, cfg: CranmerGNConfig | GNSConfig, stats: Mapping[str, Any]) -> None:
        meta, history = self.meta, self.history
        self.oracle = cfg.oracle
        # one-hot types only carry information when there is more than one type
        several = meta.n_types > 1
        self.oracle_types = self.oracle and several
        self.radius_input = "radius" in cfg.node_inputs
        self.type_input = "type" in cfg.node_inputs and several and not self.oracle_types
        self.node_in = (node_input_dim(meta.dim, history, meta.has_walls, False)
                        + int(self.radius_input) + (meta.n_types if self.type_input else 0)
                        + (1 + (meta.n_types if self.oracle_types else 0) if self.oracle else 0))
        self.edge_in = meta.dim + 1

    @property
    def given(self) -> tuple[str, ...]:
        """"radii" and "types" of ``node_inputs`` (types where the scene has several), and
        "masses" (and types) with ``oracle``."""
        types = self.type_input or self.oracle_types
        return tuple(k for k, read in (("radii", self.radius_input), ("types", types),
                                       ("masses", self.oracle)) if read)

    @property
    def label(self) -> str:
        """"GNS" / "Cranmer GN", then what it is given ("GNS + radii/types"), "(oracle)"
        when the true masses are inputs."""
        given = "/".join(self.given)
        return (LABELS[self.name] + (f" + {given}" if given else "")
                + (" (oracle)" if self.oracle else ""))

    # ------------------------------------------------------------------ inputs
    def velocity_noise(self, g: Graph) -> torch.Tensor | None:
        """Training noise on the velocity window in normalised units, or None (none here)."""
        return None

    def node_inputs(self, g: Graph, noisy: bool = False) -> torch.Tensor:
        """(N, node_in): BGN's node features (velocity window, walls), then the ``node_inputs``
        columns (radius, one-hot type), then the oracle's (log-mass, one-hot type)."""
        noise = self.velocity_noise(g) if noisy else None
        if noise is not None:  # physical noise = normalised noise x velocity scale
            g = replace(g, vel=g.vel + noise * self.normalizer.velocity_scale)
        x = node_features(g, self.normalizer, self.meta.has_walls)
        feats = [x]
        if self.radius_input:  # a fixed scale: the same disc reads the same in every frame
            feats.append(self.normalizer.rel_position(g.radius)[:, None].to(x.dtype))
        if self.type_input:
            feats.append(F.one_hot(g.types, self.meta.n_types).to(x.dtype))
        if self.oracle:
            feats.append(self.normalizer.log_mass(torch.log(g.mass))[:, None].to(x.dtype))
            if self.oracle_types:
                feats.append(F.one_hot(g.types, self.meta.n_types).to(x.dtype))
        return torch.cat(feats, dim=1) if len(feats) > 1 else x

    def _target(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _run(self, g: Graph, noisy: bool) -> torch.Tensor:
        self.check(g)
        x = self.node_inputs(g, noisy)
        return self._target(x, edge_geometry(g, self.normalizer), g.edge_index)

    def forward(self, g: Graph) -> ModelOutput:
        """Normalised forward target of a graph (one frame or a batch); noise only in training."""
        return ModelOutput(self._run(g, noisy=self.training))

    def forward_target(self, g: Graph) -> torch.Tensor:
        return self._run(g, noisy=False)


# ----------------------------------------------------------------------------- BS1
class CranmerGN(Baseline):
    """BS1: the graph network of Cranmer et al. 2020 ("Discovering symbolic models from deep
    learning with inductive biases"), their standard (unregularised) variant.

    ``m_ij = phi_e([x_i, x_j, x_i - x_j, |x_i - x_j|])``, ``y_i = phi_v([x_i, sum_j m_ij])``.
    Their nodes carry absolute positions; here positions enter only as the relative position on the
    edge (translation invariance, docs/design.md#frames-and-targets), the same inputs BGN gets.
    """

    name = "cranmer_gn"
    config_class = CranmerGNConfig

    def build(self, cfg: CranmerGNConfig, stats: Mapping[str, Any]) -> None:
        super().build(cfg, stats)
        hidden = [cfg.hidden] * cfg.hidden_layers
        self.message = EdgeMLP(self.edge_in, self.node_in, [*hidden, cfg.message_dim],
                               cfg.activation)
        self.node = mlp([self.node_in + cfg.message_dim, *hidden, self.meta.dim], cfg.activation)

    def _target(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> torch.Tensor:
        aggregated = self.message.sum_at_receivers(e, x, edge_index, x.shape[0])
        return self.node(torch.cat([x, aggregated], dim=1))


# ----------------------------------------------------------------------------- BS2
class InteractionNetwork(nn.Module):
    """One GNS processor step: ``e' = e + phi_e([e, v_i, v_j])``,
    ``v' = v + phi_v([v, sum_j phi_e(...)])`` (residual updates, LayerNorm on both MLPs)."""

    def __init__(self, latent: int, hidden: list[int], act: str) -> None:
        super().__init__()
        self.edge = EdgeMLP(latent, latent, [*hidden, latent], act, layer_norm=True)
        self.node = mlp([2 * latent, *hidden, latent], act, layer_norm=True)

    def forward(self, v: torch.Tensor, e: list[torch.Tensor], edge_index: torch.Tensor,
                slices: list[slice]) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Node latents (N, latent) and the edge latents as blocks (``e[k]`` belongs to the
        edges ``edge_index[:, slices[k]]``; ``EdgeMLP.blocks``) -> both updated."""
        fused = self.edge.fused(e, v, edge_index, slices, residual=True)
        if fused is not None:
            summed, updated = fused
            return v + self.node(torch.cat([v, summed], dim=1)), updated
        rcv = edge_index[1]
        summed: torch.Tensor | None = None
        updated = []
        for s, e_block, de in zip(slices, e, self.edge.blocks(e, v, edge_index, slices),
                                  strict=True):
            if summed is None:
                summed = de.new_zeros(v.shape[0], de.shape[1])
            # nodes aggregate the *updated* edges, as graph_nets' InteractionNetwork does
            summed.index_add_(0, rcv[s], de)
            updated.append(e_block + de)
        assert summed is not None  # edge_blocks gives at least one (maybe empty) block
        return v + self.node(torch.cat([v, summed], dim=1)), updated


class GNS(Baseline):
    """BS2: the Graph Network-based Simulator of Sanchez-Gonzalez et al. 2020 ("Learning to
    simulate complex physics with graph networks").

    Encoder: node and edge MLPs to ``latent`` (+ LayerNorm); processor: ``message_passing_steps``
    unshared ``InteractionNetwork``s; decoder: MLP without LayerNorm to the normalised target.

    Training noise (``noise_std``): a random walk over the velocity window, as their
    ``get_random_walk_noise_for_position_sequence``: increments of std ``noise_std/sqrt(k+1)``
    summed from the oldest to the newest velocity, so the newest has std ``noise_std``.
    Unlike theirs, the noise is on velocities only (positions, hence edges, stay clean) and the
    target is not shifted to undo the noise on the newest velocity: the loss stays BGN's one-step
    loss (comparable), and for acceleration targets the shift would need dt, which the model does
    not know. For next-velocity targets (collisions) their shift is zero anyway.
    """

    name = "gns"
    config_class = GNSConfig

    def build(self, cfg: GNSConfig, stats: Mapping[str, Any]) -> None:
        super().build(cfg, stats)
        hidden, act, h = [cfg.mlp_hidden] * cfg.mlp_layers, cfg.activation, cfg.latent
        self.node_encoder = mlp([self.node_in, *hidden, h], act, layer_norm=True)
        self.edge_encoder = mlp([self.edge_in, *hidden, h], act, layer_norm=True)
        self.processor = nn.ModuleList(InteractionNetwork(h, hidden, act)
                                       for _ in range(cfg.message_passing_steps))
        self.decoder = mlp([h, *hidden, self.meta.dim], act)

    def velocity_noise(self, g: Graph) -> torch.Tensor | None:
        """(N, k+1, D) random-walk noise, newest first, in normalised units (None if std 0)."""
        if self.cfg.noise_std <= 0.0:
            return None
        return random_walk(tuple(g.vel.shape), self.cfg.noise_std, g.vel)

    def _target(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> torch.Tensor:
        # the edge latents live in blocks from the encoder on (EdgeMLP.block_slices)
        edge = self.processor[0].edge
        slices = edge.block_slices(e)
        # Above the checkpointing threshold the (E, latent) edge latents of every step would
        # not fit (200 000 discs: 1.5 GB each, eleven of them, and the encoder's activations):
        # only every SEGMENT-th step's latents are kept, and the steps between them are
        # recomputed in the backward pass; the edge MLPs inside recompute their blocks too.
        recompute = torch.is_grad_enabled() and checkpointed(
            edge_index.shape[1], edge.edge_chunk, edge.checkpoint_edges.above(x))

        def run(fn, *args):
            return checkpoint(fn, *args, use_reentrant=False) if recompute else fn(*args)

        v, h_e = self.node_encoder(x), [run(self.edge_encoder, e[s]) for s in slices]
        for start in range(0, len(self.processor), self.SEGMENT):
            v, *h_e = run(self._steps, start, edge_index, slices, v, *h_e)
        return self.decoder(v)

    # processor steps per checkpointed segment on graphs above the checkpointing threshold
    SEGMENT = 2

    def _steps(self, start: int, edge_index: torch.Tensor, slices: list[slice],
               v: torch.Tensor, *h_e: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Processor steps ``start`` to ``start + SEGMENT`` (one checkpointed segment)."""
        blocks = list(h_e)
        for step in self.processor[start:start + self.SEGMENT]:
            v, blocks = step(v, blocks, edge_index, slices)
        return (v, *blocks)
