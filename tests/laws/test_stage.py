"""bgn.laws.stage: model.law=auto's formula stage inside python -m bgn.train."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from bgn.training.run import train
from tests.conftest import compose_config
from tests.laws.conftest import law_auto_overrides


def test_law_auto_tests_the_law_that_validates_better(tmp_path, shared_data_dir):
    """model.law=auto: after the fit, the law read back as a formula and fine-tuned (the
    formula stage), the better of the two on validation rollouts tested, and bgn.evaluate
    given the run directory scores that one."""
    from bgn.laws.stage import law_stage
    from bgn.training.checkpoints import resolve_run

    run = tmp_path / "newton"
    cfg = compose_config("train", law_auto_overrides(run, shared_data_dir))
    with pytest.raises(ValueError, match="needs the formula stage"):  # none handed in
        train(cfg)
    train(cfg, law_stage=law_stage)
    record = json.loads((run / "metrics.json").read_text())
    law = record["law"]
    stage = json.loads((run / "laws" / "formula.json").read_text())
    assert law["choice"] == stage["choice"] in ("network", "formula")
    horizon = str(stage["validation"]["network"]["horizon"])  # JSON keys are strings
    scores = {k: (v["failed"], v["errors"][horizon]) for k, v in stage["validation"].items()}
    assert scores[law["choice"]] == min(scores.values())  # chosen on validation alone
    rollouts = [k for k in record["metrics"] if k.startswith("test/rollout_error@")]
    assert (run / "laws" / "report.md").is_file() and rollouts and all(
        np.isfinite(record["metrics"][k]) for k in rollouts)
    ckpt, run_dir, config = resolve_run(str(run))
    if law["choice"] == "formula":
        assert ckpt == run / "laws" / "formula.ckpt"
        assert OmegaConf.load(config).model.law == "formula"
        assert "law a formula" in record["variant"]["label"]  # the tested model says so
    else:
        assert ckpt.parent == run / "checkpoints"


def test_law_auto_chooses_the_law_without_a_test(tmp_path, shared_data_dir):
    """model.law=auto with test=false: the formula stage still runs (it chooses on
    validation), the run records its choice and bgn.evaluate finds the chosen law; nothing
    is tested."""
    from bgn.laws.stage import law_stage
    from bgn.training.checkpoints import resolve_run

    run = tmp_path / "newton"
    train(compose_config("train", [*law_auto_overrides(run, shared_data_dir), "test=false"]),
          law_stage=law_stage)
    stage = json.loads((run / "laws" / "formula.json").read_text())
    record = json.loads((run / "metrics.json").read_text())
    assert record["law"]["choice"] == stage["choice"] in ("network", "formula")
    assert not any(k.startswith("test/") for k in record["metrics"])  # no test read
    ckpt, _, _ = resolve_run(str(run))
    assert (ckpt == run / "laws" / "formula.ckpt") == (stage["choice"] == "formula")
