"""LightningModule pieces: the NaN guard, rollouts and figures."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure

from bgn import figures
from bgn.graph import collate
from bgn.rollout import position_error, rollout
from bgn.train import build
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


class Oracle(torch.nn.Module):
    """Returns the recorded target of the frame it is asked about (plus an optional blow-up)."""

    def __init__(self, ds, blow_up_at: int | None = None) -> None:
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(1))  # rollout reads the device from here
        self.ds, self.blow_up_at = ds, blow_up_at

    def predict(self, g):
        t = int(g.frame)
        x = self.ds.file.read("positions", (int(g.sim), slice(t - 1, t + 2)))
        target = (x[2] - 2 * x[1] + x[0]) / self.ds.dt**2
        if self.blow_up_at is not None and t - self.ds.history - 1 >= self.blow_up_at:
            target = target * np.inf
        return torch.as_tensor(target)


def test_rollout_of_the_true_targets_reproduces_the_frames(built):
    datamodule, _ = built
    ds = datamodule.datasets["val"]
    result = rollout(Oracle(ds), ds, sim=1, n_steps=20)
    assert result["predicted"].shape == result["true"].shape == (21, 4, 2)
    np.testing.assert_allclose(result["predicted"], result["true"], atol=1e-9)
    assert int(result["first_non_finite"]) == -1
    assert position_error(result, (10, 100)) == pytest.approx({10: 0.0}, abs=1e-9)
    drift = np.abs(result["energy_predicted"] - result["energy_true"]).max()
    assert drift < 1e-6 * np.abs(result["energy_true"]).max()


def test_rollout_reports_the_first_non_finite_step(built):
    datamodule, _ = built
    ds = datamodule.datasets["val"]
    result = rollout(Oracle(ds, blow_up_at=4), ds, sim=0, n_steps=10)
    assert int(result["first_non_finite"]) == 5
    assert len(result["predicted"]) == len(result["true"]) == 5  # stopped before the bad step
    assert np.isfinite(result["predicted"]).all()


def test_model_rollout_runs(built):
    datamodule, module = built
    result = rollout(module.model, datamodule.datasets["val"], sim=0, n_steps=3)
    np.testing.assert_array_equal(result["predicted"][0], result["true"][0])  # true start


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
