"""BGN: the paper's multi-task graph network, assembled from a scene's metadata.

Encode (Eq. 1) -> process (Eq. 2-4) -> decode the forward target (Eq. 5) and, from the same
node features, infer mass (Eq. 6-10). The loss is the weighted sum of the task losses (Eq. 12).

Model only what the scene needs (docs/design.md#the-scene-record): no classifier when the scene has
one particle type, no contact head without ``cfg.contact``, no flow without ``cfg.inverse``.
All tensors are in normalised units except where a method says "physical".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from bgn.graph import Graph
from bgn.model.base import (
    LOSS_KEYS,
    DynamicsConfig,
    ModelOutput,
    PhysicsModel,
    check_positive_ints,
    contact_pos_weight,
)
from bgn.model.decoder import Decoder
from bgn.model.encoder import (
    EdgeEncoder,
    NodeEncoder,
    edge_features,
    edge_input_dim,
    node_features,
    node_input_dim,
)
from bgn.model.inverse import InverseModel, InverseOptions
from bgn.model.newton import (
    NewtonOptions,
    PairForceHead,
    build_head,
    head_given,
    head_label,
    head_physics,
    held_fit,
    held_windows,
    impulse_mass_loss,
    law_loss,
)
from bgn.model.processor import ContactOptions, Processor, ProcessorOutput
from bgn.model.soft_contact import SoftContactHead


@dataclass
class ModelConfig(NewtonOptions, ContactOptions, InverseOptions, DynamicsConfig):
    """BGN's options and their defaults (the schema of ``conf/model/bgn.yaml``,
    docs/design.md#model): the paper's own below; each head's in its module, composed here by
    inheritance so every key stays flat (``model.law=auto``): the structured dynamics head's
    (``newton.NewtonOptions``), the contact decoder's (``processor.ContactOptions``), the
    inverse model's (``inverse.InverseOptions``) and every model's (``base.DynamicsConfig``).
    Heads a scene does not need are never built."""

    hidden: int = 128
    node_layers: int = 2               # raw-residual GCN layers of the node encoder (Eq. 1)
    edge_layers: int = 2               # weighted GCN layers of the edge encoder
    decoder_hidden: int = 128          # per-dimension raw-residual decoders (Eq. 5)
    activation: str = "silu"
    classifier: bool = True            # particle-type head (Eq. 2), only with n_types > 1
    contact: bool = True               # contact decoder (Eq. 3-4)
    inverse: bool = True               # mass flow + relative-mass decoder (Eq. 6-10)
    shared_decoder: bool = False
    # D^-1/2 Â D^-1/2 in every GCN layer. The paper's plain sums grow like (degree+1)^layers,
    # so contact logits explode at initialisation on large radius graphs and the flows do not
    # train (docs/notes/2026-11-26-results-history.md, "Measurements behind the defaults").
    degree_normalize: bool = True
    # Not in the paper: a separate weight on each node's own features in every GCN layer
    # (H' = s(Â H W + H W_self + Â H)). Eq. 1 alone gives every node of a clique the same
    # features: all particles of a complete graph (spring, gravity), both discs of an isolated
    # touching pair (collisions), so no per-particle type or mass can be read from H_V there.
    # False = the paper's literal Eq. 1 (ablation).
    self_weight: bool = True
    use_absolute_position: bool = False
    # Not in the paper: the window's velocity increments (finite-difference accelerations) as
    # node inputs in their own scale. They are linear in the window, but at high fps they are
    # tiny differences of normalised velocities that GCN averaging washes out.
    velocity_increments: bool = True
    # Not in the paper: the decoder also sees the node's own input features (a skip past the
    # GCN layers, which mix each node with its neighbours).
    decoder_skip: bool = True
    # Eq. 12 weights, one per task (keys: LOSS_KEYS); missing keys weigh 1 (the paper's).
    # "law" (the structured force head with the recorded masses, newton.law_loss) is the one
    # task off unless weighted: gravity_r2 trains on it alone (conf/dataset_model/).
    loss_weights: dict[str, float] = field(
        default_factory=lambda: {**dict.fromkeys(LOSS_KEYS, 1.0), "law": 0.0})

    def __post_init__(self) -> None:
        super().__post_init__()  # the groups', in the order of the bases
        check_positive_ints(self, ("hidden", "node_layers", "edge_layers", "decoder_hidden"))
        unknown = set(self.loss_weights) - set(LOSS_KEYS)
        if unknown:
            raise ValueError(f"unknown loss weights {sorted(unknown)}; keys are {LOSS_KEYS}")
        self.loss_weights = {str(k): float(v) for k, v in dict(self.loss_weights).items()}


class BGN(PhysicsModel):
    """Graph network for bi-directional physics, built from ``(meta, stats, history, cfg)``.

    ``history`` is k: the velocity window has k+1 steps, newest first.
    """

    name = "bgn"
    config_class = ModelConfig

    def build(self, cfg: ModelConfig, stats: Mapping[str, Any]) -> None:
        meta, history = self.meta, self.history
        if cfg.contact_mode == "dense" and cfg.contact and meta.graph != "full":
            raise ValueError(
                f"contact_mode='dense' needs a full graph with a fixed number of particles; "
                f"scene {meta.name!r} uses a {meta.graph} graph. Use contact_mode='aggregate'.")
        self.contact_scene = meta.interaction == "contact"
        self.loss_weights = dict(cfg.loss_weights)
        self.register_buffer("contact_pos_weight", torch.tensor(
            contact_pos_weight(stats, cfg.contact_pos_weight) if self.contact_scene else 1.0),
            persistent=False)  # rebuilt from the statistics, which the checkpoint carries
        d, h = meta.dim, cfg.hidden
        node_in = node_input_dim(d, history, meta.has_walls, cfg.use_absolute_position,
                                 cfg.velocity_increments)
        edge_in = edge_input_dim(d, history)
        self.node_encoder = NodeEncoder(node_in, h, cfg.node_layers, cfg.activation,
                                        cfg.degree_normalize, cfg.self_weight)
        self.edge_encoder: EdgeEncoder | None = EdgeEncoder(
            node_in, edge_in, h, cfg.edge_layers, cfg.activation, cfg.degree_normalize,
            cfg.self_weight)
        self.processor = Processor(h, edge_in, meta.n_types, meta.n_particles,
                                   contact_scene=self.contact_scene, classifier=cfg.classifier,
                                   # on contact scenes the impulse head's gate is the
                                   # contact head when dynamics=newton
                                   contact=cfg.contact and not (
                                       self.contact_scene and cfg.dynamics == "newton")
                                   # imported data: no pair force law, nothing to learn
                                   and meta.interaction != "unknown",
                                   contact_mode=cfg.contact_mode,
                                   contact_edge_term=(history if cfg.contact_edge_term
                                                      else None),
                                   message=cfg.contact_message, act=cfg.activation, dim=d,
                                   contact_gap=cfg.contact_gap and self.contact_scene,
                                   decode=cfg.dynamics == "decoder")
        if cfg.dynamics == "soft_contact":  # granular media: replaces Eq. 5's decoder
            self.force_head = SoftContactHead(meta, cfg.contact_substeps,
                                              energy=cfg.contact_energy)
            self.decoder = None
        elif cfg.dynamics == "newton":  # the structured head replaces Eq. 5's decoder
            self.force_head: nn.Module | None = build_head(
                meta, self.normalizer, history, cfg.decoder_hidden, 2, cfg.activation,
                cfg.mass_law, "model.dynamics=newton", cfg.substeps,
                cfg.law_formula if cfg.law == "formula" else "", cfg.law_scale,
                cfg.rollout_masses, cfg.law_output,
                # the law's scale its own parameter where the law loss trains it beside the
                # dynamics loss, whose noise would swamp it (PairForceHead's law_gain)
                law_gain=bool(cfg.loss_weights.get("law", 0.0))
                and bool(cfg.loss_weights.get("dynamics", 1.0)) and cfg.mass_law != "coupling")
            self.decoder = None
        else:
            self.force_head = None
            self.decoder = Decoder(
                self.processor.out_features + (node_in if cfg.decoder_skip else 0),
                cfg.decoder_hidden, d, cfg.activation, cfg.shared_decoder)
        self.inverse = (InverseModel(self.processor.tilde_v_features, cfg.flow,
                                     cfg.flow_transforms, cfg.flow_hidden, cfg.activation,
                                     self._conditioning(cfg, history),
                                     cfg.mass_context_dropout,
                                     max(1, min(cfg.mass_context_frames, history)),
                                     cfg.mass_fit_error)
                        if cfg.inverse else None)
        if self.processor.contact is None and self.decoder is None:
            self.edge_encoder = None  # H_E would feed neither a contact head nor a decoder
        heads = {"dynamics"}
        if self.processor.classifier is not None:
            heads.add("type")
        if self.processor.contact is not None:
            heads.add("contact")
        if self.inverse is not None:
            heads |= {"mass_nll", "relmass"}
        if (self.force_head is not None and not self.contact_scene
                and cfg.loss_weights.get("law", 0.0)):
            heads.add("law")                    # the force law with the recorded masses
        if self.force_head is not None and self.contact_scene:
            heads.add("impulse_mass")
            if cfg.contact:
                heads.add("contact")            # the impulse head's gate
        self.heads = frozenset(heads)  # the loss keys this model produces

    @property
    def label(self) -> str:
        """"BGN (paper decoder)" or "BGN + <structured head>" (``newton.head_label``)."""
        if self.force_head is None:
            return "BGN (paper decoder)"
        return f"BGN + {head_label(self.force_head)}"

    @property
    def given(self) -> tuple[str, ...]:
        """The structured head's inputs (``newton.head_given``); with the decoder, the radii
        where the contact head reads the time-of-impact gap (``contact_gap``)."""
        if self.force_head is not None:
            return head_given(self.force_head)
        gap = self.processor.contact is not None and self.contact_scene and self.cfg.contact_gap
        return ("radii",) if gap else ()

    @property
    def physics(self) -> str:
        return "none" if self.force_head is None else head_physics(self.force_head)

    def _conditioning(self, cfg: ModelConfig, history: int) -> str:
        """The flow's context as built: a one-velocity window holds no acceleration to pair
        (``node``); ``fit`` is ``pairs`` where no pair-force head fits masses (the decoder,
        contact scenes), so one setting serves every dynamics."""
        if history < 1:
            return "node"
        if cfg.mass_context == "fit" and not hasattr(self.force_head, "fitted_log_mass"):
            return "pairs"
        return cfg.mass_context

    # ------------------------------------------------------------------ forward
    def _process(self, g: Graph):
        """Encoders and processor: (ProcessorOutput, edge weights)."""
        self.check(g)
        x = node_features(g, self.normalizer, self.meta.has_walls,
                          self.cfg.use_absolute_position, self.meta.box,
                          self.cfg.velocity_increments)
        # the edge features feed the edge encoder and the contact head only (not BGN's
        # structured head on collisions, where they cost a share of every step on large scenes:
        # docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs")
        e = (edge_features(g, self.normalizer)
             if self.edge_encoder is not None or self.processor.contact is not None else None)
        h_v = self.node_encoder(x, g.edge_index)               # Eq. 1
        h_e, w = (self.edge_encoder(x, e, g.edge_index)        # Eq. 1 with learned A
                  if self.edge_encoder is not None else (None, None))
        return self.processor(h_v, h_e, e, g), w, x            # Eq. 2-3

    def _decode(self, p: ProcessorOutput, x: torch.Tensor) -> torch.Tensor:
        """Eq. 5 on H̃_CV (and the node inputs with ``decoder_skip``), plus the contact
        impulse of a vector message."""
        assert self.decoder is not None
        y = self.decoder(torch.cat([p.h_cv, x], -1) if self.cfg.decoder_skip else p.h_cv)
        return y if p.impulse is None else y + p.impulse

    def forward(self, g: Graph, noise: torch.Tensor | None = None) -> ModelOutput:
        """All heads on a graph (one frame or a batch). ``noise`` (N,): base draws of the
        flow sample behind ``relmass`` (when None: drawn while training, the posterior's
        median in eval mode, ``InverseModel.forward``)."""
        p, w, x = self._process(g)
        contact = p.contact
        fitted = None  # the force head's fitted log-masses, for mass_context=fit
        if self.force_head is None:
            target = self._decode(p, x)                        # Eq. 5
        elif isinstance(self.force_head, PairForceHead):  # one window, one mass fit for both
            raw, terms = self.force_head.window(g)
            fit, error = self.force_head.least_squares(
                g, terms, self.inverse is not None and self.inverse.fit_error)
            target = self.target_coder.code(g, self.force_head.accelerate(g, raw, fit))
            if self.inverse is not None and self.inverse.uses_fit:
                fitted = self.force_head.fitted_log_mass(g, fit, error)
        else:  # the impulse head, its gate the contact head
            physical, gate = self.force_head(g)
            target = self.target_coder.code(g, physical)
            contact = gate if gate is not None and self.cfg.contact else contact
        mass_nll = relmass = z = None
        if self.inverse is not None:
            log_m = self.normalizer.log_mass(torch.log(g.mass))
            context = self._mass_context(p, g, fitted)           # Eq. 6
            mass_nll, z = self.inverse(context, log_m, noise)       # Eq. 7-8
            relmass = self.inverse.relative(z, g.edge_index)        # Eq. 9-10
        return ModelOutput(target, p.type_logits, contact, mass_nll, relmass, z, w)

    def _mass_context(self, p: ProcessorOutput, g: Graph,
                      fitted: torch.Tensor | None = None) -> torch.Tensor:
        """The flow's context (``InverseModel.context``), with the structured head's fitted
        log-masses under ``mass_context=fit`` (``fitted``, where ``forward`` has them)."""
        assert self.inverse is not None
        if fitted is None and self.inverse.uses_fit and self.force_head is not None:
            fit, error = self.force_head.least_squares(g, self.force_head.window(g)[1],
                                                       self.inverse.fit_error)
            fitted = self.force_head.fitted_log_mass(g, fit, error)
        return self.inverse.context(p.h_tilde_v, g, fitted)

    def held_mass_fit(self, g: Graph) -> torch.Tensor | None:
        return held_fit(self.force_head, g)

    @property
    def held_fit_windows(self) -> int:
        return held_windows(self.force_head)

    def forward_target(self, g: Graph) -> torch.Tensor:
        """The dynamics head alone (no flow): what ``predict`` and rollouts run."""
        if self.force_head is not None:  # needs no encoder: positions and window only
            self.check(g)
            return self.target_coder.code(g, self.force_head(g)[0])
        p, _, x = self._process(g)
        return self._decode(p, x)

    # ------------------------------------------------------------------ losses
    def contact_target(self, g: Graph) -> torch.Tensor:
        """Per-edge contact target in the units of ``ModelOutput.contact``: 0/1 for contact
        scenes (``contact`` holds logits), else the (log1p-compressed) normalised pairwise
        force magnitude."""
        if self.contact_scene:
            return g.edge_contact
        c = self.normalizer.contact(g.edge_contact)
        return torch.log1p(c) if self.cfg.force_transform == "log1p" else c

    def loss_terms(self, g: Graph, out: ModelOutput) -> dict[str, torch.Tensor]:
        """Scalar losses of the heads present, keys among ``LOSS_KEYS``."""
        terms = super().loss_terms(g, out)                      # L_Dec
        if out.contact is not None:                             # Eq. 4 on edges
            c = self.contact_target(g)
            if out.contact.numel() == 0:
                terms["contact"] = out.contact.sum()            # no edges: 0, not NaN
            elif self.contact_scene:  # logits: BCE is the stable form of a sigmoid + 0/1 target
                terms["contact"] = F.binary_cross_entropy_with_logits(
                    out.contact, c, pos_weight=self.contact_pos_weight.to(out.contact.dtype))
            else:
                terms["contact"] = F.mse_loss(out.contact, c)
        if out.type_logits is not None:                         # cross-entropy of Eq. 2
            terms["type"] = F.cross_entropy(out.type_logits, g.types)
        if out.mass_nll is not None:                            # Eq. 8
            terms["mass_nll"] = out.mass_nll.mean()
        if self.force_head is not None and (mass := impulse_mass_loss(
                self.force_head, g, self.normalizer)) is not None:
            terms["impulse_mass"] = mass                        # the impulse head's masses
        if "law" in self.heads and (law := law_loss(self.force_head, g)) is not None:
            terms["law"] = law                                  # the law, masses known
        if out.relmass is not None:                             # L_Inv-Dec
            r = self.normalizer.rel_log_mass(g.edge_rel_log_mass)
            terms["relmass"] = (F.mse_loss(out.relmass, r) if r.numel()
                                else out.relmass.sum())
        return terms

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def sample_log_mass(self, g: Graph, n_samples: int) -> torch.Tensor:
        """Samples of every particle's normalised log-mass, (n_samples, N)."""
        if self.inverse is None:
            raise RuntimeError("this model has no inverse head (cfg.inverse=False)")
        p, _, _ = self._process(g)
        return self.inverse.sample_log_mass(self._mass_context(p, g), n_samples)

    @torch.no_grad()
    def mass_posterior(self, g: Graph, n_samples: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The flow's posterior over every particle's natural log-mass: ``n_samples`` samples
        (n_samples, N) and the exact log-density of the true log-mass (N,) (Eq. 7, with the
        Jacobian of the normalisation), from one pass of the encoders."""
        if self.inverse is None:
            raise RuntimeError("this model has no inverse head (cfg.inverse=False)")
        p, _, _ = self._process(g)
        context = self._mass_context(p, g)
        z_true = self.normalizer.log_mass(torch.log(g.mass))
        log_density = (self.inverse.log_density(context, z_true)
                       - torch.log(self.normalizer.log_mass_scale))
        samples = self.normalizer.denormalize_log_mass(
            self.inverse.sample_log_mass(context, n_samples))
        return samples, log_density

    @torch.no_grad()
    def mass_base_value(self, g: Graph) -> torch.Tensor:
        """(N,) every particle's true normalised log-mass in the flow's base space (untempered;
        ``InverseModel.base_value``): what the calibration is fitted to."""
        if self.inverse is None:
            raise RuntimeError("this model has no inverse head (cfg.inverse=False)")
        p, _, _ = self._process(g)
        context = self._mass_context(p, g)
        return self.inverse.base_value(context, self.normalizer.log_mass(torch.log(g.mass)))

    @torch.no_grad()
    def sample_mass(self, g: Graph, n_samples: int) -> torch.Tensor:
        """Samples of every particle's mass in physical units, (n_samples, N)."""
        return torch.exp(self.normalizer.denormalize_log_mass(self.sample_log_mass(g, n_samples)))
