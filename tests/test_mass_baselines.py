"""The inverse references: the scene's mass prior, and the force-law estimator recovering
masses exactly from noise-free frames stepped by the rule its finite differences invert."""

from __future__ import annotations

import numpy as np
import pytest

from bgn.eval.mass_baselines import MassPrior, impact_log_mass, physical_log_mass
from bgn.sim import make_scene


def verlet_frames(scene, rng: np.random.Generator, dt: float, n: int) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """Frames of ``x[t+1] = 2 x[t] - x[t-1] + dt^2 a(x[t])`` (Stormer-Verlet): their second
    differences are the force law's accelerations to round-off. Returns (frames, masses)."""
    state = scene.draw_state(rng)
    x = [state.positions, state.positions + dt * state.velocities]
    for _ in range(n - 2):
        x.append(2 * x[-1] - x[-2] + dt ** 2 * scene.accelerations(x[-1], state.masses))
    return np.asarray(x), state.masses


@pytest.mark.parametrize("name", ["spring", "gravity_r1", "gravity_r2"])
def test_force_law_recovers_masses_from_one_window(name: str) -> None:
    scene = make_scene(name, n_particles=5)
    frames, masses = verlet_frames(scene, np.random.default_rng(0), 0.02, 7)
    est = physical_log_mass(scene, MassPrior.of_scene(scene), frames[None], 0.02)
    np.testing.assert_allclose(est, np.log(masses), atol=1e-9)


def test_impacts_recover_mass_ratios_and_the_prior_fixes_the_scale() -> None:
    scene = make_scene("collisions", n_particles=30)
    traj = scene.simulate(np.random.default_rng(1), np.arange(300) * 0.1)
    prior = MassPrior.of_scene(scene)
    est = physical_log_mass(scene, prior, traj.positions[None], 0.1, [traj.contacts])
    seen = np.isfinite(est)
    assert seen.mean() > 0.8
    err = est[seen] - np.log(traj.masses[seen])
    # ratios exact (one shift per linked group; one group here), the shift within the
    # prior's spread of a type (0.1 in log-mass)
    assert np.ptp(err) < 1e-8
    assert abs(err[0]) < 0.1
    # a gauge of per-disc Gaussians (a model's posteriors) places the group at their
    # precision-weighted agreement: here all 0.05 above the truth
    truth = np.log(traj.masses)
    gauged = impact_log_mass(prior, traj.positions[None], 0.1, [traj.contacts],
                             gauge=(truth + 0.05, np.ones_like(truth)))
    np.testing.assert_allclose(gauged[seen], truth[seen] + 0.05, atol=1e-8)
    # a window without impacts says nothing
    quiet = physical_log_mass(scene, prior, traj.positions[None, :3], 0.1,
                              [np.empty((0, 3), dtype=int)])
    assert np.isnan(quiet).all()


def test_mass_prior_of_each_scene() -> None:
    rng = np.random.default_rng(2)
    spring = MassPrior.of_scene(make_scene("spring"))
    draws = spring.sample((20000,), rng)
    assert draws.mean() == pytest.approx(0.0, abs=0.03)
    assert draws.std() == pytest.approx(1.0, abs=0.03)
    assert spring.log_pdf(np.array([0.0]))[0] == pytest.approx(-0.5 * np.log(2 * np.pi))
    gas = MassPrior.of_scene(make_scene("collisions"))
    draws = gas.sample((20000,), rng)
    assert np.mean(np.abs(draws - np.log(0.001)) < 0.5) == pytest.approx(0.5, abs=0.02)
    assert gas.mean == pytest.approx(0.5 * (np.log(0.001) + np.log(0.4)))


def test_the_type_only_law_tells_what_the_type_does() -> None:
    """The gas's two types draw masses 400x apart, half each: knowing a disc's type tells
    ln 2 nats of its log-mass, and the type-only sampler draws from that type's law."""
    rng = np.random.default_rng(3)
    gas = MassPrior.of_scene(make_scene("collisions"))
    assert gas.typed
    types = rng.integers(0, 2, 20000)
    draws = gas.type_sample(types, (20000,), rng)
    np.testing.assert_allclose([draws[types == k].mean() for k in (0, 1)], gas.means, atol=0.01)
    np.testing.assert_allclose([draws[types == k].std() for k in (0, 1)], gas.stds, rtol=0.03)
    gain = np.mean(gas.type_log_pdf(draws, types) - gas.log_pdf(draws))
    assert gain == pytest.approx(np.log(2), abs=1e-6)
    np.testing.assert_array_equal(gas.type_mean(types), gas.means[types])
    spring = MassPrior.of_scene(make_scene("spring"))   # one component: no per-type law
    assert not spring.typed
    np.testing.assert_array_equal(spring.type_mean(np.zeros(3, int)), np.zeros(3))
    with pytest.raises(ValueError, match="per-type law"):
        spring.type_log_pdf(np.zeros(3), np.zeros(3, int))


def test_impacts_placed_by_the_discs_types() -> None:
    """Given the discs' types, the estimator places each group of discs linked by impacts at
    the precision-weighted agreement of their types' laws (the mixture's most probable shift
    without them): the ratios as before, the scale within the type's spread over the group."""
    scene = make_scene("collisions", n_particles=30)
    traj = scene.simulate(np.random.default_rng(1), np.arange(300) * 0.1)
    prior = MassPrior.of_scene(scene)
    typed = physical_log_mass(scene, prior, traj.positions[None], 0.1, [traj.contacts],
                              traj.types)
    plain = physical_log_mass(scene, prior, traj.positions[None], 0.1, [traj.contacts])
    seen = np.isfinite(typed)
    np.testing.assert_array_equal(seen, np.isfinite(plain))
    mean, std = prior.type_law(traj.types)
    np.testing.assert_allclose(typed, impact_log_mass(prior, traj.positions[None], 0.1,
                                                      [traj.contacts], gauge=(mean, std ** 2)))
    err = typed[seen] - np.log(traj.masses[seen])
    assert np.ptp(err) < 1e-8                       # one linked group: one shift
    # the shift: minus the mean of the group's draws from their types' laws (std 0.1 each)
    expected = -np.mean(np.log(traj.masses[seen]) - mean[seen])
    assert err[0] == pytest.approx(expected, abs=1e-8)
    assert abs(err[0]) < 4 * 0.1 / np.sqrt(seen.sum())


def test_a_scene_without_a_mass_law_takes_the_training_masses_and_estimates_nothing() -> None:
    """Imported data have no mass law and no force law: the prior is the log-normal of the
    training split's masses, and the physical estimator says nothing (NaN) rather than guess."""
    from bgn.sim.imported import ImportedScene

    scene = ImportedScene(n_particles=3, dim=2)
    prior = MassPrior.of_scene(scene, {"mean": np.array([0.7]), "std": np.array([0.2])})
    assert prior.means.tolist() == [0.7] and prior.stds.tolist() == [0.2]
    with pytest.raises(ValueError, match="no mass law"):
        MassPrior.of_scene(scene)
    windows = np.random.default_rng(0).normal(size=(1, 7, 3, 2))
    assert np.isnan(physical_log_mass(scene, prior, windows, 0.01)).all()
