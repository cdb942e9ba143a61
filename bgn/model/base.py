"""The contract every model of a scene fulfils (BGN and the baselines alike).

A model is built from ``(meta, stats, history, config)``: the scene's metadata record, the
training split's statistics and the window length k (k+1 velocities, newest first). It

- runs all its heads on a graph (``forward`` -> ``ModelOutput``, in the head's units);
- turns them into task losses (``loss_terms``) and their weighted sum (``total_loss``, Eq. 12);
- predicts the forward target in physical units (``predict``), which is all a rollout needs;
- says which heads it has (``heads``: the loss keys it produces), how to label it, what it is
  given at inference beyond the position window, what its training loss reads beyond the
  frames and what physics is written into it (``label``, ``given``, ``trained_with``,
  ``physics``: derived from its config and loss weights, so every table names the variant);
- samples masses (``sample_mass``) when it has an inverse head.

Subclasses implement ``build`` (their layers), ``forward`` and ``forward_target`` (the dynamics
head alone, without training noise) and declare ``name`` and ``config_class``; the registry
(``bgn.model.registry``) builds them by name. Nothing here knows files, Lightning or Hydra.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from bgn.graph import Graph
from bgn.model.message_passing import CheckpointEdges
from bgn.model.noise import add_random_walk_noise
from bgn.model.normalizer import Normalizer
from bgn.model.target_coder import LOSSES, PRIORS, TargetCoder
from bgn.sim.scene import SceneMeta

# "unroll": the dynamics loss of steps unrolled on the model's own frames (bgn.training.unroll);
# "impulse_mass": the learned masses of the impulse head (bgn.model.impulse)
# "law": the structured force head's prediction with the recorded masses (bgn.model.newton)
LOSS_KEYS = ("dynamics", "contact", "type", "mass_nll", "relmass", "unroll", "impulse_mass",
             "law")
# What a model may be given beyond the position window (``PhysicsModel.given``): the
# particles' radii, types or true masses, all hidden from a model that is not given them.
# "earlier frames": the recorded frames before a rollout's start, beyond its window (the
# couplings a pair-force head fits per simulation, mass_law=coupling)
GIVEN_FIELDS = ("radii", "types", "masses", "earlier frames")
# What each loss term reads beyond the frames every model trains on (``trained_with``): the
# recorded quantity its target is. "contact" is the recorded contacts on contact scenes and
# the recorded pair forces elsewhere (``PhysicsModel.supervision``).
SUPERVISION = {"dynamics": (), "unroll": (), "type": ("types",), "mass_nll": ("masses",),
               "relmass": ("masses",), "impulse_mass": ("masses",), "law": ("masses",),
               "contact": ("contacts",)}


@dataclass
class ModelOutput:
    """Every head's output on a graph; heads a model does not have are None."""

    target: torch.Tensor                         # (N, D) dynamics head, in its own units
    type_logits: torch.Tensor | None = None      # (N, n_types)
    contact: torch.Tensor | None = None          # (E,) logits (contact scenes) or force values
    mass_nll: torch.Tensor | None = None         # (N,) NLL of the normalised log-mass
    relmass: torch.Tensor | None = None          # (E,) normalised R̂_ij
    log_mass_sample: torch.Tensor | None = None  # (N,) the flow sample z_K behind relmass
    edge_weight: torch.Tensor | None = None      # (E,) learned adjacency (BGN's edge encoder)


def check_positive_ints(cfg: Any, names: tuple[str, ...]) -> None:
    """Raise ValueError naming the first of ``names`` on ``cfg`` that is not an int >= 1."""
    for name in names:
        value = getattr(cfg, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name}={value!r} must be a positive integer")


@dataclass
class OptionGroup:
    """Root of the option dataclasses a model config composes by inheritance (BGN's
    ``ModelConfig``: the paper's options, ``DynamicsConfig`` and each structured head's group),
    so every key stays flat (``model.law=auto``). Each group's ``__post_init__`` checks its own
    fields and calls ``super().__post_init__()``; the chain ends here, whatever the order."""

    def __post_init__(self) -> None:
        pass


@dataclass
class DynamicsConfig(OptionGroup):
    """Options every model shares: what its dynamics head predicts and its loss
    (``bgn.model.target_coder``), so that all models train on equal terms.
    ``target_prior=none dynamics_loss=mse`` is the paper's (and the baselines' published)
    parameterisation; a scene may set its own default (``conf/dataset_model/``)."""

    # auto | none (paper) | last | linear: predict the change from the history
    target_prior: str = "auto"
    # auto (huber for accelerations with a prior, else mse) | huber | mse (paper) | relative
    # (each particle's squared error over its target's size: a law's far tail weighs too)
    dynamics_loss: str = "auto"
    huber_delta: float = 1.0
    # Training for rollouts (bgn.model.noise): std of the random-walk noise on the input
    # window, in multiples of the velocity scale, with the target corrected back onto the
    # true trajectory; 0 trains on clean windows (the paper).
    rollout_noise: float = 0.0
    # Activation checkpointing for large graphs (message_passing.edge_chunks): edge MLPs on
    # graphs with more than ``checkpoint_edges`` edges (and more than ``edge_chunk``) run in
    # chunks of ``edge_chunk`` edges and recompute their hidden layers in the backward pass.
    # The default never triggers in training on the paper's scenes (a few thousand edges per
    # batch); on large radius graphs it cuts BGN's peak memory
    # (docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs").
    # The baselines, whose edge MLPs are most of their time, checkpoint only above a million
    # edges. null: never.
    edge_chunk: int | None = 65_536
    checkpoint_edges: int | None = 65_536
    # The same threshold where the model runs on a GPU: there memory is ample and a step is
    # bound by kernel launches, so recomputing costs more than it saves
    # (docs/notes/2026-11-26-results-history.md, "On a GPU: one H100").
    checkpoint_edges_gpu: int | None = 2_097_152

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.rollout_noise >= 0.0:
            raise ValueError(f"rollout_noise={self.rollout_noise} must be >= 0")
        if self.edge_chunk is not None and not self.edge_chunk >= 1:
            raise ValueError(f"edge_chunk={self.edge_chunk} must be >= 1 (or null: never)")
        for key in ("checkpoint_edges", "checkpoint_edges_gpu"):
            value = getattr(self, key)
            if value is not None and not value >= 0:
                raise ValueError(f"{key}={value} must be >= 0 (or null: from edge_chunk)")
        if self.target_prior not in PRIORS:
            raise ValueError(f"target_prior={self.target_prior!r}; choose one of {PRIORS}")
        if self.dynamics_loss not in LOSSES:
            raise ValueError(f"dynamics_loss={self.dynamics_loss!r}; choose one of {LOSSES}")
        if not self.huber_delta > 0:
            raise ValueError(f"huber_delta={self.huber_delta} must be > 0")


def config_from_params(cls: type, params: Mapping[str, Any], model: str) -> Any:
    """``cls(**params)`` without ``name``; an unknown key (a typo in a yaml file) is an error."""
    known = {f.name for f in fields(cls)}
    values = {k: v for k, v in params.items() if k != "name"}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(f"unknown {model} model options {unknown}; known: {sorted(known)}")
    return cls(**values)


def contact_pos_weight(stats: Mapping[str, Any], setting: str | float) -> float:
    """Positive-class weight of the contact BCE: ``(1 - p) / p`` for "balanced", where ``p``
    is the contact fraction of the training split's candidate edges, else the number given."""
    if setting != "balanced":
        return float(setting)
    p = float(np.mean(stats["contact"]["mean"]))
    if not 0.0 < p < 1.0:  # no contacts (or only contacts) in training: nothing to balance
        return 1.0
    return (1.0 - p) / p


class PhysicsModel(nn.Module, ABC):
    """Base of every model: inputs check, target coding, losses, prediction (see module doc)."""

    name: ClassVar[str]                      # registry and config name (conf/model/<name>.yaml)
    config_class: ClassVar[type[DynamicsConfig]]

    def __init__(self, meta: SceneMeta, stats: Mapping[str, Any], history: int,
                 cfg: DynamicsConfig | None = None) -> None:
        super().__init__()
        cfg = self.config_class() if cfg is None else cfg
        self.meta, self.history, self.cfg = meta, history, cfg
        self.normalizer = Normalizer(stats, meta.dim)
        self.target_coder = TargetCoder(self.normalizer, stats, meta, history, cfg.target_prior,
                                        cfg.dynamics_loss, cfg.huber_delta)
        self.heads: frozenset[str] = frozenset({"dynamics"})  # subclasses add theirs
        self.loss_weights: dict[str, float] = {}              # missing keys weigh 1
        self.build(cfg, stats)
        for module in self.modules():  # the edge MLPs (ops.EdgeMLP, the relative-mass decoder)
            if hasattr(module, "edge_chunk"):
                module.edge_chunk = cfg.edge_chunk
                module.checkpoint_edges = CheckpointEdges(cfg.checkpoint_edges,
                                                          cfg.checkpoint_edges_gpu)
            if hasattr(module, "edge_block"):  # ops.EdgeMLP; the option of the baselines' configs
                module.edge_block = getattr(cfg, "edge_block", None)

    @abstractmethod
    def build(self, cfg: Any, stats: Mapping[str, Any]) -> None:
        """Create the model's layers from its config (``__init__`` calls it once, after the
        shared parts: ``meta``, ``history``, ``normalizer``, ``target_coder`` exist)."""

    @property
    def label(self) -> str:
        """How reports name this model: the variant, from its config (e.g. "BGN + impulse
        head (radii)", "GNS + radii/types"); subclasses say theirs."""
        return self.name

    @property
    def given(self) -> tuple[str, ...]:
        """What the model reads beyond the position window every model reads, among
        ``GIVEN_FIELDS`` ("radii", "types", "masses", "earlier frames"), from its config and
        scene."""
        return ()

    @property
    def physics(self) -> str:
        """The physics written into the model's dynamics ("none": a learned map only)."""
        return "none"

    @property
    def supervision(self) -> dict[str, list[str]]:
        """What the training loss reads beyond the frames: each recorded quantity (masses,
        contacts, pair forces, types) -> the loss terms that read it, from the heads the model
        has and their weights (``SUPERVISION``; a term weighted 0 reads nothing)."""
        out: dict[str, list[str]] = {}
        for key in LOSS_KEYS:
            if key not in self.heads or not self.loss_weights.get(key, 1.0) > 0:
                continue
            for quantity in SUPERVISION[key]:
                if quantity == "contacts" and self.meta.interaction != "contact":
                    quantity = "pair forces"  # the contact head regresses |F_ij| there
                out.setdefault(quantity, []).append(key)
        return out

    @property
    def trained_with(self) -> tuple[str, ...]:
        """The recorded quantities the training loss reads beyond the frames
        (``supervision``'s keys), e.g. ("masses", "types"); () for the frames alone."""
        return tuple(self.supervision)

    def describe(self) -> dict[str, Any]:
        """``name``, ``label``, ``given`` (at inference), ``trained_with`` and
        ``supervision`` (at training) and ``physics`` as one record (reports, metrics.json)."""
        return {"name": self.name, "label": self.label, "given": list(self.given),
                "trained_with": list(self.trained_with), "supervision": self.supervision,
                "physics": self.physics}

    @property
    def has_inverse(self) -> bool:
        return "mass_nll" in self.heads

    # ------------------------------------------------------------------ forward
    def check(self, g: Graph) -> None:
        """One clear error when a graph's window does not fit the model."""
        if g.vel.shape[1] != self.history + 1 or g.vel.shape[2] != self.meta.dim:
            raise ValueError(f"graph velocity window {tuple(g.vel.shape[1:])} does not match "
                             f"the model's (history + 1, dim) = "
                             f"({self.history + 1}, {self.meta.dim})")

    @abstractmethod
    def forward(self, g: Graph) -> ModelOutput:
        """All heads on a graph (one frame or a batch), in training mode with its noise."""

    @abstractmethod
    def forward_target(self, g: Graph) -> torch.Tensor:
        """The dynamics head alone, (N, D) in its own units, never with training noise."""

    def corrupt(self, g: Graph) -> Graph:
        """A training graph with the rollout noise of ``cfg.rollout_noise`` (``bgn.model.noise``),
        or ``g`` itself when it is 0. Training only: the module calls it before ``forward``."""
        if self.cfg.rollout_noise <= 0.0:
            return g
        std = self.cfg.rollout_noise * self.normalizer.velocity_scale
        return add_random_walk_noise(g, std, self.meta.target)

    # ------------------------------------------------------------------ losses
    def loss_terms(self, g: Graph, out: ModelOutput) -> dict[str, torch.Tensor]:
        """Scalar task losses, keys among ``LOSS_KEYS`` (here: ``L_Dec``; heads add theirs)."""
        return {"dynamics": self.target_coder.loss(out.target, g)}

    def total_loss(self, terms: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Eq. 12: the weighted sum of the task losses."""
        if not terms:
            raise ValueError("no loss terms to sum")
        return torch.stack([self.loss_weights.get(k, 1.0) * v for k, v in terms.items()]).sum()

    # ------------------------------------------------------------------ units
    def normalized_target(self, g: Graph) -> torch.Tensor:
        """The graph's target in the dynamics head's units, (N, D)."""
        return self.target_coder.encode(g)

    def denormalize_target(self, target: torch.Tensor, g: Graph) -> torch.Tensor:
        """``ModelOutput.target`` of graph ``g`` -> physical units."""
        return self.target_coder.decode(g, target)

    def denormalize_relmass(self, relmass: torch.Tensor) -> torch.Tensor:
        """``ModelOutput.relmass`` -> ``log m_i - log m_j``."""
        return self.normalizer.denormalize_rel_log_mass(relmass)

    def contact_target(self, g: Graph) -> torch.Tensor:
        """Per-edge contact target in the units of ``ModelOutput.contact``."""
        raise RuntimeError(f"{self.label} has no contact head")

    # ------------------------------------------------------------------ inference
    def predict(self, g: Graph) -> torch.Tensor:
        """Forward target (next velocity or acceleration) in physical units, (N, D).
        Wrap in ``torch.no_grad()`` for rollouts."""
        return self.target_coder.decode(g, self.forward_target(g))

    def held_mass_fit(self, g: Graph) -> torch.Tensor | None:
        """(N,) what a rollout fits once to its first window ``g`` and holds along it (the
        learned simulator sets it as each later graph's ``mass_fit``): the pair-force head's
        mass fit with ``rollout_masses=held``; None, the default: nothing held."""
        return None

    @property
    def held_fit_windows(self) -> int:
        """How many windows of the frames before a rollout's start ``held_mass_fit`` reads
        where the rollout is given them (1, the default: its first window alone)."""
        return 1

    def sample_mass(self, g: Graph, n_samples: int) -> torch.Tensor:
        """Samples of every particle's mass in physical units, (n_samples, N)."""
        raise RuntimeError(f"{self.label} has no inverse head")
