"""Synthetic graphs, statistics and scene records for the model tests (no files, no sims)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from bgn.graph import Graph
from bgn.sim.scene import SceneMeta


def fake_stats(dim: int = 2) -> dict[str, dict[str, np.ndarray]]:
    """Statistics with distinct, non-trivial values, a heavy-tailed target (std >> robust
    scale) and a zero robust scale for contacts (the fallback to std is exercised)."""

    def entry(mean, std, median, robust, width):
        return {"mean": np.full(width, mean), "std": np.full(width, std),
                "median": np.full(width, median), "robust_scale": np.full(width, robust)}

    return {
        "velocity": entry(0.1, 2.0, 0.05, 1.5, dim),
        "target": entry(0.3, 50.0, 0.2, 2.0, dim),
        "log_mass": entry(0.2, 1.1, 0.1, 0.9, 1),
        "rel_position": entry(0.0, 1.6, 0.0, 1.3, dim),
        "rel_velocity": entry(0.0, 2.2, 0.0, 1.7, dim),
        "contact": entry(0.5, 0.8, 0.0, 0.0, 1),
        "rel_log_mass": entry(0.0, 1.5, 0.0, 1.2, 1),
        "target_diff1": entry(0.0, 9.0, 0.0, 0.4, dim),
        "target_diff2": entry(0.0, 3.0, 0.0, 0.05, dim),
    }


def make_meta(n: int = 6, n_types: int = 2, interaction: str = "pairwise",
              graph: str = "full", dim: int = 2, box: float | None = None) -> SceneMeta:
    return SceneMeta(name=f"test_{interaction}_{graph}", dim=dim, n_particles=n,
                     n_types=n_types, interaction=interaction,
                     target="velocity" if interaction == "contact" else "acceleration",
                     graph=graph, box=box)


def random_graph(n: int = 6, dim: int = 2, history: int = 2, kind: str = "full",
                 n_types: int = 2, contact: bool = False, box: float | None = None,
                 seed: int = 0, dtype: torch.dtype = torch.float64,
                 cutoff: float = 1.5) -> Graph:
    """One frame: random state, complete (``kind="full"``) or radius (``"radius"``) graph."""
    gen = torch.Generator().manual_seed(seed)

    def randn(*shape):
        return torch.randn(*shape, generator=gen, dtype=dtype)

    if box is not None:
        pos = torch.rand(n, dim, generator=gen, dtype=dtype) * box
    else:
        pos = randn(n, dim) * 1.5
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    keep = i != j
    if kind == "radius":
        keep &= torch.cdist(pos, pos) < cutoff  # test-sized N only
    elif kind != "full":
        raise ValueError(kind)
    receivers, senders = i[keep], j[keep]
    edge_index = torch.stack([senders, receivers])
    diff = pos[receivers] - pos[senders]
    if contact:  # symmetric, like real contacts
        touching = torch.rand(n, n, generator=gen) < 0.3
        edge_contact = (touching | touching.T)[receivers, senders].to(dtype)
    else:  # a softened inverse-square magnitude: heavy-ish tail
        edge_contact = 1.0 / ((diff * diff).sum(-1) + 0.1)
    mass = torch.exp(randn(n))
    log_m = torch.log(mass)
    return Graph(
        pos=pos, vel=randn(n, history + 1, dim), edge_index=edge_index,
        target=randn(n, dim) * 3.0, edge_contact=edge_contact, mass=mass,
        edge_rel_log_mass=log_m[receivers] - log_m[senders],
        types=torch.randint(0, n_types, (n,), generator=gen),
        radius=torch.full((n,), 0.1, dtype=dtype),
        wall=None if box is None else torch.cat([pos, box - pos], 1),
        batch=torch.zeros(n, dtype=torch.long), num_nodes=torch.tensor([n]),
        sim=torch.tensor([0]), frame=torch.tensor([seed]), dt=torch.tensor([0.1], dtype=dtype))


@pytest.fixture
def stats():
    return fake_stats


@pytest.fixture
def meta():
    return make_meta


@pytest.fixture
def graph():
    return random_graph


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny graphs: intra-op threads only add overhead (and stall badly on a busy 2-core box)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def permute_graph(g: Graph, seed: int = 5) -> tuple[Graph, torch.Tensor, torch.Tensor]:
    """Relabel the nodes and reorder the edges of ``g`` at random.

    Returns the permuted graph, ``perm`` (new node a is old node ``perm[a]``) and
    ``edge_perm`` (new edge e is old edge ``edge_perm[e]``).
    """
    gen = torch.Generator().manual_seed(seed)
    n = g.pos.shape[0]
    perm = torch.randperm(n, generator=gen)
    inverse = torch.argsort(perm)
    edge_perm = torch.randperm(g.edge_index.shape[1], generator=gen)
    permuted = replace(
        g, pos=g.pos[perm], vel=g.vel[perm], target=g.target[perm], mass=g.mass[perm],
        types=g.types[perm], radius=g.radius[perm],
        wall=None if g.wall is None else g.wall[perm],
        edge_index=inverse[g.edge_index][:, edge_perm],
        edge_contact=g.edge_contact[edge_perm], edge_rel_log_mass=g.edge_rel_log_mass[edge_perm])
    return permuted, perm, edge_perm
