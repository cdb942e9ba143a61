"""The columns of the metric tables that ``python -m bgn.evaluate``'s report.md and the
study's report (``bgn.studies.report``) both print, in one place so that the two agree."""

from __future__ import annotations

from typing import Any

INVERSE_COLUMNS = ["coverage50", "coverage90", "coverage_max_dev", "sbc_p", "tarp_atc",
                   "info_gain", "info_gain_over_type", "relmass_r2", "relmass_r2_estimate",
                   "mass_rel_err", "sim_mass_rel_err", "sim_mass_rel_err_flow", "identified",
                   "sim_identified", "welch_p", "wasserstein1", "modes_true", "modes_recovered"]
# the references evaluated beside each inverse model (bgn.eval.evaluate.evaluate_inverse);
# the type-only sampler only where the mass law has one component per type
INVERSE_REFERENCES = {"prior": "prior-only sampler",
                      "type_prior": "type-only sampler (the true type's mass law)",
                      "physical": "physical estimator (force law, no learning)",
                      "learned_law": "law estimator (the model's learned pair law)",
                      "law_posterior": ("law posterior (the model's learned pair law, all "
                                        "frames of a simulation)"),
                      "impact_posterior": ("impact posterior (the model's contact head, all "
                                           "frames of a simulation)")}
# the columns that say what a model is, beside its name in every model table: what its
# training loss reads beyond the frames, what it reads at inference beyond the position window
# (PhysicsModel.describe) and the physics written into it
TRAINED_WITH, GIVEN, PHYSICS = "trained with", "given at inference", "physics written in"
VARIANT_COLUMNS = [TRAINED_WITH, GIVEN, PHYSICS]
NO_LEARNING = "- (no learning)"  # what a reference that learns nothing is trained with


def supervision_text(info: dict[str, Any]) -> str:
    """The ``trained with`` cell of a ``PhysicsModel.describe`` record: each recorded quantity
    the training loss reads beyond the frames, with the loss terms that read it ("masses
    (mass_nll, relmass, law)"); "-" for the frames alone, "not recorded" for an older record
    that lacks it."""
    if "supervision" not in info:
        return "not recorded" if info else ""
    return "; ".join(f"recorded {quantity} ({', '.join(terms)})"
                     for quantity, terms in info["supervision"].items()) or "-"


def inverse_reference_variant(key: str, contact_scene: bool) -> dict[str, str]:
    """What an inverse reference (``INVERSE_REFERENCES``) reads and has written in: the
    physical estimator reads the recorded contacts and the types on contact scenes only; the
    law estimator learns nothing of its own: it reads the masses off the frames through the
    pair law the model learned (trained as the model's row says), per window, or per
    simulation for the law posterior, whose free scale the validation split's masses place;
    the impact posterior reads them off the impacts the model's contact head sees, per
    simulation, each disc's type (its radius shows it) giving its prior."""
    given = {"prior": "-", "type_prior": "types",
             "physical": "recorded contacts, types" if contact_scene else "-",
             "learned_law": "-", "law_posterior": "-", "impact_posterior": "types"}[key]
    physics = {"prior": "the scene's mass law", "type_prior": "each type's mass law",
               "physical": ("momentum exchange at impacts, each type's mass law"
                            if contact_scene else "the scene's force law and mass law"),
               "learned_law": ("the model's learned pair law (least squares per window), its "
                               "free scale placed by the scene's mass law"),
               "law_posterior": ("the model's learned pair law (one least squares per "
                                 "simulation over its frames, a Laplace posterior with the "
                                 "scene's mass law as prior), its scale physical or placed on "
                                 "the validation split's masses"),
               "impact_posterior": ("momentum exchange at the impacts the model's contact head "
                                    "sees (one Gaussian posterior per simulation over its "
                                    "frames), each type's mass law as prior, the impacts' "
                                    "noise set on the validation split's masses")}[key]
    trained = {"learned_law": "the model's pair law", "law_posterior": "the model's pair law",
               "impact_posterior": "the model's contact head"}.get(key, NO_LEARNING)
    return {TRAINED_WITH: trained, GIVEN: given, PHYSICS: physics}

ROLLOUT_COLUMNS = ["pos_err_mean@1", "pos_err_mean@10", "pos_err_mean@50", "pos_err_mean@100",
                   "pos_err_median@100", "pos_err_mean@all", "pos_mse_mean@all",
                   "energy_err@all", "energy_err_truth@all", "momentum_err@all",
                   "speed_w1_type0", "speed_w1_type1", "collision_rate_ratio", "failed_share",
                   "rollout_cap", "rollout_steps", "seconds_per_step"]
