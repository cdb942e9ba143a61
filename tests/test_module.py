"""LightningModule pieces: the NaN guard and figures."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.figure import Figure

from bgn import figures
from bgn.graph import collate
from bgn.rollout import rollout
from bgn.training.run import build
from tests.conftest import SMALL, compose_config


@pytest.fixture
def built(tmp_path, shared_data_dir):
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"],
                                   f"paths.data_dir={shared_data_dir}",
                                   f"paths.output_dir={tmp_path}", "model.hidden=16"])
    return build(cfg)


def test_non_finite_loss_is_one_clear_error(built, monkeypatch):
    datamodule, module = built
    batch = collate([datamodule.datasets["train"][i] for i in range(4)])
    real = module.model.loss_terms

    def poisoned(g, out):
        terms = real(g, out)
        terms["dynamics"] = terms["dynamics"] * float("nan")
        return terms

    monkeypatch.setattr(module.model, "loss_terms", poisoned)
    with pytest.raises(FloatingPointError, match="train loss became nan.*dynamics"):
        module.training_step(batch, 0)


def test_figures_are_drawn(built):
    rng = np.random.default_rng(0)
    assert isinstance(figures.predicted_vs_true(rng.normal(size=(50, 2)),
                                                rng.normal(size=(50, 2)), "acceleration"), Figure)
    assert isinstance(figures.mass_density(np.exp(rng.normal(size=40)),
                                           np.exp(rng.normal(size=400))), Figure)
    datamodule, module = built
    result = rollout(module.model, datamodule.datasets["val"], sim=0, n_steps=5)
    assert isinstance(figures.rollout(result), Figure)


def test_mass_density_draws_equal_laws_alike():
    """True masses and their samples share one kernel width: the same bimodal values, once and
    repeated 32 times (as the samples are), give the same curve; Scott's rule per series would
    draw the single copy about 2x flatter."""
    rng = np.random.default_rng(0)
    log_m = np.concatenate([rng.normal(-3.0, 0.04, 300), rng.normal(-0.4, 0.04, 300)])
    fig = figures.mass_density(10**log_m, np.tile(10**log_m, 32))
    true_line, sampled_line = fig.axes[0].get_lines()[:2]
    np.testing.assert_allclose(true_line.get_ydata(), sampled_line.get_ydata(), rtol=0.02,
                               atol=0.01 * sampled_line.get_ydata().max())


def test_a_checkpoint_written_before_a_default_changed_keeps_its_old_value():
    from bgn.training.module import with_changed_defaults
    assert with_changed_defaults({"name": "bgn"})["mass_context"] == "node"
    assert with_changed_defaults({"name": "bgn", "mass_context": "pairs"})["mass_context"] == \
        "pairs"
    assert "mass_context" not in with_changed_defaults({"name": "gns"})


def test_soft_contacts_without_radii_measure_their_distances_before_the_sanity_check(tmp_path):
    """Discs whose file records no radii (a GNS-layout file): the soft-contact head's contact
    distances are measured when the fit starts, so Lightning's sanity-check validation, which
    runs before the first training step, already has them; the checkpoint keeps them."""
    import torch

    from bgn.data import from_arrays
    from bgn.training.run import train
    from tests.training.test_calibrate import DT, bouncing_discs

    x = bouncing_discs(0.3, sims=5, frames=150)
    from_arrays(x, DT, box=1.0, name="bare", data_dir=tmp_path / "data",
                splits={"train": [0, 1, 2], "val": [3], "test": [4]})
    cfg = compose_config("train", [
        "dataset=imported", "dataset.name=bare", f"paths.data_dir={tmp_path / 'data'}",
        f"paths.output_dir={tmp_path / 'out'}", "model.dynamics=soft_contact",
        "model.contact_calibration=none", "trainer.max_steps=2", "+trainer.num_sanity_val_steps=1",
        "rollout_steps=3", "val_rollout_steps=4", "val_rollout_sims=1", "dataset.batch_size=4",
        "test=false"])
    metrics = train(cfg)
    assert np.isfinite(metrics["train/loss"])
    state = torch.load(tmp_path / "out" / "checkpoints" / "last.ckpt", weights_only=True)
    wall = state["state_dict"]["model.force_head.wall_reach"]  # they bounce on the floor
    assert abs(float(wall.min()) - 0.03) < 0.003                # the discs' radius, 0.03
    assert not bool(state["state_dict"]["model.force_head.radii_given"])
