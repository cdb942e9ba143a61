"""Newton's laws for hard discs: pair impulses along the normal at the time of impact, equal
and opposite by construction, divided by learned masses.

The collisions scene is free flight between elastic impacts (SIMS.md). What a frame of a disc
gas shows is mostly free flight, and an impact changes two velocities by
``dv_i = -(1 + e) m_j / (m_i + m_j) ((v_i - v_j) . n) n`` at the instant the discs touch (``n``
the unit normal from j to i then, ``e`` the restitution, 1 for elastic). A generic network
must learn that map from frames; an error of a light disc's impulse that leaks into a heavy
disc's velocity (400 times the mass here) multiplies the gas's energy within a hundred steps.
This head writes the structure down and learns only what the frames do not say:

- when the window's free flight brings two discs (or a disc and a wall) into contact within
  the next frame (the time of impact, solved from positions and velocities), a learned gate
  says whether they really touch (trained on the recorded contacts, ``ModelOutput.contact``);
- the masses, as a function of a disc's radius (``log m(r)``: types differ in size), trained
  on the training split's relative log-masses like BGN's Eq. 9-10 (the loss
  ``impulse_mass``), and the restitution ``e``;
- the next finite-difference velocity is the exact one of a single impact at time ``s`` into
  a frame of length ``dt``: ``v + dv (1 - s / dt)``.

A backward-difference velocity that straddles an impact is not the disc's velocity: the head
first replays the window's last frames and adds the part of each impact's change that the
average over its frame missed (``dv s' / dt``), then predicts the next frame.
Several impacts of one disc within one frame are treated one pair at a time.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F
from torch.utils.checkpoint import checkpoint

from bgn.graph import Graph
from bgn.model.message_passing import CheckpointEdges, edge_chunks, edge_difference
from bgn.model.ops import mlp, scatter_sum
from bgn.sim.scene import SceneMeta

TINY = 1e-20         # keeps roots, divisions and norms (and their gradients) finite
REPLAY_FRAMES = 3    # frames of the window replayed to recover the velocity at frame t
LOG_MASS_RANGE = 5.0  # e-folds of mass per unit of the mass MLP's output
RULE_LOGIT = 4.0      # the gates start at the time-of-impact rule: +-4 (probability 0.98)
NEAR_FRAMES = 1.0     # candidate pairs: a gap their speeds close within this many frames


def time_of_impact(dx: torch.Tensor, dv: torch.Tensor, reach: torch.Tensor,
                   dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First time ``s`` in ``[0, dt)`` at which ``|dx + dv s| = reach`` while approaching, for
    pairs (E, D) -> ``(s / dt, hit)``; ``s / dt`` is 1 where there is no impact."""
    a = (dv * dv).sum(-1)
    b = (dx * dv).sum(-1)
    c = (dx * dx).sum(-1) - reach * reach
    disc = b * b - a * c
    # every branch finite, so that torch.where's unused branch cannot turn a gradient to NaN
    root = (-b - torch.sqrt(disc.clamp_min(TINY))) / (a + TINY)
    s = torch.where(c <= 0, torch.zeros_like(root), root.clamp_min(0.0))  # overlapping: now
    hit = (b < 0) & (disc >= 0) & (s < dt)
    return torch.where(hit, s / dt, torch.ones_like(s)), hit


def wall_impact(x: torch.Tensor, v: torch.Tensor, radius: torch.Tensor,
                walls: tuple[torch.Tensor, torch.Tensor],
                dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per disc and axis (N, D): the fraction of the frame at which free flight reaches a wall
    (1 if it does not) and whether it does."""
    r = radius[:, None]
    low, high = walls                                                 # (N, D) coordinates
    gap = torch.where(v < 0, x - r - low, high - r - x)               # to the wall ahead
    s = (gap / (v.abs() + TINY)).clamp_min(0.0)
    hit = (v != 0) & (s < dt[:, None])
    return torch.where(hit, s / dt[:, None], torch.ones_like(s)), hit


def walls(g: Graph) -> tuple[torch.Tensor, torch.Tensor]:
    """The lower and upper wall coordinates (N, D) each disc of a graph sees: from the graph's
    wall distances, so a box of another size or position than training's is handled."""
    if g.wall is None:
        raise ValueError("the impulse head needs graphs with wall distances (a scene in a box)")
    dim = g.pos.shape[1]
    return g.pos - g.wall[:, :dim], g.pos + g.wall[:, dim:]


class ContactImpulseHead(nn.Module):
    """Positions and velocity window of a contact scene's graph -> the next finite-difference
    velocity (N, D, physical units) and the contact gate's logits on the edges (E,)."""

    def __init__(self, meta: SceneMeta, length_scale: torch.Tensor, speed_scale: torch.Tensor,
                 hidden: int, act: str) -> None:
        super().__init__()
        if meta.box is None:
            raise ValueError("the impulse head needs a scene in a box (its walls)")
        self.register_buffer("length_scale", length_scale.detach().clone())
        self.register_buffer("speed_scale", speed_scale.detach().clone())
        self.log_mass = mlp([1, hidden, 1], act)             # log m(radius), up to a constant
        self.gate = mlp([4, hidden, hidden, 1], act)         # pair: touch within the frame?
        self.wall_gate = mlp([3, hidden, 1], act)
        # restitution = exp(-softplus(p)): 0.993 at p = -5, approaching 1 (elastic) from below
        self.restitution = nn.Parameter(torch.full((), -5.0))
        self.wall_restitution = nn.Parameter(torch.full((), -5.0))
        self.edge_chunk: int | None = None             # set by PhysicsModel (its config)
        self.checkpoint_edges = CheckpointEdges()
        with torch.no_grad():  # start as the time-of-impact rule: a hit is a contact
            for gate in (self.gate, self.wall_gate):
                gate[-1].weight.zero_()
                gate[-1].bias.zero_()

    def restitutions(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Pair and wall restitution in [0, 1]: an impact may lose energy, never create it."""
        return (torch.exp(-F.softplus(self.restitution)),
                torch.exp(-F.softplus(self.wall_restitution)))

    def log_masses(self, g: Graph) -> torch.Tensor:
        """(N,) the learned log-masses (a function of the radius: the scene's types differ in
        size)."""
        # log-radius in, log-mass out at LOG_MASS_RANGE e-folds per unit: the masses of a
        # scene's types differ by several e-folds (collisions: 6 for radii 0.1 and 0.2), which
        # a unit-scale MLP of the radius reached only after thousands of steps
        # once per distinct radius (a scene's types: two), not per disc: the (N, hidden)
        # layer was the largest node-level cost of a step at 200 000 discs
        radii, index = torch.unique(g.radius, return_inverse=True)
        log_r = torch.log(radii.clamp_min(TINY))[:, None]
        return LOG_MASS_RANGE * self.log_mass(log_r).squeeze(-1)[index]

    def gate_logits(self, feats: torch.Tensor, hit: torch.Tensor) -> torch.Tensor:
        """The gate's logits (E,) from the pair features (E, 4): the MLP plus the rule's
        +-RULE_LOGIT; in chunks with activation checkpointing on large graphs (``edge_chunk``,
        as the edge MLPs)."""
        return (edge_chunks(self.gate, self.edge_chunk, (feats,), (),
                            self.checkpoint_edges.above(feats))
                .squeeze(-1) + RULE_LOGIT * (2 * hit.to(feats.dtype) - 1))

    def pair_geometry(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                      ) -> tuple[torch.Tensor, ...]:
        """Per edge, for free flight from ``(x, v)``: the fraction of the frame before the time
        of impact (E,; 1 where none), whether there is one (E,), the unit normal at impact
        (E, D), the approach speed along it (E,; < 0 when closing) and the gate's features
        (E, 4)."""
        snd, rcv = g.edge_index
        dx, dv = edge_difference(x, g.edge_index), edge_difference(v, g.edge_index)
        reach = g.radius[rcv] + g.radius[snd]
        frac, hit = time_of_impact(dx, dv, reach, dt[rcv])
        at_impact = dx + dv * (frac * dt[rcv])[:, None]
        normal = at_impact / torch.sqrt((at_impact * at_impact).sum(-1, keepdim=True) + TINY)
        approach = (dv * normal).sum(-1)                                  # < 0 when closing
        feats = torch.stack([frac, hit.to(frac.dtype), approach / self.speed_scale,
                             (torch.sqrt((dx * dx).sum(-1) + TINY) - reach) / self.length_scale],
                            dim=-1)
        return frac, hit, normal, approach, feats

    def candidates(self, g: Graph, v: torch.Tensor, dt: torch.Tensor, hit: torch.Tensor,
                   feats: torch.Tensor) -> torch.Tensor:
        """(E,) the edges whose contact the gate's MLP decides: a time of impact within the
        frame, or a gap that the two discs' speeds could close within ``NEAR_FRAMES`` frames
        (an impact with a third disc can turn one towards the other). Elsewhere no contact is
        possible within the frame, and the MLP on every edge was 40 % of a training step at
        20 000 discs (docs/results.md): on the default collisions data 6 % of the edges are
        candidates, and 0.7 % of the recorded contacts lie outside them."""
        snd, rcv = g.edge_index
        speed = torch.sqrt((v * v).sum(-1) + TINY)
        gap = feats[:, 3] * self.length_scale                   # physical units
        return hit | (gap < NEAR_FRAMES * (speed[rcv] + speed[snd]) * dt[rcv])

    def impacts(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                every_edge: bool = True) -> tuple[torch.Tensor, ...]:
        """The impacts free flight from ``(x, v)`` meets within a frame: per edge the velocity
        change of its receiver (E, D) and the fraction of the frame before it (E,), the gate's
        logits (E,); per disc and axis the wall's velocity change and fraction (N, D).

        The gate's MLP runs on the candidate edges only (``candidates``: a few % of a disc
        gas's edges); the others get the rule's logit, ``-RULE_LOGIT``. ``every_edge=False``
        (a replayed frame) narrows them to the edges with a time of impact and returns None for
        the logits: the kick is zero, value and gradient, wherever there is none, so the
        velocities are the same."""
        snd, rcv = g.edge_index
        frac, hit, normal, approach, feats = self.pair_geometry(g, x, v, dt)
        chosen = (self.candidates(g, v, dt, hit, feats) if every_edge else hit).nonzero()[:, 0]
        chosen_logits = self.gate_logits(feats.index_select(0, chosen), hit.index_select(0, chosen))
        logits = (frac.new_full(frac.shape, -RULE_LOGIT).index_copy(0, chosen, chosen_logits)
                  if every_edge else None)
        gate = frac.new_zeros(frac.shape).index_copy(0, chosen, torch.sigmoid(chosen_logits))
        log_m = self.log_masses(g)
        share = torch.sigmoid(log_m[snd] - log_m[rcv])                   # m_j / (m_i + m_j)
        e_pair, e_wall = self.restitutions()
        # the gate may veto an impact of the rule, not create one without a time of impact
        kick = -(1 + e_pair) * share * approach * gate * hit

        # the wall gate on the discs and axes that reach a wall within the frame only: the
        # kick is zero, value and gradient, elsewhere
        wall_frac, wall_hit = wall_impact(x, v, g.radius, walls(g), dt)
        wall_feats = torch.stack([wall_frac, wall_hit.to(v.dtype), v.abs() / self.speed_scale],
                                 dim=-1)[wall_hit]                          # (hits, 3)
        wall_gate = torch.zeros_like(v).masked_scatter(wall_hit, torch.sigmoid(
            self.wall_gate(wall_feats).squeeze(-1) + RULE_LOGIT))
        wall_dv = -(1 + e_wall) * v * wall_gate
        return kick[:, None] * normal, frac, logits, wall_dv, wall_frac

    def _impacts(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                 every_edge: bool) -> tuple[torch.Tensor, ...]:
        """``impacts``; on graphs of more than ``checkpoint_edges`` edges with its per-edge
        intermediates (a few dozen (E,) and (E, D) tensors per frame) recomputed in the
        backward pass instead of kept (activation checkpointing: element-wise work only)."""
        n_edges = g.edge_index.shape[1]
        if (torch.is_grad_enabled() and self.edge_chunk
                and n_edges > max(self.edge_chunk, self.checkpoint_edges.above(x) or 0)):
            return checkpoint(self.impacts, g, x, v, dt, every_edge, use_reentrant=False)
        return self.impacts(g, x, v, dt, every_edge)

    def _replay_start(self, g: Graph) -> tuple[int, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The frame spacing per disc, how many of the window's frames are replayed (``depth``)
        and the position and backward-difference velocity ``depth`` frames before t."""
        if g.dt is None:
            raise ValueError("the impulse head needs the frame spacing: the graph has no dt")
        dt = g.dt.to(g.pos.dtype)[g.batch]
        depth = min(REPLAY_FRAMES, g.vel.shape[1] - 1)
        x = g.pos - (g.vel[:, :depth] * dt[:, None, None]).sum(1)     # x[t - depth]
        return depth, dt, x, g.vel[:, depth]

    def _replay_frame(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                      j: int) -> tuple[torch.Tensor, torch.Tensor]:
        """From ``(x, v)`` at frame t - j to frame t - j + 1: the recorded positions, and the
        backward difference plus what the frame's impacts changed after their instant."""
        rcv, n = g.edge_index[1], g.pos.shape[0]
        # the replays' logits are not outputs: the gate runs on their impacts only
        pair_dv, frac, _, wall_dv, wall_frac = self._impacts(g, x, v, dt, False)
        return (x + g.vel[:, j - 1] * dt[:, None],
                g.vel[:, j - 1] + scatter_sum(pair_dv * frac[:, None], rcv, n)
                + wall_dv * wall_frac)

    def forward(self, g: Graph) -> tuple[torch.Tensor, torch.Tensor]:
        rcv, n = g.edge_index[1], g.pos.shape[0]
        # The velocity at frame t: the backward difference plus what each frame's impacts
        # changed after their instant (a backward difference averages over its frame). Replayed
        # from REPLAY_FRAMES back, so that a disc that bounced in consecutive frames starts
        # each replay with its velocity after the last bounce, not the average that still
        # approaches its partner (which would bounce it again).
        depth, dt, x, v = self._replay_start(g)
        for j in range(depth, 0, -1):
            x, v = self._replay_frame(g, x, v, dt, j)
        # the next frame: free flight, then each impact's change for the rest of the frame
        pair_dv, frac, logits, wall_dv, wall_frac = self._impacts(g, g.pos, v, dt, True)
        v_next = (v + scatter_sum(pair_dv * (1 - frac)[:, None], rcv, n)
                  + wall_dv * (1 - wall_frac))
        return v_next, logits

    @torch.no_grad()
    def window_contacts(self, g: Graph) -> torch.Tensor:
        """The pair impacts the head sees in the window's replayed frames, as rows
        ``(j, i, k)`` (M, 3): discs i < k (graph-wide node indices) touch between frames
        t - j and t - j + 1, where free flight has a time of impact and the gate is open
        (probability > 1/2). What the head's per-simulation mass solve reads
        (``bgn.inverse_references.impact_log_mass``)."""
        snd, rcv = g.edge_index
        depth, dt, x, v = self._replay_start(g)
        rows = []
        for j in range(depth, 0, -1):
            _, hit, _, _, feats = self.pair_geometry(g, x, v, dt)
            hits = torch.nonzero(hit & (rcv < snd)).squeeze(1)
            touch = hits[self.gate_logits(feats[hits], hit[hits]) > 0]
            rows.append(torch.stack([torch.full_like(touch, j), rcv[touch], snd[touch]], 1))
            x, v = self._replay_frame(g, x, v, dt, j)
        return torch.cat(rows)
