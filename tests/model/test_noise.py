"""Rollout noise (bgn.model.noise): the corrupted graph is the graph of a consistent noisy
window, and its target steps back onto the true trajectory."""

from dataclasses import fields, replace

import numpy as np
import pytest
import torch

from bgn.data.dataset import frame_graph
from bgn.model import build_model
from bgn.model.noise import add_random_walk_noise, random_walk
from bgn.sim import make_scene
from tests.model.conftest import fake_stats, make_meta, random_graph

DT = 0.02
HISTORY = 3


def true_frame(kind: str, box: float | None = None):
    """A frame of a smooth 4-body motion in float64, its position window and next position."""
    scene = make_scene("spring")
    meta = replace(scene.meta, target=kind, box=box)
    rng = np.random.default_rng(1)
    t = np.arange(HISTORY + 3)[:, None, None] * DT
    x = 3.0 + rng.normal(size=(4, 2)) + t * rng.normal(size=(4, 2)) + t**2 * rng.normal(size=(4, 2))
    g = frame_graph(x[:-1], DT, meta, scene, np.ones(4), np.full(4, 0.1), np.zeros(4, int),
                    margin=0.0, next_position=x[-1])
    g = replace(g, **{f.name: getattr(g, f.name).double() for f in fields(g)
                      if torch.is_tensor(getattr(g, f.name))
                      and getattr(g, f.name).is_floating_point()})
    return g, x[:-1], x[-1]


@pytest.mark.parametrize("kind", ["acceleration", "velocity"])
def test_noisy_graph_is_the_graph_of_a_noisy_window_stepping_onto_the_truth(kind):
    g, window, nxt = true_frame(kind, box=10.0)
    torch.manual_seed(0)
    noisy = add_random_walk_noise(g, 0.3, kind)
    vel = noisy.vel.numpy()[:, ::-1].transpose(1, 0, 2)          # oldest first, (k+1, N, D)
    # hold the oldest position and integrate the noisy velocities: a consistent window
    positions = window[0] + DT * np.cumsum(vel, axis=0)
    np.testing.assert_allclose(noisy.pos.numpy(), positions[-1], atol=1e-12)
    np.testing.assert_allclose(noisy.wall.numpy(),
                               np.concatenate([positions[-1], 10.0 - positions[-1]], 1),
                               atol=1e-12)
    assert not torch.allclose(noisy.vel, g.vel)  # it did corrupt the window
    # the model's step from the noisy state with the corrected target gives the true v[t+1]
    v_next_true = (nxt - window[-1]) / DT
    if kind == "acceleration":
        stepped = noisy.vel[:, 0] + DT * noisy.target
    else:
        stepped = noisy.target
    np.testing.assert_allclose(stepped.numpy(), v_next_true, atol=1e-9)
    assert torch.equal(noisy.edge_index, g.edge_index)


def test_random_walk_has_the_stated_std_at_the_newest_velocity_and_grows_towards_it():
    torch.manual_seed(0)
    like = torch.zeros((), dtype=torch.float64)
    noise = random_walk((200_000, 6, 1), 0.5, like)
    std = noise.std(dim=0).squeeze()                              # newest first
    np.testing.assert_allclose(std[0].item(), 0.5, rtol=0.01)
    np.testing.assert_allclose(std[-1].item(), 0.5 / 6**0.5, rtol=0.02)
    assert torch.all(std[:-1] > std[1:])


def test_corrupt_is_the_identity_without_noise_and_only_then(model_parts):
    meta, stats, graph = model_parts
    clean = build_model({"name": "bgn"}, meta, stats, HISTORY)
    assert clean.corrupt(graph) is graph
    noisy = build_model({"name": "gns", "rollout_noise": 0.1}, meta, stats, HISTORY)
    assert not torch.equal(noisy.corrupt(graph).vel, graph.vel)


def test_negative_rollout_noise_is_refused(model_parts):
    meta, stats, _ = model_parts
    with pytest.raises(ValueError, match="rollout_noise"):
        build_model({"name": "bgn", "rollout_noise": -0.1}, meta, stats, HISTORY)


@pytest.fixture
def model_parts():
    meta = make_meta(n=5, n_types=1)
    graph = random_graph(n=5, history=HISTORY, n_types=1)
    graph = replace(graph, dt=torch.full((1,), DT, dtype=graph.vel.dtype))
    return meta, fake_stats(), graph
