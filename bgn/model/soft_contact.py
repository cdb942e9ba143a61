"""Soft contacts for granular media: dissipative pair and wall contacts with friction, a
uniform field and drag, integrated over substeps within a frame.

Granular discs under gravity (docs/design.md#granular-media) touch in two ways that the
impulse head (``bgn.model.impulse``) cannot write: impacts that lose energy and push the discs
sideways by friction, and contacts that last (a pile at rest on the floor). The discrete
element method's contact law holds both: while two discs overlap by ``delta = d_ij - |x_ij|``
(``d_ij`` their contact distance) they push apart along the normal ``n`` with a spring and a
dashpot, and slide against a tangential force that opposes the tangential relative velocity
``v_t``, at most Coulomb's ``mu`` times the normal force:

    a_ij^n = s_ij (k delta - c v_n) n
    a_ij^t = -s_ij min(c_t |v_t|, mu |k delta - c v_n|) v_t / |v_t|

with ``s_ij = m_j / (m_i + m_j)`` the share of the pair's acceleration that i takes (equal and
opposite forces: ``m_i a_ij = -m_j a_ji``); a wall is a disc of infinite mass (``s = 1``) at the
plane. The head learns, from the frames alone: the stiffness and damping of pair and wall
contacts (their restitution follows: no elasticity is written in; the damping is at least 0
by default, ``contact_energy="lose"``, or of either sign, ``"any"``), tangential damping and
friction, one mass per particle type (ratios only enter),
a uniform acceleration (gravity) and a linear drag. Contact distances are the discs' radii
where the file gives them (``r_i + r_j``, ``r_i`` to a wall); where it does not (a GNS-layout
file has types, no radii), the closest approaches in the training frames, per pair of types
and per type to a wall (``bgn.data.contacts.closest_approach``, set before the first step).

The stiffness is a fraction of the fastest one the substeps integrate stably (``omega h <
OMEGA_H_MAX``), so no setting of the learned values can blow a step up. The velocity at frame
t is the backward difference plus half a frame of the head's own acceleration there (exact
in free fall); the frame is then integrated over ``substeps`` semi-implicit Euler steps and
the head returns the finite-difference acceleration ``(x[t+1] - 2 x[t] + x[t-1]) / dt^2`` it
implies (the imported data's target).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from bgn.graph import Graph
from bgn.model.impulse import walls
from bgn.model.message_passing import edge_vector
from bgn.sim.scene import SceneMeta

TINY = 1e-20
OMEGA_H_MAX = 1.5         # semi-implicit Euler is stable for omega h < 2 (undamped)
# the damping's sign: "lose" (>= 0, the default: chosen on validation rollouts, docs/results.md
# "Granular media") or "any" (a contact may also create energy)
CONTACT_ENERGY = ("lose", "any")
# after the fit: "rollout" sets the damping on rollouts of the training split (the default:
# chosen on validation, docs/results.md "Granular media"; bgn.training.calibrate) or "none"
CONTACT_CALIBRATION = ("rollout", "none")
# starting values: a contact lasts about one frame (omega = pi / dt), damping ratio 0.1
# (restitution 0.73), tangential damping a twentieth of the substep's limit, mu 0.5
START_ZETA, START_TANGENT, START_MU = 0.1, 0.05, 0.5
REPLAY_FRAMES = 2        # frames of the window replayed to find the velocity at frame t


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def _softplus_inverse(y: float) -> float:
    return math.log(math.expm1(y))


class ContactLaw(nn.Module):
    """The learned constants of one kind of contact (pairs or walls), all without a unit once
    multiplied by the frame's scales: stiffness as ``omega h`` (a fraction of the stable
    limit), the damping ratio (``energy``: "lose", at least 0, so a contact never creates
    energy; "any", either sign), tangential damping as ``c_t h`` and the friction
    coefficient."""

    def __init__(self, substeps: int, energy: str = "lose") -> None:
        super().__init__()
        if energy not in CONTACT_ENERGY:
            raise ValueError(f"contact_energy={energy!r}; choose one of {CONTACT_ENERGY}")
        self.energy = energy
        start_omega_h = min(math.pi / substeps, 0.9 * OMEGA_H_MAX)
        self.stiffness = nn.Parameter(torch.tensor(_logit(start_omega_h / OMEGA_H_MAX)))
        self.damping = nn.Parameter(torch.tensor(
            _softplus_inverse(START_ZETA) if energy == "lose" else START_ZETA))
        self.tangent = nn.Parameter(torch.tensor(_logit(START_TANGENT)))
        self.friction = nn.Parameter(torch.tensor(_softplus_inverse(START_MU)))

    def constants(self, h: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """``(k, c, c_t, mu)`` for substeps of ``h`` (any shape): k in 1/time^2, c and c_t
        in 1/time."""
        omega = OMEGA_H_MAX * torch.sigmoid(self.stiffness) / h
        return (omega * omega, 2 * self.zeta() * omega, torch.sigmoid(self.tangent) / h,
                F.softplus(self.friction))

    @torch.no_grad()
    def set_zeta(self, zeta: float) -> None:
        """Set the damping ratio (> 0 with ``energy="lose"``; the rollout calibration,
        ``bgn.training.calibrate``)."""
        if self.energy == "lose":
            if not zeta > 0:
                raise ValueError(f"a dissipative contact's damping ratio must be > 0; got {zeta}")
            self.damping.fill_(_softplus_inverse(float(zeta)))
        else:
            self.damping.fill_(float(zeta))

    def zeta(self) -> torch.Tensor:
        """The damping ratio."""
        return F.softplus(self.damping) if self.energy == "lose" else self.damping

    def restitution(self) -> float:
        """The normal restitution of a head-on contact of the learned damping ratio (no
        friction): ``exp(-pi zeta / sqrt(1 - zeta^2))``, 0 where overdamped."""
        zeta = float(self.zeta().detach())
        if abs(zeta) >= 1:
            return 0.0 if zeta > 0 else math.inf
        return math.exp(-math.pi * zeta / math.sqrt(1 - zeta * zeta))


def contact_acceleration(delta: torch.Tensor, normal: torch.Tensor, dv: torch.Tensor,
                         constants: tuple[torch.Tensor, ...]) -> torch.Tensor:
    """(C, D) the acceleration of contacts of overlap ``delta`` (C,; > 0 in contact), unit
    normal ``normal`` (C, D; towards the particle) and relative velocity ``dv`` (C, D; the
    particle's minus the other's), per unit share of the pair (the module doc's law)."""
    k, c, c_t, mu = constants
    v_n = (dv * normal).sum(-1)
    push = k * delta - c * v_n                                   # along the normal
    v_t = dv - v_n[:, None] * normal
    speed_t = torch.sqrt((v_t * v_t).sum(-1) + TINY)
    slide = torch.minimum(c_t * speed_t, mu * push.abs())
    touch = (delta > 0).to(delta.dtype)
    return touch[:, None] * (push[:, None] * normal - (slide / speed_t)[:, None] * v_t)


class SoftContactHead(nn.Module):
    """Positions and velocity window of a granular scene's graph -> the finite-difference
    acceleration (N, D, physical units); no contact logits (``None``)."""

    def __init__(self, meta: SceneMeta, substeps: int, replay: int = REPLAY_FRAMES,
                 energy: str = "lose") -> None:
        super().__init__()
        self.replay = int(replay)
        if meta.target != "acceleration":
            raise ValueError("the soft-contact head predicts an acceleration target; the "
                             f"scene {meta.name!r} has a {meta.target} target")
        self.substeps = int(substeps)
        self.pair = ContactLaw(self.substeps, energy)
        self.wall = ContactLaw(self.substeps, energy)
        self.log_mass = nn.Parameter(torch.zeros(max(1, meta.n_types)))
        # gravity in units of box / frame^2 scaled by 1e-3, drag in 1e-3 per frame: the
        # optimiser's steps then move them at a sensible pace
        self.field = nn.Parameter(torch.zeros(meta.dim))
        self.drag = nn.Parameter(torch.zeros(()))
        # the field's unit: the box, or the particles' spread scale where there is none
        scale = meta.box if meta.box is not None else 1.0
        self.register_buffer("box", torch.as_tensor(float(np.max(scale))), persistent=False)
        types = max(1, meta.n_types)
        # contact distances measured from the data (NaN: not measured; radii given instead)
        self.register_buffer("pair_reach", torch.full((types, types), math.nan))
        self.register_buffer("wall_reach", torch.full((types,), math.nan))
        # whether the training data gave radii (what the model was given: its label)
        self.register_buffer("radii_given", torch.ones((), dtype=torch.bool))

    def set_reach(self, pair: Any, wall: Any, radii_given: bool = True) -> None:
        """The contact distances measured from the data (``bgn.data.contacts``): per pair of
        types (T, T) and per type to a wall (T,); NaN where never close. ``radii_given``:
        whether the data give radii (then those are used)."""
        self.pair_reach.copy_(torch.as_tensor(pair, dtype=self.pair_reach.dtype))
        self.wall_reach.copy_(torch.as_tensor(wall, dtype=self.wall_reach.dtype))
        self.radii_given.fill_(bool(radii_given))

    @property
    def measured(self) -> bool:
        """Whether contact distances were measured (``set_reach``; NaN throughout before)."""
        return not (bool(torch.isnan(self.pair_reach).all())
                    and bool(torch.isnan(self.wall_reach).all()))

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: Any) -> None:
        # checkpoints from before the flag: every one was trained on data with radii
        state_dict.setdefault(prefix + "radii_given", torch.ones((), dtype=torch.bool))
        super()._load_from_state_dict(state_dict, prefix, *args)

    def reach(self, g: Graph) -> tuple[torch.Tensor, torch.Tensor]:
        """Per edge and per disc: the contact distance of the pair and to a wall, the radii
        where the graph has them (all positive), else the measured ones."""
        snd, rcv = g.edge_index
        if g.radius is not None and bool((g.radius > 0).all()):
            return g.radius[rcv] + g.radius[snd], g.radius
        if not self.measured:
            raise ValueError("the soft-contact head has no contact distances: the data give "
                             "no radii and none were measured (set when a fit starts, before "
                             "its first validation)")
        pair = self.pair_reach.to(g.pos.dtype)
        wall = self.wall_reach.to(g.pos.dtype)
        # a pair of types never seen close never touches: distance 0
        return (torch.nan_to_num(pair[g.types[rcv], g.types[snd]], nan=0.0),
                torch.nan_to_num(wall[g.types], nan=0.0))

    def uniform(self, dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The learned uniform acceleration (., D) and drag rate (.,) for frame spacings
        ``dt`` (.,)."""
        g = 1e-3 * self.box * self.field / (dt * dt)[..., None]
        return g, 1e-3 * self.drag / dt

    def acceleration(self, g: Graph, x: torch.Tensor, v: torch.Tensor, h: torch.Tensor,
                     reach: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """(N, D) every disc's acceleration at positions ``x`` and velocities ``v`` for
        substeps of ``h`` (N,): pair and wall contacts (at the distances ``reach``), the field
        and the drag."""
        snd, rcv = g.edge_index
        dt = g.dt.to(x.dtype)[g.batch]
        field, drag = self.uniform(dt)
        acc = field - drag[:, None] * v
        # pairs, each edge from its receiver's side (graphs are symmetric)
        dx = edge_vector(x, g)
        dist = torch.sqrt((dx * dx).sum(-1) + TINY)
        delta = reach[0] - dist
        near = (delta > 0).nonzero()[:, 0]
        if len(near):
            r, s = rcv[near], snd[near]
            normal = dx[near] / dist[near, None]
            share = torch.sigmoid(self.log_mass[g.types[s]] - self.log_mass[g.types[r]])
            a = contact_acceleration(delta[near], normal, v[r] - v[s],
                                     self.pair.constants(h[r]))
            acc = acc.index_add(0, r, share[:, None] * a)
        if g.wall is None:                     # no walls (an open or periodic scene)
            return acc
        # walls: per axis the lower (normal +e) and the upper (normal -e) plane
        low, high = walls(g)
        dim = x.shape[1]
        for side, normal_sign in ((x - low, 1.0), (high - x, -1.0)):
            delta_w = reach[1][:, None] - side                           # (N, D)
            disc, axis = (delta_w > 0).nonzero().unbind(1)
            if not len(disc):
                continue
            normal = normal_sign * F.one_hot(axis, dim).to(x.dtype)
            a = contact_acceleration(delta_w[disc, axis], normal, v[disc],
                                     self.wall.constants(h[disc]))
            acc = acc.index_add(0, disc, a)
        return acc

    def frame(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
              reach: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """One frame from positions ``x`` and velocities ``v`` over ``substeps`` semi-implicit
        Euler steps: the displacement (kept apart from ``x``: float32 keeps a small step exact)
        and the velocity at the frame's end."""
        h = dt / self.substeps
        moved = torch.zeros_like(x)
        for _ in range(self.substeps):
            v = v + h[:, None] * self.acceleration(g, x + moved, v, h, reach)
            moved = moved + h[:, None] * v
        return moved, v

    def velocity(self, g: Graph, dt: torch.Tensor, reach: tuple[torch.Tensor, torch.Tensor],
                 ) -> torch.Tensor:
        """The velocity at frame t. A backward difference is its frame's mean velocity: where
        a contact changed the velocity within the frame it is neither the velocity before nor
        after, and a model fed it learns contacts that create energy (they must push apart
        discs whose input says they barely separate). So the window's last ``replay`` frames
        are replayed as the impulse head does: each from the recorded position with the
        velocity so far, and the velocity at its end is the recorded mean velocity plus what
        the head's own frame changed after its mean (``v_end - moved / dt``). Without
        gradients: the replay corrects an input."""
        depth = min(self.replay, g.vel.shape[1] - 1)
        x = g.pos - (g.vel[:, :depth] * dt[:, None, None]).sum(1)       # x[t - depth]
        back = g.vel[:, depth]
        with torch.no_grad():
            h = dt / self.substeps
            v = back + 0.5 * dt[:, None] * self.acceleration(g, x, back, h, reach)
            for j in range(depth, 0, -1):
                moved, end = self.frame(g, x, v, dt, reach)
                x = x + g.vel[:, j - 1] * dt[:, None]
                v = g.vel[:, j - 1] + (end - moved / dt[:, None])
        if depth:
            return v
        return back + 0.5 * dt[:, None] * self.acceleration(g, g.pos, back, h, reach)

    def forward(self, g: Graph) -> tuple[torch.Tensor, None]:
        if g.dt is None:
            raise ValueError("the soft-contact head needs the frame spacing: the graph has no dt")
        dt = g.dt.to(g.pos.dtype)[g.batch]
        reach = self.reach(g)
        moved, _ = self.frame(g, g.pos, self.velocity(g, dt, reach), dt, reach)
        # (x[t+1] - 2 x[t] + x[t-1]) / dt^2
        return (moved / dt[:, None] - g.vel[:, 0]) / dt[:, None], None

    def summary(self) -> dict[str, float]:
        """The learned constants in physical units of a frame spacing of 1 (per frame)."""
        one = torch.ones(())
        g, drag = self.uniform(one)
        out = {"pair_restitution": self.pair.restitution(),
               "wall_restitution": self.wall.restitution(),
               "pair_friction": float(self.pair.constants(one)[3]),
               "wall_friction": float(self.wall.constants(one)[3]),
               "drag_per_frame": float(drag)}
        out.update({f"field_{i}_per_frame2": float(c) for i, c in enumerate(g)})
        out.update({f"mass_type{i}": float(m) for i, m in
                    enumerate(torch.exp(self.log_mass - self.log_mass[0]))})
        return out
