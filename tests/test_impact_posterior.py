"""The per-simulation posterior through impacts (``bgn.eval.impact_posterior``): the linear
Gaussian model against its closed form, the masses of an exact event-driven trajectory, and
the noise chosen by the validation masses' density or by the equations' own scatter."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bgn.eval.evaluate import evaluate_model, report_text
from bgn.eval.impact_posterior import (
    SimulationImpacts,
    choose_noise,
    impact_posterior,
    mixed_with_types,
    posterior_of,
    residual_noise,
)
from bgn.eval.mass_baselines import MassPrior, impact_equations
from bgn.sim import make_scene
from bgn.training.run import build
from tests.conftest import REPORT_RECORD, SMALL, compose_config


def impacts_of(seed: int, frames: int = 300, n: int = 30, noise: float = 0.0,
               ) -> tuple[SimulationImpacts, MassPrior]:
    """One exact collisions trajectory's equations from its recorded contacts, each ratio
    with Gaussian ``noise`` added."""
    scene = make_scene("collisions", n_particles=n)
    traj = scene.simulate(np.random.default_rng(seed), np.arange(frames) * 0.1)
    pairs, ratios = impact_equations(traj.positions[None], 0.1, [traj.contacts])
    ratios = ratios + noise * np.random.default_rng(seed + 100).standard_normal(len(ratios))
    return (SimulationImpacts(seed, pairs, ratios, traj.types, np.log(traj.masses), 1),
            MassPrior.of_scene(scene))


def test_two_discs_and_one_impact_match_the_closed_form() -> None:
    prior = MassPrior(np.ones(2), np.array([0.0, 1.0]), np.array([0.3, 0.3]))
    sim = SimulationImpacts(0, np.array([[0, 1]]), np.array([-0.5]), np.array([0, 1]),
                            np.zeros(2), 1)
    s2, noise = 0.3 ** 2, 0.2
    mean, std = impact_posterior(sim, prior, noise)
    # x0 - x1 = -0.5 observed against a prior difference of -1: each moves by half the gain
    gain = s2 * (-0.5 - (0.0 - 1.0)) / (2 * s2 + noise ** 2)
    np.testing.assert_allclose(mean, [0.0 + gain, 1.0 - gain])
    np.testing.assert_allclose(std, np.sqrt(s2 - s2 ** 2 / (2 * s2 + noise ** 2)) * np.ones(2))


def test_an_exact_trajectory_pins_the_ratios_and_the_types_place_them() -> None:
    sim, prior = impacts_of(1)
    mean, std = impact_posterior(sim, prior, 1e-4)
    seen = np.isin(np.arange(len(sim.types)), sim.pairs)
    assert seen.mean() > 0.8
    z = (mean - sim.true_log) / std
    assert np.all(np.abs(z) < 4)
    # the linked discs share one shift, pinned by their types' laws together: sharper than
    # one type's law (0.1); a disc in no impact keeps its type's law
    assert np.all(std[seen] < 0.05)
    type_mean, type_std = prior.type_law(sim.types)
    np.testing.assert_allclose(mean[~seen], type_mean[~seen])
    np.testing.assert_allclose(std[~seen], type_std[~seen])
    posterior = posterior_of([sim], prior, 1e-4)
    gain = np.mean(posterior.log_pdf(sim.true_log) - prior.type_log_pdf(sim.true_log,
                                                                        sim.types))
    assert gain > 0.5


@pytest.mark.parametrize("noise", [0.0, 0.1])
def test_the_noise_is_the_one_the_validation_masses_make_most_probable(noise: float) -> None:
    test = [impacts_of(seed, noise=noise)[0] for seed in (1, 2)]
    validation, prior = impacts_of(3, noise=noise)
    chosen, share, source = choose_noise(test, [validation], prior)
    assert source == "validation" and 0 <= share < 1
    if noise == 0:
        assert chosen < 0.01
    else:
        assert noise / 3 < chosen < noise * 3
    # without validation masses: the equations' own scatter, no share mixed in
    unknown = [SimulationImpacts(s.sim, s.pairs, s.ratios, s.types,
                                 np.full_like(s.true_log, np.nan), 1) for s in [validation]]
    fallback, share, source = choose_noise(test, unknown, prior)
    assert source == "residuals" and share == 0 and fallback == residual_noise(test)


def test_the_residual_scatter_measures_the_noise_of_redundant_equations() -> None:
    sims = [impacts_of(seed, frames=600, noise=0.05)[0] for seed in (4, 5)]
    assert residual_noise(sims) == pytest.approx(0.05, rel=0.3)


def test_the_types_law_mixed_in_bounds_the_cost_of_a_false_impact() -> None:
    sim, prior = impacts_of(1)
    wrong = SimulationImpacts(0, sim.pairs, sim.ratios.copy(), sim.types, sim.true_log, 1)
    wrong.ratios[0] += 2.0          # one impact read a factor e^2 off
    sharp = posterior_of([wrong], prior, 1e-4)
    mixed = mixed_with_types(sharp, [wrong], prior, 0.01)
    # the mixture's density is never below its share of the type's law
    floor = np.log(0.01) + prior.type_log_pdf(wrong.true_log, wrong.types)
    assert np.all(mixed.log_pdf(wrong.true_log) >= floor - 1e-9)
    assert np.min(sharp.log_pdf(wrong.true_log)) < np.min(floor)
    # the share's weights sum to one per disc
    np.testing.assert_allclose(np.exp(mixed.log_weights).sum(1), 1.0)


def test_a_model_trained_without_masses_reads_them_through_its_impacts(
        shared_data_dir: Path) -> None:
    """``ablation=unsupervised`` on collisions: no flow; at test the masses come from the
    impacts the model's contact head sees, per simulation, scored against the recorded ones;
    the validation masses are not read even when the split is given (the noise is the
    equations' own scatter), and the report says so."""
    cfg = compose_config("train", ["dataset=collisions", *SMALL["collisions"],
                                   "model.hidden=8", "model.decoder_hidden=8",
                                   f"paths.data_dir={shared_data_dir}", "figures=false",
                                   "val_rollout_steps=0", "ablation=unsupervised"])
    datamodule, module = build(cfg)
    assert not module.model.has_inverse and "masses" not in module.model.trained_with
    metrics, arrays = evaluate_model(module.eval(), datamodule.datasets["test"], max_frames=4,
                                     mass_frames=6, mass_samples=16, batch_size=3,
                                     calibration=datamodule.datasets["val"], law_frames=4)
    assert metrics["impact_posterior/noise_from"] == "residuals"
    assert metrics["impact_posterior/contamination"] == 0.0
    for key in ("sim_mass_rel_err", "info_gain", "info_gain_over_type",
                "physical_sim_mass_rel_err", "physical_relmass_r2_estimate", "coverage50"):
        assert np.isfinite(metrics[f"impact_posterior/{key}"]), key
    assert not any(k.startswith("law_posterior/") for k in metrics)
    assert "coverage50" not in metrics and arrays == {}        # no flow to score
    record = REPORT_RECORD
    report = report_text(record, metrics, [])
    assert "## Inverse model (through the impacts)" in report and "from residuals" in report
