"""The two baselines of Table 1 (DESIGN section 6), built like BGN from ``(meta, stats, history)``.

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
masses or types, unless ``oracle=True``, which appends the true normalised log-mass (and the
one-hot type when the scene has several) to the node inputs and labels the model ``...+oracle``.
Positions enter only as differences (translation invariance); every graph operation is a gather
or a ``scatter_sum`` over the edge list (O(E)). Targets are normalised by the same ``Normalizer``
methods as BGN's, so the ``dynamics`` losses of all three models are in the same units.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from bgn.data.batch import Graph
from bgn.model.encoder import DIRECTION_EPS, node_features, node_input_dim
from bgn.model.normalizer import Normalizer
from bgn.model.ops import EdgeMLP, activation, mlp, scatter_sum
from bgn.model.target import TargetCoder
from bgn.sim.scene import SceneMeta


# ----------------------------------------------------------------------------- configs
@dataclass
class CranmerGNConfig:
    """BS1 options; defaults are the published ones (Cranmer et al. 2020, their ``GN``)."""

    hidden: int = 300          # width of every hidden layer
    message_dim: int = 100     # width of the messages (edge MLP output)
    hidden_layers: int = 3     # hidden layers per MLP (edge and node)
    activation: str = "relu"
    oracle: bool = False       # also feed true log-mass (and one-hot type) to the nodes
    # what the head predicts and its loss, as BGN's (bgn.model.target): equal terms
    target_prior: str = "auto"
    dynamics_loss: str = "auto"
    huber_delta: float = 1.0

    def __post_init__(self) -> None:
        _check_positive(self, ("hidden", "message_dim", "hidden_layers"))
        activation(self.activation)  # raises ValueError on an unknown name


@dataclass
class GNSConfig:
    """BS2 options; defaults follow Sanchez-Gonzalez et al. 2020 (section 3 and appendix).

    ``noise_std`` is the std of the noise on the newest input velocity in *normalised* velocity
    units (random walk over the window, as in their ``noise_utils``). Their default is 6.7e-4 in
    position units per step, against a per-step velocity std of about 1.35e-3 on their WaterDrop
    data (``metadata.json``): a ratio of 0.5, hence 0.5 here.
    """

    latent: int = 128                  # width of the node and edge latents
    mlp_hidden: int = 128              # width of the hidden layers of every MLP
    mlp_layers: int = 2                # hidden layers per MLP
    message_passing_steps: int = 10    # unshared interaction networks
    activation: str = "relu"
    noise_std: float = 0.5
    oracle: bool = False
    target_prior: str = "auto"         # as BGN's (bgn.model.target): equal terms
    dynamics_loss: str = "auto"
    huber_delta: float = 1.0

    def __post_init__(self) -> None:
        _check_positive(self, ("latent", "mlp_hidden", "mlp_layers", "message_passing_steps"))
        if not self.noise_std >= 0.0:
            raise ValueError(f"noise_std={self.noise_std} must be >= 0")
        activation(self.activation)


def _check_positive(cfg: Any, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name}={value!r} must be a positive integer")


def config_from_params(cls: type, params: Mapping[str, Any], model: str) -> Any:
    """``cls(**params)`` without ``name``; an unknown key (a typo in a yaml file) is an error."""
    known = {f.name for f in fields(cls)}
    values = {k: v for k, v in params.items() if k != "name"}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown {model} model options {unknown}; known: {sorted(known)}")
    return cls(**values)


# ----------------------------------------------------------------------------- building blocks
def edge_geometry(g: Graph, norm: Normalizer) -> torch.Tensor:
    """(E, D+1): ``[x_i - x_j, |x_i - x_j|]`` (receiver minus sender) in relative-position units.

    GNS's edge features (their relative displacement and its norm); the same lengths BGN uses.
    The distance is softened like BGN's so that coincident particles give no NaN gradient.
    """
    snd, rcv = g.edge_index[0], g.edge_index[1]
    rel = norm.rel_position(g.pos[rcv] - g.pos[snd])
    dist = torch.sqrt((rel * rel).sum(-1, keepdim=True) + DIRECTION_EPS**2)
    return torch.cat([rel, dist], dim=1)


@dataclass
class BaselineOutput:
    """Same fields as ``BGNOutput``; a baseline has only the forward head, the rest is None."""

    target: torch.Tensor                         # (N, D) normalised forward target
    type_logits: torch.Tensor | None = None
    contact: torch.Tensor | None = None
    mass_nll: torch.Tensor | None = None
    relmass: torch.Tensor | None = None
    log_mass_sample: torch.Tensor | None = None
    edge_weight: torch.Tensor | None = None


class Baseline(nn.Module):
    """What both baselines share with BGN's API: inputs, normalisation, loss and prediction.

    Subclasses implement ``_target(x, e, edge_index)``: normalised node inputs (N, F) and edge
    inputs (E, D+1) -> normalised target (N, D). ``history`` is k (window of k+1 velocities).
    """

    model_name = "baseline"

    def __init__(self, meta: SceneMeta, stats: Mapping[str, Any], history: int,
                 oracle: bool, target_prior: str = "none", dynamics_loss: str = "mse",
                 huber_delta: float = 1.0) -> None:
        super().__init__()
        self.meta, self.history, self.oracle = meta, history, oracle
        self.normalizer = Normalizer(stats, meta.dim)
        self.target_coder = TargetCoder(self.normalizer, stats, meta, history, target_prior,
                                        dynamics_loss, huber_delta)
        # one-hot types only carry information when there is more than one type
        self.oracle_types = oracle and meta.n_types > 1
        self.node_in = (node_input_dim(meta.dim, history, meta.has_walls, False)
                        + (1 + (meta.n_types if self.oracle_types else 0) if oracle else 0))
        self.edge_in = meta.dim + 1
        self.label = self.model_name + ("+oracle" if oracle else "")
        self.heads = frozenset({"dynamics"})  # the loss keys this model produces

    @property
    def name(self) -> str:
        """``cranmer_gn`` / ``gns``, with ``+oracle`` when masses and types are inputs."""
        return self.label

    # ------------------------------------------------------------------ inputs
    def _check(self, g: Graph) -> None:
        if g.vel.shape[1] != self.history + 1 or g.vel.shape[2] != self.meta.dim:
            raise ValueError(f"graph velocity window {tuple(g.vel.shape[1:])} does not match "
                             f"the model's (history + 1, dim) = "
                             f"({self.history + 1}, {self.meta.dim})")

    def velocity_noise(self, g: Graph) -> torch.Tensor | None:
        """Training noise on the velocity window in normalised units, or None (none here)."""
        return None

    def node_inputs(self, g: Graph, noisy: bool = False) -> torch.Tensor:
        """(N, node_in): BGN's node features (velocity window, walls), then oracle columns."""
        noise = self.velocity_noise(g) if noisy else None
        if noise is not None:  # physical noise = normalised noise x velocity scale
            g = replace(g, vel=g.vel + noise * self.normalizer.velocity_scale)
        x = node_features(g, self.normalizer, self.meta.has_walls)
        if self.oracle:
            feats = [x, self.normalizer.log_mass(torch.log(g.mass))[:, None].to(x.dtype)]
            if self.oracle_types:
                feats.append(F.one_hot(g.types, self.meta.n_types).to(x.dtype))
            x = torch.cat(feats, dim=1)
        return x

    def _target(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError

    def _run(self, g: Graph, noisy: bool) -> torch.Tensor:
        self._check(g)
        x = self.node_inputs(g, noisy)
        return self._target(x, edge_geometry(g, self.normalizer), g.edge_index)

    def forward(self, g: Graph) -> BaselineOutput:
        """Normalised forward target of a graph (one frame or a batch); noise only in training."""
        return BaselineOutput(self._run(g, noisy=self.training))

    # ------------------------------------------------------------------ losses
    def loss_terms(self, g: Graph, out: BaselineOutput) -> dict[str, torch.Tensor]:
        """``{"dynamics": loss}`` in the head's units, exactly as BGN's ``L_Dec``."""
        return {"dynamics": self.target_coder.loss(out.target, g)}

    def total_loss(self, terms: Mapping[str, torch.Tensor]) -> torch.Tensor:
        if not terms:
            raise ValueError("no loss terms to sum")
        return torch.stack(list(terms.values())).sum()

    # ------------------------------------------------------------------ inference
    def normalized_target(self, g: Graph) -> torch.Tensor:
        """The graph's target in the model's (normalised) units, (N, D)."""
        return self.target_coder.encode(g)

    def denormalize_target(self, target: torch.Tensor, g: Graph) -> torch.Tensor:
        """``BaselineOutput.target`` of graph ``g`` -> physical units."""
        return self.target_coder.decode(g, target)

    def predict(self, g: Graph) -> torch.Tensor:
        """Forward target in physical units, (N, D), never with noise (rollouts, figures)."""
        return self.target_coder.decode(g, self._run(g, noisy=False))


# ----------------------------------------------------------------------------- BS1
class CranmerGN(Baseline):
    """BS1: the graph network of Cranmer et al. 2020 ("Discovering symbolic models from deep
    learning with inductive biases"), their standard (unregularised) variant.

    ``m_ij = phi_e([x_i, x_j, x_i - x_j, |x_i - x_j|])``, ``y_i = phi_v([x_i, sum_j m_ij])``.
    Their nodes carry absolute positions; here positions enter only as the relative position
    on the edge (translation invariance, DESIGN section 2), the same inputs BGN gets.
    """

    model_name = "cranmer_gn"

    def __init__(self, meta: SceneMeta, stats: Mapping[str, Any], history: int,
                 cfg: CranmerGNConfig | None = None) -> None:
        cfg = cfg or CranmerGNConfig()
        super().__init__(meta, stats, history, cfg.oracle, cfg.target_prior,
                         cfg.dynamics_loss, cfg.huber_delta)
        self.cfg = cfg
        hidden = [cfg.hidden] * cfg.hidden_layers
        self.message = EdgeMLP(self.edge_in, self.node_in, [*hidden, cfg.message_dim],
                               cfg.activation)
        self.node = mlp([self.node_in + cfg.message_dim, *hidden, meta.dim], cfg.activation)

    def _target(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> torch.Tensor:
        m = self.message(e, x, edge_index)
        aggregated = scatter_sum(m, edge_index[1], x.shape[0])   # sum at the receiver
        return self.node(torch.cat([x, aggregated], dim=1))


# ----------------------------------------------------------------------------- BS2
class InteractionNetwork(nn.Module):
    """One GNS processor step: ``e' = e + phi_e([e, v_i, v_j])``,
    ``v' = v + phi_v([v, sum_j phi_e(...)])`` (residual updates, LayerNorm on both MLPs)."""

    def __init__(self, latent: int, hidden: list[int], act: str) -> None:
        super().__init__()
        self.edge = EdgeMLP(latent, latent, [*hidden, latent], act, layer_norm=True)
        self.node = mlp([2 * latent, *hidden, latent], act, layer_norm=True)

    def forward(self, v: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        de = self.edge(e, v, edge_index)
        # nodes aggregate the *updated* edges, as graph_nets' InteractionNetwork does
        dv = self.node(torch.cat([v, scatter_sum(de, edge_index[1], v.shape[0])], dim=1))
        return v + dv, e + de


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

    model_name = "gns"

    def __init__(self, meta: SceneMeta, stats: Mapping[str, Any], history: int,
                 cfg: GNSConfig | None = None) -> None:
        cfg = cfg or GNSConfig()
        super().__init__(meta, stats, history, cfg.oracle, cfg.target_prior,
                         cfg.dynamics_loss, cfg.huber_delta)
        self.cfg = cfg
        hidden, act, h = [cfg.mlp_hidden] * cfg.mlp_layers, cfg.activation, cfg.latent
        self.node_encoder = mlp([self.node_in, *hidden, h], act, layer_norm=True)
        self.edge_encoder = mlp([self.edge_in, *hidden, h], act, layer_norm=True)
        self.processor = nn.ModuleList(InteractionNetwork(h, hidden, act)
                                       for _ in range(cfg.message_passing_steps))
        self.decoder = mlp([h, *hidden, meta.dim], act)

    def velocity_noise(self, g: Graph) -> torch.Tensor | None:
        """(N, k+1, D) random-walk noise, newest first, in normalised units (None if std 0)."""
        if self.cfg.noise_std <= 0.0:
            return None
        steps = g.vel.shape[1]
        increments = torch.randn_like(g.vel) * (self.cfg.noise_std / steps**0.5)
        # the window is newest first: accumulate from the oldest (last) entry
        return increments.flip(1).cumsum(1).flip(1)

    def _target(self, x: torch.Tensor, e: torch.Tensor,
                edge_index: torch.Tensor) -> torch.Tensor:
        v, h_e = self.node_encoder(x), self.edge_encoder(e)
        for step in self.processor:
            v, h_e = step(v, h_e, edge_index)
        return self.decoder(v)


# ----------------------------------------------------------------------------- registry
def build_cranmer_gn(meta: SceneMeta, stats: Mapping[str, Any], history: int,
                     params: Mapping[str, Any]) -> CranmerGN:
    """BS1 from a config dict (``conf/model/cranmer_gn.yaml`` without the optimiser keys)."""
    return CranmerGN(meta, stats, history, config_from_params(CranmerGNConfig, params,
                                                              "cranmer_gn"))


def build_gns(meta: SceneMeta, stats: Mapping[str, Any], history: int,
              params: Mapping[str, Any]) -> GNS:
    """BS2 from a config dict (``conf/model/gns.yaml`` without the optimiser keys)."""
    return GNS(meta, stats, history, config_from_params(GNSConfig, params, "gns"))


# name -> callable(meta, stats, history, params) -> nn.Module, read by ``registry.build_model``
ModelFactory = Callable[[SceneMeta, Mapping[str, Any], int, Mapping[str, Any]], nn.Module]
MODELS: dict[str, ModelFactory] = {"cranmer_gn": build_cranmer_gn, "gns": build_gns}
