"""The columns of the metric tables that ``python -m bgn.evaluate``'s report.md and the
study's report (``bgn.studies.report``) both print, in one place so that the two agree."""

INVERSE_COLUMNS = ["coverage50", "coverage90", "coverage_max_dev", "sbc_p", "tarp_atc",
                   "info_gain", "info_gain_over_type", "relmass_r2", "relmass_r2_estimate",
                   "mass_rel_err", "sim_mass_rel_err", "sim_mass_rel_err_flow", "identified",
                   "sim_identified", "welch_p", "wasserstein1", "modes_true", "modes_recovered"]
# the references evaluated beside each inverse model (bgn.eval.evaluate.evaluate_inverse);
# the type-only sampler only where the mass law has one component per type
INVERSE_REFERENCES = {"prior": "prior-only sampler",
                      "type_prior": "type-only sampler (the true type's mass law)",
                      "physical": "physical estimator (force law, no learning)"}
# what each reference reads beyond the position window, and the physics written into it
# (the columns a model's row has from its PhysicsModel.describe)
INVERSE_REFERENCE_VARIANTS = {
    "prior": {"given": "-", "physics written in": "the scene's mass law"},
    "type_prior": {"given": "types", "physics written in": "each type's mass law"},
    "physical": {"given": "collisions: the recorded contacts, types",
                 "physics written in": "the scene's force law (collisions: momentum exchange "
                                       "at impacts) and mass law"}}


ROLLOUT_COLUMNS = ["pos_err_mean@1", "pos_err_mean@10", "pos_err_mean@50", "pos_err_mean@100",
                   "pos_err_median@100", "pos_err_mean@all", "pos_mse_mean@all",
                   "energy_err@all", "energy_err_truth@all", "momentum_err@all",
                   "speed_w1_type0", "speed_w1_type1", "collision_rate_ratio", "failed_share",
                   "rollout_cap", "rollout_steps", "seconds_per_step"]
