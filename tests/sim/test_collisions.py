"""Property tests of the event-driven hard-disc simulator (bgn.sim.collisions)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.distance import pdist

from bgn.sim.collisions import CollisionScene, EventLog, ParticleType, integrate
from bgn.sim.scene import Trajectory

SEED = 7
TOL = 1e-9


@pytest.fixture(scope="module")
def default_run() -> tuple[CollisionScene, Trajectory, EventLog]:
    """The default scene (200 discs) over 1000 frames at fps 50 (20 time units)."""
    scene = CollisionScene()
    traj, log = scene.simulate_events(np.random.default_rng(SEED), np.arange(1000) / 50)
    return scene, traj, log


@pytest.fixture(scope="module")
def fine_run() -> tuple[CollisionScene, Trajectory, EventLog]:
    """The default scene at a fine frame interval (fps 1000, 3 time units)."""
    scene = CollisionScene()
    traj, log = scene.simulate_events(np.random.default_rng(SEED + 1), np.arange(3000) / 1000)
    return scene, traj, log


def _momentum(traj: Trajectory) -> np.ndarray:
    return np.einsum("n,tnd->td", traj.masses, traj.velocities)


def _pair_sigma(radii: np.ndarray) -> np.ndarray:
    n = radii.size
    iu = np.triu_indices(n, 1)
    return (radii[:, None] + radii[None, :])[iu]


def _check_geometry(traj: Trajectory, box: float) -> None:
    sig = _pair_sigma(traj.radii)
    for x in traj.positions:
        assert (pdist(x) - sig).min() >= -TOL
    r = traj.radii[None, :, None]
    assert (traj.positions - r).min() >= -TOL
    assert (box - r - traj.positions).min() >= -TOL


# --- the default run: conservation, geometry, contacts -------------------------------------


def test_output_format(default_run):
    scene, traj, _ = default_run
    n = scene.n_particles
    assert traj.positions.shape == traj.velocities.shape == (1000, n, 2)
    assert traj.positions.dtype == traj.velocities.dtype == np.float64
    assert traj.masses.shape == traj.radii.shape == traj.types.shape == (n,)
    assert traj.types.dtype == np.int64
    assert traj.accelerations is None
    c = traj.contacts
    assert c.dtype == np.int64 and c.ndim == 2 and c.shape[1] == 3 and len(c) > 100
    assert np.all(c[:, 1] < c[:, 2])
    assert c[:, 0].min() >= 0 and c[:, 0].max() <= 998
    assert len(np.unique(c, axis=0)) == len(c)  # one row per pair and interval
    assert np.isfinite(traj.positions).all() and np.isfinite(traj.velocities).all()
    # Bimodal masses: each particle close to its type's mode.
    modes = np.array([t.mass_mode for t in scene.types])[traj.types]
    assert np.all(np.abs(np.log(traj.masses / modes)) < 0.1 * 6)
    assert np.array_equal(np.bincount(traj.types), [100, 100])
    assert np.array_equal(traj.radii, np.array([0.1, 0.2])[traj.types])


def test_energy_conserved(default_run):
    scene, traj, log = default_run
    e = scene.energy(traj.positions, traj.velocities, traj.masses)
    assert e.shape == (1000,)
    assert np.abs(e / e[0] - 1).max() < 1e-9
    assert (log.j >= 0).sum() > 1000  # many collisions really happened


def test_no_overlap_and_inside_box(default_run):
    scene, traj, _ = default_run
    _check_geometry(traj, scene.box)


def test_momentum_conserved_between_wall_hits(fine_run):
    _, traj, log = fine_run
    p = _momentum(traj)
    scale = np.einsum("n,tnd->", traj.masses, np.abs(traj.velocities)) / len(p)
    wall_frames = np.searchsorted(traj.times, log.times[log.j < 0], side="left") - 1
    disc_frames = np.searchsorted(traj.times, log.times[log.j >= 0], side="left") - 1
    clean = np.ones(len(p) - 1, dtype=bool)
    clean[wall_frames[wall_frames >= 0]] = False
    busy = np.zeros_like(clean)
    busy[disc_frames[disc_frames >= 0]] = True
    assert (clean & busy).sum() > 300  # many intervals with disc-disc events and no wall hit
    dp = np.abs(p[1:] - p[:-1]).max(axis=1)
    assert dp[clean].max() < 1e-12 * scale
    assert dp[~clean].max() > 1e-6 * scale  # walls do change it: the check has teeth


def test_events_replay_to_frames(default_run):
    """Replaying the logged events from each frame reproduces the next frame.

    Independent physics in the test: every logged impact happens at contact distance
    between approaching discs, every wall hit at the wall, and the contacts are exactly the
    logged impacts per interval.
    """
    scene, traj, log = default_run
    x_all, v_all, m, r, box = traj.positions, traj.velocities, traj.masses, traj.radii, scene.box
    bounds = np.searchsorted(log.times, traj.times, side="right")
    expected = set()
    for f in range(len(traj.times) - 1):
        x, v, now = x_all[f].copy(), v_all[f].copy(), traj.times[f]
        for e in range(bounds[f], bounds[f + 1]):
            te, i, j = log.times[e], log.i[e], log.j[e]
            x += v * (te - now)
            now = te
            if j >= 0:
                d = x[j] - x[i]
                dist = np.linalg.norm(d)
                assert abs(dist - r[i] - r[j]) < TOL
                nrm = d / dist
                vn = (v[j] - v[i]) @ nrm
                assert vn <= TOL
                v[i] += 2 * m[j] / (m[i] + m[j]) * vn * nrm
                v[j] -= 2 * m[i] / (m[i] + m[j]) * vn * nrm
                expected.add((f, i, j))
            else:
                a = -1 - j
                assert min(abs(x[i, a] - r[i]), abs(x[i, a] - (box - r[i]))) < TOL
                v[i, a] = -v[i, a]
        x += v * (traj.times[f + 1] - now)
        np.testing.assert_allclose(x, x_all[f + 1], rtol=0, atol=TOL)
        np.testing.assert_allclose(v, v_all[f + 1], rtol=0, atol=TOL)
    assert expected == {tuple(c) for c in traj.contacts.tolist()}


def test_contacts_are_real_from_frames_only(fine_run):
    """From the frames alone: each recorded pair touches within its frame interval.

    With a short frame interval a pair's other events rarely fall in the same interval, so
    the ballistic motion forward from frame f or backward from frame f+1 brings the two discs
    to contact distance (within TOL) inside the interval. The rare exceptions must be pairs
    with other events both before and after their impact in that interval (a light disc
    rattling between heavy ones); the replay test covers those.
    """
    scene, traj, log = fine_run
    dt = traj.times[1] - traj.times[0]
    c = traj.contacts
    assert len(c) > 300
    f, i, j = c.T
    sig = traj.radii[i] + traj.radii[j]

    def min_dist(frame: np.ndarray, sign: float) -> np.ndarray:
        dx = traj.positions[frame, j] - traj.positions[frame, i]
        dv = traj.velocities[frame, j] - traj.velocities[frame, i]
        # minimise |dx + dv s| over s in [0, dt] (forward) or [-dt, 0] (backward)
        s = np.clip(-np.einsum("kd,kd->k", dx, dv) / np.einsum("kd,kd->k", dv, dv),
                    *sorted((0.0, sign * dt)))
        return np.linalg.norm(dx + dv * s[:, None], axis=1)

    touches = (min_dist(f, 1.0) <= sig + TOL) | (min_dist(f + 1, -1.0) <= sig + TOL)
    assert touches.mean() > 0.99
    for ff, ii, jj in c[~touches].tolist():
        inside = (log.times > traj.times[ff]) & (log.times <= traj.times[ff + 1])
        involved = np.isin(log.i, [ii, jj]) | np.isin(log.j, [ii, jj])
        assert (inside & involved).sum() >= 3
    _check_geometry(traj, scene.box)


# --- frame-rate invariance and reproducibility ---------------------------------------------


def test_fps_invariance(default_run):
    scene, traj50, _ = default_run
    traj10 = scene.simulate(np.random.default_rng(SEED), np.arange(200) / 10)
    assert np.array_equal(traj10.times, traj50.times[::5])
    assert np.array_equal(traj10.positions, traj50.positions[::5])
    assert np.array_equal(traj10.velocities, traj50.velocities[::5])
    assert np.array_equal(traj10.masses, traj50.masses)
    assert np.array_equal(traj10.types, traj50.types)
    # Contacts of the coarse interval g are those of the fine intervals 5g .. 5g+4.
    fine = {(f // 5, i, j) for f, i, j in traj50.contacts.tolist() if f // 5 < 199}
    assert fine == {tuple(c) for c in traj10.contacts.tolist()}


def test_same_seed_same_trajectory():
    scene = CollisionScene(n_particles=40)
    times = np.arange(100) / 20
    a = scene.simulate(np.random.default_rng(3), times)
    b = scene.simulate(np.random.default_rng(3), times)
    c = scene.simulate(np.random.default_rng(4), times)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.contacts, b.contacts)
    assert not np.array_equal(a.positions, c.positions)


# --- analytic cases ------------------------------------------------------------------------


@pytest.mark.parametrize(("m1", "m2", "v1_after", "v2_after"),
                         [(1.0, 1.0, -1.0, 1.0), (1.0, 3.0, -2.0, 0.0)])
def test_head_on(m1, m2, v1_after, v2_after):
    # Gap 3, closing speed 2: impact at t = 1.5, which is a frame time (shown in that frame,
    # contact in the interval (1.0, 1.5], frame 2).
    x = np.array([[3.0, 5.0], [7.0, 5.0]])
    v = np.array([[1.0, 0.0], [-1.0, 0.0]])
    times = np.arange(7) * 0.5
    pos, vel, contacts, _ = integrate(x, v, np.array([m1, m2]), np.array([0.5, 0.5]), 10.0,
                                      times)
    assert np.array_equal(contacts, [[2, 0, 1]])
    np.testing.assert_allclose(vel[3:, :, 0], [[v1_after, v2_after]] * 4, atol=1e-14)
    np.testing.assert_allclose(vel[:3, :, 0], [[1.0, -1.0]] * 3, atol=0)
    np.testing.assert_allclose(vel[:, :, 1], 0.0, atol=0)
    np.testing.assert_allclose(pos[-1, :, 0], [4.5 + 1.5 * v1_after, 5.5 + 1.5 * v2_after],
                               atol=1e-14)


def test_head_on_1d():
    x = np.array([[2.0], [6.0]])
    v = np.array([[2.0], [0.0]])
    pos, vel, contacts, _ = integrate(x, v, np.array([2.0, 2.0]), np.array([0.5, 0.5]), 20.0,
                                      np.arange(5) * 1.0)
    # impact at t = 1.5 (gap 3, speed 2): the moving disc stops, the other takes its speed
    np.testing.assert_allclose(vel[-1, :, 0], [0.0, 2.0], atol=1e-14)
    np.testing.assert_allclose(pos[-1, :, 0], [5.0, 6.0 + 2.0 * 2.5], atol=1e-13)
    assert np.array_equal(contacts, [[1, 0, 1]])


def test_oblique_equal_masses():
    # Equal masses, one at rest, off-centre hit: the outgoing velocities are perpendicular.
    x = np.array([[2.0, 5.0], [5.0, 5.3]])
    v = np.array([[1.0, 0.0], [0.0, 0.0]])
    m = np.array([0.7, 0.7])
    pos, vel, contacts, _ = integrate(x, v, m, np.array([0.25, 0.25]), 10.0,
                                      np.linspace(0, 3.5, 8))
    assert len(contacts) == 1
    va, vb = vel[-1]
    assert abs(va @ vb) < 1e-14
    np.testing.assert_allclose(va + vb, [1.0, 0.0], atol=1e-14)
    np.testing.assert_allclose(va @ va + vb @ vb, 1.0, atol=1e-14)
    # the impulse is along the line of centres at impact (offset 0.3, contact distance 0.5)
    np.testing.assert_allclose(vb / np.linalg.norm(vb), [0.8, 0.6], atol=1e-12)


def test_wall_bounce():
    # r = 0.5, box 10: the wall contact is x = 9.5, reached at t = 1.5 (a frame time).
    x = np.array([[5.0, 5.0]])
    v = np.array([[3.0, 0.25]])
    pos, vel, contacts, log = integrate(x, v, np.array([1.0]), np.array([0.5]), 10.0,
                                        np.arange(5) * 0.5, return_events=True)
    assert len(contacts) == 0
    assert log.times.tolist() == [1.5] and log.j.tolist() == [-1]
    np.testing.assert_array_equal(vel[:3, 0], [[3.0, 0.25]] * 3)
    np.testing.assert_array_equal(vel[3:, 0], [[-3.0, 0.25]] * 2)
    np.testing.assert_allclose(pos[:, 0, 0], [5.0, 6.5, 8.0, 9.5, 8.0], atol=1e-14)
    np.testing.assert_allclose(pos[:, 0, 1], 5.0 + 0.25 * np.arange(5) * 0.5, atol=1e-14)


def test_momentum_conserved_without_walls():
    # A 3x3 cluster in the middle of a large box: many impacts, no disc reaches a wall.
    rng = np.random.default_rng(0)
    g = np.arange(3) * 0.6
    x = 50.0 + np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    v = rng.normal(size=(9, 2))
    v -= v.mean(axis=0)
    m = rng.uniform(0.5, 2.0, size=9)
    times = np.arange(500) / 50
    pos, vel, contacts, log = integrate(x, v, m, np.full(9, 0.25), 100.0, times,
                                        return_events=True)
    assert (log.j < 0).sum() == 0
    assert len(contacts) >= 5
    p = np.einsum("n,tnd->td", m, vel)
    np.testing.assert_allclose(p, np.broadcast_to(p[0], p.shape), rtol=0, atol=1e-13)
    e = 0.5 * np.einsum("n,tnd,tnd->t", m, vel, vel)
    assert np.abs(e / e[0] - 1).max() < 1e-12


# --- configuration -------------------------------------------------------------------------


def test_three_types_3d_by_config():
    types = [
        {"radius": 0.5, "mass_mode": 1.0, "mass_log_std": 0.1, "fraction": 0.5},
        {"radius": 0.3, "mass_mode": 0.01, "mass_log_std": 0.2, "fraction": 1 / 3},
        (0.4, 0.2, 0.0, 1 / 6),
    ]
    scene = CollisionScene(n_particles=6, dim=3, box=4.0, types=types, velocity_std=1.0)
    assert all(isinstance(t, ParticleType) for t in scene.types)
    assert scene.meta.dim == 3 and scene.meta.n_types == 3 and scene.meta.n_particles == 6
    assert scene.meta.interaction == "contact" and scene.meta.target == "velocity"
    assert scene.meta.graph == "radius" and scene.meta.box == 4.0
    assert scene.type_counts().tolist() == [3, 2, 1]
    traj = scene.simulate(np.random.default_rng(SEED), np.arange(1000) / 50)
    assert traj.positions.shape == (1000, 6, 3)
    assert np.array_equal(np.bincount(traj.types), [3, 2, 1])
    assert np.all(traj.masses[traj.types == 2] == 0.2)
    assert len(traj.contacts) > 10
    e = scene.energy(traj.positions, traj.velocities, traj.masses)
    assert np.abs(e / e[0] - 1).max() < 1e-9
    _check_geometry(traj, scene.box)


def test_type_counts_remainder_to_last():
    types = [{"radius": 0.1, "mass_mode": 1.0, "fraction": 0.3}] * 2 + \
            [{"radius": 0.1, "mass_mode": 1.0, "fraction": 0.4}]
    assert CollisionScene(n_particles=11, types=types).type_counts().tolist() == [3, 3, 5]


@pytest.mark.parametrize("kwargs", [
    {"n_particles": 0},
    {"dim": 0},
    {"box": -1.0},
    {"velocity_std": 0.0},
    {"types": []},
    {"types": [{"radius": -0.1, "mass_mode": 1.0}]},
    {"types": [{"radius": 0.1, "mass_mode": 0.0}]},
    {"types": [{"radius": 0.1, "mass_mode": 1.0, "mass_log_std": -1.0}]},
    {"types": [{"radius": 0.1, "mass_mode": 1.0, "fraction": 0.6},
               {"radius": 0.2, "mass_mode": 1.0, "fraction": 0.6}]},
    {"types": [{"radius": 0.1, "mass_mode": 1.0, "colour": "red"}]},
    {"types": [{"radius": 6.0, "mass_mode": 1.0}]},
    {"n_particles": 2000, "types": [{"radius": 0.15, "mass_mode": 1.0}]},  # 141 % covered
])
def test_bad_config_raises(kwargs):
    with pytest.raises(ValueError):
        CollisionScene(**kwargs)


def test_energy_formula():
    scene = CollisionScene(n_particles=2)
    v = np.array([[[1.0, 2.0], [0.0, -3.0]]])
    e = scene.energy(np.zeros_like(v), v, np.array([2.0, 4.0]))
    np.testing.assert_allclose(e, [0.5 * 2 * 5 + 0.5 * 4 * 9])


def test_hydra_style_config():
    omegaconf = pytest.importorskip("omegaconf")
    cfg = omegaconf.OmegaConf.create({"n_particles": 9, "dim": 3, "box": 5, "types": [
        {"radius": 0.3, "mass_mode": 1, "mass_log_std": 0.1, "fraction": 0.5},
        {"radius": 0.2, "mass_mode": 0.01, "mass_log_std": 0.1, "fraction": 0.5}]})
    scene = CollisionScene(**cfg)
    assert scene.types[1] == ParticleType(0.2, 0.01, 0.1, 0.5)
    assert isinstance(scene.box, float) and scene.type_counts().tolist() == [4, 5]
    traj = scene.simulate(np.random.default_rng(0), np.arange(50) / 10)
    assert traj.positions.shape == (50, 9, 3)


def test_integrate_rejects_bad_start():
    times = np.arange(3) * 0.1
    with pytest.raises(ValueError, match="overlap"):
        integrate(np.array([[1.0, 1.0], [1.3, 1.0]]), np.zeros((2, 2)), np.ones(2),
                  np.full(2, 0.2), 10.0, times)
    with pytest.raises(ValueError, match="inside the box"):
        integrate(np.array([[0.1, 1.0]]), np.zeros((1, 2)), np.ones(1), np.full(1, 0.2), 10.0,
                  times)
    with pytest.raises(ValueError, match="increasing"):
        integrate(np.array([[1.0, 1.0]]), np.zeros((1, 2)), np.ones(1), np.full(1, 0.2), 10.0,
                  times[::-1])


def test_large_n_path_matches_table(monkeypatch):
    """Beyond _SIG2_TABLE_MAX contact distances are computed per row: same bits."""
    import bgn.sim.collisions as col

    scene = CollisionScene(n_particles=60, box=5.0)
    times = np.arange(100) / 50
    a = scene.simulate(np.random.default_rng(5), times)
    monkeypatch.setattr(col, "_SIG2_TABLE_MAX", 10)
    monkeypatch.setattr(col, "_PREDICT_CHUNK", 7)
    b = scene.simulate(np.random.default_rng(5), times)
    assert np.array_equal(a.positions, b.positions)
    assert np.array_equal(a.contacts, b.contacts) and len(a.contacts) > 0
