"""Newton's laws for hard discs: pair impulses along the normal at the time of impact, equal
and opposite by construction, divided by learned masses.

The collisions scene is free flight between elastic impacts (docs/design.md#collisions-scene).
What a frame of a disc
gas shows is mostly free flight, and an impact changes two velocities by
``dv_i = -(1 + e) m_j / (m_i + m_j) ((v_i - v_j) . n) n`` at the instant the discs touch (``n``
the unit normal from j to i then, ``e`` the restitution, 1 for elastic). A generic network
must learn that map from frames; an error of a light disc's impulse that leaks into a heavy
disc's velocity (400 times the mass here) soon multiplies the gas's energy in a rollout
(docs/notes/2026-11-26-results-history.md, "Measurements behind the defaults").
This head writes the structure down and learns only what the frames do not say:

- when the window's free flight brings two discs (or a disc and a wall) into contact within
  the next frame (the time of impact, solved from positions and velocities), a learned gate
  says whether they really touch (trained on the recorded contacts, ``ModelOutput.contact``);
- the masses, as a function of a disc's radius relative to the largest of its scene
  (``log m(r / r_max)``: types differ in size), trained on the training split's relative
  log-masses like BGN's Eq. 9-10 (the loss ``impulse_mass``), and the restitution ``e``;
- the next finite-difference velocity is the exact one of a single impact at time ``s`` into
  a frame of length ``dt``: ``v + dv (1 - s / dt)``.

A backward-difference velocity that straddles an impact is not the disc's velocity: the head
first replays the window's last frames and adds the part of each impact's change that the
average over its frame missed (``dv s' / dt``), then predicts the next frame.
Several impacts within one frame are resolved one at a time in time order, each disc flying
from its last impact (``ContactImpulseHead.resolve``), as the simulator does.

Nothing the head reads has a length or a time unit: the gates see times as fractions of the
frame, gaps in contact distances (``r_i + r_j``) and speeds relative to the root mean square
speed of the disc's scene (the window's last velocities), the masses see radii relative to
the largest. Elastic impacts in a box are the same
motion at any length scale (``bgn.sim.transform.scaled``), and so is the head's prediction
(tested): a scene in millimetres is the scene in metres.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F
from torch.utils.checkpoint import checkpoint

from bgn.graph import Graph
from bgn.model.message_passing import (
    CheckpointEdges,
    checkpointed,
    edge_chunks,
    edge_difference,
    edge_period,
    edge_vector,
    minimum_image,
)
from bgn.model.ops import mlp
from bgn.sim.scene import SceneMeta

TINY = 1e-20         # keeps roots, divisions and norms (and their gradients) finite
# frames of the window replayed to recover the velocity at frame t (at most history - 1): a
# replay starts from a backward difference, which is wrong when that frame held an impact, and
# each frame further back dilutes the error: four gave the smallest energy error on the dense
# gas (docs/notes/2026-11-26-results-history.md,
# "The replay without gradients, and four frames replayed")
REPLAY_FRAMES = 4
LOG_MASS_RANGE = 5.0  # e-folds of mass per unit of the mass MLP's output
RULE_LOGIT = 4.0      # the gates start at the time-of-impact rule: +-4 (probability 0.98)
NEAR_FRAMES = 1.0     # candidate pairs: a gap their speeds close within this many frames
MAX_ROUNDS = 256     # rounds of impacts per frame; beyond, an inelastic collapse is cut off
REACH_FRAMES = 2.0   # pairs that may meet within a frame: a gap twice their speeds close in one


def time_of_impact(dx: torch.Tensor, dv: torch.Tensor, reach: torch.Tensor,
                   dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """First time ``s`` in ``[0, dt)`` at which ``|dx + dv s| = reach`` while approaching, for
    pairs (E, D) -> ``(s / dt, hit)``; ``s / dt`` is 1 where there is no impact."""
    a = (dv * dv).sum(-1)
    b = (dx * dv).sum(-1)
    c = (dx * dx).sum(-1) - reach * reach
    disc = b * b - a * c
    # the root without cancellation, c / (-b + sqrt(disc)) (as the simulator): -b - sqrt(disc)
    # subtracts two nearly equal numbers for a pair near contact (small c). Every branch
    # finite, so that torch.where's unused branch cannot turn a gradient to NaN
    closing = b < 0
    root = c / torch.where(closing, torch.sqrt(disc.clamp_min(TINY)) - b, torch.ones_like(b))
    s = torch.where(c <= 0, torch.zeros_like(root), root.clamp_min(0.0))  # overlapping: now
    hit = closing & (disc >= 0) & (s < dt)
    # a disc whose last impact ends the frame has no time left (dt = 0): no hit, no 0 / 0
    span = torch.where(dt > 0, dt, torch.ones_like(dt))
    return torch.where(hit, s / span, torch.ones_like(s)), hit


def wall_impact(x: torch.Tensor, v: torch.Tensor, radius: torch.Tensor,
                walls: tuple[torch.Tensor, torch.Tensor],
                dt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per disc and axis (N, D): the fraction of the frame at which free flight reaches a wall
    (1 if it does not) and whether it does."""
    r = radius[:, None]
    low, high = walls                                                 # (N, D) coordinates
    gap = torch.where(v < 0, x - r - low, high - r - x)               # to the wall ahead
    # finite in every branch (gradients too): a disc at rest, or with no time left, hits none
    speed = torch.where(v != 0, v.abs(), torch.ones_like(v))
    s = (gap / speed).clamp_min(0.0)
    hit = (v != 0) & (s < dt[:, None])
    span = torch.where(dt > 0, dt, torch.ones_like(dt))[:, None]
    return torch.where(hit, s / span, torch.ones_like(s)), hit


def walls(g: Graph) -> tuple[torch.Tensor, torch.Tensor]:
    """The lower and upper wall coordinates (N, D) each disc of a graph sees: from the graph's
    wall distances, so a box of another size or position than training's is handled."""
    if g.wall is None:
        raise ValueError("the impulse head needs graphs with wall distances (a scene in a box)")
    dim = g.pos.shape[1]
    return g.pos - g.wall[:, :dim], g.pos + g.wall[:, dim:]


def gate_features(when: torch.Tensor, hit: torch.Tensor, approach: torch.Tensor,
                  gap: torch.Tensor, reach: torch.Tensor, speed_unit: torch.Tensor,
                  ) -> torch.Tensor:
    """The pair gate's inputs (E, 4), none with a unit: the time of impact as a fraction of
    the frame, whether the window's free flight hits, the approach speed along the normal in
    ``speed_unit`` (``scene_speed``; < 0 when closing) and the gap in contact distances
    ``reach``."""
    return torch.stack([when, hit.to(when.dtype), approach / speed_unit,
                        gap / reach.clamp_min(TINY)], dim=-1)


def scene_speed(g: Graph) -> torch.Tensor:
    """(N,) the root mean square speed of each disc's scene over its last window velocity:
    the gates' unit of speed. Neither the length scale nor the frame rate changes what a
    gate sees of a thermal gas then (a unit of contact distances per frame would grow five
    times from fps 50 to fps 10)."""
    square = (g.vel[:, 0] ** 2).sum(-1)
    total = square.new_zeros(g.num_graphs).index_add_(0, g.batch, square)
    count = square.new_zeros(g.num_graphs).index_add_(0, g.batch, torch.ones_like(square))
    return torch.sqrt(total / count).clamp_min(TINY).index_select(0, g.batch)


class FrameImpacts(NamedTuple):
    """What ``ContactImpulseHead.resolve`` finds in one frame."""

    velocity: torch.Tensor            # (N, D) after the frame's impacts
    mean_velocity: torch.Tensor       # (N, D) the frame's finite-difference velocity
    logits: torch.Tensor | None       # (E,) the gate at the frame's start (``every_edge``)
    pairs: torch.Tensor               # (M,) edges (receiver < sender) of the pair impacts
    pair_logits: torch.Tensor         # (M,) their gate logits


def _pick(index: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """``t -> t[index]`` along the first dimension, as ``index_select``: its backward is
    ``index_add_``, not the slower accumulating ``index_put_`` of ``t[index]``."""
    return lambda t: t.index_select(0, index)


class _Flight(NamedTuple):
    """Free flight of each disc from its last impact: position ``x`` at time ``tau`` (a
    fraction of the frame) and velocity ``v`` since."""

    x: torch.Tensor
    v: torch.Tensor
    tau: torch.Tensor

    def at(self, discs: torch.Tensor, when: torch.Tensor, dt: torch.Tensor) -> torch.Tensor:
        """Positions of ``discs`` at ``when`` (fractions of the frame, not before their tau)."""
        pick = _pick(discs)
        return pick(self.x) + pick(self.v) * ((when - pick(self.tau)) * pick(dt))[:, None]

    def advance(self, discs: torch.Tensor, when: torch.Tensor, kick: torch.Tensor,
                dt: torch.Tensor) -> _Flight:
        """Each of ``discs`` (distinct) flies to ``when`` and takes ``kick`` there."""
        return _Flight(self.x.index_copy(0, discs, self.at(discs, when, dt)),
                       self.v.index_add(0, discs, kick), self.tau.index_copy(0, discs, when))


class _FrameTerms(NamedTuple):
    """What every impact of a frame reads: the learned log-masses (N,), the pair and wall
    restitutions, the walls each disc sees and the gates' unit of speed (N,)."""

    log_mass: torch.Tensor
    pair_restitution: torch.Tensor
    wall_restitution: torch.Tensor
    walls: tuple[torch.Tensor, torch.Tensor]
    speed_unit: torch.Tensor


class _PairEvents(NamedTuple):
    edge: torch.Tensor      # (P,) edge index (receiver < sender)
    rcv: torch.Tensor
    snd: torch.Tensor
    time: torch.Tensor      # (P,) fraction of the frame
    logit: torch.Tensor     # (P,) the gate's
    dv_rcv: torch.Tensor    # (P, D)
    dv_snd: torch.Tensor    # (P, D)

    def take(self, keep: torch.Tensor) -> _PairEvents:
        """The events of a mask."""
        index = keep.nonzero()[:, 0]
        return _PairEvents(*(t.index_select(0, index) for t in self))

    def cat(self, other: _PairEvents) -> _PairEvents:
        return _PairEvents(*(torch.cat(pair) for pair in zip(self, other, strict=True)))


class _WallEvents(NamedTuple):
    disc: torch.Tensor      # (W,)
    axis: torch.Tensor      # (W,)
    time: torch.Tensor      # (W,) fraction of the frame
    dv: torch.Tensor        # (W,) velocity change along the axis

    def take(self, keep: torch.Tensor) -> _WallEvents:
        """The events of a mask."""
        index = keep.nonzero()[:, 0]
        return _WallEvents(*(t.index_select(0, index) for t in self))

    def cat(self, other: _WallEvents) -> _WallEvents:
        return _WallEvents(*(torch.cat(pair) for pair in zip(self, other, strict=True)))


def _ready(n: int, edge_index: torch.Tensor, pairs: _PairEvents, walls: _WallEvents,
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The pending impacts that can be applied now, as masks over ``pairs`` and ``walls``:
    each the earliest of its discs (ties by index: every disc in at most one) and no later
    than any pending impact of the discs linked to them in ``edge_index`` (the pairs that may
    meet within the frame), whose changes could otherwise bring an earlier impact to them.
    The earliest impact of all is always among them."""
    n_pair, n_wall = len(pairs.time), len(walls.time)
    # every (event, disc) incidence: a pair impact twice, a wall impact once
    when = torch.cat([pairs.time, pairs.time, walls.time]).detach()
    disc = torch.cat([pairs.rcv, pairs.snd, walls.disc])
    ids = torch.cat([torch.arange(n_pair, device=disc.device).repeat(2),
                     torch.arange(n_pair, n_pair + n_wall, device=disc.device)])
    earliest = when.new_full((n,), float("inf")).scatter_reduce_(0, disc, when, "amin")
    near = earliest.scatter_reduce(0, edge_index[1], earliest.index_select(0, edge_index[0]),
                                   "amin")
    ok = when <= near.index_select(0, disc)
    pair_first = ok[:n_pair] & ok[n_pair:2 * n_pair]
    wall_first = ok[2 * n_pair:]
    first = torch.cat([pair_first, pair_first, wall_first])
    none = n_pair + n_wall
    lowest = torch.full((n,), none, device=disc.device).scatter_reduce_(
        0, disc, torch.where(first, ids, none), "amin")
    mine = lowest.index_select(0, disc) == ids
    return pair_first & mine[:n_pair] & mine[n_pair:2 * n_pair], wall_first & mine[2 * n_pair:]


def _take_ready(n: int, near_edges: torch.Tensor, pending_pairs: _PairEvents,
                pending_walls: _WallEvents) -> tuple[_PairEvents, _WallEvents, bool]:
    """The pending impacts applied this round (``_ready``) and whether that is all of them."""
    pair_now, wall_now = _ready(n, near_edges, pending_pairs, pending_walls)
    if bool(pair_now.all() & wall_now.all()):     # the usual case: none wait
        return pending_pairs, pending_walls, True
    return pending_pairs.take(pair_now), pending_walls.take(wall_now), False


def _kicks(pairs: _PairEvents, walls: _WallEvents, like: torch.Tensor,
           ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per disc a round's impact changes (pairs' receivers, senders, then walls): the disc,
    when (a fraction of the frame) and its velocity change (K, D) in ``like``'s dtype."""
    discs = torch.cat([pairs.rcv, pairs.snd, walls.disc])
    when = torch.cat([pairs.time, pairs.time, walls.time])
    kick = torch.cat([pairs.dv_rcv, pairs.dv_snd, walls.dv[:, None]
                      * F.one_hot(walls.axis, like.shape[1]).to(like.dtype)])
    return discs, when, kick


class _NearPairs(NamedTuple):
    """The pairs that may meet within the frame, even after a kick (``REACH_FRAMES``): the
    impacts' work is on these alone (a few % of a gas's edges), round after round."""

    edges: torch.Tensor     # (2, K) the near edges, both directions (what ``_ready`` links)
    pairs: torch.Tensor     # (P,) edge index of each near pair once (receiver < sender)
    snd: torch.Tensor       # (P,)
    rcv: torch.Tensor       # (P,)


def _near_pairs(g: Graph, v: torch.Tensor, dt: torch.Tensor, gap: torch.Tensor) -> _NearPairs:
    """The pairs whose gap (E,) twice their speeds close within a frame."""
    snd, rcv = g.edge_index
    speed = torch.sqrt((v * v).sum(-1) + TINY)
    near = (gap < REACH_FRAMES * (speed[rcv] + speed[snd]) * dt[rcv]).nonzero()[:, 0]
    near_edges = g.edge_index.index_select(1, near)
    once = near_edges[1] < near_edges[0]                # each pair once (graphs are symmetric)
    near_snd, near_rcv = near_edges[:, once]
    return _NearPairs(near_edges, near[once], near_snd, near_rcv)


class _FrameContext(NamedTuple):
    """What stays fixed while a frame's impacts are resolved: the graph, the frame spacing
    per disc (N,), the pairs that may meet and the terms every impact reads."""

    g: Graph
    dt: torch.Tensor
    near: _NearPairs
    terms: _FrameTerms


class ContactImpulseHead(nn.Module):
    """Positions and velocity window of a contact scene's graph -> the next finite-difference
    velocity (N, D, physical units) and the contact gate's logits on the edges (E,)."""

    def __init__(self, meta: SceneMeta, hidden: int, act: str) -> None:
        super().__init__()
        if meta.box is None:
            raise ValueError("the impulse head needs a scene in a box (its walls)")
        self.log_mass = mlp([1, hidden, 1], act)     # log m(r / r_max), up to a constant
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
        """(N,) the learned log-masses: a function of the radius relative to the largest in
        the disc's scene (the scene's types differ in size; only mass ratios enter an impact,
        and a ratio of radii has no unit)."""
        # log-radius in, log-mass out at LOG_MASS_RANGE e-folds per unit: the masses of a
        # scene's types differ by several e-folds (collisions: 6 for radii 0.1 and 0.2), which
        # a unit-scale MLP of the radius reached only slowly (docs/results.md, "Measurements
        # behind the defaults")
        # once per distinct ratio (a scene's types: two), not per disc: the (N, hidden)
        # layer was the largest node-level cost of a step at 200 000 discs
        largest = g.radius.new_zeros(g.num_graphs).scatter_reduce_(0, g.batch, g.radius, "amax")
        ratios, index = torch.unique(g.radius / largest.clamp_min(TINY)[g.batch],
                                     return_inverse=True)
        log_r = torch.log(ratios.clamp_min(TINY))[:, None]
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
        (E, D), the approach speed along it (E,; < 0 when closing), the gap between the
        discs (E,) and the gate's features (E, 4)."""
        snd, rcv = g.edge_index
        dx, dv = edge_vector(x, g), edge_difference(v, g.edge_index)
        reach = g.radius[rcv] + g.radius[snd]
        frac, hit = time_of_impact(dx, dv, reach, dt[rcv])
        at_impact = dx + dv * (frac * dt[rcv])[:, None]
        normal = at_impact / torch.sqrt((at_impact * at_impact).sum(-1, keepdim=True) + TINY)
        approach = (dv * normal).sum(-1)                                  # < 0 when closing
        gap = torch.sqrt((dx * dx).sum(-1) + TINY) - reach
        return (frac, hit, normal, approach, gap,
                gate_features(frac, hit, approach, gap, reach, scene_speed(g)[rcv]))

    def candidates(self, g: Graph, v: torch.Tensor, dt: torch.Tensor, hit: torch.Tensor,
                   gap: torch.Tensor) -> torch.Tensor:
        """(E,) the edges whose contact the gate's MLP decides: a time of impact within the
        frame, or a gap that the two discs' speeds could close within ``NEAR_FRAMES`` frames
        (an impact with a third disc can turn one towards the other). Elsewhere no contact is
        possible within the frame, and the MLP on every edge was a large share of a training step
        on big scenes, while few edges are candidates and few recorded contacts lie outside them
        (docs/notes/2026-11-26-results-history.md, "BGN's bars met")."""
        snd, rcv = g.edge_index
        speed = torch.sqrt((v * v).sum(-1) + TINY)
        return hit | (gap < NEAR_FRAMES * (speed[rcv] + speed[snd]) * dt[rcv])

    def resolve(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                every_edge: bool = True) -> FrameImpacts:
        """The frame ahead of ``(x, v)`` resolved event by event, as the scene's simulator does:
        each disc flies freely until its earliest impact (a gated pair impact along the
        normal, or a wall), whose kick changes its velocity for the rest of the frame; the
        discs it changed then look for their next impact from where they are.

        Events are applied in rounds: at once, every impact that is the earliest of its discs
        and of the discs that may reach them within the frame (a gap that twice their speeds
        close in a frame: an earlier impact could send one into them first), then the pairs
        and walls of the discs that changed are solved again. That is the simulator's order
        unless a chain of impacts runs through discs further apart.

        A Jacobi sum of every impact a disc meets, each from the velocities at the frame's
        start, creates energy whenever a disc is hit twice within a frame
        (docs/notes/2026-11-26-results-history.md,
        "Impacts one at a time"); one impact at a time, an elastic impact conserves energy and
        every pair impact momentum, whatever the number of impacts. As in the simulator, a
        pair (or a wall) is not solved again right after its own impact, only once one of
        its discs has had another.

        ``every_edge``: also the gate's logits at the frame's start on every edge (the contact
        head's output; the MLP runs on ``candidates`` only, ``-RULE_LOGIT`` elsewhere); a
        replayed frame needs none."""
        logits, hit, gap = self._frame_start(g, x, v, dt, every_edge)
        near = _near_pairs(g, v, dt, gap)
        first = near.pairs if hit is None else near.pairs[hit[near.pairs]]
        flight = _Flight(x, v, x.new_zeros(x.shape[0]))
        terms = _FrameTerms(self.log_masses(g), *self.restitutions(), walls(g), scene_speed(g))
        return self._impacts(_FrameContext(g, dt, near, terms), flight, first, logits)

    def _frame_start(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                     every_edge: bool,
                     ) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor]:
        """Per edge at the frame's start: the gate's logits (the MLP on ``candidates``,
        ``-RULE_LOGIT`` elsewhere) and whether free flight hits, both None unless
        ``every_edge``, and the gap between the discs."""
        if not every_edge:
            snd, rcv = g.edge_index
            return None, None, (torch.sqrt((edge_vector(x, g) ** 2).sum(-1) + TINY)
                                - g.radius[rcv] - g.radius[snd])
        frac, hit, _, _, gap, feats = self.pair_geometry(g, x, v, dt)
        chosen = self.candidates(g, v, dt, hit, gap).nonzero()[:, 0]
        chosen_logits = self.gate_logits(feats.index_select(0, chosen),
                                         hit.index_select(0, chosen))
        logits = frac.new_full(frac.shape, -RULE_LOGIT).index_copy(0, chosen, chosen_logits)
        return logits, hit, gap

    def _impacts(self, ctx: _FrameContext, flight: _Flight, first: torch.Tensor,
                 logits: torch.Tensor | None) -> FrameImpacts:
        """``resolve``'s rounds from the frame's start (``flight``): the pair impacts ahead on
        the ``first`` edges and every disc's walls, then, round after round, the ready
        impacts applied (``_ready``) and the changed discs' next ones solved."""
        g, dt, n = ctx.g, ctx.dt, flight.x.shape[0]
        pending = (self._pair_events(g, flight, dt, first, ctx.terms),
                   self._wall_events(g, flight, dt, torch.arange(n, device=flight.x.device),
                                     None, ctx.terms))
        mean_v, fired, fired_logits = flight.v, [first[:0]], [flight.x.new_zeros(0)]
        for _ in range(MAX_ROUNDS):
            if not (len(pending[0].edge) or len(pending[1].disc)):
                break
            pairs, walls_now, every = _take_ready(n, ctx.near.edges, *pending)
            discs, when, kick = _kicks(pairs, walls_now, flight.x)
            flight = flight.advance(discs, when, kick, dt)
            mean_v = mean_v.index_add(0, discs, kick * (1 - when)[:, None])
            fired.append(pairs.edge)
            fired_logits.append(pairs.logit)
            pending = self._pending_after(ctx, flight, pairs, walls_now, discs,
                                          None if every else pending)
        return FrameImpacts(flight.v, mean_v, logits, torch.cat(fired), torch.cat(fired_logits))

    def _pending_after(self, ctx: _FrameContext, flight: _Flight, pairs: _PairEvents,
                       walls_now: _WallEvents, discs: torch.Tensor,
                       waiting: tuple[_PairEvents, _WallEvents] | None,
                       ) -> tuple[_PairEvents, _WallEvents]:
        """The impacts pending after a round that changed ``discs``: the ``waiting`` ones (None
        when the round applied them all) of discs that did not change (the others are void),
        and the changed discs' next pair impacts (not with the partner just met) and walls
        (not an axis just hit)."""
        n, dim, device = flight.x.shape[0], flight.x.shape[1], flight.x.device
        changed = torch.zeros(n, dtype=torch.bool, device=device)
        changed[discs] = True
        if waiting is not None:
            waiting = (waiting[0].take(~(changed[waiting[0].rcv] | changed[waiting[0].snd])),
                       waiting[1].take(~changed[waiting[1].disc]))
        # each changed disc met one partner at most
        partner = torch.full((n,), -1, dtype=torch.long, device=device)
        partner[pairs.rcv] = pairs.snd
        near = ctx.near
        again = (changed[near.rcv] | changed[near.snd]) & (partner[near.rcv] != near.snd)
        moved = changed.nonzero()[:, 0]
        just_walled = torch.zeros(n, dim, dtype=torch.bool, device=device)
        just_walled[walls_now.disc, walls_now.axis] = True
        new_pairs = self._pair_events(ctx.g, flight, ctx.dt, near.pairs[again], ctx.terms)
        new_walls = self._wall_events(ctx.g, flight, ctx.dt, moved, just_walled[moved],
                                      ctx.terms)
        if waiting is None:
            return new_pairs, new_walls
        return waiting[0].cat(new_pairs), waiting[1].cat(new_walls)

    def _pair_events(self, g: Graph, flight: _Flight, dt: torch.Tensor, edges: torch.Tensor,
                     frame: _FrameTerms) -> _PairEvents:
        """The impacts ahead on the given edges (receiver < sender), each pair from the later
        of its two discs' times: when, the gate's logit, and both discs' velocity changes."""
        snd, rcv = g.edge_index.index_select(1, edges)
        at_rcv, at_snd = _pick(rcv), _pick(snd)
        start = torch.maximum(at_rcv(flight.tau), at_snd(flight.tau))
        dx = minimum_image(flight.at(rcv, start, dt) - flight.at(snd, start, dt),
                           edge_period(g, rcv))
        dv = at_rcv(flight.v) - at_snd(flight.v)
        reach = at_rcv(g.radius) + at_snd(g.radius)
        rest = (1 - start) * at_rcv(dt)                  # what is left of the frame
        frac, hit = time_of_impact(dx, dv, reach, rest)
        k = hit.nonzero()[:, 0]
        if not len(k):
            return _PairEvents(edges[:0], rcv[:0], snd[:0], *(dx.new_zeros(0),) * 2,
                               *(dx.new_zeros(0, dx.shape[1]),) * 2)
        rcv, snd = rcv.index_select(0, k), snd.index_select(0, k)
        dx, dv, frac, start, rest, reach = (t.index_select(0, k)
                                            for t in (dx, dv, frac, start, rest, reach))
        at_impact = dx + dv * (frac * rest)[:, None]
        normal = at_impact / torch.sqrt((at_impact * at_impact).sum(-1, keepdim=True) + TINY)
        approach = (dv * normal).sum(-1)                                  # < 0 when closing
        when = start + frac * (1 - start)                                 # in frames
        gap = torch.sqrt((dx * dx).sum(-1) + TINY) - reach
        hit = torch.ones_like(when, dtype=torch.bool)
        logit = self.gate_logits(gate_features(when, hit, approach, gap, reach,
                                               frame.speed_unit.index_select(0, rcv)), hit)
        # equal and opposite: m_i dv_i = -m_j dv_j (shares m_j / (m_i + m_j) and m_i / ...)
        kick = -(1 + frame.pair_restitution) * approach * torch.sigmoid(logit)
        log_ratio = (frame.log_mass.index_select(0, snd)
                     - frame.log_mass.index_select(0, rcv))                  # log m_j / m_i
        dv_rcv = (torch.sigmoid(log_ratio) * kick)[:, None] * normal
        dv_snd = -(torch.sigmoid(-log_ratio) * kick)[:, None] * normal
        return _PairEvents(edges.index_select(0, k), rcv, snd, when, logit, dv_rcv, dv_snd)

    def _wall_events(self, g: Graph, flight: _Flight, dt: torch.Tensor, discs: torch.Tensor,
                     skip: torch.Tensor | None, frame: _FrameTerms) -> _WallEvents:
        """The wall impacts ahead of the given discs (per axis; ``skip`` (len, D): axes not
        to solve again): when, and the velocity change along the axis."""
        pick = _pick(discs)
        tau, v = pick(flight.tau), pick(flight.v)
        rest = (1 - tau) * pick(dt)
        low, high = frame.walls
        frac, hit = wall_impact(pick(flight.x), v, pick(g.radius), (pick(low), pick(high)), rest)
        if skip is not None:
            hit = hit & ~skip
        row, axis = hit.nonzero().unbind(1)
        if not len(row):
            return _WallEvents(row, axis, v.new_zeros(0), v.new_zeros(0))
        flat = row * v.shape[1] + axis                   # (row, axis) into the flattened (N, D)
        tau = tau.index_select(0, row)
        when = tau + frac.flatten().index_select(0, flat) * (1 - tau)
        speed = v.flatten().index_select(0, flat)
        disc = discs.index_select(0, row)
        feats = torch.stack([when, torch.ones_like(when),
                             speed.abs() / frame.speed_unit.index_select(0, disc)], -1)
        gate = torch.sigmoid(self.wall_gate(feats).squeeze(-1) + RULE_LOGIT)
        return _WallEvents(disc, axis, when, -(1 + frame.wall_restitution) * speed * gate)

    def _resolve(self, g: Graph, x: torch.Tensor, v: torch.Tensor, dt: torch.Tensor,
                 every_edge: bool) -> FrameImpacts:
        """``resolve``; on graphs of more than ``checkpoint_edges`` edges with its per-edge
        intermediates (a few dozen (E,) and (E, D) tensors per frame) recomputed in the
        backward pass instead of kept (activation checkpointing: element-wise work only)."""
        if torch.is_grad_enabled() and checkpointed(g.edge_index.shape[1], self.edge_chunk,
                                                    self.checkpoint_edges.above(x)):
            return checkpoint(self.resolve, g, x, v, dt, every_edge, use_reentrant=False)
        return self.resolve(g, x, v, dt, every_edge)

    def _replay_start(self, g: Graph) -> tuple[int, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The frame spacing per disc, how many of the window's frames are replayed (``depth``)
        and the position and backward-difference velocity ``depth`` frames before t."""
        if g.dt is None:
            raise ValueError("the impulse head needs the frame spacing: the graph has no dt")
        dt = g.dt.to(g.pos.dtype)[g.batch]
        depth = min(REPLAY_FRAMES, g.vel.shape[1] - 1)
        x = g.pos - (g.vel[:, :depth] * dt[:, None, None]).sum(1)     # x[t - depth]
        return depth, dt, x, g.vel[:, depth]

    def _replay(self, g: Graph) -> tuple[torch.Tensor, torch.Tensor, list[FrameImpacts]]:
        """The velocity at frame t, the frame spacing per disc and the replayed frames'
        impacts (oldest first). Each frame from t - j to t - j + 1 keeps the recorded
        positions; its velocity is the backward difference plus what the frame's impacts
        changed after their instant (a backward difference averages over its frame).
        Replayed from REPLAY_FRAMES back, so that a disc that bounced in consecutive frames
        starts each replay with its velocity after the last bounce, not the average that
        still approaches its partner (which would bounce it again).

        Without gradients: the replays only correct the input velocity. The gates, masses and
        restitution learn from the predicted frame and the contact loss; the replays' backward
        was a sizeable share of a default training step, and the default job trained without it is
        as accurate (docs/notes/2026-11-26-results-history.md,
        "The replay without gradients")."""
        depth, dt, x, v = self._replay_start(g)
        frames = []
        with torch.no_grad():
            for j in range(depth, 0, -1):
                # the replays' logits are not outputs: the gate runs on their impacts only
                frame = self._resolve(g, x, v, dt, False)
                frames.append(frame)
                x = x + g.vel[:, j - 1] * dt[:, None]
                v = g.vel[:, j - 1] + (frame.velocity - frame.mean_velocity)
        return v, dt, frames

    def forward(self, g: Graph) -> tuple[torch.Tensor, torch.Tensor]:
        v, dt, _ = self._replay(g)
        # the next frame: free flight and its impacts, one at a time
        frame = self._resolve(g, g.pos, v, dt, True)
        return frame.mean_velocity, frame.logits

    @torch.no_grad()
    def window_contacts(self, g: Graph) -> torch.Tensor:
        """The pair impacts the head resolves in the window's replayed frames, as rows
        ``(j, i, k)`` (M, 3): discs i < k (graph-wide node indices) touch between frames
        t - j and t - j + 1, where free flight meets and the gate is open (probability
        > 1/2). What the head's per-simulation mass solve reads
        (``bgn.eval.mass_baselines.impact_log_mass``)."""
        snd, rcv = g.edge_index
        _, _, frames = self._replay(g)
        depth = len(frames)
        rows = []
        for j, frame in zip(range(depth, 0, -1), frames, strict=True):
            touch = frame.pairs[frame.pair_logits > 0]
            rows.append(torch.stack([torch.full_like(touch, j), rcv[touch], snd[touch]], 1))
        return torch.cat(rows)
