"""The graph type every model consumes: one frame, or a disjoint union of frames.

Edges are ``edge_index = (senders, receivers)``; relative quantities on an edge are
receiver minus sender (``x_i - x_j`` for edge j -> i), by the minimum image in a scene with
periodic boundaries (``Graph.period``; ``bgn.model.message_passing.edge_vector``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import torch


@dataclass
class Graph:
    pos: torch.Tensor            # (N, D) current positions x[t] (input only in relative form)
    vel: torch.Tensor            # (N, k+1, D) finite-difference velocities, newest first
    edge_index: torch.Tensor     # (2, E) int64 senders, receivers
    target: torch.Tensor         # (N, D) next velocity or finite-difference acceleration
    edge_contact: torch.Tensor   # (E,) contact (0/1) or pairwise force magnitude
    mass: torch.Tensor           # (N,) true masses (inverse-model targets, never inputs)
    edge_rel_log_mass: torch.Tensor  # (E,) log m_i - log m_j (receiver minus sender)
    types: torch.Tensor          # (N,) int64 particle types
    radius: torch.Tensor         # (N,)
    wall: torch.Tensor | None    # (N, 2D) distances to the lower and upper walls, or None
    batch: torch.Tensor          # (N,) index of the graph each node belongs to
    num_nodes: torch.Tensor      # (G,) nodes per graph
    sim: torch.Tensor            # (G,) simulation index of each graph
    frame: torch.Tensor          # (G,) frame index t of each graph
    dt: torch.Tensor | None = None  # (G,) frame spacing (turns velocity windows into accelerations)
    # (N, S, D) true velocities v[t+2] .. v[t+S+1] after the target's: unrolled training
    # (bgn.training.unroll); None unless the dataset was asked for them (dataset.unroll)
    future_vel: torch.Tensor | None = None
    # (N,) bool: particles the source moves (imported data's kinematic types): inputs only,
    # never scored (losses and metrics skip them) and set from the record in rollouts
    kinematic: torch.Tensor | None = None
    # (G, D) box length per periodic dimension of each graph (0: not periodic), or None for
    # scenes without periodic boundaries (SceneMeta.period): edge vectors are minimum-image
    period: torch.Tensor | None = None
    # (N,) the pair-force head's mass fit a rollout holds from its first window
    # (rollout_masses=held), set by the learned simulator; None: fitted to this graph's window
    mass_fit: torch.Tensor | None = None

    @property
    def num_graphs(self) -> int:
        return int(self.num_nodes.shape[0])

    @property
    def local_index(self) -> torch.Tensor:
        """(N,) each node's index within its own graph (0 .. num_nodes - 1)."""
        counts = self.num_nodes.to(self.batch.device)
        first = torch.cumsum(counts, 0) - counts
        return torch.arange(self.batch.shape[0], device=self.batch.device) - first[self.batch]

    def to(self, device: torch.device | str, non_blocking: bool = False) -> Graph:
        moved = {f.name: (v.to(device, non_blocking=non_blocking)
                          if isinstance(v := getattr(self, f.name), torch.Tensor) else v)
                 for f in fields(self)}
        return replace(self, **moved)


def collate(graphs: list[Graph]) -> Graph:
    """Disjoint union: concatenate nodes and edges, offset edge indices by preceding nodes."""
    if len(graphs) == 1:
        return graphs[0]
    offsets = torch.cumsum(torch.tensor([0] + [int(g.num_nodes.sum()) for g in graphs[:-1]]), 0)
    cat = {}
    for f in fields(Graph):
        values = [getattr(g, f.name) for g in graphs]
        if f.name == "edge_index":
            cat[f.name] = torch.cat([v + o for v, o in zip(values, offsets)], dim=1)
        elif f.name == "batch":
            starts = torch.cumsum(torch.tensor([0] + [g.num_graphs for g in graphs[:-1]]), 0)
            cat[f.name] = torch.cat([v + s for v, s in zip(values, starts)])
        elif values[0] is None:
            cat[f.name] = None
        else:
            cat[f.name] = torch.cat(values)
    return Graph(**cat)


def window_graph(window: torch.Tensor, dt: float, edge_index: torch.Tensor,
                 masses: torch.Tensor, radii: torch.Tensor, types: torch.Tensor,
                 box: float | None, sims: torch.Tensor, frames: torch.Tensor,
                 dtype: torch.dtype = torch.float32,
                 kinematic: torch.Tensor | None = None,
                 period: tuple[float, ...] | None = None) -> Graph:
    """The graph of B frames from their position windows: what every model sees.

    ``window`` (B, k+2, N, D) holds frames t-k-1 .. t of B simulations (float64 keeps the
    finite differences exact); ``edge_index`` (2, E) indexes the B x N nodes (simulation b's
    particles are nodes b*N .. b*N+N-1); ``masses``, ``radii``, ``types`` are (B, N);
    ``sims``, ``frames`` (B,). Inputs follow docs/design.md#frames-and-targets: backward-difference
    velocities ``v[t] = (x[t] - x[t-1]) / dt``, newest first. Targets and contact labels are zero
    (unknown here); the data layer fills them for training samples. ``kinematic`` (B, N) bool marks
    particles moved by the source (None: none). ``period`` (D,): the box lengths of a periodic scene
    (``SceneMeta.period``), carried as ``Graph.period``; positions stay as given (unwrapped), edge
    vectors take the minimum image.
    """
    b, _, n, d = window.shape
    pos = window[:, -1]                                         # (B, N, D)
    vel = (torch.diff(window, dim=1) / dt).flip(1).transpose(1, 2)  # (B, N, k+1, D), v[t] first
    log_m = torch.log(masses.to(window.dtype)).reshape(-1)
    snd, rcv = edge_index
    wall = None if box is None else torch.cat([pos, box - pos], dim=-1).reshape(b * n, 2 * d)
    device, n_edges = window.device, edge_index.shape[1]
    return Graph(
        pos=pos.reshape(b * n, d).to(dtype),
        vel=vel.reshape(b * n, -1, d).to(dtype),
        edge_index=edge_index,
        target=torch.zeros(b * n, d, dtype=dtype, device=device),
        edge_contact=torch.zeros(n_edges, dtype=dtype, device=device),
        mass=masses.reshape(-1).to(dtype),
        edge_rel_log_mass=(log_m[rcv] - log_m[snd]).to(dtype),
        types=types.reshape(-1).long(),
        radius=radii.reshape(-1).to(dtype),
        wall=None if wall is None else wall.to(dtype),
        batch=torch.arange(b, device=device).repeat_interleave(n),
        num_nodes=torch.full((b,), n, device=device),
        sim=sims.reshape(b).long(),
        frame=frames.reshape(b).long(),
        dt=torch.full((b,), dt, dtype=dtype, device=device),
        kinematic=None if kinematic is None else kinematic.reshape(-1).to(device, torch.bool),
        period=None if period is None else torch.tensor(
            period, dtype=dtype, device=device).expand(b, d).clone(),
    )
