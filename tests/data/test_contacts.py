"""Contacts read from positions alone (bgn.data.contacts): the contact distance of each pair of
types and to a wall, and the free-flight evidence that admits soft contacts."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from bgn.data.contacts import FREE_RESIDUAL_MAX, closest_approach, free_flight

DT = 0.01


class Frames:
    """What the readers need of a DatasetFile: sizes and ``read``."""

    def __init__(self, positions: np.ndarray, types: np.ndarray) -> None:
        self.arrays = {"positions": positions, "types": types}
        self.n_sims, self.n_frames = positions.shape[:2]

    def read(self, name: str, index=()):
        return self.arrays[name][index]


def meta(n_types: int = 2, box: float | None = 1.0):
    return SimpleNamespace(n_types=n_types, box=box, period=None)


def touching_pairs(rng: np.random.Generator, sims: int = 3, frames: int = 20) -> Frames:
    """Pairs of discs (types 0-0, 0-1, 1-1, radii 0.02 and 0.03) that sit at their contact
    distance or further apart, and discs that come within their radius of a wall."""
    radius = np.array([0.02, 0.03])
    types = np.array([0, 0, 0, 1, 1, 1, 0, 1])
    pos = np.empty((sims, frames, 8, 2))
    for s in range(sims):
        for t in range(frames):
            gap = rng.uniform(0.0, 0.05, 3)               # one pair of each kind touches
            gap[rng.integers(3)] = 0.0
            centres = [(0.2, 0.3), (0.5, 0.3), (0.8, 0.6)]
            kinds = [(0, 1), (2, 3), (4, 5)]
            for (i, j), c, g in zip(kinds, centres, gap, strict=True):
                d = radius[types[i]] + radius[types[j]] + g
                pos[s, t, i] = c
                pos[s, t, j] = (c[0] + d, c[1])
            pos[s, t, 6] = (0.5, radius[0] + rng.uniform(0.0, 0.01))  # on the floor, or near
            pos[s, t, 7] = (1.0 - radius[1] - rng.uniform(0.0, 0.01), 0.9)  # at a wall
    return Frames(pos, np.broadcast_to(types, (sims, 8)).copy())


def test_the_closest_approaches_are_the_contact_distances():
    a = closest_approach(touching_pairs(np.random.default_rng(0)), meta(), cutoff=0.2)
    np.testing.assert_allclose(a.pair, [[0.04, 0.05], [0.05, 0.06]], atol=1e-9)
    np.testing.assert_allclose(a.wall, [0.02, 0.03], atol=2e-3)


def falling(rng: np.random.Generator, pull: float = 0.0, n: int = 12, frames: int = 30,
            sims: int = 2) -> Frames:
    """Discs far apart falling under gravity with a drag; ``pull`` > 0 adds a spring between
    every pair (forces that reach beyond contact)."""
    g, gamma = np.array([0.0, -1.0]), 0.1
    pos = np.empty((sims, frames, n, 2))
    for s in range(sims):
        x = np.stack([np.linspace(0.1, 0.9, n), rng.uniform(0.5, 0.9, n)], 1)
        v = rng.normal(0.0, 0.2, (n, 2))
        for t in range(frames):
            pos[s, t] = x
            for _ in range(10):
                h = DT / 10
                a = g - gamma * v
                if pull:
                    a = a + pull * (x.mean(0) - x)
                v = v + h * a
                x = x + h * v
    return Frames(pos, np.zeros((sims, n), dtype=np.int64))


def test_free_fall_with_drag_is_contact_data_and_the_field_is_found():
    data = falling(np.random.default_rng(1))
    m = meta(n_types=1, box=None)
    approach = closest_approach(data, m, cutoff=0.02)    # nothing closer: no contacts at all
    flight = free_flight(data, m, approach, cutoff=0.02)
    assert flight.residual is not None and flight.residual < FREE_RESIDUAL_MAX / 100
    assert flight.breaks() == ""
    np.testing.assert_allclose(flight.field, [0.0, -DT * DT], atol=2e-6)
    np.testing.assert_allclose(flight.drag, 0.1 * DT, rtol=0.05)


def test_forces_that_reach_beyond_contact_are_named():
    data = falling(np.random.default_rng(2), pull=30.0)
    m = meta(n_types=1, box=None)
    flight = free_flight(data, m, closest_approach(data, m, cutoff=0.02), cutoff=0.02)
    assert flight.residual > FREE_RESIDUAL_MAX
    assert "reach beyond contact" in flight.breaks()


def test_without_a_free_particle_there_is_no_evidence():
    data = touching_pairs(np.random.default_rng(3))
    m = meta()
    flight = free_flight(data, m, closest_approach(data, m, cutoff=0.2), cutoff=0.2)
    assert flight.residual is None
    assert "no evidence" in flight.breaks()


def test_many_pairs_read_fewer_frames_not_all_of_memory():
    """A complete graph of many particles: the frames read shrink so the distances held stay
    within ``PAIRS_READ`` (a 2 500-particle SPH file was killed for memory before)."""
    from bgn.data import contacts

    rng = np.random.default_rng(0)
    many = Frames(rng.uniform(0, 1, (2, 40, 300, 2)), np.zeros((2, 300), dtype=np.int64))
    pairs = 300 * 299 // 2
    read = contacts._frames(many, 2, 40, np.inf, None)
    assert [len(x) for x in read] == [40, 40]
    old = contacts.PAIRS_READ
    try:
        contacts.PAIRS_READ = 10 * pairs * 2          # room for 10 frames of both simulations
        assert [len(x) for x in contacts._frames(many, 2, 40, np.inf, None)] == [10, 10]
        contacts.PAIRS_READ = 1                       # never fewer than a second difference's 3
        assert [len(x) for x in contacts._frames(many, 2, 40, np.inf, None)] == [3, 3]
    finally:
        contacts.PAIRS_READ = old


def test_the_cutoff_is_the_radius_graphs_reach():
    """Contacts are looked for as far as the graph's edges reach: the connectivity radius
    (the file's margin) plus the two largest radii, every pair on a complete graph."""
    from bgn.data.contacts import contact_cutoff

    class File:
        def __init__(self, graph: str, radii: np.ndarray | None) -> None:
            self.meta = SimpleNamespace(graph=graph)
            self.margin = 0.1
            self.handle = {} if radii is None else {"radii": radii}

        def read(self, name: str, index=()):
            return self.handle[name][index]

    assert contact_cutoff(File("full", None)) == np.inf
    assert contact_cutoff(File("radius", None)) == 0.1
    assert contact_cutoff(File("radius", np.array([[0.02, 0.03]]))) == 0.1 + 0.06
