"""bgn.laws.stage: model.law=auto's formula stage inside python -m bgn.train."""

from __future__ import annotations

import json

import numpy as np
import pytest
from omegaconf import OmegaConf

from bgn.training.run import train
from tests.conftest import compose_config
from tests.laws.conftest import ANY_FORMULA, CHEAP, law_auto_overrides


def test_law_auto_tests_the_law_that_validates_better(tmp_path, shared_data_dir, monkeypatch):
    """model.law=auto: after the fit, the law read back as a formula and fine-tuned (the
    formula stage; a cheap search that always chooses a formula, whatever the tiny run's
    law), the better of the two on validation rollouts tested, and bgn.evaluate given the
    run directory scores that one."""
    import bgn.laws.stage as stage
    from bgn.laws.stage import law_stage
    from bgn.training.checkpoints import resolve_run

    monkeypatch.setattr(stage, "DEFAULTS", ANY_FORMULA)

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


def test_law_auto_chooses_the_law_without_a_test(tmp_path, shared_data_dir, monkeypatch):
    """model.law=auto with test=false: the formula stage still runs (it chooses on
    validation), the run records its choice and bgn.evaluate finds the chosen law; nothing
    is tested."""
    import bgn.laws.stage as stage
    from bgn.laws.stage import law_stage
    from bgn.training.checkpoints import resolve_run

    monkeypatch.setattr(stage, "DEFAULTS", ANY_FORMULA)

    run = tmp_path / "newton"
    train(compose_config("train", [*law_auto_overrides(run, shared_data_dir), "test=false"]),
          law_stage=law_stage)
    stage = json.loads((run / "laws" / "formula.json").read_text())
    record = json.loads((run / "metrics.json").read_text())
    assert record["law"]["choice"] == stage["choice"] in ("network", "formula")
    assert not any(k.startswith("test/") for k in record["metrics"])  # no test read
    ckpt, _, _ = resolve_run(str(run))
    assert (ckpt == run / "laws" / "formula.ckpt") == (stage["choice"] == "formula")


def test_a_stage_where_no_formula_fits_keeps_the_network_law_and_reports_the_front(
        tmp_path, monkeypatch):
    """The formula stage on learned laws no tree fits, two pairs of types (one pair's
    members would be tuned on the frames: ``finetune_formula``'s frames check, tested in
    test_finetune.py): report.md says so in one sentence per pair and shows the fronts;
    nothing is fine-tuned, no formula checkpoint or config is written, and the record keeps
    the network law."""
    from dataclasses import replace

    import bgn.laws.stage as stage
    import bgn.training.module as module
    from bgn.laws.compare import LawReport, read_pair

    d = np.exp(np.random.default_rng(0).normal(0, 0.4, 20_000))
    pair = read_pair((0, 0), d, lambda r: np.exp(-r) * (1 + 0.3 * np.sin(9 * np.log(r))), CHEAP)
    report = LawReport("synthetic", "fake", "inertial", "physical", 1.0, 0.0, 1.0,
                       [pair, replace(pair, types=(0, 1))])
    monkeypatch.setattr(module, "load_model", lambda checkpoint: None)
    monkeypatch.setattr(stage, "read_law", lambda model, split, options: report)
    record = stage.formula_stage(tmp_path / "best.ckpt", None, None, None, tmp_path / "laws",
                                 finetune=True, options=CHEAP)
    assert record["choice"] == "network" and record["outcome"] == "no formula fits"
    assert sorted(p.name for p in (tmp_path / "laws").iterdir()) == [
        "law.csv", "law.json", "law.png", "report.md"]
    text = (tmp_path / "laws" / "report.md").read_text()
    assert text.count("**No formula fits**") == 2  # the read-back's sentence, per pair
    assert "No formula fits the learned law within the tolerance 0.02" in text  # the tuning's
    assert "| complexity | error | held out | formula | tree | chosen |" in text
    law = json.loads((tmp_path / "laws" / "law.json").read_text())
    assert law["outcome"] == "no formula fits" and not law["pairs"][0]["chosen"]
    assert len(law["pairs"][0]["front"]) == len(pair.search.front)
