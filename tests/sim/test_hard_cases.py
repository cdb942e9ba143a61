"""Hard cases of the simulators from given initial states (``simulate_from``): simultaneous,
grazing and frame-time contacts, many impacts within one frame, gravity close encounters, and
the symmetries (offset, scale) that must give the same motion up to the transformation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from bgn.sim import State, make_scene
from bgn.sim.transform import offset, scaled

ROUND_OFF = 1e-12


def _momentum(traj) -> np.ndarray:
    return np.einsum("n,tnd->td", traj.masses, traj.velocities)


def _energy_drift(scene, traj) -> float:
    e = scene.energy(traj.positions, traj.velocities, traj.masses)
    return float(np.abs(e / e[0] - 1).max())


def _min_gap(traj) -> float:
    """Smallest surface gap over frames and pairs, relative to the mean radius."""
    n = traj.radii.size
    i, j = np.triu_indices(n, 1)
    sig = traj.radii[i] + traj.radii[j]
    return float(min((pdist(x) - sig).min() for x in traj.positions) / traj.radii.mean())


def _inside(traj, box: float) -> bool:
    r = traj.radii[None, :, None]
    return bool((traj.positions - r).min() >= -ROUND_OFF * box
                and (box - r - traj.positions).min() >= -ROUND_OFF * box)


def _discs(box: float = 10.0):
    return make_scene("collisions", n_particles=3, box=box)


# --- collisions -----------------------------------------------------------------------------


def test_three_discs_meeting_at_once_conserve_energy_and_momentum():
    """Three discs of different masses, 120 degrees apart, all three pairs touch at t = 1."""
    r, speed, box = 0.5, 1.0, 10.0
    angles = np.array([0.0, 2.0, 4.0]) * np.pi / 3
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    # all pairs touch when the discs are 2r apart, i.e. 2r / sqrt(3) from the centre
    d0 = 2 * r / np.sqrt(3) + speed * 1.0
    state = State(box / 2 + d0 * u, -speed * u, [1.0, 2.0, 3.0], [r, r, r], [0, 0, 0])
    scene = _discs(box)
    traj, log = scene.simulate_events_from(state, np.arange(21) / 10)
    assert np.isfinite(traj.positions).all() and np.isfinite(traj.velocities).all()
    disc_events = log.j >= 0
    assert disc_events.sum() >= 3 and (log.j < 0).sum() == 0  # no wall within 2 time units
    np.testing.assert_allclose(log.times[disc_events][:3], 1.0, rtol=0, atol=1e-12)
    assert _energy_drift(scene, traj) < ROUND_OFF
    p = _momentum(traj)
    assert np.abs(p - p[0]).max() < ROUND_OFF * np.abs(traj.masses[:, None]
                                                       * traj.velocities[0]).sum()
    assert _min_gap(traj) > -1e-9
    # they leave: the discs do not stay in contact
    assert np.abs(traj.velocities[-1] - traj.velocities[0]).max() > 0.1
    assert pdist(traj.positions[-1]).min() > 2 * r + 0.5


def test_contact_exactly_at_a_frame_time():
    """Two discs touch at t = 1.0 exactly (fps 10, frame 10): frame 10 already shows the
    bounce, the contact belongs to the interval (0.9, 1.0], and nothing overlaps."""
    state = State([[2.0, 5.0], [5.0, 5.0]], [[1.0, 0.0], [-1.0, 0.0]], [1.0, 1.0],
                  [0.5, 0.5], [0, 0])
    scene = _discs()
    traj = scene.simulate_from(state, np.arange(21) / 10)
    np.testing.assert_array_equal(traj.velocities[9], state.velocities)
    np.testing.assert_allclose(traj.velocities[10], -state.velocities, rtol=0, atol=1e-15)
    gap = np.linalg.norm(traj.positions[10, 0] - traj.positions[10, 1]) - 1.0
    assert abs(gap) < ROUND_OFF
    assert traj.contacts.tolist() == [[9, 0, 1]]
    assert _min_gap(traj) > -1e-12 and _energy_drift(scene, traj) < ROUND_OFF


def test_contact_at_a_wall_at_a_frame_time():
    """At t = 1.0 exactly, disc 0 hits the wall while disc 1 hits disc 0: the disc squeezed
    against the wall never leaves the box nor overlaps, energy is kept to round-off."""
    state = State([[1.5, 5.0], [3.5, 5.0]], [[-1.0, 0.0], [-2.0, 0.0]], [1.0, 3.0],
                  [0.5, 0.5], [0, 1])
    scene = _discs()
    traj, log = scene.simulate_events_from(state, np.arange(31) / 10)
    np.testing.assert_allclose(log.times[:2], 1.0, rtol=0, atol=1e-12)
    assert set(log.j[:2].tolist()) == {1, -1}  # a disc-disc and a wall (axis 0) event
    assert _inside(traj, scene.box) and _min_gap(traj) > -1e-9
    assert _energy_drift(scene, traj) < ROUND_OFF
    assert (traj.velocities[-1, :, 0] > 0).all()  # both end up moving away from the wall


@pytest.mark.parametrize("factor, touches", [(1 - 1e-9, True), (1.0, None), (1 + 1e-9, False)])
def test_grazing_contact(factor, touches):
    """Impact parameter just inside, at, and just outside contact: finite, no overlap, energy
    and momentum kept; a miss leaves the velocities untouched, bit for bit."""
    r = 0.3
    b = 2 * r * factor
    state = State([[2.0, 5.0], [8.0, 5.0 + b]], [[1.0, 0.0], [-1.0, 0.0]], [1.0, 0.5],
                  [r, r], [0, 0])
    scene = _discs()
    traj = scene.simulate_from(state, np.arange(51) / 10)
    assert np.isfinite(traj.positions).all()
    assert _min_gap(traj) > -1e-9
    assert _energy_drift(scene, traj) < ROUND_OFF
    p = _momentum(traj)
    assert np.abs(p - p[0]).max() < ROUND_OFF
    if touches is False:
        np.testing.assert_array_equal(traj.velocities[-1], state.velocities)
    if touches is True:
        assert len(traj.contacts) == 1
        # a graze turns the velocities by a tiny angle only
        assert 0 < np.abs(traj.velocities[-1] - state.velocities).max() < 1e-3


def test_disc_bouncing_many_times_within_one_frame():
    """A light fast disc trapped between a wall and a heavy disc bounces dozens of times per
    frame at fps 10: every impact is resolved, no overlap, energy to round-off."""
    state = State([[0.3, 5.0], [1.0, 5.0]], [[-50.0, 0.0], [0.0, 0.0]], [1e-3, 1.0],
                  [0.1, 0.5], [0, 1])
    scene = _discs()
    times = np.arange(11) / 10
    traj, log = scene.simulate_events_from(state, times)
    frame = np.searchsorted(times, log.times, side="left") - 1
    first = (frame == 0) & ((log.i == 0) | (log.j == 0))
    assert first.sum() >= 10  # the light disc's impacts within the first frame
    assert ((frame == 0) & (log.j == 1)).sum() >= 5  # of which disc-disc impacts
    assert _inside(traj, scene.box) and _min_gap(traj) > -1e-9
    assert _energy_drift(scene, traj) < 1e-11
    assert traj.velocities[-1, 1, 0] > 0  # the heavy disc is pushed away


def _scaled_twin(scene, rng, times, factor, atol):
    """Simulate a drawn state and its copy with every length times ``factor``; check the twin
    is the same motion scaled (bit for bit for powers of two, else to ``atol``) and return it
    (its scene as ``.scene``)."""
    state = scene.draw_state(rng)
    base = scene.simulate_from(state, times)
    scene2, state2 = scaled(scene, state, factor)
    twin = scene2.simulate_from(state2, times)
    if np.log2(factor).is_integer():
        np.testing.assert_array_equal(twin.positions / factor, base.positions)
    else:
        np.testing.assert_allclose(twin.positions / factor, base.positions, rtol=0, atol=atol)
    twin.scene = scene2
    return twin


@pytest.mark.parametrize("factor", [2.0 ** -10, 2.0 ** 10, 1e-3, 1e3])
def test_scaled_discs_move_the_same(factor):
    """Lengths times ``factor`` (box, radii, positions, velocities): the same motion scaled;
    bit for bit for powers of two, to round-off (grown by the gas's chaos) otherwise."""
    scene = make_scene("collisions", n_particles=50, box=5.0)
    twin = _scaled_twin(scene, np.random.default_rng(3), np.arange(51) / 50, factor, 1e-9)
    assert _min_gap(twin) > -1e-9


# --- n-body ---------------------------------------------------------------------------------


@pytest.mark.parametrize("softening", [1e-3, 1e-2])
def test_gravity_close_encounter_keeps_energy(softening):
    """A pair 0.05 apart approaching at speed 10 passes within 1e-4 (|a| up to ~1e6 at
    softening 1e-3): energy stays within the integrator's tolerance, momentum to round-off."""
    scene = make_scene("gravity_r2", n_particles=2, softening=softening)
    state = State([[-0.025, 0.0], [0.025, 0.0]], [[5.0, 0.02], [-5.0, -0.02]], [1.0, 1.0])
    fine = scene.simulate_from(state, np.linspace(0.0, 0.02, 2001))
    dist = np.linalg.norm(fine.positions[:, 0] - fine.positions[:, 1], axis=-1)
    assert dist.min() < 2e-4
    traj = scene.simulate_from(state, np.arange(101) / 50)
    assert np.isfinite(traj.positions).all()
    assert _energy_drift(scene, traj) < 1e-8
    p = _momentum(traj)
    assert np.abs(p - p[0]).max() < 1e-12


@pytest.mark.parametrize("name", ["spring", "gravity_r1", "gravity_r2"])
def test_offset_by_1e4_gives_the_same_motion(name):
    """All coordinates + 1e4: the same trajectory, up to the integrator's tolerance at that
    magnitude (relative tolerance 1e-10 of 1e4) grown by the scene's chaos."""
    scene = make_scene(name)
    state = scene.draw_state(np.random.default_rng(0))
    times = np.arange(101) / 50
    base = scene.simulate_from(state, times)
    moved = scene.simulate_from(offset(state, 1e4), times)
    np.testing.assert_allclose(moved.positions - 1e4, base.positions, rtol=0, atol=1e-7)
    np.testing.assert_allclose(moved.velocities, base.velocities, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", ["gravity_r1", "gravity_r2"])
@pytest.mark.parametrize("factor", [2.0 ** -10, 2.0 ** 10, 1e-3, 1e3])
def test_scaled_gravity_moves_the_same(name, factor):
    """Lengths times ``factor`` with softening, masses and tolerance scaled to match: the same
    motion scaled (bit for bit for powers of two)."""
    scene = make_scene(name)
    twin = _scaled_twin(scene, np.random.default_rng(0), np.arange(101) / 50, factor, 1e-11)
    # (relative drifts differ: the log potential shifts by a constant under scaling)
    assert np.isfinite(twin.velocities).all() and _energy_drift(twin.scene, twin) < 1e-8


def test_spring_has_no_scaled_twin():
    scene = make_scene("spring")
    with pytest.raises(ValueError, match="rest length"):
        scaled(scene, scene.draw_state(np.random.default_rng(0)), 2.0)


def test_simulate_is_simulate_from_the_drawn_state():
    for name, params in (("spring", {}), ("collisions", {"n_particles": 20, "box": 4.0})):
        scene = make_scene(name, **params)
        times = np.arange(30) / 10
        a = scene.simulate(np.random.default_rng(5), times)
        b = scene.simulate_from(scene.draw_state(np.random.default_rng(5)), times)
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.velocities, b.velocities)


def test_simulate_from_rejects_a_state_of_the_wrong_size():
    scene = make_scene("spring")
    with pytest.raises(ValueError, match="n_particles"):
        scene.simulate_from(State(np.zeros((3, 2)), np.zeros((3, 2)), np.ones(3)),
                            np.arange(3) / 10)
