"""Periodic boundaries in the models: every edge vector is the minimum image, so a prediction
is a function of the scene on the torus (bgn.model.message_passing.edge_vector)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bgn.data.edges import scene_edges
from bgn.graph import collate, window_graph
from bgn.model import build_model
from bgn.model.message_passing import edge_vector, minimum_image
from bgn.sim.scene import SceneMeta
from tests.model.conftest import fake_stats

L = 6.0
N, HISTORY, CUTOFF = 14, 3, 1.4
MODELS = [  # name, options, graph kinds it runs on
    ("bgn", {"hidden": 16, "decoder_hidden": 16, "flow_hidden": 8, "flow_transforms": 2},
     ("full", "radius")),
    ("bgn", {"hidden": 16, "decoder_hidden": 16, "flow_hidden": 8, "flow_transforms": 2,
             "dynamics": "newton"}, ("full",)),
    ("newton", {}, ("full",)),
    ("gns", {}, ("full", "radius")),
    ("cranmer_gn", {}, ("full", "radius")),
]
CASES = [(name, opts, kind) for name, opts, kinds in MODELS for kind in kinds]


def torus_meta(kind: str, period: tuple[float, ...] | None = (L, L)) -> SceneMeta:
    return SceneMeta(name="torus", dim=2, n_particles=N, n_types=2, interaction="unknown",
                     target="acceleration", graph=kind, period=period)


def model_for(name: str, opts: dict, meta: SceneMeta) -> torch.nn.Module:
    torch.manual_seed(3)
    return build_model({"name": name, **opts}, meta, fake_stats(), HISTORY).double().eval()


def cluster_window(seed: int, centre: np.ndarray) -> np.ndarray:
    """(k+2, N, D) a smooth window of a cluster around ``centre`` (dense enough that many
    pairs are within the cut-off), unwrapped."""
    rng = np.random.default_rng(seed)
    x0 = centre + rng.uniform(-1.8, 1.8, (N, 2))
    v = rng.normal(0, 1, (N, 2))
    a = rng.normal(0, 1, (N, 2))
    t = 0.05 * np.arange(-HISTORY - 1, 1)[:, None, None]
    return x0 + v * t + 0.5 * a * t**2


def graph_of(window: np.ndarray, meta: SceneMeta, seed: int = 0):
    rng = np.random.default_rng(100 + seed)
    masses = torch.as_tensor(rng.uniform(0.5, 2.0, (1, N)))
    types = torch.as_tensor(rng.integers(0, 2, (1, N)))
    edges = scene_edges(meta.graph, window[-1], np.zeros(N), CUTOFF, meta.period)
    return window_graph(torch.as_tensor(window)[None], 0.05, torch.as_tensor(edges), masses,
                        torch.zeros(1, N, dtype=torch.float64), types, None,
                        torch.tensor([0]), torch.tensor([HISTORY + 1]), torch.float64,
                        period=meta.period)


def pairs(g) -> set[tuple[int, int]]:
    return set(zip(*g.edge_index.tolist()))


def close(a: torch.Tensor, b: torch.Tensor) -> None:
    torch.testing.assert_close(a, b, rtol=1e-7, atol=1e-9)


@pytest.mark.parametrize(("name", "opts", "kind"), CASES)
def test_whole_periods_per_particle_change_nothing(name, opts, kind):
    """Each particle moved by its own whole number of box lengths (what unwrapping leaves
    arbitrary): the same edges and the same prediction."""
    meta = torus_meta(kind)
    model = model_for(name, opts, meta)
    window = cluster_window(1, np.array([0.3, L - 0.2]))
    turns = np.random.default_rng(2).integers(-4, 5, (1, N, 2)) * L
    g, moved = graph_of(window, meta), graph_of(window + turns, meta)
    assert pairs(g) == pairs(moved)
    close(model.predict(g), model.predict(moved))


@pytest.mark.parametrize(("name", "opts", "kind"), CASES)
@pytest.mark.parametrize("seed", [0, 1])
def test_translation_on_the_torus_changes_nothing(name, opts, kind, seed):
    """A translation by any vector, each particle wrapped back into the box (its whole
    window with it): the same edges and the same prediction."""
    meta = torus_meta(kind)
    model = model_for(name, opts, meta)
    rng = np.random.default_rng(seed)
    window = cluster_window(seed, rng.uniform(0, L, 2))
    shifted = window + rng.uniform(-2 * L, 2 * L, 2)
    shifted -= L * np.floor(shifted[-1:] / L)                      # wrapped by the newest frame
    g, moved = graph_of(window, meta), graph_of(shifted, meta)
    assert pairs(g) == pairs(moved)
    close(model.predict(g), model.predict(moved))


@pytest.mark.parametrize(("name", "opts", "kind"), CASES)
def test_a_scene_across_the_boundary_is_the_scene_in_the_middle(name, opts, kind):
    """A cluster around the box's corner, wrapped (so it is cut into four pieces at the box's
    faces), predicts what the same cluster in the middle of the box does; without the period
    the cut pieces would lose their edges (the test would fail)."""
    meta = torus_meta(kind)
    model = model_for(name, opts, meta)
    middle = cluster_window(4, np.array([L / 2, L / 2]))
    corner = middle - L / 2
    corner -= L * np.floor(corner[-1:] / L)
    g, cut = graph_of(middle, meta), graph_of(corner, meta)
    assert pairs(g) == pairs(cut)
    if kind == "radius":  # the boundary does cut pairs here
        flat = torus_meta(kind, period=None)
        assert len(pairs(graph_of(corner, flat))) < len(pairs(g))
    close(model.predict(g), model.predict(cut))


def test_a_batch_of_periodic_graphs_is_each_alone():
    meta = torus_meta("radius")
    model = model_for("bgn", MODELS[0][1], meta)
    graphs = [graph_of(cluster_window(s, np.array([0.1, 0.2]) * s), meta, s) for s in (5, 6)]
    batch = collate(graphs)
    assert batch.period.shape == (2, 2)
    close(model.predict(batch), torch.cat([model.predict(g) for g in graphs]))


def test_edge_vectors_are_minimum_images_and_mixed_dimensions_stay_as_they_are():
    """Only periodic dimensions wrap; the gradient of an edge vector is the identity."""
    meta = torus_meta("full", period=(L, 0.0))
    g = graph_of(cluster_window(7, np.array([0.0, 0.0])) * np.array([1.0, 3.0]), meta)
    pos = g.pos.clone().requires_grad_(True)
    dx = edge_vector(pos, g)
    raw = pos[g.edge_index[1]] - pos[g.edge_index[0]]
    assert (dx[:, 0].abs() <= L / 2 + 1e-12).all()
    torch.testing.assert_close(dx[:, 1], raw[:, 1], rtol=0, atol=0)
    turns = (raw[:, 0] - dx[:, 0]) / L
    torch.testing.assert_close(turns, torch.round(turns))
    dx.sum().backward()
    torch.testing.assert_close(pos.grad, torch.zeros_like(pos))  # +1 at i, -1 at j per edge
    assert minimum_image(raw, None) is raw


def test_the_absolute_position_feature_is_refused_on_a_torus():
    meta = torus_meta("full")
    model = model_for("bgn", {**MODELS[0][1], "use_absolute_position": True}, meta)
    with pytest.raises(ValueError, match="periodic boundaries.*use_absolute_position=false"):
        model.predict(graph_of(cluster_window(0, np.array([1.0, 1.0])), meta))


def test_scene_meta_period_from_json_and_bad_periods():
    meta = SceneMeta(name="t", dim=2, n_particles=2, n_types=1, interaction="unknown",
                     target="acceleration", graph="full", period=[4, 0])
    assert meta.period == (4.0, 0.0) and meta.periodic and hash(meta)
    none = SceneMeta("t", 2, 2, 1, "unknown", "acceleration", "full", period=[0, 0])
    assert none.period is None and not none.periodic
    with pytest.raises(ValueError, match="one finite length >= 0 per dimension"):
        SceneMeta("t", 2, 2, 1, "unknown", "acceleration", "full", period=(4.0,))
