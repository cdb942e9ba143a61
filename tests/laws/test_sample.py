"""bgn.laws.sample: a head's law on a grid and the data's pair distances."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from bgn.laws.sample import pair_distances, sample_law
from bgn.model.newton import PairForceHead
from bgn.sim.scene import SceneMeta


def test_distances_are_the_training_pairs(trained_spring):
    _, data = trained_spring
    distances = pair_distances(data)[(0, 0)]
    x = data.file.read("positions", (0, 0))
    assert len(distances) == len(data.sims) * data.file.n_frames * 6
    assert distances[0] == pytest.approx(np.linalg.norm(x[0] - x[1]))


def test_distances_on_a_radius_graph_are_those_within_its_reach(tmp_path):
    """Imported with a connectivity radius, a pair beyond it has no edge: the law is read
    only where it acts."""
    from bgn.data import from_arrays
    from bgn.data.dataset import FrameDataset
    from bgn.data.files import DatasetFile

    rng = np.random.default_rng(0)
    start, velocity = rng.uniform(0, 3, size=(3, 1, 12, 2)), rng.normal(size=(3, 1, 12, 2))
    x = start + 0.1 * np.arange(9)[:, None, None] * velocity                # (S, T, N, D)
    paths = from_arrays(x, 0.1, connectivity_radius=0.8, name="gas", data_dir=tmp_path,
                        splits={"train": [0], "val": [1], "test": [2]})
    data = FrameDataset(DatasetFile(paths["train"]), history=3)
    distances = pair_distances(data)[(0, 0)]
    i, j = np.triu_indices(12, 1)
    brute = np.linalg.norm(x[0][:, i] - x[0][:, j], axis=-1)
    assert 0 < distances.max() <= 0.8
    np.testing.assert_allclose(np.sort(distances), np.sort(brute[brute <= 0.8]))


# ----------------------------------------------------------------------------- command line


def test_the_sampled_law_is_the_force_along_the_pair():
    torch.manual_seed(0)
    meta = SceneMeta("spring", 2, 2, 1, "pairwise", "acceleration", "full")
    normalizer = SimpleNamespace(rel_position_scale=torch.tensor(0.7))
    head = PairForceHead(meta, normalizer, 8, 1, "silu", "inertial")
    s = np.array([0.3, 1.0, 2.5])
    law = sample_law(head, s, 1)
    for d, f in zip(s, law):  # two particles at any orientation: F on 1 = f(s) u (0 -> 1)
        u = torch.tensor([0.6, -0.8])
        positions = torch.stack([torch.tensor([1.0, 2.0]), torch.tensor([1.0, 2.0]) + d * u])
        g = SimpleNamespace(edge_index=torch.tensor([[0], [1]]), types=torch.zeros(2, dtype=int))
        force = head.pair_terms(g, positions[:, None])[0, 0].detach()
        assert torch.allclose(force, float(f) * u, atol=1e-6)
