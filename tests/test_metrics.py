"""Metrics on synthetic arrays: calibrated, shifted and collapsed mass samples, KDE modes,
R^2, type metrics, rollout metrics and LagrangeBench's rollout metrics on hand-made particle
clouds."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import norm, wasserstein_distance

from bgn.metrics import (
    COVERAGE_LEVELS,
    aggregate_gaussian,
    binary_f1,
    calibration_metrics,
    collisions_per_frame,
    contact_rollout_metrics,
    coverage_curve,
    fit_radius_map,
    information_gain,
    inverse_metrics,
    kde_modes,
    kinetic_energy,
    lagrangebench_metrics,
    minimum_image,
    r2_score,
    recovered_modes,
    relative_mass_error,
    rollout_failures,
    rollout_metrics,
    sbc_ranks,
    sinkhorn_divergence,
    tarp,
    type_metrics,
)


def bimodal_log_masses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Two types, as in collisions: log-masses around log 0.001 and log 0.4."""
    centre = np.where(rng.random(n) < 0.5, np.log(0.001), np.log(0.4))
    return centre + 0.1 * rng.standard_normal(n)


def test_perfect_samples_are_calibrated() -> None:
    rng = np.random.default_rng(0)
    n, s = 400, 64
    centre = np.where(rng.random(n) < 0.5, np.log(0.001), np.log(0.4))
    true = centre + 0.1 * rng.standard_normal(n)
    # each particle's samples from the same distribution its true value came from
    samples = centre + 0.1 * rng.standard_normal((s, n))
    m = inverse_metrics(true, samples)
    assert m["coverage50"] == pytest.approx(0.5, abs=0.08)
    assert m["coverage90"] == pytest.approx(0.9, abs=0.05)
    assert m["wasserstein1"] < 0.1
    assert m["welch_p"] > 0.01
    assert m["modes_true"] == 2 and m["modes_recovered"] == 2


def test_shifted_samples_are_not() -> None:
    rng = np.random.default_rng(1)
    true = bimodal_log_masses(rng, 400)
    samples = true[None, :] + 2.0 + 0.1 * rng.standard_normal((64, 400))
    m = inverse_metrics(true, samples)
    assert m["coverage50"] < 0.05 and m["coverage90"] < 0.05
    assert m["wasserstein1"] == pytest.approx(2.0, abs=0.1)
    assert m["welch_p"] < 1e-6
    assert m["modes_recovered"] == 0


def test_collapsed_samples_lose_a_mode() -> None:
    rng = np.random.default_rng(2)
    true = bimodal_log_masses(rng, 400)
    samples = np.log(0.4) + 0.1 * rng.standard_normal((32, 400))  # every particle "heavy"
    n_true, n_matched = recovered_modes(true, samples)
    assert (n_true, n_matched) == (2, 1)


def test_kde_modes_and_r2() -> None:
    grid = np.linspace(-5, 5, 501)
    values = np.concatenate([np.full(50, -2.0), np.full(50, 2.0)])
    values = values + 0.05 * np.random.default_rng(3).standard_normal(100)
    assert np.allclose(kde_modes(values, grid), [-2, 2], atol=0.1)
    x = np.arange(10.0)
    assert r2_score(x, x) == 1.0 and r2_score(np.full(10, x.mean()), x) == pytest.approx(0.0)
    assert np.isnan(r2_score(x, np.ones(10)))


def test_bad_sample_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="n_samples"):
        inverse_metrics(np.zeros(5), np.zeros((3, 4)))


def test_type_metrics() -> None:
    logits = np.array([[2.0, 0.0], [0.0, 2.0], [1.0, 0.0], [0.0, 1.0]])
    assert type_metrics(logits, np.array([0, 1, 0, 1])) == {"type_accuracy": 1.0,
                                                            "type_auroc": 1.0}
    assert type_metrics(logits, np.array([1, 0, 1, 0]))["type_accuracy"] == 0.0


# ----------------------------------------------------------------------------- rollouts
def free_flight(r: int = 3, steps: int = 12, n: int = 4, dt: float = 0.1, seed: int = 0):
    """(R, steps+2, N, 2) particles in uniform motion, their masses, and a kinetic energy."""
    rng = np.random.default_rng(seed)
    x0, v = rng.normal(size=(r, 1, n, 2)), rng.normal(size=(r, 1, n, 2))
    t = np.arange(steps + 2)[None, :, None, None] * dt
    masses = np.exp(rng.normal(size=(r, n)))

    def kinetic(x, vel, m):
        return 0.5 * np.einsum("n,tnd->t", m, vel**2)

    return x0 + v * t, masses, kinetic, dt


def test_rollout_metrics_of_the_truth_are_zero():
    x, m, energy, dt = free_flight()
    out = rollout_metrics(x, x.copy(), m, dt, energy, np.full(3, -1), momentum=True)
    for key in ("pos_err_mean@1", "pos_err_median@10", "pos_err_mean@all", "pos_mse_mean@all",
                "energy_err@all", "momentum_err@all", "failed_share"):
        assert out[key] == pytest.approx(0.0, abs=1e-12), key
    assert "pos_err_mean@50" not in out and out["rollout_steps"] == 12


def test_a_failed_rollout_counts_at_the_cap_in_the_mean_and_the_mse():
    """One rollout in three fails: the median of the position error does not move (it
    would hide the failure), the mean and the MSE count it at 10 scene scales."""
    x, m, energy, dt = free_flight()
    pred = x.copy()
    pred[:, 2:] += 0.5                          # every particle 0.5 * sqrt(2) off from step 1
    pred[0, 5:] = np.nan                        # rollout 0 fails at step 4 (index 5)
    out = rollout_metrics(pred, x, m, dt, energy, np.array([4, -1, -1]))
    e = 0.5 * np.sqrt(2)
    centre = x[0].mean(axis=(0, 1))
    cap = 10 * np.linalg.norm(x[0] - centre, axis=-1).max()   # rollout 0's scene, 10 scales
    assert out["failed_share"] == pytest.approx(1 / 3)
    assert out["pos_err_mean@1"] == pytest.approx(e)          # three equal errors, none failed
    assert out["pos_err_median@10"] == pytest.approx(e)       # cap, e, e: the median hides it
    assert out["pos_err_mean@10"] == pytest.approx((cap + 2 * e) / 3)
    assert out["pos_err_mean@10"] > 2 * out["pos_err_median@10"]
    assert out["pos_mse_mean@10"] == pytest.approx((cap**2 / 2 + 2 * 0.25) / 3)
    assert out["energy_err@1"] > 0                               # the jump shows in dx/dt
    assert out["energy_err@10"] == pytest.approx(0.0, abs=1e-12)  # uniform motion again


def test_a_particle_far_astray_fails_the_rollout():
    x, m, energy, dt = free_flight()
    pred = x.copy()
    pred[1, 5:, 0] += 1e3                       # finite, but far outside the scene's scale
    assert rollout_failures(pred, x, None, np.full(3, -1)).tolist() == [-1, 4, -1]
    boxed = rollout_failures(pred, x, 10.0, np.full(3, -1))
    assert boxed[1] == 4


def test_binary_f1():
    assert binary_f1(np.array([1, 1, 0, 0]), np.array([1, 0, 1, 0])) == pytest.approx(0.5)
    assert binary_f1(np.ones(3), np.ones(3)) == 1.0
    assert np.isnan(binary_f1(np.zeros(3), np.zeros(3)))


def test_impacts_between_frames_are_counted():
    """Two discs approach head on and bounce back in the second interval; a third passes
    the first at a distance; a fourth pair touches a grazing path without any change."""
    radii = np.full(4, 0.1)
    x = np.zeros((5, 4, 2))
    x[:, 1, 0] = [0.8, 0.55, 0.3, 0.5, 0.7]           # approaches disc 0, bounces back
    x[:, 2] = np.stack([np.linspace(-1, 1, 5), np.full(5, 0.5)], 1)  # passes at 0.5
    x[:, 3] = [5.0, 5.0]
    assert collisions_per_frame(x, radii).tolist() == [0, 1, 0]
    passing = x.copy()
    passing[:, 1, 0] = [0.8, 0.55, 0.3, 0.05, -0.2]   # straight through: touches, no change
    assert collisions_per_frame(passing, radii).tolist() == [0, 0, 0]


def test_contact_rollout_metrics_of_the_truth():
    rng = np.random.default_rng(1)
    true = np.cumsum(rng.normal(scale=0.05, size=(2, 12, 20, 2)), axis=1) + 5.0
    radii, types = np.full((2, 20), 0.1), np.tile(np.arange(20) % 2, (2, 1))
    out = contact_rollout_metrics(true, true, radii, types, 0.1, np.full(2, -1))
    assert out["speed_w1_type0"] == 0 and out["speed_w1_type1"] == 0
    assert out["collision_rate_ratio"] == 1.0
    slower = true.copy()
    slower[:, -1] = slower[:, -2] + 0.5 * (true[:, -1] - true[:, -2])
    assert contact_rollout_metrics(slower, true, radii, types, 0.1,
                                   np.full(2, -1))["speed_w1_type0"] == pytest.approx(0.5)


def test_a_failed_rollout_counts_in_the_contact_metrics():
    """Two rollouts of the truth, one of them failed: its discs count at 10 x the mean speed
    (the W1 of half the speeds moved there), and its impacts after the failure are missing."""
    rng = np.random.default_rng(1)
    true = np.cumsum(rng.normal(scale=0.05, size=(2, 12, 20, 2)), axis=1) + 5.0
    radii, types = np.full((2, 20), 0.3), np.zeros((2, 20), dtype=int)
    whole = contact_rollout_metrics(true, true, radii, types, 0.1, np.full(2, -1))
    out = contact_rollout_metrics(true, true, radii, types, 0.1, np.array([3, -1]))
    speeds = np.linalg.norm(true[:, -1] - true[:, -2], axis=-1) / 0.1
    failed = np.concatenate([np.full(20, 10 * speeds.mean()), speeds[1]])
    assert out["speed_w1_type0"] == pytest.approx(
        wasserstein_distance(failed, speeds.ravel()) / speeds.mean())
    assert out["speed_w1_type0"] > 1
    assert whole["collision_rate_ratio"] == 1.0
    assert out["collision_rate_ratio"] < 1.0


# ----------------------------------------------------------------------------- calibration
def gaussian_posteriors(rng: np.random.Generator, n: int, s: int, width: float,
                        sigma: float = 0.3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Truths from the prior N(0, 1), observations y = truth + N(0, sigma^2) and posterior
    samples N(mu, width^2 * var) about the exact posterior N(mu, var): width 1 is calibrated,
    < 1 overconfident. Returns (truth, samples (s, n), exact log posterior at the truth)."""
    truth = rng.standard_normal(n)
    y = truth + sigma * rng.standard_normal(n)
    var = 1 / (1 + 1 / sigma ** 2)
    mu = var * y / sigma ** 2
    samples = mu + width * np.sqrt(var) * rng.standard_normal((s, n))
    log_post = -0.5 * (truth - mu) ** 2 / (width ** 2 * var) \
        - 0.5 * np.log(2 * np.pi * width ** 2 * var)
    return truth, samples, log_post


def log_normal_pdf(x: np.ndarray) -> np.ndarray:
    return -0.5 * x ** 2 - 0.5 * np.log(2 * np.pi)


def test_a_calibrated_gaussian_passes_every_check() -> None:
    truth, samples, log_post = gaussian_posteriors(np.random.default_rng(0), 2000, 64, 1.0)
    curve = coverage_curve(truth, samples)
    assert np.max(np.abs(curve - COVERAGE_LEVELS)) < 0.04
    m = calibration_metrics(truth, samples, log_post, log_normal_pdf(truth))
    assert m["coverage_max_dev"] < 0.04
    assert m["sbc_p"] > 0.01 and m["tarp_ks_p"] > 0.01
    assert abs(m["tarp_atc"]) < 0.02
    # KL from N(0, 1) to the posterior N(mu, 0.083): about 1.2 nats on average
    assert m["info_gain"] == pytest.approx(0.5 * np.log(1 + 1 / 0.3 ** 2), abs=0.1)


def test_an_overconfident_gaussian_fails() -> None:
    truth, samples, log_post = gaussian_posteriors(np.random.default_rng(1), 2000, 64, 0.4)
    m = calibration_metrics(truth, samples, log_post, log_normal_pdf(truth))
    assert m["coverage_max_dev"] > 0.2
    assert m["sbc_p"] < 1e-6 and m["tarp_ks_p"] < 1e-6
    assert m["tarp_atc"] < -0.02                      # the TARP curve falls below the diagonal
    assert coverage_curve(truth, samples, np.array([0.9]))[0] < 0.6


def test_a_sampler_that_ignores_the_data_gains_nothing() -> None:
    """A sampler that ignores the data: the prior itself is calibrated and gains nothing, a
    wider one (N(0, 4)) loses the KL divergence from the prior to it,
    ln 2 + 1/8 - 1/2 nats, whether its density is given or estimated from its samples (a KDE
    per particle, as for a posterior known by samples only)."""
    rng = np.random.default_rng(2)
    truth = rng.standard_normal(2000)
    log_prior = log_normal_pdf(truth)
    prior, wide = rng.standard_normal((256, 2000)), 2 * rng.standard_normal((256, 2000))
    m = calibration_metrics(truth, prior)
    assert m["coverage_max_dev"] < 0.05 and m["sbc_p"] > 0.01
    assert calibration_metrics(truth, wide)["coverage_max_dev"] > 0.1
    kl = np.log(2) + 1 / 8 - 1 / 2
    exact = calibration_metrics(truth, wide, log_normal_pdf(truth / 2) - np.log(2), log_prior)
    assert exact["info_gain"] == pytest.approx(-kl, abs=0.05)
    for samples, gain in ((prior, 0.0), (wide, -kl)):
        kde = calibration_metrics(truth[:400], samples[:, :400], None, log_prior[:400])
        assert kde["info_gain"] == pytest.approx(gain, abs=0.08)


def test_sbc_ranks_and_groups() -> None:
    truth = np.array([0.0, 10.0, -10.0])
    samples = np.tile(np.array([-1.0, 1.0])[:, None], (1, 3))
    assert sbc_ranks(truth, samples).tolist() == [1, 2, 0]
    # one particle seen in many frames counts once in the tests, every row in the curve
    rng = np.random.default_rng(3)
    truth = np.repeat(rng.standard_normal(300), 10)
    samples = rng.standard_normal((64, 3000))
    grouped = calibration_metrics(truth, samples, groups=np.repeat(np.arange(300), 10))
    assert grouped["sbc_p"] > 0.01 and grouped["tarp_ks_p"] > 0.01


def test_coverage_is_unbiased_with_few_samples() -> None:
    """32 samples of the exact posterior: the central interval between the samples' own
    quantiles holds the truth about (S - 1) / (S + 1) of the time at every level (0.84 at
    0.9); the randomised rank does not shrink it."""
    truth, samples, _ = gaussian_posteriors(np.random.default_rng(7), 20000, 32, 1.0)
    curve = coverage_curve(truth, samples, np.array([0.5, 0.9]))
    assert curve == pytest.approx([0.5, 0.9], abs=0.01)
    lo, hi = np.quantile(samples, [0.05, 0.95], axis=0)
    assert np.mean((truth >= lo) & (truth <= hi)) == pytest.approx(0.9 * 31 / 33, abs=0.01)


def test_information_gain_and_relative_mass_error() -> None:
    assert information_gain(np.array([1.0, 3.0]), np.array([0.0, 0.0])) == 2.0
    assert relative_mass_error(np.log([1.1, 0.9, 1.0]), np.zeros(3)) == pytest.approx(0.1)
    assert tarp(np.zeros(4), np.ones((8, 4)))["ecp"][-1] == 1.0


# ----------------------------------------------------------------------------- post-hoc fixes
@pytest.mark.parametrize("width", [0.4, 1.0, 2.0])
def test_a_fitted_radius_map_restores_coverage(width: float) -> None:
    """Posteriors N(mu, width^2 var) about the exact N(mu, var): the truth in the base space of
    the reported posterior is (truth - mu) / (width sd), N(0, 1/width^2). The map fitted on
    one set of cases is about the scale 1/width, and samples drawn through it are calibrated
    on fresh cases."""
    rng = np.random.default_rng(4)
    sd = np.sqrt(1 / (1 + 1 / 0.3 ** 2))
    truth, samples, _ = gaussian_posteriors(rng, 4000, 64, width)    # the validation split
    z, r = fit_radius_map((truth - samples.mean(0)) / (width * sd))
    middle = (z > 0.3) & (z < 2.0)
    assert r[middle] / z[middle] == pytest.approx(np.full(middle.sum(), 1 / width), rel=0.1)
    truth, samples, _ = gaussian_posteriors(rng, 4000, 64, width)    # the test split
    e = rng.standard_normal(samples.shape)
    base = np.sign(e) * np.interp(np.abs(e), z, r)
    recalibrated = samples.mean(0) + width * sd * base
    assert np.max(np.abs(coverage_curve(truth, recalibrated) - COVERAGE_LEVELS)) < 0.03


def test_a_radius_map_fixes_heavy_tails_that_a_scale_cannot() -> None:
    """Base values from a Student t (3 dof): no single scale makes both the 50 % and the 90 %
    intervals right; the fitted map does, and it is strictly increasing from 0."""
    u = np.random.default_rng(5).standard_t(3, 20000)
    z, r = fit_radius_map(u)
    assert r[0] == 0 and np.all(np.diff(r) > 0)
    for level in (0.5, 0.9):
        radius = np.interp(norm.ppf((1 + level) / 2), z, r)
        assert np.mean(np.abs(u) <= radius) == pytest.approx(level, abs=0.01)
    scale50, scale90 = (np.interp(q, z, r) / q for q in norm.ppf([0.75, 0.95]))
    assert scale90 > 1.2 * scale50                # the tails need a wider map than the centre


def test_aggregating_gaussians_gives_their_product() -> None:
    labels, mean, var = aggregate_gaussian(np.array([0.0, 3.0, 5.0]), np.array([1.0, 2.0, 4.0]),
                                           np.array([7, 7, 2]))
    assert labels.tolist() == [2, 7]
    # N(0, 1) x N(3, 2): precision 1.5, mean (0 + 3/2) / 1.5 = 1
    assert mean.tolist() == pytest.approx([5.0, 1.0]) and var.tolist() == pytest.approx([4, 2 / 3])
    # many noisy frames of one value: the product's mean converges to it at the 1/sqrt(T) rate
    rng = np.random.default_rng(6)
    frames_var = rng.uniform(0.1, 2.0, 400)
    _, pooled, pooled_var = aggregate_gaussian(
        1.5 + np.sqrt(frames_var) * rng.standard_normal(400), frames_var, np.zeros(400))
    assert abs(pooled[0] - 1.5) < 4 * np.sqrt(pooled_var[0]) and pooled_var[0] < 0.01


# ----------------------------------------------------------------------------- LagrangeBench
def test_lagrangebench_metrics_of_the_truth_are_zero():
    x, m, _, dt = free_flight(n=16)
    out = lagrangebench_metrics(x, x.copy(), m, dt, np.full(3, -1), sinkhorn_stride=1)
    for key in ("mse@5", "mse@10", "mse@all", "sinkhorn", "e_kin_mse", "failed_share"):
        assert out[key] == pytest.approx(0.0, abs=1e-12), key
    assert "mse@20" not in out and out["sinkhorn_frames"] == 11 and out["sinkhorn_rollouts"] == 3


@pytest.mark.parametrize("shift", [(0.03, -0.04), (0.5, 0.0)])
def test_a_translated_cloud_gives_its_squared_shift(shift):
    """Every particle moved by c from step 1 on: the MSE per coordinate is |c|^2 / D at every
    horizon, the Sinkhorn divergence |c|^2 (the cost's cross term is separable, so the plan
    is the unshifted one's), the kinetic energy unchanged from step 2 on."""
    x, m, _, dt = free_flight(n=32, seed=1)
    c = np.asarray(shift)
    pred = x.copy()
    pred[:, 2:] += c
    out = lagrangebench_metrics(pred, x, m, dt, np.full(3, -1), sinkhorn_stride=5,
                                sinkhorn_rollouts=1)
    for h in ("@5", "@10", "@all"):
        assert out[f"mse{h}"] == pytest.approx(c @ c / 2, rel=1e-12)
        assert out[f"mse_std{h}"] == pytest.approx(0.0, abs=1e-15)
    assert out["sinkhorn"] == pytest.approx(c @ c, rel=1e-2)  # to ott-jax's tolerance
    # converged far beyond ott-jax's tolerance: |c|^2 exactly
    exact = sinkhorn_divergence(pred[0, 5], x[0, 5], max_iter=20_000, threshold=1e-12)
    assert exact == pytest.approx(c @ c, rel=1e-4)
    assert out["e_kin_mse"] == pytest.approx(0.0, abs=1e-20)


def test_a_permuted_cloud_is_the_same_cloud_to_sinkhorn_but_not_to_the_mse():
    rng = np.random.default_rng(2)
    x, m, _, dt = free_flight(r=2, n=24, seed=2)
    perm = rng.permutation(24)
    pred = x.copy()
    pred[:, 2:] = x[:, 2:, perm]              # the same cloud, particles relabelled
    out = lagrangebench_metrics(pred, x, np.ones_like(m), dt, np.full(2, -1),
                                sinkhorn_stride=1)
    assert out["sinkhorn"] == pytest.approx(0.0, abs=1e-9)
    assert out["mse@5"] > 0.1
    assert out["e_kin_mse"] == pytest.approx(0.0, abs=1e-20)  # unit masses: the same energy
    assert sinkhorn_divergence(x[0, 3], x[0, 3, perm]) == pytest.approx(0.0, abs=1e-12)
    assert sinkhorn_divergence(x[0, 3], x[0, 3] + 0.1) > 0


def test_the_kinetic_energy_mse_of_a_known_velocity_change():
    """The prediction moves every particle at v' instead of v from the start: per frame
    E = sum m |v|^2 (LagrangeBench's, no 1/2), so the MSE is (E' - E)^2; the position MSE
    averaged over steps 1..h is the mean of (k dt |v' - v|)^2 / D."""
    rng = np.random.default_rng(3)
    r, n, steps, dt = 2, 8, 30, 0.05
    m = rng.uniform(0.5, 2.0, (r, n))
    x0, v = rng.normal(size=(r, 1, n, 2)), rng.normal(size=(r, 1, n, 2))
    dv = rng.normal(size=(r, 1, n, 2))
    k = np.arange(-1, steps + 1)[None, :, None, None]     # the frame before the start: -1
    true = x0 + v * k * dt
    pred = true + np.clip(k, 0, None) * dv * dt
    out = lagrangebench_metrics(pred, true, m, dt, np.full(r, -1), sinkhorn_rollouts=1)
    e_true = np.einsum("rn,rn->r", m, (v[:, 0] ** 2).sum(-1))
    e_pred = np.einsum("rn,rn->r", m, ((v + dv)[:, 0] ** 2).sum(-1))
    assert out["e_kin_mse"] == pytest.approx(np.mean((e_pred - e_true) ** 2), rel=1e-9)
    np.testing.assert_allclose(kinetic_energy(true[0], m[0], dt), e_true[0], rtol=1e-9)
    per_step = (np.arange(1, steps + 1)[None, :] * dt) ** 2 \
        * (dv[:, 0] ** 2).sum(-1).mean(-1)[:, None] / 2                       # (R, T)
    for h in (5, 10, 20):
        assert out[f"mse@{h}"] == pytest.approx(per_step[:, :h].mean(), rel=1e-9)
    assert out["mse@all"] == pytest.approx(per_step.mean(), rel=1e-9)
    assert out["sinkhorn_rollouts"] == 1 and "mse@50" not in out


def test_a_failed_rollout_counts_at_the_cap_in_the_lagrangebench_metrics():
    x, m, _, dt = free_flight(n=16)
    pred = x.copy()
    pred[0, 5:] = np.nan                        # rollout 0 fails at step 4 (index 5)
    out = lagrangebench_metrics(pred, x, m, dt, np.array([4, -1, -1]), sinkhorn_stride=1)
    centre = x[0].mean(axis=(0, 1))
    cap = 10 * np.linalg.norm(x[0] - centre, axis=-1).max()
    assert out["failed_share"] == pytest.approx(1 / 3)
    # rollout 0: steps 1-3 exact, 4.. at cap^2 / D; the others exact
    assert out["mse@5"] == pytest.approx(2 / 5 * cap**2 / 2 / 3)
    assert out["mse@all"] == pytest.approx(9 / 12 * cap**2 / 2 / 3)
    assert out["sinkhorn"] == pytest.approx(8 / 11 * cap**2 / 3)   # steps 4..11 of 1..11
    assert np.isfinite(out["e_kin_mse"]) and out["e_kin_mse"] > 0


@pytest.mark.parametrize("seed", range(5))
def test_the_one_minimum_image_serves_arrays_and_tensors_alike(seed):
    """``minimum_image`` is the package's one: numpy and torch give the same differences, a
    dimension marked 0 (the graphs' convention) or inf (the metrics') is left as it is, each
    periodic one lands in [-L/2, L/2], and a tensor's gradient is the identity."""
    import torch

    rng = np.random.default_rng(seed)
    side = rng.uniform(0.5, 3.0)
    d = rng.normal(scale=4.0, size=(40, 3))
    for marked in (0.0, np.inf):
        period = np.array([side, marked, 2 * side])
        out = minimum_image(d, period)
        assert np.all(np.abs(out[:, [0, 2]]) <= np.array([side, 2 * side]) / 2 + 1e-12)
        np.testing.assert_array_equal(out[:, 1], d[:, 1])
        np.testing.assert_allclose(np.round((d - out)[:, [0, 2]] / [side, 2 * side]),
                                   (d - out)[:, [0, 2]] / [side, 2 * side], atol=1e-9)
        t = torch.tensor(d, requires_grad=True)
        shifted = minimum_image(t, torch.tensor(period))
        np.testing.assert_allclose(shifted.detach().numpy(), out, rtol=0, atol=1e-12)
        shifted.sum().backward()
        np.testing.assert_array_equal(t.grad.numpy(), np.ones_like(d))
    assert minimum_image(d, None) is d


def test_periodic_dimensions_take_the_minimum_image():
    d = np.array([[0.9, 0.9], [-0.6, 0.2]])
    np.testing.assert_allclose(minimum_image(d, np.array([1.0, np.inf])),
                               [[-0.1, 0.9], [0.4, 0.2]])
    x, m, _, dt = free_flight(n=16)
    pred = x.copy()
    pred[:, 2:, :, 0] += 3.0                   # a whole period along x: the same state
    out = lagrangebench_metrics(pred, x, m, dt, np.full(3, -1), period=np.array([3.0, np.inf]))
    assert out["mse@all"] == pytest.approx(0.0, abs=1e-20)
    assert out["sinkhorn"] == pytest.approx(0.0, abs=1e-12)
    assert out["e_kin_mse"] == pytest.approx(0.0, abs=1e-20)
