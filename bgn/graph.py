"""The graph type every model consumes: one frame, or a disjoint union of frames.

Edges are ``edge_index = (senders, receivers)``; relative quantities on an edge are
receiver minus sender (``x_i - x_j`` for edge j -> i).
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

    @property
    def num_graphs(self) -> int:
        return int(self.num_nodes.shape[0])

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
