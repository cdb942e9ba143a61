"""The job's budget (bgn.training.budget, docs/design.md#budgets): a deadline that caps the
whole job, SIGTERM recorded inside deferred sections and acted on at the next check, a run
bounded by steps that gives the same model under load, a run the cap cuts that says so."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lightning.pytorch.utilities.exceptions import SIGTERMException

from bgn.coerce import ConfigError
from bgn.training import budget
from bgn.training.budget import Deadline, OutOfTime, check, deferred, received
from bgn.training.run import summary, train
from bgn.training.signals import resume_command
from tests.conftest import NETWORK_LAW, SMALL, compose_config

TINY = ["model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16", "figures=false",
        "val_rollout_steps=0", "callbacks.progress_bar=null", "dataset.batch_size=16",
        "+trainer.enable_progress_bar=false", "+trainer.num_sanity_val_steps=0",
        "trainer.enable_model_summary=false", "~logger", "callbacks.lr_monitor=null"]


@pytest.fixture(autouse=True)
def fresh_signals():
    """Each test starts with no SIGTERM recorded and leaves none behind (and the process's
    SIGTERM handler as it found it)."""
    before = signal.getsignal(signal.SIGTERM)
    budget.reset_signals()
    yield
    budget.reset_signals()
    signal.signal(signal.SIGTERM, before)


def tiny_cfg(tmp_path: Path, data_dir: Path, *overrides: str, run: str = "run"):
    return compose_config("train", [
        "dataset=spring", *SMALL["spring"], f"paths.data_dir={data_dir}",
        f"paths.output_dir={tmp_path / run}", *TINY, NETWORK_LAW, *overrides])


# ----------------------------------------------------------------------------- Deadline
@settings(max_examples=50, deadline=None)
@given(st.floats(0.0, 1e6), st.floats(0.0, 1e6), st.floats(0.0, 1e3))
def test_a_deadline_is_never_later_than_what_it_is_combined_with(a, b, reserve):
    d = Deadline.after(a)
    sooner = d.sooner(b)
    assert sooner.end is not None and sooner.end <= d.end
    assert d.sooner(None) == d
    assert d.less(reserve).end == pytest.approx(d.end - reserve)
    left = d.left()
    assert left is not None and 0.0 <= left <= a + 1e-6
    assert not d.passed() or a < 1.0


def test_no_cap_never_passes_and_a_past_one_has_nothing_left():
    assert Deadline.after(None).left() is None and not Deadline.after(None).passed()
    assert Deadline.after(None).less(5.0) == Deadline.after(None)
    assert Deadline.after(None).sooner(3.0).left() == pytest.approx(3.0, abs=0.5)
    past = Deadline(time.monotonic() - 1.0)
    assert past.passed() and past.left() == 0.0
    with pytest.raises(OutOfTime, match="the formula stage reached the job's wall-clock cap"):
        check(past, "the formula stage")
    check(Deadline.after(60.0), "a fit")  # nothing to say
    check(None)


# ----------------------------------------------------------------------------- SIGTERM
def test_sigterm_inside_a_deferred_section_is_recorded_and_raised_at_the_next_check():
    budget.watch_signals()
    with deferred():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # the handler runs in the main thread at the next bytecode
        assert received() == "SIGTERM"  # recorded, not raised: no step is cut in half
        with pytest.raises(SIGTERMException):
            check(None, "a fit")


def test_sigterm_outside_a_deferred_section_raises_at_once():
    budget.watch_signals()
    with pytest.raises(SIGTERMException):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1.0)  # never reached in full
    assert received() == "SIGTERM"


def test_the_resume_command_names_the_run_and_its_own_overrides():
    command = resume_command(Path("/runs/a b"), ["dataset=gravity_r2", "seed=3",
                                                 "ckpt_path=/x.ckpt", "+trainer.max_steps=9"])
    assert command == ("python -m bgn.train dataset=gravity_r2 seed=3 +trainer.max_steps=9 "
                       "ckpt_path=last hydra.run.dir='/runs/a b'")


# ----------------------------------------------------------------------------- train
def test_a_step_budget_gives_the_same_model_under_load(tmp_path, shared_data_dir):
    """The same command and seed, once alone and once while another thread keeps the CPU
    busy: bounded by steps, the runs train the same steps and reach the same metrics."""
    common = ["trainer.max_steps=12", "trainer.max_epochs=1000", "seed=5"]
    alone = train(tiny_cfg(tmp_path, shared_data_dir, *common, run="alone"))
    stop = threading.Event()

    def burn() -> None:  # numpy releases the GIL: real load on the cores, not a lock
        a = np.random.default_rng(0).normal(size=(300, 300))
        while not stop.is_set():
            a = np.tanh(a @ a.T / 300)

    burners = [threading.Thread(target=burn, daemon=True) for _ in range(2)]
    for t in burners:
        t.start()
    try:
        loaded = train(tiny_cfg(tmp_path, shared_data_dir, *common, run="loaded"))
    finally:
        stop.set()
    for run in ("alone", "loaded"):
        record = json.loads((tmp_path / run / "metrics.json").read_text())
        assert record["budget"] == {"max_steps": 12, "steps": 12, "cut_by": None, "cut": [],
                                    "max_time_s": record["budget"]["max_time_s"]}
    keys = [k for k in alone if k.startswith(("val/", "test/"))]
    assert keys and {k: alone[k] for k in keys} == {k: loaded[k] for k in keys}


def test_train_honours_the_deadline_it_is_given_and_says_it_cut_the_run(
        tmp_path, shared_data_dir, caplog):
    """A deadline shorter than the step budget needs: the fit stops at it (less the test's
    reserve), the run is validated, tested and recorded, and a warning and metrics.json say
    the cap cut it."""
    cfg = tiny_cfg(tmp_path, shared_data_dir, "trainer.max_steps=100000",
                   "trainer.max_epochs=100000", "callbacks.early_stopping=null")
    began = time.monotonic()
    with caplog.at_level("WARNING", logger="bgn.train"):
        metrics = train(cfg, deadline=Deadline.after(12.0))
    took = time.monotonic() - began
    assert took < 12.0 + 20.0  # the cap, plus the last step's validation and the test
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["budget"]["cut_by"] == "max_time"
    assert "training" in record["budget"]["cut"]
    assert 0 < record["budget"]["steps"] < 100000
    assert "cut this run short" in caplog.text
    # usable: validated and checkpointed; tested where the test's reserve sufficed, else
    # the record says the cap cut the test too (its figures: python -m bgn.evaluate <run>)
    assert (tmp_path / "run" / "checkpoints" / "best.ckpt").is_file()
    assert ("test/nmse" in metrics) != ("test" in record["budget"]["cut"])


def test_a_cap_spent_before_training_is_refused_in_one_line(tmp_path, shared_data_dir):
    cfg = tiny_cfg(tmp_path, shared_data_dir, "trainer.max_steps=5")
    with pytest.raises(ConfigError, match="spent before training began"):
        train(cfg, deadline=Deadline(time.monotonic() - 1.0))
    assert not (tmp_path / "run" / "metrics.json").exists()


def test_a_step_budget_that_trains_nothing_is_refused(tmp_path, shared_data_dir):
    with pytest.raises(ConfigError, match="trainer.max_steps=0"):
        train(tiny_cfg(tmp_path, shared_data_dir, "trainer.max_steps=0"))


def test_a_step_budget_below_one_validation_is_warned_of(tmp_path, shared_data_dir, caplog):
    # batches of 2 frames: an epoch is far more than 3 steps
    cfg = tiny_cfg(tmp_path, shared_data_dir, "trainer.max_steps=3", "dataset.batch_size=2",
                   "test=false")
    with caplog.at_level("WARNING", logger="bgn.train"):
        train(cfg)
    assert "trainer.max_steps=3 ends the run before its first validation" in caplog.text


def test_the_closing_summary_names_the_model_the_figures_the_run_and_the_next_command(
        tmp_path, shared_data_dir, caplog):
    with caplog.at_level("INFO", logger="bgn.train"):
        train(tiny_cfg(tmp_path, shared_data_dir, "trainer.max_steps=4"))
    run = tmp_path / "run"
    text = caplog.text
    assert "trained BGN" in text and "4 steps of 4" in text
    assert "test rollouts, position error" in text and "no learning after" in text
    assert "one-step test NMSE" in text
    assert f"next: python -m bgn.evaluate {run}" in text
    record = json.loads((run / "metrics.json").read_text())  # complete, as before
    assert {"test/nmse", "test/rollout_error@10", "wall_time_s"} <= set(record["metrics"])


def test_the_summary_says_when_the_cap_cut_the_run_and_nothing_was_tested(tmp_path):
    record = {"metrics": {"wall_time_s": 75.0}, "model": "bgn", "variant": {"label": "BGN"},
              "budget": {"max_steps": 900, "steps": 120, "cut_by": "max_time",
                         "cut": ["training", "test"]}}
    text = summary(record, tmp_path)
    assert "120 steps of 900 in 1 min 15 s" in text and "CUT SHORT" in text
    assert "not tested" in text and f"python -m bgn.evaluate {tmp_path}" in text
    # model.law=auto: where the cap stopped the formula stage's validation rollouts, nothing
    # was compared, and the summary does not say that the network law validates better
    record["law"] = {"choice": "network", "validation": {}, "report": "r.md",
                     "budget": {"cut_by": "max_time", "cut": ["the validation rollouts"]}}
    text = summary(record, tmp_path)
    assert "law: the network law kept: the formula was not compared (trainer.max_time) " \
        "(report: r.md)" in text and "validates better" not in text
    record["law"].update(choice="formula", validation={"network": {}, "formula": {}},
                         budget={"cut_by": None, "cut": []})
    assert "law: the formula law validates better and is the run's model (report: r.md)" \
        in summary(record, tmp_path)


# ----------------------------------------------------------------------------- formula stage
def test_the_formula_stage_is_bounded_by_work_and_capped_by_the_job_deadline(monkeypatch,
                                                                             tmp_path):
    """model.law=auto's stage gets the job's deadline (no share of max_time): its fit ends on
    its evaluation count, the same on any machine, unless the deadline comes first."""
    import bgn.laws.stage as laws

    seen = {}
    monkeypatch.setattr(laws, "formula_stage", lambda *a, **options: (
        seen.update(options) or {"choice": "network", "report": "report.md"}))
    datamodule = type("DM", (), {"datasets": {"train": None, "val": None}})()
    deadline = Deadline.after(100.0)
    laws.law_stage(None, tmp_path / "best.ckpt", datamodule, tmp_path, world_size=1,
                   deadline=deadline)
    # the job's deadline and the stage's default options, no share of the clock
    assert seen["deadline"] is deadline and "max_seconds" not in seen
    assert set(seen) <= {"deadline", "options"}


@pytest.mark.parametrize("validation, said", [
    ({}, "the network law kept: the formula was not compared (trainer.max_time)"),
    ({"network": {"mean": 2.0}, "formula": {"mean": 1.0}},
     "the formula law validates better and is the run's model")])
def test_the_formula_stage_says_what_it_compared(monkeypatch, tmp_path, caplog, validation,
                                                 said):
    """Its log line: the law that validates better, or, where the job's cap stopped the
    validation rollouts (nothing compared), the network law kept without a comparison."""
    import bgn.laws.stage as laws

    choice = "formula" if validation else "network"
    monkeypatch.setattr(laws, "formula_stage", lambda *a, **options: {
        "choice": choice, "validation": validation, "report": "report.md"})
    datamodule = type("DM", (), {"datasets": {"train": None, "val": None}})()
    with caplog.at_level("INFO", logger="bgn.train"):
        laws.law_stage(None, tmp_path / "best.ckpt", datamodule, tmp_path, world_size=1)
    assert f"model.law=auto: {said} (report: report.md)" in caplog.text
    assert ("validates better" in caplog.text) == bool(validation)


def test_a_tuning_past_the_deadline_stops_between_evaluations(monkeypatch):
    from types import SimpleNamespace

    import torch

    import bgn.laws.finetune as laws
    from bgn.model.formula_law import FormulaLaw

    law = FormulaLaw(json.dumps([{"types": [0, 0], "terms": [
        {"kind": "const", "power": 0, "a": 1.0, "c": None}]}]))
    head = SimpleNamespace(force_law=law)
    calls = []

    def slow_bowl(model, head, batch):
        calls.append(1)
        time.sleep(0.05)
        return torch.tensor((float(head.force_law.amplitude[0]) - 1.2) ** 2)

    monkeypatch.setattr(laws, "law_objective", slow_bowl)
    loss, n = laws.tune_constants(None, head, [(1.0, None)], 10_000, Deadline.after(0.5))
    assert 0 < n == len(calls) < 40  # stopped by the deadline, not by its 10 000 evaluations
    with pytest.raises(laws._Budget):  # no time for even one evaluation
        laws.tune_constants(None, head, [(1.0, None)], 10, Deadline(time.monotonic() - 1))


def test_a_job_trains_on_the_threads_it_is_given_and_refuses_none(tmp_path, shared_data_dir):
    import torch

    before = torch.get_num_threads()
    try:
        train(tiny_cfg(tmp_path, shared_data_dir, "trainer.max_steps=2", "test=false",
                       "threads=1"))
        assert torch.get_num_threads() == 1
        with pytest.raises(ConfigError, match="threads=0"):
            train(tiny_cfg(tmp_path, shared_data_dir, "threads=0", run="none"))
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("value", ["abc", "00:00:-1:00", "00:00:00:00"])
def test_a_cap_lightning_cannot_read_is_refused_in_one_line(tmp_path, shared_data_dir, value):
    with pytest.raises(ConfigError, match="trainer.max_time"):
        train(tiny_cfg(tmp_path, shared_data_dir, f"trainer.max_time='{value}'"))
