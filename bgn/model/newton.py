"""A physically structured forward model: learned central pair forces, Newton's third law by
construction, masses fitted to the window.

The n-body scenes are pair forces along the line between two particles
(docs/design.md#n-body-scenes): spring
``F_ij = -2 (s_ij - 1) u_ij`` whatever the masses, gravity ``F_ij ~ m_i m_j g(s_ij) u_ij``. A
network that sees only a velocity window must re-infer every particle's mass from that window
at every step of a rollout, and a small error in its own frames changes the masses it reads:
the one-step error is small, the rollout drifts. This model writes the structure down and
learns only the force law:

- ``f(s)``: a scalar MLP of the pair's distance (and its particle types), ``F_ij = f(s_ij)
  u_ij`` with ``u_ij`` the unit vector from j to i. ``F_ij = -F_ji``: equal and opposite.
- ``mass_law="inertial"`` (spring-like, the force does not depend on the masses):
  ``a_i = w_i sum_j F_ij`` with ``w_i = 1 / m_i`` the least-squares fit of the window's own
  accelerations to the same forces at the window's frames, ``w_i = sum_tau F_i.a_i /
  sum_tau |F_i|^2``; ``mass_law="source"`` (gravity-like, a particle's own mass cancels):
  ``a_i = sum_j m_j F_ij`` with the masses fitted jointly per simulation; ``mass_law="type"``
  (the force does not depend on the masses, one mass per particle type, learned like the law:
  all equal where there is one type): ``a_i = F_i / m_type(i)``, nothing fitted to the window;
  ``mass_law="coupling"`` (charges of either sign and hidden masses, ``F_ij = q_i q_j f u``):
  ``a_i = k_i sum_j c_j f(s_ij) u_ij`` with ``k_i = q_i / m_i`` and ``c_j = q_j`` fitted per
  simulation, over every window of the batch from that simulation pooled
  (``bgn.model.coupling``); in a rollout fitted once, to windows of the frames before its start
  (``COUPLING_WINDOWS`` of them), and held.
  A window fit reads masses off a few frames at every rollout step; where the masses are in
  fact shared, its errors at stiff encounters feed energy into the rollout, which a fixed mass
  cannot (docs/notes/2026-11-26-force-matching.md).

A window made by the model itself is consistent with the masses that made it, so the fit
returns them: masses stay put in a rollout. The scale of ``f`` is free (the fitted masses
absorb it); only the shape of the force law is learned. The finite-difference target is
written with Numerov's weights (``numerov``; implicit at frame t, one fixed-point step). The
head needs pairwise forces, an acceleration target and history >= 3. The forces are summed over
the graph's edges: a complete graph, or a radius graph (imported short-range data), where a pair
beyond the radius has no edge and so no force, and the law learns to vanish at the cut-off. The
edge set of frame t serves the whole window and the positions moved within the frame (the
implicit step, ``shoot``'s substeps): exact where the law vanishes at the radius or the graph's
margin covers a frame's motion, as a connectivity radius at the law's cut-off does.

``build_head`` gives a scene its structured head: this one for force scenes, pair impulses at
the time of impact (``bgn.model.impulse``) for contact scenes. BGN uses it with
``model.dynamics=newton``; ``Newton`` is the head alone as a model (``model=newton``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from bgn.graph import Graph
from bgn.model.base import (
    DynamicsConfig,
    ModelOutput,
    OptionGroup,
    PhysicsModel,
    check_positive_ints,
    contact_pos_weight,
)
from bgn.model.coupling import MAX_PARTICLES as COUPLING_MAX_PARTICLES
from bgn.model.coupling import coupling_errors, fit_couplings, simulation_system
from bgn.model.encoder import DIRECTION_EPS
from bgn.model.formula_law import FormulaLaw, check_law, pair_text
from bgn.model.impulse import ContactImpulseHead
from bgn.model.message_passing import edge_vector
from bgn.model.normalizer import Normalizer
from bgn.model.ops import activation, mlp, scatter_sum
from bgn.model.soft_contact import CONTACT_CALIBRATION, CONTACT_ENERGY, SoftContactHead
from bgn.model.target_coder import observed_targets, relative_squared_error
from bgn.sim.scene import SceneMeta

MASS_LAWS = ("inertial", "source", "type", "coupling")
LAW_INITS = ("random", "match")  # the MLP law's start (ForceLawOptions.law_init)
LAW_OUTPUTS = ("linear", "exp_scaled")  # how the MLP law's outputs make f (ForceLawOptions)
# exp_scaled: |log-scale| at most this (smoothly, a tanh), so f stays within exp(10) of its
# amplitude early in training, where an unbounded one overflowed the gradient
# (docs/results.md, "The network's law per distance band"); the amplitude carries the rest
LOG_SCALE_MAX = 10.0
ROLLOUT_MASSES = ("window", "held")  # a rollout's mass fit (ForceLawOptions.rollout_masses)
# BGN's dynamics head: Eq. 5's decoder, the scene's structured head, or soft contacts with
# friction, a field and drag (granular media, ``bgn.model.soft_contact``)
DYNAMICS = ("decoder", "newton", "soft_contact")
FIT_EPS = 1e-12  # keeps a mass fit finite when a particle feels no force over the window
ROBUST_STEPS, ROBUST_SCALE = 2, 0.01  # reweighting of the gravity mass fit (source law)
REL_ERROR_FLOOR = 1e-6  # the log of a fit's relative error stays finite for an exact fit
IMPLICIT_STEPS = 1  # fixed-point steps of the implicit Numerov prediction (more: no gain)
# Newton steps of the shooting that finds the velocity at frame t (substeps > 1); how many
# converge: docs/notes/2026-11-26-results-history.md, "Measurements behind the defaults",
# "Shooting iterations"
SHOOTING_ITERATIONS = 4
# windows of the frames before a rollout's start that its held coupling fit pools
# (mass_law=coupling): a window's few frames do not pin 2 n - 1 couplings, a simulation's do
COUPLING_WINDOWS = 32


@dataclass
class ForceLawOptions(OptionGroup):
    """The pair-force head's law and integration: options of ``model=newton`` (``NewtonConfig``)
    and of BGN with ``model.dynamics=newton`` (``NewtonOptions``)."""

    # how masses enter the forces: inertial, a = F / m (spring) | source, a = sum m_j F_ij
    # (gravity) | type, a = F / m with one learned mass per type | coupling, a_i = k_i sum_j
    # c_j F_ij, couplings of either sign (charges) fitted per simulation; each scene sets its
    # own (conf/dataset_model/)
    mass_law: str = "inertial"
    substeps: int = 1                  # 1: Numerov's weights; > 1: integrate the frame (shoot)
    law: str = "mlp"                   # mlp: f(s) a network | formula: law_formula | auto
    law_formula: str = ""              # the formula's JSON spec (bgn.laws.finetune.formula_spec)
    # what puts law_formula's amplitudes in physical units where the model keeps the formula in
    # the network law's free scale (inertial masses fitted to the window absorb any scale; the
    # formula stage sets it): read by the model's labels only, never by its predictions
    law_scale: float = 1.0
    # random: the MLP law as initialised | match: first fitted to a least-squares table of
    # the law on the training frames (bgn.model.force_matching); imported data set match;
    # mass_law=coupling starts as initialised (the table cannot weigh couplings of either sign)
    law_init: str = "random"
    # the mass fit along a rollout: window, refitted at every step to the window, which after
    # the first step holds the rollout's own predicted frames | held, fitted once to the
    # rollout's first (observed) window and kept: masses do not change along a simulation, and
    # a refit from predicted frames feeds their error back into the masses. One-step
    # predictions (training, Table 1) are the same either way.
    rollout_masses: str = "window"
    # linear: f the MLP's one output | exp_scaled: f = a exp(b) from its two outputs
    # (ExpScaledLaw), the optimiser's noise a relative change of f at every distance
    law_output: str = "linear"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_ints(self, ("substeps",))
        if self.law_output not in LAW_OUTPUTS:
            raise ValueError(f"law_output={self.law_output!r}; choose one of {LAW_OUTPUTS}")
        if self.rollout_masses not in ROLLOUT_MASSES:
            raise ValueError(f"rollout_masses={self.rollout_masses!r}; choose one of "
                             f"{ROLLOUT_MASSES}")
        if self.mass_law not in MASS_LAWS:
            raise ValueError(f"mass_law={self.mass_law!r}; choose one of {MASS_LAWS}")
        if self.law_init not in LAW_INITS:
            raise ValueError(f"law_init={self.law_init!r}; choose one of {LAW_INITS}")
        check_law(self.law, self.law_formula, self.law_scale)


@dataclass
class NewtonOptions(ForceLawOptions):
    """BGN's structured dynamics head (``bgn.model.bgn.ModelConfig`` composes it): which head
    predicts the target, and the pair-force head's options."""

    # Not in the paper: "newton" replaces the decoder of Eq. 5 by the scene's structured head
    # (``build_head``: learned central pair forces, equal and opposite, masses fitted to the
    # window, on pairwise-force scenes; pair impulses on contact scenes); "decoder" is the
    # paper's. "auto" is resolved before a model is built (bgn.studies.auto).
    dynamics: str = "decoder"
    # substeps of a frame that dynamics=soft_contact integrates (its contacts' stiffness is
    # bounded by what they integrate stably)
    contact_substeps: int = 10
    # its contacts' damping: lose (>= 0: a contact never creates energy) | any (either sign)
    contact_energy: str = "lose"
    # after the fit: rollout (its damping set on rollouts of the training split,
    # bgn.training.calibrate) | none
    contact_calibration: str = "rollout"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_ints(self, ("contact_substeps",))
        if self.contact_calibration not in CONTACT_CALIBRATION:
            raise ValueError(f"contact_calibration={self.contact_calibration!r}; choose one "
                             f"of {CONTACT_CALIBRATION}")
        if self.contact_energy not in CONTACT_ENERGY:
            raise ValueError(f"contact_energy={self.contact_energy!r}; choose one of "
                             f"{CONTACT_ENERGY}")
        if self.dynamics not in DYNAMICS:
            raise ValueError(f"dynamics={self.dynamics!r}; choose one of {DYNAMICS}")


@dataclass
class NewtonConfig(ForceLawOptions, DynamicsConfig):
    """Options of the structured force model (the schema of ``conf/model/newton.yaml``)."""

    hidden: int = 64                   # width of the force-law MLP f(s)
    layers: int = 2                    # its hidden layers
    activation: str = "silu"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_positive_ints(self, ("hidden", "layers"))
        activation(self.activation)


def past_positions(g: Graph) -> torch.Tensor:
    """(N, k+1, D) positions x[t], x[t-1], .., x[t-k] (newest first) from the graph's current
    position and its backward-difference velocity window."""
    dt = g.dt.to(g.vel.dtype)[g.batch][:, None, None]
    back = torch.cumsum(g.vel[:, :-1] * dt, dim=1)               # x[t] - x[t-j], j = 1..k
    return torch.cat([g.pos[:, None], g.pos[:, None] - back], dim=1)


def numerov(f: torch.Tensor) -> torch.Tensor:
    """What a finite-difference acceleration ``(x[t+1] - 2 x[t] + x[t-1]) / dt^2`` (the
    training target) sees of an instantaneous acceleration ``f`` (., F, D) given at frames t,
    t-1, .., t-F+1 (newest first): Numerov's weights ``(f[t+1] + 10 f[t] + f[t-1]) / 12``,
    exact to O(dt^4), at frames t-1 .. t-F+2; at frame t, whose f[t+1] is not known yet, with
    f[t+1] extrapolated quadratically, ``(13 f[t] - 2 f[t-1] + f[t-2]) / 12``. Returns
    (., F-1, D), frames t .. t-F+2. With the true force law and masses this brings the
    instantaneous force closer to the recorded target
    (docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs")."""
    now = (13 * f[:, 0] - 2 * f[:, 1] + f[:, 2]) / 12
    centred = (f[:, :-2] + 10 * f[:, 1:-1] + f[:, 2:]) / 12
    return torch.cat([now[:, None], centred], dim=1)


def verlet(accel: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, v: torch.Tensor,
           h: torch.Tensor, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Velocity Verlet (kick-drift-kick), ``steps`` steps of ``h`` (N, 1; negative: backwards in
    time) from positions ``x`` and velocities ``v`` (N, D) under ``accel(positions)``. Returns
    the displacement from ``x`` (kept apart from the absolute positions so that a large offset
    does not swallow it in float32) and the final velocities."""
    moved = torch.zeros_like(x)
    a = accel(x)
    for _ in range(steps):
        v = v + 0.5 * h * a
        moved = moved + h * v
        a = accel(x + moved)
        v = v + 0.5 * h * a
    return moved, v


def shoot(accel: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor, back: torch.Tensor,
          dt: torch.Tensor, steps: int, iterations: int = SHOOTING_ITERATIONS) -> torch.Tensor:
    """The finite-difference acceleration ``(x[t+1] - 2 x[t] + x[t-1]) / dt^2`` (the training
    target) of the trajectory under ``accel`` through the last two frames: the velocity at
    frame t is found by shooting (integrate back over one frame in ``steps`` Verlet substeps,
    correct the velocity by the miss at x[t-1], a Newton step with the Jacobian -dt I), then
    the frame ahead is integrated from it. ``back``: (N, D) ``(x[t] - x[t-1]) / dt``; ``dt``:
    (N, 1). A close encounter within a frame, which one force evaluation per frame cannot
    follow, is integrated in substeps, which reproduce the recorded targets far more closely
    (docs/notes/2026-11-26-results-history.md, "Gravity_r2: what frames allow")."""
    h = dt / steps
    v = back + 0.5 * dt * accel(x)
    for _ in range(iterations):
        moved, _ = verlet(accel, x, v, -h, steps)
        v = v + (moved + dt * back) / dt                    # miss at x[t-1] = x[t] - dt back
    moved, _ = verlet(accel, x, v, h, steps)
    return (moved / dt - back) / dt


def check_scene(meta: SceneMeta, history: int, option: str) -> None:
    """One clear error when a scene or window cannot carry the structured force head."""
    # "unknown": imported data, whose law the head is a candidate for
    # (docs/design.md#imported-scenes)
    # a radius graph is fine: a pair beyond it has no edge and no force (the module doc)
    if meta.interaction not in ("pairwise", "unknown") or meta.target != "acceleration" \
            or meta.graph not in ("full", "radius"):
        raise ValueError(f"{option} needs pairwise forces on a complete or radius graph with "
                         f"an acceleration target; {meta.name} is {meta.interaction}, "
                         f"{meta.graph} graph, {meta.target} target: use model=bgn with "
                         "model.dynamics=decoder")
    if history < 3:
        raise ValueError(f"{option} fits masses to the window's accelerations: "
                         f"dataset.history={history} must be >= 3")


class ExpScaledLaw(nn.Sequential):
    """An MLP law ``f = a exp(b)`` from the MLP's two outputs ``(a, b)`` (``law_output=
    exp_scaled``). An optimiser's step moves every parameter by about its learning rate
    whatever the gradient (Adam); in a plain output that is an absolute change of f, which a
    law falling over orders of magnitude (an inverse square from encounters to pairs far apart)
    cannot afford where it is small: a gravity law's far tail then carries the last layer's
    jitter as an offset. Through ``exp(b)`` the same step is a relative change of f at every
    distance, and a zero crossing (a spring's) stays ``a``'s. Output (..., 1) as the plain
    MLP's."""

    def __init__(self, *layers: nn.Module) -> None:
        super().__init__(*layers)
        with torch.no_grad():  # b = 0 at the start: f starts as the plain MLP's would
            self[-1].weight[1:].zero_()
            self[-1].bias[1:].zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = super().forward(x)
        return y[..., :1] * torch.exp(LOG_SCALE_MAX * torch.tanh(y[..., 1:] / LOG_SCALE_MAX))


class PairForceHead(nn.Module):
    """The structured dynamics head (see the module doc): positions and the velocity window
    of a graph -> its acceleration at frame t in physical units, (N, D)."""

    def __init__(self, meta: SceneMeta, normalizer: Normalizer, hidden: int, layers: int,
                 act: str, mass_law: str, substeps: int = 1, law_formula: str = "",
                 law_scale: float = 1.0, rollout_masses: str = "window",
                 law_output: str = "linear", law_gain: bool = False) -> None:
        super().__init__()  # mass_law: checked by the model configs (NewtonConfig, BGN's)
        self.mass_law, self.types, self.substeps = mass_law, meta.n_types, substeps
        self.rollout_masses = rollout_masses  # ForceLawOptions.rollout_masses
        self.law_scale = law_scale  # labels only (ForceLawOptions.law_scale)
        if mass_law == "type":  # log m per type; the law's free scale is type 0's mass
            self.log_type_mass = nn.Parameter(torch.zeros(max(meta.n_types, 1)))
        # lengths in the units the model normalises relative positions by (a copy: the
        # normaliser belongs to the model)
        self.register_buffer("length_scale", normalizer.rel_position_scale.detach().clone())
        # law_formula: the law a formula of the physical distance (bgn.model.formula_law),
        # its constants trainable; else an MLP
        sizes = [3 + (meta.n_types if meta.n_types > 1 else 0), *[hidden] * layers]
        if law_formula:
            self.force_law: nn.Module = FormulaLaw(law_formula, meta.n_types)
        elif law_output == "exp_scaled":
            self.force_law = ExpScaledLaw(*mlp([*sizes, 2], act))
        else:
            self.force_law = mlp([*sizes, 1], act)
        # law_gain: the MLP law's overall factor as a parameter of its own (log). Where the
        # window's mass fit absorbs the law's scale, only the law loss (recorded masses) sees
        # that direction; spread over the MLP's weights beside the dynamics loss, Adam's steps
        # along it are set by that loss's noise on those weights and the scale barely moves
        # (slower still at a matched law's reduced rate). One parameter gets its own step size
        # from the law loss alone (docs/design.md, "The law's scale").
        self.log_law_gain = (nn.Parameter(torch.zeros(()))
                             if law_gain and not law_formula else None)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: Any) -> None:
        # a checkpoint written before the law had a gain of its own: its law's factor is 1
        if self.log_law_gain is not None and prefix + "log_law_gain" not in state_dict:
            state_dict[prefix + "log_law_gain"] = torch.zeros(())
        super()._load_from_state_dict(state_dict, prefix, *args)

    def pair_terms(self, g: Graph, positions: torch.Tensor) -> torch.Tensor:
        """(E, F, D) ``f(s_ij) u_ij`` on every edge j -> i at each of the F frames of
        ``positions`` (N, F, D); relative positions in normalised units (the scale is free)."""
        rel, dist = self.separations(g, positions)
        pair = self.pair_index(g)
        if isinstance(self.force_law, FormulaLaw):  # physical distances, physical law
            return self.force_law(dist * self.length_scale, pair) * rel / dist
        f = self.force_law(self.law_input(dist, pair))
        if self.log_law_gain is not None:
            f = f * torch.exp(self.log_law_gain)
        return f * rel / dist

    @torch.no_grad()
    def law_at(self, r: np.ndarray, dim: int, types: tuple[int, int] = (0, 0)) -> np.ndarray:
        """The law ``f(r)`` (float64, the shape of ``r``) at physical distances ``r`` between a
        particle of type ``types[0]`` (the source) and one of ``types[1]``, through
        ``pair_terms`` on a two-particle graph of one edge per distance: whatever inputs the
        law reads, they are read so. In the law's own scale (``law_scale`` puts a formula
        kept in the network's free scale in physical units)."""
        param = next(self.parameters())
        r = np.asarray(r, dtype=np.float64)
        pos = torch.zeros(2, r.size, dim, dtype=param.dtype, device=param.device)
        pos[1, :, 0] = torch.as_tensor(r.ravel(), dtype=param.dtype)
        g = SimpleNamespace(edge_index=torch.tensor([[0], [1]], device=param.device),
                            types=torch.tensor(types, device=param.device))
        return self.pair_terms(g, pos)[0, :, 0].double().cpu().numpy().reshape(r.shape)

    def labelled_law_at(self, r: np.ndarray, dim: int, types: tuple[int, int] = (0, 0),
                        ) -> np.ndarray:
        """``law_at`` times ``law_scale``: the law in the units its labels and formula text
        are written in (physical where the formula stage put it so)."""
        return float(self.law_scale) * self.law_at(r, dim, types)

    def separations(self, g: Graph, positions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, F, D) relative positions of every edge j -> i at each frame of ``positions``
        (N, F, D), in normalised units, and their lengths (E, F, 1)."""
        rel = edge_vector(positions, g) / self.length_scale
        return rel, torch.sqrt((rel * rel).sum(-1, keepdim=True) + DIRECTION_EPS**2)

    def pair_index(self, g: Graph) -> torch.Tensor | None:
        """(E,) each edge's unordered pair of types, ``lo * n_types + hi`` (None: one type)."""
        if self.types <= 1:
            return None
        snd, rcv = g.edge_index
        a, b = g.types[snd], g.types[rcv]
        return torch.minimum(a, b) * self.types + torch.maximum(a, b)

    def law_input(self, dist: torch.Tensor, pair: torch.Tensor | None) -> torch.Tensor:
        """(E, F, 3 [+ types]) what the MLP law reads of each pair (``pair_index``) at each of
        the F frames of ``dist`` (E, F, 1)."""
        # distance, its inverse and its log: a spring's linear law and gravity's 1/s^2 near
        # an encounter are then a few units of the MLP each, not a curve it must bend to
        feats = [dist, 1 / dist, torch.log(dist)]
        if pair is not None:  # symmetric in the pair: the law may differ per pair of types
            both = F.one_hot(pair // self.types, self.types) + F.one_hot(pair % self.types,
                                                                         self.types)
            feats.append(both[:, None].expand(-1, dist.shape[1], -1).to(dist.dtype))
        return torch.cat(feats, dim=-1)

    def forward(self, g: Graph, known_masses: bool = False) -> tuple[torch.Tensor, None]:
        """(N, D) predicted acceleration at frame t, physical units (and no contact logits:
        the interface of ``build_head``'s heads). ``known_masses``: the graph's recorded
        masses in place of the window's fit (training only: ``law_loss``); a graph's
        ``mass_fit``, where a rollout holds one (``held_fit``), in place of the window's."""
        raw, terms = self.window(g)
        if known_masses:
            if self.mass_law == "coupling":
                raise ValueError("mass_law=coupling has no recorded couplings to train with")
            mass = g.mass.to(terms.dtype)
            fit = mass if self.mass_law == "source" else 1 / mass
        elif g.mass_fit is not None:
            fit = g.mass_fit.to(terms.dtype)
        else:
            fit = self.fit(g, terms)
        return self.accelerate(g, raw, fit), None

    def held_fit(self, g: Graph) -> torch.Tensor | None:
        """(N,) the fit a rollout holds from its first window ``g`` (``rollout_masses=held``;
        the learned simulator passes it back as the graph's ``mass_fit``), else None. One
        learned mass per type (``mass_law=type``) is held by construction: None. Couplings
        (``mass_law=coupling``) are always held: ``g`` is then the windows of the frames before
        the start (``context_windows``), pooled per simulation."""
        if self.mass_law == "type" or (self.rollout_masses != "held"
                                       and self.mass_law != "coupling"):
            return None
        return self.fit(g, self.window(g)[1])

    @property
    def context_windows(self) -> int:
        """How many windows before a rollout's start its held fit reads (``held_fit``)."""
        return COUPLING_WINDOWS if self.mass_law == "coupling" else 1

    def window(self, g: Graph) -> tuple[torch.Tensor, torch.Tensor]:
        """The pair terms of the window's frames t, t-1, .., t-k (E, k+1, D) and what a
        finite-difference acceleration sees of them (``numerov``), frames t .. t-k+1."""
        raw = self.pair_terms(g, past_positions(g))
        return raw, numerov(raw)

    def accelerate(self, g: Graph, raw: torch.Tensor, fit: torch.Tensor) -> torch.Tensor:
        """(N, D) the acceleration at frame t from the window's pair terms ``raw`` and the
        mass fit ``fit`` (``1 / m_i`` inertial, ``m_i`` source, ``(k_i, c_i)`` coupling)."""
        snd, rcv = g.edge_index
        if self.mass_law == "coupling":
            def combine(t: torch.Tensor) -> torch.Tensor:          # a_i = k_i sum_j c_j F_ij
                return fit[:, :1] * scatter_sum(fit[snd, 1:] * t, rcv, g.pos.shape[0])
        elif self.mass_law != "source":
            def combine(t: torch.Tensor) -> torch.Tensor:          # a_i = sum_j F_ij / m_i
                return fit[:, None] * scatter_sum(t, rcv, g.pos.shape[0])
        else:
            def combine(t: torch.Tensor) -> torch.Tensor:          # a_i = sum_j m_j F_ij
                return scatter_sum(fit[snd, None] * t, rcv, g.pos.shape[0])
        dt = g.dt.to(g.vel.dtype)[g.batch][:, None]
        if self.substeps > 1:  # the frame integrated in substeps with the fitted masses
            return shoot(lambda x: combine(self.pair_terms(g, x[:, None])[:, 0]), g.pos,
                         g.vel[:, 0], dt, self.substeps)
        # Numerov at frame t needs the forces at x[t+1], which the acceleration sets: a few
        # fixed-point steps of the implicit scheme, the next position by the step rule
        a = combine(numerov(raw)[:, 0])
        for _ in range(IMPLICIT_STEPS):
            x_next = g.pos + dt * (g.vel[:, 0] + dt * a)
            ahead = self.pair_terms(g, x_next[:, None])[:, 0]
            a = combine((ahead + 10 * raw[:, 0] + raw[:, 1]) / 12)
        return a

    def fit(self, g: Graph, terms: torch.Tensor) -> torch.Tensor:
        """(N,) the window's least-squares fit: ``1 / m_i`` under the inertial law, ``m_i``
        under the source law, to the pair terms ``terms`` (E, F, D) of frames t .. t-k+1;
        (N, 2) ``(k_i, c_i)`` under the coupling law, pooled over each simulation's windows."""
        return self.least_squares(g, terms)[0]

    def least_squares(self, g: Graph, terms: torch.Tensor, with_error: bool = False,
                      ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``fit`` and, ``with_error``, its standard error (N,) from the residuals: small where
        the window pins the mass, large where it does not (bodies far apart under gravity).
        Without it (rollouts, the heads that do not read it) the error is not computed."""
        return self.fit_observed(g, *self.observed_system(g, terms), with_error)

    def observed_system(self, g: Graph, terms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """What ``least_squares`` fits: the pair terms ``terms`` (E, F, D) of frames t ..
        t-k+1 at the frames whose accelerations the window shows, (E, F-1, D), and those
        accelerations a[t-1] .. a[t-k+1], (N, F-1, D)."""
        return terms[:, 1:], observed_targets(g, "acceleration")[:, :terms.shape[1] - 1]

    def observed_prediction(self, g: Graph, past: torch.Tensor, fit: torch.Tensor,
                            ) -> torch.Tensor:
        """(N, F, D) the accelerations the law gives at the F frames of the pair terms ``past``
        (E, F, D) with the fit ``fit`` (N,) (``1 / m_i`` inertial or type, ``m_i`` source;
        (N, 2) ``(k_i, c_i)`` coupling): what ``fit_observed`` matches to the observed ones."""
        snd, rcv = g.edge_index
        if self.mass_law == "coupling":
            return fit[:, :1, None] * scatter_sum(fit[snd, 1:, None] * past, rcv, g.pos.shape[0])
        if self.mass_law == "source":
            return scatter_sum(fit[snd, None, None] * past, rcv, g.pos.shape[0])
        return fit[:, None, None] * scatter_sum(past, rcv, g.pos.shape[0])

    def fit_observed(self, g: Graph, past: torch.Tensor, seen: torch.Tensor,
                     with_error: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``least_squares`` of pair terms ``past`` (E, F, D) to accelerations ``seen``
        (N, F, D) at the same F frames, whichever frames they are: one window's
        (``observed_system``), or the windows of a whole simulation stacked along F on one
        graph (``bgn.eval.law_posterior``). Under the coupling law, over every graph of one
        simulation (``g.sim``) pooled; its error (N, 2), those of ``k`` and ``c``."""
        if self.mass_law == "coupling":
            return self.couplings(g, past, seen, with_error)
        if self.mass_law == "source":
            return self.source_masses(g, past, seen, with_error)
        if self.mass_law == "type":  # 1 / m of each particle's type, known exactly
            fit = torch.exp(-self.log_type_mass.to(past.dtype))[g.types]
            return fit, torch.zeros_like(fit) if with_error else None
        past = scatter_sum(past, g.edge_index[1], g.pos.shape[0])
        norm = (past * past).sum((1, 2)) + FIT_EPS
        fit = (past * seen).sum((1, 2)) / norm
        if not with_error:
            return fit, None
        residual = ((seen - fit[:, None, None] * past) ** 2).sum((1, 2))
        dof = max(seen.shape[1] * seen.shape[2] - 1, 1)  # one unknown per particle
        return fit, torch.sqrt(residual / dof / norm)

    def fitted_log_mass(self, g: Graph, fit: torch.Tensor | None = None,
                        error: torch.Tensor | None = None) -> torch.Tensor:
        """(N,) log of the masses the window's fit gives (up to the free scale of the learned
        force law, a constant per model): a feature that carries each particle's mass, for
        the inverse model's context (``mass_context=fit``). ``fit``: the head's own fit of
        this graph where the caller has it (no second solve). With the fit's standard
        ``error`` (``least_squares``): (N, 2), also the log of the relative error, which says
        how far the log-mass can be trusted."""
        if fit is None:
            fit = self.fit(g, self.window(g)[1])
        if self.mass_law == "coupling":  # m_i = c_i / k_i, up to the law's free scale
            log_fit = torch.log(fit[:, 1].abs() + FIT_EPS) - torch.log(fit[:, 0].abs() + FIT_EPS)
            if error is None:
                return log_fit
            rel = torch.sqrt(((error / (fit.abs() + FIT_EPS)) ** 2).sum(-1))
            return torch.stack([log_fit, torch.log(rel + REL_ERROR_FLOOR)], -1)
        log_fit = torch.log(fit.abs() + FIT_EPS)
        log_fit = log_fit if self.mass_law == "source" else -log_fit
        if error is None:
            return log_fit
        return torch.stack([log_fit, torch.log(error / (fit.abs() + FIT_EPS) + REL_ERROR_FLOOR)],
                           -1)

    def couplings(self, g: Graph, past: torch.Tensor, seen: torch.Tensor,
                  with_error: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(N, 2) every particle's ``(k_i, c_i)`` of ``a_i = k_i sum_j c_j f(s_ij) u_ij``
        fitted over all windows of its simulation in ``g`` at once (``bgn.model.coupling``),
        in the gauge ``normalise`` fixes; ``with_error``: their standard errors (N, 2)."""
        design, target, real, where = simulation_system(g, past, seen)
        k, c = fit_couplings(design, target, real)
        fit = torch.stack([k[where], c[where]], -1)
        if not with_error:
            return fit, None
        k_err, c_err = coupling_errors(design.detach(), target, real, k.detach(), c.detach())
        return fit, torch.stack([k_err[where], c_err[where]], -1)

    def source_masses(self, g: Graph, past: torch.Tensor, seen: torch.Tensor,
                      with_error: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(N,) one mass per particle such that ``a_i = sum_j m_j f(s_ij) u_ij`` fits the
        window's accelerations best, by least squares jointly per simulation (ridge-regularised
        normal equations, differentiable). ``past``: (E, F, D) pair terms at the F frames of
        ``seen`` (N, F, D). ``with_error``: also their standard errors (N,), the residuals'
        variance times the inverse normal matrix (else None). The system is dense per graph
        (N x N particles, the pairs without an edge zero: a radius graph's far pairs); graphs
        of fewer particles than the batch's largest are padded with particles that feel and
        exert nothing, which the ridge pins at mass 0 and the result drops."""
        n_graphs, n_frames, dim = g.num_graphs, past.shape[1], past.shape[2]
        counts = g.num_nodes.to(g.batch.device)
        n = int(counts.max())
        local = g.local_index
        snd, rcv = g.edge_index
        # design[b, i, frame, d, j]: the term of particle j in particle i's acceleration
        design = past.new_zeros(n_graphs, n, n_frames, dim, n)
        design[g.batch[rcv], local[rcv], :, :, local[snd]] = past
        # in float64: the normal equations square the condition number
        design = design.reshape(n_graphs, -1, n).double()
        padded = seen.new_zeros(n_graphs, n, n_frames, dim)
        padded[g.batch, local] = seen
        target = padded.reshape(n_graphs, -1, 1).double()
        real = (g.batch, local)  # the rows of (B, n) that hold a particle
        # Relative errors, then a robust reweighting (Cauchy, scale ROBUST_SCALE): the frames
        # of a close encounter are the least resolved by the frame rate, and one of them would
        # otherwise set every mass of its simulation.
        size = target.abs().sum(1, keepdim=True) / (counts * n_frames * dim)[:, None, None]
        weight = 1 / (target.abs() + size * 1e-3 + FIT_EPS)  # size: the mean over real rows
        for step in range(ROBUST_STEPS + 1):
            wd = design * weight
            gram = wd.transpose(1, 2) @ wd
            # a ridge relative to each particle's own column: a particle that pulls on no one
            # within the window gets a finite mass, not a singular system. (A ridge relative
            # to the mean of the diagonal shrank the columns of heavy particles, whose pull
            # shows in the light ones' small, down-weighted rows: masses 1, 1e-3, 1e-3, 1e-3
            # came out far off, now close: docs/notes/2026-11-26-results-history.md,
            # "Gravity's mass fit"; tested)
            ridge = torch.diag_embed(1e-6 * gram.diagonal(dim1=1, dim2=2) + FIT_EPS)
            masses = torch.linalg.solve(gram + ridge, wd.transpose(1, 2) @ (target * weight))
            residual = (design @ masses - target) * weight
            if step < ROBUST_STEPS:
                weight = weight / (1 + (residual / ROBUST_SCALE) ** 2).sqrt()
        fitted = masses[..., 0][real].to(past.dtype)
        if not with_error:
            return fitted, None
        rows = (counts * n_frames * dim - counts).clamp_min(1)[:, None]  # dof per graph
        variance = (residual**2).sum(1) / rows.to(residual.dtype)               # (B, 1)
        error = (variance * torch.linalg.inv(gram + ridge).diagonal(dim1=1, dim2=2)).sqrt()
        return fitted, error[real].to(past.dtype)


def check_mass_law(meta: SceneMeta, mass_law: str, option: str) -> None:
    """One clear error where ``mass_law`` cannot serve the scene: couplings are fitted densely
    per simulation, a cost that grows as n^3, so at most ``coupling.MAX_PARTICLES``."""
    if mass_law == "coupling" and meta.n_particles > COUPLING_MAX_PARTICLES:
        raise ValueError(f"{option} with mass_law=coupling fits the couplings densely per "
                         f"simulation, for at most {COUPLING_MAX_PARTICLES} particles; "
                         f"{meta.name} has {meta.n_particles}: use mass_law=inertial, source "
                         "or type")


def build_head(meta: SceneMeta, normalizer: Normalizer, history: int, hidden: int, layers: int,
               act: str, mass_law: str, option: str, substeps: int = 1,
               law_formula: str = "", law_scale: float = 1.0, rollout_masses: str = "window",
               law_output: str = "linear", law_gain: bool = False,
               ) -> PairForceHead | ContactImpulseHead:
    """The structured dynamics head of a scene: pair forces (``PairForceHead``) or pair
    impulses at the time of impact (``bgn.model.impulse``); ``head(g)`` gives the physical
    target and the contact gate's logits (None for forces). ``option`` names the setting in
    errors. ``law_gain``: the law's overall factor a parameter of its own (where the law loss
    trains the law beside the dynamics loss, ``PairForceHead``)."""
    if meta.interaction == "contact":
        if meta.target != "velocity":
            raise ValueError(f"{option} on a contact scene needs a next-velocity target")
        return ContactImpulseHead(meta, hidden, act)
    check_scene(meta, history, option)
    check_mass_law(meta, mass_law, option)
    return PairForceHead(meta, normalizer, hidden, layers, act, mass_law, substeps, law_formula,
                         law_scale, rollout_masses, law_output, law_gain)


def head_given(head: nn.Module) -> tuple[str, ...]:
    """What a structured head reads beyond the position window (``PhysicsModel.given``): the
    impulse head the radii (contact distances, masses per radius), the pair-force head the
    types where the scene has several (its law per pair of types) and, fitting couplings
    (``mass_law=coupling``), the recorded frames before a rollout's start."""
    if isinstance(head, ContactImpulseHead):
        return ("radii",)
    if isinstance(head, SoftContactHead):
        return ("radii", "types") if bool(head.radii_given) else ("types",)
    if not isinstance(head, PairForceHead):
        return ()
    return (("types",) if head.types > 1 else ()) + (
        ("earlier frames",) if head.mass_law == "coupling" else ())


def head_physics(head: nn.Module) -> str:
    """The physics a structured head writes in (``PhysicsModel.physics``)."""
    if isinstance(head, ContactImpulseHead):
        return ("impulses along the normal at the time of impact, equal and opposite, in "
                "event order (restitution learned, at most elastic); masses learned per radius")
    if isinstance(head, SoftContactHead):
        damping = ("of either sign" if head.pair.energy == "any"
                   else "dissipative: a contact never creates energy")
        return ("soft pair and wall contacts at the contact distances, equal and opposite: "
                f"spring, dashpot ({damping}), Coulomb-capped tangential damping; one mass per "
                "type, a uniform field and a linear drag, all learned")
    assert isinstance(head, PairForceHead)
    masses = {"inertial": "inertial masses fitted to the window, a = F / m",
              "source": "masses at the source fitted per simulation, a_i = sum_j m_j F_ij",
              "type": "one mass per particle type, learned (equal where one type), a = F / m",
              "coupling": "couplings of either sign fitted per simulation, a_i = k_i sum_j c_j "
                          "F_ij (k = q / m, c = q), in a rollout fitted to the frames before "
                          "its start"}
    formula = formula_text(head)
    law = "" if formula is None else f"; the pair law a fitted formula {formula}"
    held = ("; in a rollout fitted once, to its first window, and held"
            if head.rollout_masses == "held" and head.mass_law not in ("type", "coupling")
            else "")
    return (f"central pair forces, equal and opposite; {masses[head.mass_law]} "
            f"(mass_law={head.mass_law}){held}{law}")


def formula_text(head: PairForceHead) -> str | None:
    """The head's formula law as text, in the units of its labels (``law_scale``), each pair
    of types named where the law reads types; None for a network law."""
    if not isinstance(head.force_law, FormulaLaw):
        return None
    return "; ".join(
        pair_text(p, head.law_scale) + (f" (types {p['types']})" if head.types > 1 else "")
        for p in json.loads(head.force_law.spec()))


def head_label(head: nn.Module) -> str:
    """The head's part of a model's label: "impulse head (radii)", "pair-force head (masses
    inertial)" ("(types, masses source)" where its law reads the types)."""
    if isinstance(head, ContactImpulseHead):
        return "impulse head (radii)"
    if isinstance(head, SoftContactHead):
        return ("soft-contact head (radii, types)" if bool(head.radii_given) else
                "soft-contact head (types, contact distances measured)")
    assert isinstance(head, PairForceHead)
    law = ", law a formula" if isinstance(head.force_law, FormulaLaw) else ""
    held = " held" if head.mass_law == "coupling" or (
        head.rollout_masses == "held" and head.mass_law != "type") else ""
    return (f"pair-force head ({'types, ' if head.types > 1 else ''}masses {head.mass_law}"
            f"{held}{law})")


def pair_force_head_of(model: nn.Module) -> PairForceHead | None:
    """A model's pair-force head (BGN's ``force_head``, ``model=newton``'s ``head``), or None."""
    head = getattr(model, "force_head", None) or getattr(model, "head", None)
    return head if isinstance(head, PairForceHead) else None


def held_fit(head: nn.Module | None, g: Graph) -> torch.Tensor | None:
    """``PairForceHead.held_fit`` of a model's structured head (None for other heads)."""
    return head.held_fit(g) if isinstance(head, PairForceHead) else None


def held_windows(head: nn.Module | None) -> int:
    """``PairForceHead.context_windows`` of a model's structured head (1 for other heads)."""
    return head.context_windows if isinstance(head, PairForceHead) else 1


def law_loss(head: nn.Module, g: Graph, reduce: bool = True) -> torch.Tensor | None:
    """The force head's prediction with the recorded masses in place of the window's fit,
    scored by its squared error relative to the target's own size (None for other heads). The
    fit absorbs any law's scale, and over the few frames of a window almost any shape: trained
    through the fit alone, gravity_r2's law came out nowhere near 1/s^2 while the one-step error
    stayed small (docs/notes/2026-11-26-results-history.md, "Gravity_r2: what frames allow").
    With the true masses the law is identified; relative errors
    (``target_coder.relative_squared_error``) weigh every distance alike, where a squared error
    is set by the few close encounters (docs/notes/2026-11-26-results-history.md, "Moved here
    from code comments and configs").
    ``reduce=False``: the relative error of each particle, (N,)."""
    if not isinstance(head, PairForceHead) or head.mass_law == "coupling":
        return None  # no recorded couplings to train the law with
    predicted, target = head(g, known_masses=True)[0], g.target.to(g.pos.dtype)
    rel = relative_squared_error(predicted, target)
    return rel.mean() if reduce else rel


def impulse_mass_loss(head: nn.Module, g: Graph, normalizer: Normalizer) -> torch.Tensor | None:
    """The impulse head's relative log-masses against the training masses (normalised MSE, as
    BGN's Eq. 9-10 loss), or None for a head without learned masses. The velocities alone
    barely constrain a heavy disc's mass: its velocity changes are small in absolute terms."""
    if not isinstance(head, ContactImpulseHead) or g.edge_index.shape[1] == 0:
        return None
    log_m = head.log_masses(g)
    predicted = normalizer.rel_log_mass(log_m[g.edge_index[1]] - log_m[g.edge_index[0]])
    return F.mse_loss(predicted, normalizer.rel_log_mass(g.edge_rel_log_mass).to(predicted.dtype))


class Newton(PhysicsModel):
    """Newton's laws with a learned interaction: the structured force head on pairwise-force
    scenes (see the module doc; BGN carries it with ``model.dynamics=newton``), pair impulses
    at the time of impact on contact scenes (``bgn.model.impulse``)."""

    name = "newton"
    config_class = NewtonConfig

    def build(self, cfg: NewtonConfig, stats: Mapping[str, Any]) -> None:
        self.head = build_head(self.meta, self.normalizer, self.history, cfg.hidden, cfg.layers,
                               cfg.activation, cfg.mass_law, "model=newton", cfg.substeps,
                               cfg.law_formula if cfg.law == "formula" else "", cfg.law_scale,
                               cfg.rollout_masses, cfg.law_output)
        if self.meta.interaction == "contact":
            self.heads = frozenset({"dynamics", "contact", "impulse_mass"})
            self.register_buffer("contact_pos_weight", torch.tensor(
                contact_pos_weight(stats, "balanced")), persistent=False)

    @property
    def label(self) -> str:
        return f"Newton {head_label(self.head)}"

    @property
    def given(self) -> tuple[str, ...]:
        return head_given(self.head)

    @property
    def physics(self) -> str:
        return head_physics(self.head)

    def held_mass_fit(self, g: Graph) -> torch.Tensor | None:
        return held_fit(self.head, g)

    @property
    def held_fit_windows(self) -> int:
        return held_windows(self.head)

    def forward(self, g: Graph) -> ModelOutput:
        self.check(g)
        target, logits = self.head(g)
        return ModelOutput(self.target_coder.code(g, target), contact=logits)

    def forward_target(self, g: Graph) -> torch.Tensor:
        return self.forward(g).target

    def contact_target(self, g: Graph) -> torch.Tensor:
        return g.edge_contact

    def loss_terms(self, g: Graph, out: ModelOutput) -> dict[str, torch.Tensor]:
        terms = super().loss_terms(g, out)
        if out.contact is not None and out.contact.numel():
            terms["contact"] = F.binary_cross_entropy_with_logits(
                out.contact, g.edge_contact.to(out.contact.dtype),
                pos_weight=self.contact_pos_weight.to(out.contact.dtype))
        mass = impulse_mass_loss(self.head, g, self.normalizer)
        if mass is not None:
            terms["impulse_mass"] = mass
        return terms
