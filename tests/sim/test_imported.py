"""The scene of imported trajectories: a record without a simulator or a force law."""

import numpy as np
import pytest

from bgn.model.newton import check_scene
from bgn.sim import SCENES, make_scene
from bgn.sim.imported import ImportedScene, NoSimulatorError
from bgn.sim.scene import State


def test_imported_is_a_registered_scene_whose_meta_says_the_law_is_unknown():
    assert "imported" in SCENES
    scene = make_scene("imported", name="water", n_particles=7, dim=3, n_types=2,
                       graph="radius", connectivity_radius=0.1, periodic=[True, False, False],
                       bounds=[[0, 1], [0, 1], [0, 1]], kinematic_types=[3])
    meta = scene.meta
    assert (meta.name, meta.n_particles, meta.dim, meta.n_types) == ("water", 7, 3, 2)
    assert meta.interaction == "unknown" and meta.graph == "radius" and meta.box is None
    assert scene.margin == 0.1 and scene.periodic == (True, False, False)
    assert scene.kinematic_types == (3,)


def test_there_is_no_simulator_and_no_pair_force_law():
    scene = ImportedScene(name="x", n_particles=2)
    rng = np.random.default_rng(0)
    state = State(np.zeros((2, 2)), np.zeros((2, 2)), np.ones(2))
    for call in (lambda: scene.simulate(rng, np.arange(3.0)), lambda: scene.draw_state(rng),
                 lambda: scene.simulate_from(state, np.arange(3.0))):
        with pytest.raises(NoSimulatorError, match="no simulator"):
            call()
    with pytest.raises(NotImplementedError, match="unknown"):
        scene.pair_force_magnitude(np.zeros((2, 2)), np.ones(2), np.array([0]), np.array([1]))
    assert ImportedScene.has_simulator is False


def test_energy_is_the_kinetic_energy_per_frame():
    rng = np.random.default_rng(1)
    x, v, m = rng.normal(size=(5, 4, 2)), rng.normal(size=(5, 4, 2)), rng.uniform(1, 2, 4)
    expected = [0.5 * sum(m[i] * v[t, i] @ v[t, i] for i in range(4)) for t in range(5)]
    np.testing.assert_allclose(ImportedScene(n_particles=4).energy(x, v, m), expected)
    # independent of the positions: no potential is known
    np.testing.assert_array_equal(ImportedScene(n_particles=4).energy(2 * x, v, m),
                                  ImportedScene(n_particles=4).energy(x, v, m))


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"graph": "grid"}, "graph"), ({"target": "jerk"}, "target"), ({"n_particles": 0}, ">= 1"),
    ({"graph": "radius"}, "connectivity_radius")])
def test_bad_fields_are_refused(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ImportedScene(**kwargs)


def test_the_pair_force_head_is_a_candidate_for_imported_data():
    check_scene(ImportedScene(n_particles=3).meta, 3, "model=newton")  # accepted
    with pytest.raises(ValueError, match="acceleration target"):
        check_scene(ImportedScene(n_particles=3, target="velocity").meta, 3, "model=newton")


def test_periodic_dimensions_become_the_metas_period():
    """The box length of each periodic dimension from the source's bounds (any origin), 0 for
    the others; no periodic dimension: no period (as every built-in scene)."""
    scene = ImportedScene(dim=2, periodic=[True, False], bounds=[[-1.0, 3.0], [0.0, 5.0]])
    assert scene.meta.period == (4.0, 0.0) and scene.meta.periodic
    assert ImportedScene(dim=2, periodic=[False, False], bounds=[[0, 1], [0, 1]]).meta.period \
        is None
    assert all(make_scene(name).meta.period is None for name in SCENES if name != "imported")
    with pytest.raises(ValueError, match="one flag and one \\(low, high\\) bound per dimension"):
        ImportedScene(dim=2, periodic=[True, True], bounds=[[0.0, 1.0]])
