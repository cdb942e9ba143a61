"""Tests for bgn.data.edges: radius graphs against an O(N^2) oracle, boundaries, invariances."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from bgn.data.edges import (
    batch_edges,
    contact_margin,
    full_graph,
    minimum_image,
    pair_distance,
    radius_graph,
    scene_edges,
)

PROPERTY = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ----------------------------------------------------------------------------- helpers


def brute_force(
    positions: np.ndarray,
    radii: np.ndarray | None = None,
    margin: float = 0.0,
    cutoff: float | None = None,
) -> np.ndarray:
    """O(N^2) oracle: every pair, the same distance formula, both directions, lexsorted."""
    pos = np.asarray(positions, dtype=np.float64)
    n = pos.shape[0]
    i, j = np.triu_indices(n, k=1)
    d = pair_distance(pos, i, j)
    if radii is not None:
        r = np.asarray(radii, dtype=np.float64)
        keep = d <= (r[i] + r[j]) + margin
    else:
        keep = d <= cutoff
    s = np.concatenate([i[keep], j[keep]]).astype(np.int64)
    t = np.concatenate([j[keep], i[keep]]).astype(np.int64)
    order = np.lexsort((s, t))
    return np.stack([s[order], t[order]]).reshape(2, -1)


def assert_valid_edges(edges: np.ndarray, n: int) -> None:
    """int64 (2, E), in range, no self-loops or duplicates, both directions, sorted by receiver."""
    assert edges.dtype == np.int64
    assert edges.ndim == 2 and edges.shape[0] == 2
    s, r = edges
    if edges.shape[1] == 0:
        return
    assert s.min() >= 0 and r.min() >= 0 and s.max() < n and r.max() < n
    assert not np.any(s == r), "self-loop"
    key = r * n + s
    assert np.all(np.diff(key) > 0), "not strictly sorted by (receiver, sender)"
    reverse = np.sort(s * n + r)
    assert np.array_equal(reverse, key), "some edge lacks its reverse"


def edge_set(edges: np.ndarray) -> set[tuple[int, int]]:
    return set(zip(edges[0].tolist(), edges[1].tolist(), strict=True))


# ----------------------------------------------------------------------------- strategies


@st.composite
def float_configurations(
    draw: st.DrawFn,
) -> tuple[np.ndarray, np.ndarray | None, float, float | None]:
    """Random float points in 1-3 D (sometimes 4), either per-node radii + margin or a cutoff."""
    n = draw(st.integers(0, 60))
    dim = draw(st.sampled_from([1, 2, 3, 4]))
    coords = st.floats(-10.0, 10.0, allow_nan=False, allow_infinity=False, width=64)
    positions = draw(hnp.arrays(np.float64, (n, dim), elements=coords))
    if draw(st.booleans()):
        radii = draw(hnp.arrays(np.float64, (n,), elements=st.floats(0.0, 3.0)))
        margin = draw(st.floats(0.0, 2.0))
        return positions, radii, margin, None
    return positions, None, 0.0, draw(st.floats(0.0, 12.0))


@st.composite
def lattice_configurations(
    draw: st.DrawFn,
) -> tuple[np.ndarray, np.ndarray | None, float, float | None]:
    """Integer-valued points and thresholds: many pairs sit exactly at the cut-off."""
    n = draw(st.integers(0, 60))
    dim = draw(st.sampled_from([1, 2, 3]))
    positions = draw(hnp.arrays(np.int64, (n, dim), elements=st.integers(-5, 5))).astype(float)
    if draw(st.booleans()):
        radii = draw(hnp.arrays(np.int64, (n,), elements=st.integers(0, 2))).astype(float)
        margin = float(draw(st.integers(0, 2)))
        return positions, radii, margin, None
    # sqrt of an integer: the same float sqrt(k) the distance formula gives for k = sum of squares.
    return positions, None, 0.0, float(np.sqrt(draw(st.integers(0, 30))))


# ------------------------------------------------------------------------ radius_graph vs oracle


@PROPERTY
@given(float_configurations())
def test_radius_graph_matches_brute_force_floats(config) -> None:
    positions, radii, margin, cutoff = config
    edges = radius_graph(positions, radii=radii, margin=margin, cutoff=cutoff)
    assert_valid_edges(edges, positions.shape[0])
    np.testing.assert_array_equal(edges, brute_force(positions, radii, margin, cutoff))


@PROPERTY
@given(lattice_configurations())
def test_radius_graph_matches_brute_force_lattice(config) -> None:
    positions, radii, margin, cutoff = config
    edges = radius_graph(positions, radii=radii, margin=margin, cutoff=cutoff)
    assert_valid_edges(edges, positions.shape[0])
    np.testing.assert_array_equal(edges, brute_force(positions, radii, margin, cutoff))


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("mode", ["cutoff", "radii"])
def test_radius_graph_matches_brute_force_larger(dim: int, mode: str) -> None:
    # A few hundred points with around ten neighbours each: the tree prunes for real here.
    rng = np.random.default_rng(dim)
    n = 600
    positions = rng.uniform(0.0, n ** (1.0 / dim), size=(n, dim))
    if mode == "radii":
        radii = rng.uniform(0.05, 0.6, size=n)
        kwargs = {"radii": radii, "margin": 0.1}
    else:
        kwargs = {"cutoff": 1.2}
    edges = radius_graph(positions, **kwargs)
    assert_valid_edges(edges, n)
    assert edges.shape[1] > n  # not trivially empty
    np.testing.assert_array_equal(edges, brute_force(positions, **kwargs))


@pytest.mark.parametrize("dim", [1, 2, 3, 5])
def test_threshold_equal_to_a_realised_distance_is_included(dim: int) -> None:
    # Set the threshold to the exact float distance of some pair: that pair must be an edge,
    # whatever rounding the tree's own distance arithmetic does.
    rng = np.random.default_rng(100 + dim)
    positions = rng.normal(scale=3.0, size=(80, dim))
    i, j = np.triu_indices(80, k=1)
    distances = pair_distance(positions, i, j)
    for k in rng.choice(len(i), size=40, replace=False):
        d = float(distances[k])
        for edges in (
            radius_graph(positions, cutoff=d),
            radius_graph(positions, radii=np.zeros(80), margin=d),
        ):
            members = edge_set(edges)
            assert (int(i[k]), int(j[k])) in members and (int(j[k]), int(i[k])) in members
            np.testing.assert_array_equal(edges, brute_force(positions, cutoff=d))


# ----------------------------------------------------------------------------- boundaries


@pytest.mark.parametrize("spacing", [1.0, 2.0, 0.5, 4.0])
def test_lattice_neighbours_exactly_at_cutoff_are_included(spacing: float) -> None:
    # Spacings that are powers of two keep every coordinate difference exact.
    side = 7
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side), indexing="ij"), -1)
    positions = grid.reshape(-1, 2) * spacing
    n = side * side
    edges = radius_graph(positions, cutoff=spacing)
    assert_valid_edges(edges, n)
    # 4-neighbourhood: 2 * side * (side - 1) undirected lattice bonds.
    assert edges.shape[1] == 2 * 2 * side * (side - 1)
    degree = np.bincount(edges[1], minlength=n).reshape(side, side)
    assert np.all(degree[1:-1, 1:-1] == 4)
    # The same contacts in radii mode: touching spheres of radius spacing / 2.
    touching = radius_graph(positions, radii=np.full(n, spacing / 2))
    np.testing.assert_array_equal(touching, edges)
    # Diagonals sit at sqrt(2) * spacing; the cut-off computed the same way includes them.
    diagonal = float(np.sqrt(2 * spacing**2))
    edges8 = radius_graph(positions, cutoff=diagonal)
    degree8 = np.bincount(edges8[1], minlength=n).reshape(side, side)
    assert np.all(degree8[1:-1, 1:-1] == 8)
    # Just below the cut-off the lattice falls apart.
    assert radius_graph(positions, cutoff=np.nextafter(spacing, 0.0)).shape == (2, 0)


def test_one_dimensional_chain_at_cutoff() -> None:
    positions = np.arange(10.0).reshape(-1, 1)
    edges = radius_graph(positions, cutoff=1.0)
    expected = np.array(
        [
            [1] + [k for r in range(1, 9) for k in (r - 1, r + 1)] + [8],
            [0] + [r for r in range(1, 9) for _ in range(2)] + [9],
        ]
    )
    np.testing.assert_array_equal(edges, expected)


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_identical_points_are_all_connected(dim: int) -> None:
    n = 12
    positions = np.full((n, dim), 3.25)
    full = full_graph(n)
    np.testing.assert_array_equal(radius_graph(positions, cutoff=0.0), full)
    np.testing.assert_array_equal(radius_graph(positions, radii=np.zeros(n)), full)
    np.testing.assert_array_equal(radius_graph(positions, cutoff=1.0), full)


def test_all_points_within_one_cell() -> None:
    rng = np.random.default_rng(1)
    positions = 100.0 + rng.uniform(0.0, 1e-3, size=(50, 3))
    np.testing.assert_array_equal(radius_graph(positions, cutoff=1.0), full_graph(50))
    np.testing.assert_array_equal(radius_graph(positions, radii=np.full(50, 0.5)), full_graph(50))


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_zero_and_one_point(dim: int) -> None:
    for n in (0, 1):
        positions = np.zeros((n, dim))
        for edges in (
            radius_graph(positions, cutoff=1.0),
            radius_graph(positions, radii=np.ones(n), margin=0.5),
        ):
            assert edges.shape == (2, 0) and edges.dtype == np.int64


def test_far_apart_points_have_no_edges() -> None:
    positions = np.arange(5.0).reshape(-1, 1) * 10.0
    assert radius_graph(positions, cutoff=9.999).shape == (2, 0)
    assert radius_graph(positions, radii=np.full(5, 4.0), margin=1.9).shape == (2, 0)
    assert radius_graph(positions, radii=np.full(5, 4.0), margin=2.0).shape == (2, 8)


# ----------------------------------------------------------------------------- full_graph


@pytest.mark.parametrize("n", [0, 1, 2, 3, 7, 30])
def test_full_graph(n: int) -> None:
    edges = full_graph(n)
    assert edges.shape == (2, n * (n - 1))
    assert_valid_edges(edges, n)
    assert edge_set(edges) == {(s, r) for r in range(n) for s in range(n) if s != r}


@pytest.mark.parametrize("dim", [1, 2, 3])
def test_huge_cutoff_gives_full_graph(dim: int) -> None:
    rng = np.random.default_rng(dim)
    positions = rng.uniform(-1.0, 1.0, size=(40, dim))
    np.testing.assert_array_equal(radius_graph(positions, cutoff=1e6), full_graph(40))
    np.testing.assert_array_equal(
        radius_graph(positions, radii=np.full(40, 1e3), margin=1.0), full_graph(40)
    )


def test_full_graph_rejects_bad_n() -> None:
    for bad in (-1, 2.5, True, "3"):
        with pytest.raises(ValueError, match="n must"):
            full_graph(bad)  # type: ignore[arg-type]
    assert full_graph(np.int32(4)).shape == (2, 12)


# ----------------------------------------------------------------------------- batch_edges


def test_batch_edges_offsets() -> None:
    a = full_graph(2)  # nodes 0-1
    b = np.zeros((2, 0), dtype=np.int64)  # 3 isolated nodes: 2-4
    c = np.array([[1, 0], [0, 1]])  # nodes 5-6, int64 from a plain list
    d = full_graph(3).astype(np.int32)  # nodes 7-9
    batched = batch_edges([a, b, c, d], [2, 3, 2, 3])
    expected = np.concatenate([a, b, c + 5, full_graph(3) + 7], axis=1)
    np.testing.assert_array_equal(batched, expected)
    assert batched.dtype == np.int64
    assert_valid_edges(batched, 10)


def test_batch_edges_of_radius_graphs_equals_radius_graph_of_separated_union() -> None:
    # Integer-valued clouds shifted far apart by integers: every difference stays exact, so the
    # union's radius graph must be exactly the batch of the separate graphs.
    rng = np.random.default_rng(5)
    sizes = [0, 17, 1, 30, 9]
    clouds = [rng.integers(0, 6, size=(k, 2)).astype(float) for k in sizes]
    cutoff = float(np.sqrt(2.0))
    separate = [radius_graph(c, cutoff=cutoff) for c in clouds]
    union = np.concatenate([c + 1000.0 * g for g, c in enumerate(clouds)])
    batched = batch_edges(separate, sizes)
    assert_valid_edges(batched, sum(sizes))
    assert batched.shape[1] > 0
    np.testing.assert_array_equal(batched, radius_graph(union, cutoff=cutoff))


def test_batch_edges_empty_and_validation() -> None:
    assert batch_edges([], []).shape == (2, 0)
    with pytest.raises(ValueError, match="one per graph"):
        batch_edges([full_graph(2)], [2, 3])
    with pytest.raises(ValueError, match="outside"):
        batch_edges([full_graph(3)], [2])
    with pytest.raises(ValueError, match="shape"):
        batch_edges([np.zeros((3, 2), dtype=np.int64)], [4])
    with pytest.raises(ValueError, match="integers"):
        batch_edges([np.zeros((2, 1))], [4])
    with pytest.raises(ValueError, match=">= 0"):
        batch_edges([np.zeros((2, 0), dtype=np.int64)], [-1])


# ----------------------------------------------------------------------------- invariances


@settings(max_examples=100, deadline=None)
@given(
    positions=hnp.arrays(
        np.int64, st.tuples(st.integers(0, 40), st.integers(1, 3)), elements=st.integers(-20, 20)
    ),
    shift=st.integers(-(10**6), 10**6),
    cutoff=st.integers(0, 12),
    use_radii=st.booleans(),
)
def test_translation_does_not_change_edges(positions, shift, cutoff, use_radii) -> None:
    # Integer-valued coordinates: differences are exact before and after the shift.
    pos = positions.astype(np.float64)
    shifted = pos + float(shift)
    if use_radii:
        radii = np.full(pos.shape[0], cutoff / 2.0)
        kwargs = {"radii": radii, "margin": 0.5}
    else:
        kwargs = {"cutoff": float(np.sqrt(cutoff))}
    np.testing.assert_array_equal(radius_graph(pos, **kwargs), radius_graph(shifted, **kwargs))


@settings(max_examples=100, deadline=None)
@given(config=float_configurations(), seed=st.integers(0, 2**32 - 1))
def test_permutation_permutes_edges(config, seed) -> None:
    positions, radii, margin, cutoff = config
    n = positions.shape[0]
    perm = np.random.default_rng(seed).permutation(n)  # new node k is old node perm[k]
    edges = radius_graph(positions, radii=radii, margin=margin, cutoff=cutoff)
    permuted = radius_graph(
        positions[perm],
        radii=None if radii is None else radii[perm],
        margin=margin,
        cutoff=cutoff,
    )
    assert_valid_edges(permuted, n)
    # Map the permuted graph back to old labels: perm[k] is the old index of new node k.
    assert edge_set(np.stack([perm[permuted[0]], perm[permuted[1]]]).reshape(2, -1)) == edge_set(
        edges
    )


# ----------------------------------------------------------------------------- distance, margin


def test_pair_distance_is_euclidean_and_symmetric() -> None:
    rng = np.random.default_rng(3)
    positions = rng.normal(size=(50, 3))
    i, j = np.triu_indices(50, k=1)
    d = pair_distance(positions, i, j)
    np.testing.assert_allclose(d, np.linalg.norm(positions[i] - positions[j], axis=1), rtol=1e-14)
    np.testing.assert_array_equal(d, pair_distance(positions, j, i))
    assert pair_distance(positions, np.array([], dtype=int), np.array([], dtype=int)).shape == (0,)
    with pytest.raises(ValueError):
        pair_distance(positions, i, j[:-1])


def test_contact_margin() -> None:
    assert contact_margin(2.0, 0.1) == pytest.approx(0.3)
    assert contact_margin(2.0, 0.1, safety=1.0) == pytest.approx(0.2)
    assert contact_margin(0.0, 0.1) == 0.0
    # A pair closing at the largest relative speed touches within one frame: it is a candidate.
    positions = np.array([[0.0, 0.0], [2.0 + 0.19, 0.0]])
    margin = contact_margin(2.0, 0.1)
    assert radius_graph(positions, radii=np.ones(2), margin=margin).shape == (2, 2)
    for bad in (
        {"max_relative_speed": -1.0, "dt": 0.1},
        {"max_relative_speed": 1.0, "dt": 0.0},
        {"max_relative_speed": 1.0, "dt": 0.1, "safety": 0.5},
        {"max_relative_speed": np.inf, "dt": 0.1},
    ):
        with pytest.raises(ValueError):
            contact_margin(**bad)


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("positions", "kwargs", "match"),
    [
        (np.zeros(5), {"cutoff": 1.0}, r"shape \(N, D\)"),
        (np.zeros((5, 0)), {"cutoff": 1.0}, "D >= 1"),
        (np.zeros((2, 2, 2)), {"cutoff": 1.0}, r"shape \(N, D\)"),
        (np.array([[0.0], [np.nan]]), {"cutoff": 1.0}, "finite"),
        (np.array([[0.0], [np.inf]]), {"cutoff": 1.0}, "finite"),
        (np.array([["a"], ["b"]]), {"cutoff": 1.0}, "real numbers"),
        (np.zeros((3, 2)), {}, "exactly one"),
        (np.zeros((3, 2)), {"cutoff": 1.0, "radii": np.ones(3)}, "exactly one"),
        (np.zeros((3, 2)), {"cutoff": -1.0}, ">= 0"),
        (np.zeros((3, 2)), {"cutoff": np.inf}, "finite"),
        (np.zeros((3, 2)), {"cutoff": np.nan}, "finite"),
        (np.zeros((3, 2)), {"cutoff": 1.0, "margin": 0.5}, "margin applies only"),
        (np.zeros((3, 2)), {"radii": np.ones(4)}, r"shape \(N,\)"),
        (np.zeros((3, 2)), {"radii": np.ones((3, 1))}, r"shape \(N,\)"),
        (np.zeros((3, 2)), {"radii": np.array([1.0, -1.0, 1.0])}, ">= 0"),
        (np.zeros((3, 2)), {"radii": np.array([1.0, np.nan, 1.0])}, "finite"),
        (np.zeros((3, 2)), {"radii": np.ones(3), "margin": -0.1}, ">= 0"),
        (np.zeros((3, 2)), {"radii": np.ones(3), "margin": np.inf}, "finite"),
    ],
)
def test_radius_graph_validation(positions, kwargs, match) -> None:
    with pytest.raises(ValueError, match=match):
        radius_graph(positions, **kwargs)


def test_integer_positions_accepted() -> None:
    positions = np.array([[0, 0], [1, 0], [3, 0]])
    np.testing.assert_array_equal(radius_graph(positions, cutoff=1), np.array([[1, 0], [0, 1]]))


# ----------------------------------------------------------------------------- periodic boxes


def torus_pairs(positions: np.ndarray, period: np.ndarray, cutoff: float) -> set[tuple]:
    """O(N^2 3^D) oracle: ordered pairs whose nearest image (of every shift by -1, 0, +1 box
    lengths in each periodic dimension) lies within ``cutoff``; no rounding formula shared
    with the code under test."""
    pos = np.asarray(positions, dtype=np.float64)
    n, d = pos.shape
    shifts = np.array(np.meshgrid(*[[-1, 0, 1] if p > 0 else [0] for p in period],
                                  indexing="ij")).reshape(d, -1).T * period       # (K, D)
    out = set()
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            dx = (pos[i] - pos[j]) % np.where(period > 0, period, np.inf)
            dx = np.where(period > 0, dx, pos[i] - pos[j])   # in [0, L): one shift suffices
            if np.sqrt(((dx + shifts) ** 2).sum(1)).min() <= cutoff:
                out.add((j, i))
    return out


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 40), dim=st.integers(1, 3),
       mixed=st.booleans())
def test_periodic_radius_graph_is_the_minimum_image_brute_force(seed, n, dim, mixed):
    """Random clouds crowded near the box's faces, each particle moved by its own whole number
    of box lengths (unwrapped data): the torus's neighbours, each pair once per direction."""
    rng = np.random.default_rng(seed)
    period = rng.uniform(2.0, 5.0, dim)
    if mixed and dim > 1:
        period[rng.integers(dim)] = 0.0  # one dimension not periodic
    cutoff = rng.uniform(0.1, 0.49) * period[period > 0].min() if period.any() else 0.5
    near_face = rng.uniform(-0.6, 0.6, (n, dim)) * cutoff % np.where(period > 0, period, 1)
    inside = rng.uniform(0, 1, (n, dim)) * np.where(period > 0, period, 3.0)
    pos = np.where(rng.random((n, 1)) < 0.6, near_face, inside)
    pos = pos + rng.integers(-3, 4, (n, dim)) * period                        # unwrapped
    edges = radius_graph(pos, cutoff=cutoff, period=period)
    assert set(zip(*edges.tolist())) == torus_pairs(pos, period, cutoff)
    assert edges.shape[1] == len(torus_pairs(pos, period, cutoff))           # no duplicates
    order = np.lexsort((edges[0], edges[1]))
    np.testing.assert_array_equal(order, np.arange(edges.shape[1]))
    # the same graph through the radii rule (zero radii, margin = cutoff), as scenes build it
    np.testing.assert_array_equal(
        scene_edges("radius", pos, np.zeros(n), cutoff, tuple(period)), edges)


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1))
def test_minimum_image_is_the_nearest_image(seed):
    rng = np.random.default_rng(seed)
    period = np.array([rng.uniform(0.5, 4.0), 0.0, rng.uniform(0.5, 4.0)])
    dx = rng.normal(0, 10, (50, 3))
    out = minimum_image(dx, period)
    periodic = period > 0
    assert (np.abs(out[:, periodic]) <= period[periodic] / 2 * (1 + 1e-12)).all()
    turns = (dx[:, periodic] - out[:, periodic]) / period[periodic]
    np.testing.assert_allclose(turns, np.rint(turns), atol=1e-9)          # whole box lengths
    np.testing.assert_array_equal(out[:, ~periodic], dx[:, ~periodic])
    np.testing.assert_array_equal(minimum_image(dx, None), dx)
    i, j = np.arange(25), np.arange(25, 50)
    x = np.concatenate([dx[:25], np.zeros((25, 3))])
    np.testing.assert_allclose(pair_distance(x, j, i, period),
                               np.linalg.norm(minimum_image(dx[:25], period), axis=1))


def test_a_periodic_reach_of_half_the_box_or_more_is_refused():
    pos = np.zeros((3, 2))
    with pytest.raises(ValueError, match="below half the periodic box length"):
        radius_graph(pos, cutoff=1.0, period=(2.0, 0.0))
    with pytest.raises(ValueError, match="one finite length >= 0 per dimension"):
        radius_graph(pos, cutoff=0.5, period=(2.0,))
    # a zero period in every dimension is no periodic boundary at all
    np.testing.assert_array_equal(radius_graph(pos + [[0], [3], [6]], cutoff=2.0,
                                               period=(0.0, 0.0)),
                                  radius_graph(pos + [[0], [3], [6]], cutoff=2.0))
