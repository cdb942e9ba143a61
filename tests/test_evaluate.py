"""Evaluation of the inverse model beside its references, on small real datasets with an
untrained BGN: every metric is there, the prior-only sampler adds no information, and the
force-law estimator reads the masses off the frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bgn.evaluate import evaluate_model, mass_figure
from bgn.train import build
from tests.conftest import SMALL, compose_config

TINY_BGN = ["model.hidden=8", "model.decoder_hidden=8", "model.flow_hidden=8",
            "model.mass_context=pairs"]


@pytest.mark.parametrize("scene", ["spring", "gravity_r2", "collisions"])
def test_inverse_evaluation_with_references(scene: str, tmp_path: Path,
                                            shared_data_dir: Path) -> None:
    cfg = compose_config("train", [f"dataset={scene}", *SMALL[scene], *TINY_BGN,
                                   f"paths.data_dir={shared_data_dir}", "figures=false",
                                   "val_rollout_steps=0"])
    datamodule, module = build(cfg)
    metrics, arrays = evaluate_model(module.eval(), datamodule.datasets["test"], max_frames=4,
                                     mass_frames=6, mass_samples=16, batch_size=3)
    for key in ("coverage50", "coverage_max_dev", "sbc_p", "tarp_atc", "info_gain",
                "sim_mass_rel_err", "prior/coverage90", "physical/relmass_r2_estimate"):
        assert np.isfinite(metrics[key]), key
    assert metrics["prior/info_gain"] == 0.0
    if scene == "collisions":  # the contact head's per-simulation impact solve beside the flow's
        assert np.isfinite(metrics["sim_mass_rel_err_flow"])
    if scene != "collisions":  # O(dt^2) finite differences of the adaptive integrator's frames
        assert metrics["physical/mass_rel_err"] < 0.01
        assert metrics["physical/identified"] == 1.0
    assert mass_figure(arrays, tmp_path / "mass.png").stat().st_size > 0
