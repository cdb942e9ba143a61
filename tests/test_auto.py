"""model.dynamics=auto (bgn/studies/auto.py): which structures a scene admits, how the budget is
split, how candidates are scored and chosen, and (slow tier) that on a tiny spring scene it picks
the structure the scene was made with."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import time
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from bgn.metrics import ESCAPE_FACTOR, capped_rollout_error, rollout_scores
from bgn.model.bgn import ModelConfig
from bgn.model.newton import build_head
from bgn.sim import make_scene
from bgn.sim.scene import SceneMeta
from bgn.studies.auto import (
    Candidate,
    Result,
    candidates,
    choose,
    compose_candidate,
    split_budget,
    write_report,
)
from bgn.training.validate import ConfigError, validate_train
from tests.conftest import NETWORK_LAW, SMALL, compose_config
from tests.test_train import CLI_ENV, command_line

REFS = ("gns", "cranmer_gn")
# mass_law: each way (coupling: few bodies only)
PAIR_FORCE = ("newton_inertial", "newton_source", "newton_type", "newton_coupling")


def admitted(meta: SceneMeta, history: int = 5, radii: bool = True) -> list[str]:
    return [c.name for c in candidates(meta, history, radii, REFS) if c.admitted]


# ----------------------------------------------------------------------------- candidates
def test_candidates_of_the_built_in_scenes():
    spring = make_scene("spring").meta
    assert admitted(spring) == ["decoder", *PAIR_FORCE, *REFS]
    assert admitted(make_scene("gravity_r2").meta) == admitted(spring)
    collisions = make_scene("collisions").meta
    assert admitted(collisions) == ["decoder", "impulse", *REFS]
    pool = candidates(spring, 5, True, REFS)
    assert [c.name for c in pool if c.eligible and c.admitted] == [
        "decoder", *PAIR_FORCE]                                          # references never win
    impulse = next(c for c in pool if c.name == "impulse")
    assert "not contacts" in impulse.reason
    assert "history=2" in next(c.reason for c in candidates(spring, 2, True, ())
                               if c.name == "newton_source")


def test_imported_scenes_without_radii_or_forces_get_the_decoder():
    gas = SceneMeta("imported", 2, 30, 1, "unknown", "velocity", "radius", box=1.0)
    assert admitted(gas, radii=False) == ["decoder", *REFS]
    discs = SceneMeta("discs", 2, 30, 1, "contact", "velocity", "radius", box=1.0)
    assert admitted(discs, radii=False) == ["decoder", *REFS]
    assert admitted(discs, radii=True) == ["decoder", "impulse", *REFS]
    bodies = SceneMeta("imported", 3, 5, 1, "unknown", "acceleration", "full")
    assert admitted(bodies) == ["decoder", *PAIR_FORCE, *REFS]


def test_an_imported_short_range_gas_on_a_radius_graph_admits_the_pair_force_head():
    """A gas imported with a connectivity radius: forces summed over the radius graph's
    edges, the law learns to vanish at the cut-off (the ASE Morse gas)."""
    gas = SceneMeta("imported", 2, 64, 1, "unknown", "acceleration", "radius",
                    masses_known=False, period=(10.0, 10.0))
    assert admitted(gas, radii=False) == ["decoder", *PAIR_FORCE[:3], *REFS]
    assert "64 particles" in next(c.reason for c in candidates(gas, 5, False, ())
                                  if c.name == "newton_coupling")
    refused = {c.name: c.reason for c in candidates(replace(gas, target="velocity"), 5, False,
                                                    REFS) if not c.admitted}
    assert "velocity target" in refused["newton_inertial"]
    assert "history=2" in next(c.reason for c in candidates(gas, 2, False, ())
                               if c.name == "newton_inertial")


def test_soft_contacts_are_admitted_by_the_free_flight_evidence_alone():
    from bgn.data.contacts import FreeFlight

    grains = SceneMeta("imported", 2, 60, 2, "unknown", "acceleration", "radius", box=1.0)
    free = FreeFlight(7e-10, (0.0, -1e-4), 1e-3, 4000)
    assert "soft_contact" in [c.name for c in candidates(grains, 5, False, REFS, None, None,
                                                         free) if c.admitted]
    reasons = {}
    for label, meta, evidence in (
            ("long range", grains, FreeFlight(0.14, (0.0, 0.0), 0.0, 4000)),
            ("none free", grains, FreeFlight(None, samples=0, reason="no particle flies free")),
            ("not read", grains, None),
            ("velocity", replace(grains, target="velocity"), free)):
        soft = next(c for c in candidates(meta, 5, True, REFS, None, None, evidence)
                    if c.name == "soft_contact")
        assert not soft.admitted
        reasons[label] = soft.reason
    assert "reach beyond contact" in reasons["long range"]
    assert "no particle flies free" in reasons["none free"]
    assert "not read" in reasons["not read"]
    assert "acceleration target" in reasons["velocity"]


@pytest.mark.parametrize("interaction,target,graph,box,history", itertools.product(
    ("pairwise", "contact", "unknown"), ("acceleration", "velocity"), ("full", "radius"),
    (None, 2.0), (2, 3)))
def test_admitted_exactly_where_the_structured_head_builds(interaction, target, graph, box,
                                                           history):
    meta = SceneMeta("s", 2, 4, 1, interaction, target, graph, box=box)
    normalizer = SimpleNamespace(rel_position_scale=torch.tensor(1.0))
    try:
        build_head(meta, normalizer, history, 8, 1, "silu", "inertial", "test")
        builds = True
    except ValueError:
        builds = False
    names = admitted(meta, history, radii=True)
    assert "decoder" in names
    structured = {*PAIR_FORCE, "impulse"} & set(names)
    assert bool(structured) == builds
    assert not (set(PAIR_FORCE) & structured and "impulse" in structured)


# ----------------------------------------------------------------------------- budget
def test_budget_split_in_steps_and_the_winners_rest():
    """Candidates are bounded by optimiser steps (auto.share of trainer.max_steps, else of
    auto.max_steps), never by their own time: trainer.max_time is the job's one deadline."""
    each, winner = split_budget({"max_time": "00:00:08:00", "max_steps": 600,
                                 "max_epochs": 300}, 0.5, 3)
    assert each == {"max_steps": 100, "max_epochs": -1}
    # the winner resumes (Lightning counts from the start): its share plus the rest
    assert winner == {"max_steps": 400, "max_epochs": -1}
    for n, share, total in itertools.product((1, 2, 5, 7), (0.1, 0.5, 0.9), (10, 999)):
        each, winner = split_budget({"max_steps": total}, share, n)
        assert n * each["max_steps"] + winner["max_steps"] - each["max_steps"] == max(
            total, n * each["max_steps"])
    for trainer in ({"max_time": {"hours": 1}, "max_steps": -1}, {"max_epochs": 10}):
        with pytest.raises(ValueError, match="trainer.max_steps"):
            split_budget(trainer, 0.5, 2)


def test_a_share_below_min_steps_is_refused_in_one_line():
    from bgn.studies.auto import check_shares

    check_shares({"max_steps": 100}, 100, 6, 1200)
    with pytest.raises(ConfigError) as err:
        check_shares({"max_steps": 99}, 100, 6, 1200)
    message = str(err.value)
    assert "\n" not in message and "auto.min_steps" in message and "trainer.max_steps" in message


def test_a_candidate_below_min_steps_is_never_compared_and_a_result_survives_a_resume(
        tmp_path):
    """Not trained (fewer than auto.min_steps) or failed: never in the choice, whatever its
    score; result.json gives a resumed run the same result back."""
    from bgn.studies.auto import fallback, stored_result

    decoder = Candidate("decoder", ["model.dynamics=decoder"])
    newton = Candidate("newton_inertial", ["model.dynamics=newton"], pair_force=True)
    short = Result(newton, errors={10: 0.001, 50: 0.01}, steps=40,
                   untrained="not trained (40 steps of auto.min_steps=100 ...)")
    trained = Result(decoder, errors={10: 0.1, 50: 1.0}, steps=100)
    assert not short.compared and trained.compared
    assert choose([short, trained], 50)[0] is trained
    assert short.status().startswith("not trained") and trained.status() == "trained"
    with pytest.raises(ValueError):
        choose([short], 50)
    assert fallback([short]) is short and fallback([Result(newton)]) is None
    (tmp_path / "result.json").write_text(json.dumps(trained.state()))
    again = stored_result(Candidate("decoder", []), tmp_path)
    assert again is not None and again.errors == trained.errors and again.steps == 100
    assert again.candidate.overrides == ["model.dynamics=decoder"]
    assert stored_result(decoder, tmp_path / "none") is None


def test_the_warning_of_candidates_left_out_says_what_became_of_each():
    """A candidate the cap stopped during its validation rollouts trained all its steps: the
    warning says it was not scored, not that it trained fewer than auto.min_steps."""
    from bgn.studies.auto import not_compared

    short = "not trained (40 steps of auto.min_steps=100 before trainer.max_time)"
    unscored = "not scored (trainer.max_time was reached during its validation rollouts)"
    text = not_compared([
        Result(Candidate("decoder", []), untrained=short, steps=40),
        Result(Candidate("gns", [], eligible=False), untrained=unscored, steps=300),
        Result(Candidate("newton_inertial", [], pair_force=True), errors={50: 0.1}, steps=300)])
    assert text == f"decoder {short}; gns {unscored}"
    assert not_compared([Result(Candidate("decoder", []), errors={50: 0.1}, steps=300)]) == ""


def test_a_kept_formula_candidate_is_kept_only_while_its_law_is_the_best_ones(tmp_path,
                                                                             caplog):
    """On a resume a candidate the cap left untrained is trained and may now be the best
    pair-force one: the formula fitted from the former best's law is then not kept (the log
    says so, and the new best's is fitted); while its candidate is the best it is kept."""
    from bgn.studies.auto import best_pair_force, kept_formula

    formula = Result(Candidate("formula_newton_inertial", ["model.law=formula"],
                               pair_force=True), errors={50: 0.05}, steps=300)
    (tmp_path / formula.candidate.name).mkdir()
    (tmp_path / formula.candidate.name / "result.json").write_text(json.dumps(formula.state()))
    decoder = Result(Candidate("decoder", []), errors={50: 0.01}, steps=300)  # no pair law
    inertial = Result(Candidate("newton_inertial", [], pair_force=True), errors={50: 0.2},
                      steps=300)
    # not trained in the first attempt, trained on the resume: now the best pair-force one
    source = Result(Candidate("newton_source", [], pair_force=True), errors={50: 0.1},
                    steps=300)
    kept = kept_formula(tmp_path, [decoder, inertial], 50)
    assert kept is not None and kept.kept and kept.candidate.name == "formula_newton_inertial"
    assert best_pair_force([decoder, inertial, source], 50) is source
    with caplog.at_level("INFO", logger="bgn.train"):
        assert kept_formula(tmp_path, [decoder, inertial, source], 50) is None
    assert "formula_newton_inertial (the run's earlier attempt) not kept" in caplog.text
    assert "now newton_source, whose law is fitted in its place" in caplog.text


def test_a_candidates_training_time_is_its_fits_over_the_runs_attempts(tmp_path,
                                                                      monkeypatch):
    """``train_s``: the fit's own wall time (train()'s wall_time_s, not auto's scoring of
    it), ``train_steps`` the steps it added to the checkpoint it continued; an earlier
    attempt's record of that checkpoint adds its time and steps, so that their ratio is the
    candidate's steps per second (the engines' baselines' rate)."""
    from omegaconf import OmegaConf

    import bgn.training.run as run
    from bgn.studies.auto import train_candidate

    last = tmp_path / "checkpoints" / "last.ckpt"
    last.parent.mkdir()

    def fit(cfg, **kwargs):  # continues the checkpoint to step 250 in 6 s
        torch.save({"state_dict": {}, "global_step": 250}, last)
        return {"wall_time_s": 6.0}

    monkeypatch.setattr(run, "train", fit)
    cfg = OmegaConf.create({"paths": {"output_dir": str(tmp_path)}, "ckpt_path": str(last)})
    cand = Candidate("gns", ["model=gns"], eligible=False)
    earlier = Result(cand, steps=40, train_s=2.0, train_steps=40, wall_s=9.0,
                     untrained="not trained (40 steps of auto.min_steps=100 ...)")
    torch.save({"state_dict": {}, "global_step": 40}, last)
    result = train_candidate(cand, cfg, min_steps=100, earlier=earlier)
    assert (result.steps, result.train_steps, result.train_s) == (250, 250, 8.0)
    assert not result.untrained and math.isnan(result.wall_s)  # the run's loop times it
    # an attempt a signal stopped records nothing: this attempt's steps in its own time
    torch.save({"state_dict": {}, "global_step": 40}, last)
    alone = train_candidate(cand, cfg, min_steps=100)
    assert (alone.steps, alone.train_steps, alone.train_s) == (250, 210, 6.0)
    again = Result.restored(Candidate("gns", []), json.loads(json.dumps(result.state())))
    assert (again.train_s, again.train_steps) == (8.0, 250)


def test_each_fit_gets_an_even_part_of_the_time_left():
    from bgn.studies.auto import WINNER_RESERVE, candidate_deadline
    from bgn.training.budget import NO_DEADLINE, Deadline

    assert candidate_deadline(NO_DEADLINE, 3) is NO_DEADLINE
    job = Deadline.after(100.0)
    for remaining in (1, 2, 7):
        part = candidate_deadline(job, remaining).left()
        assert part == pytest.approx(100 * (1 - WINNER_RESERVE) / remaining, abs=0.5)
        assert candidate_deadline(job, remaining).end <= job.end


# ----------------------------------------------------------------------------- scores
def test_failed_rollouts_count_at_the_cap():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(3, 22, 4, 2))
    predicted = true + 0.01 * rng.normal(size=true.shape)
    scale = np.linalg.norm(true - true.mean(axis=(1, 2))[:, None, None], axis=-1).max((1, 2))
    predicted[1, 2 + 4:] = np.nan                             # fails at step 5
    predicted[2, 2 + 7, 0] += 100 * scale[2]                  # escapes at step 8, comes back
    first_bad = np.array([-1, 5, -1])
    errors, failed, curve = rollout_scores(predicted, true, first_bad, None, (3, 10, 20))
    cap = ESCAPE_FACTOR * scale
    assert failed == pytest.approx(2 / 3)
    step_err = np.linalg.norm(predicted - true, axis=-1).mean(-1)[:, 2:]
    assert errors[3] == pytest.approx(step_err[:, 2].mean())     # none failed yet
    assert errors[10] == pytest.approx((step_err[0, 9] + cap[1] + cap[2]) / 3)
    assert errors[20] == pytest.approx((step_err[0, 19] + cap[1] + cap[2]) / 3)
    assert 20 in errors and 21 not in errors and len(curve) == 20
    clean = true + 0.01
    assert rollout_scores(clean, true, np.full(3, -1), None, (1,))[2].mean() == pytest.approx(
        capped_rollout_error(clean, true, None))


def result(name: str, errors: dict[int, float], eligible: bool = True, error: str = "",
           ) -> Result:
    return Result(Candidate(name, [], eligible=eligible), errors=errors, error=error)


def test_choice_on_given_scores():
    decoder = result("decoder", {10: 0.1, 50: 2.0})
    inertial = result("inertial", {10: 0.01, 50: 0.2})
    reference = result("gns", {10: 0.001, 50: 0.01}, eligible=False)
    crashed = result("source", {}, error="RuntimeError: boom")
    winner, margin = choose([decoder, inertial, reference, crashed], 50)
    assert winner is inertial and margin == pytest.approx(10.0)
    # a failed rollout scores the cap, a non-finite score never wins
    nan = result("nan", {10: float("nan"), 50: float("nan")})
    assert choose([nan, decoder], 50)[0] is decoder
    # ties: the shorter horizon, then the order given (the decoder first)
    a, b = result("a", {10: 0.3, 50: 1.0}), result("b", {10: 0.2, 50: 1.0})
    assert choose([a, b], 50) == (b, 1.0)
    c = result("c", {10: 0.3, 50: 1.0})
    assert choose([a, c], 50)[0] is a and choose([c, a], 50)[0] is c
    alone, margin = choose([decoder, reference], 50)
    assert alone is decoder and math.isnan(margin)
    with pytest.raises(ValueError, match="no candidate"):
        choose([reference, crashed], 50)


# ----------------------------------------------------------------------------- evidence
def test_report_names_the_choice_and_shows_its_evidence(tmp_path):
    rng = np.random.default_rng(0)
    true_log = rng.normal(size=40)
    s = np.geomspace(0.1, 3.0, 20)
    about = {"name": "bgn", "label": "BGN + pair-force head (masses inertial)", "given": [],
             "trained_with": ["masses"], "supervision": {"masses": ["mass_nll", "law"]},
             "physics": "central pair forces, equal and opposite"}
    pair = Result(Candidate("newton_inertial", [], pair_force=True), model=about,
                  errors={10: 0.01, 50: 0.1}, failed_share=0.0, curve=[0.05] * 50, steps=30,
                  wall_s=2.0, train_s=1.5, train_steps=30,
                  law={"s": s.tolist(), "sign": 1.0, "f": {"0-0": (1 - s).tolist()}},
                  masses={"true_log": true_log.tolist(), "fitted_log": (true_log + 1).tolist(),
                          "relative_r2": 1.0, "median_fit": 0.5},
                  law_match={"val_error": 2e-4, "val_error_before": 0.99,
                             "table_val_error": 5e-5, "kept": True})
    decoder = Result(Candidate("decoder", []), errors={10: 0.02, 50: 0.4},
                     failed_share=0.5, curve=[0.2] * 50, steps=30, wall_s=1.0)
    absent = Result(Candidate("impulse", [], admitted=False, reason="no contacts"))
    failed = Result(Candidate("newton_source", [], pair_force=True),
                    error="FloatingPointError: train loss became nan at step 3")
    short = Result(Candidate("newton_type", [], pair_force=True), steps=7,
                   untrained="not trained (7 steps of auto.min_steps=20 before trainer.max_time)")
    protocol = {"horizon": 50, "horizons": [10, 50], "sims": [0, 1, 2, 5], "starts": [6],
                "rollouts": 2, "share": 0.5, "budget_each": {"max_steps": 30},
                "budget_winner": {"max_steps": 70}, "masses_known": True, "min_steps": 20,
                "balance": {"linear": 2e-9, "angular": 3e-7, "sims": 8, "frames": 256},
                "velocity": {"distance": 3e-4, "velocity": 2.9e-4, "sims": 8, "frames": 130},
                "cut": ["the formula candidate: not fitted (trainer.max_time was reached)"]}
    report = write_report(tmp_path, [decoder, pair, failed, short, absent], pair, 4.0,
                          protocol).read_text()
    # a failed candidate with its reason, one cut short with its steps, what the cap cut
    assert "| failed: FloatingPointError: train loss became nan at step 3 |" in report
    assert "| not trained (7 steps of auto.min_steps=20 before trainer.max_time) |" in report
    assert "- newton_source could not be trained or scored: FloatingPointError" in report
    assert "- newton_type: not trained (7 steps" in report and "never compared" in report
    assert "Cut by trainer.max_time: the formula candidate: not fitted" in report
    assert "(at least 20 to count as trained" in report
    assert "**newton_inertial**" in report and "4 times that" in report
    assert "no: no contacts" in report
    assert "momentum imbalance 2e-09" in report and "Verdict: balanced" in report
    assert "a law of the distance 0.0003, of the distance and the relative speed along the " \
        "pair 0.00029. Verdict: no" in report
    assert "simulations 0-2, 5 from" in report
    assert "- newton_inertial: 0.0002 (the initial law: 0.99; the table it was fitted to: " \
        "5e-05); kept" in report and "- decoder:" not in report
    # its training time beside its wall time (training and scoring)
    assert "| steps | train s | wall s |" in report and "| 0 | 30 | 1.5 | 2 | 1 |" in report
    record = json.loads((tmp_path / "auto.json").read_text())
    assert (record["candidates"][1]["train_s"], record["candidates"][1]["train_steps"]) == (
        1.5, 30)
    assert record["choice"] == "newton_inertial" and record["margin"] == 4.0
    rows = (tmp_path / "auto.csv").read_text().splitlines()
    # the chosen one, no error, trained in this attempt
    assert len(rows) == 6 and rows[2].endswith("True,,trained,False")
    for key in ("errors", "law", "masses_newton_inertial"):
        assert (tmp_path / record["figures"][key]).stat().st_size > 0
    # each named as Table 1 names its model (describe()), else by its name
    assert "| **newton_inertial** | BGN + pair-force head (masses inertial) | recorded masses " \
        "(mass_nll, law) | - | central pair forces, equal and opposite | yes |" in report
    assert "| newton_source | newton_source | - | - | - | yes |" in report
    labels = {c["candidate"]: c["label"] for c in record["candidates"]}
    assert labels == {"decoder": "decoder", "newton_inertial": about["label"],
                      "newton_source": "newton_source", "newton_type": "newton_type",
                      "impulse": "impulse"}
    assert record["candidates"][1]["model"] == about


# ----------------------------------------------------------------------------- configs
def test_candidates_compose_from_the_real_configs(tmp_path):
    base = ["dataset=gravity_r2", "model.dynamics=auto", "model.hidden=16", "trainer.max_steps=9"]
    limits = {"max_steps": 3}
    pool = {c.name: c for c in candidates(make_scene("gravity_r2").meta, 5, True, REFS)}
    newton = compose_candidate(base, pool["newton_inertial"], tmp_path / "n", limits)
    assert (newton.model.dynamics, newton.model.mass_law, newton.model.hidden) == (
        "newton", "inertial", 16)
    assert newton.model.loss_weights.dynamics == 0 and newton.model.loss_weights.law == 1
    assert newton.trainer.max_steps == 3 and newton.test is False
    assert newton.paths.output_dir == str(tmp_path / "n")
    # gravity_r2 trains its pair-force head on the law alone: the decoder needs its dynamics
    # recorded masses: the law learns with them and the flow reads the fit, unless set
    plain = {c.name: c for c in candidates(make_scene("spring").meta, 5, True, REFS)}
    free = ["dataset=spring", "model.mass_context=pairs"]
    taught = compose_candidate(free, plain["newton_inertial"], tmp_path / "m", limits,
                               masses=True)
    assert taught.model.loss_weights.law == 1.0 and taught.model.mass_context == "fit"
    assert taught.model.mass_fit_error and "model.mass_context=fit" in \
        plain["newton_inertial"].overrides
    blind = compose_candidate(free, plain["newton_source"], tmp_path / "b", limits)
    assert blind.model.mass_context == "pairs" and not blind.model.loss_weights.law
    compose_candidate(base, pool["newton_source"], tmp_path / "k", limits, masses=True)
    assert pool["newton_source"].overrides == ["model.dynamics=newton",   # gravity_r2's own
                                               "model.mass_law=source"]   # defaults stand
    decoder = compose_candidate(base, pool["decoder"], tmp_path / "d", limits)
    assert decoder.model.dynamics == "decoder" and decoder.model.loss_weights.dynamics == 1
    assert decoder.model.target_prior == "none"              # the scene's defaults apply
    # gravity_r2's law stage is for the pair-force head; the decoder has no law to read
    assert decoder.model.law == "mlp" and newton.model.law == "auto"
    gns = compose_candidate(base, pool["gns"], tmp_path / "g", limits, test=True)
    assert gns.model.name == "gns" and "hidden" not in gns.model and gns.test is True
    pool = {c.name: c for c in candidates(make_scene("collisions").meta, 5, True, REFS)}
    impulse = compose_candidate(["dataset=collisions"], pool["impulse"], tmp_path / "i", limits)
    assert impulse.model.dynamics == "newton" and impulse.model.contact_message == "vector"
    assert "contact_message" not in compose_candidate(["dataset=collisions"], pool["gns"],
                                                      tmp_path / "j", limits).model


def test_auto_is_a_config_value_only(tmp_path):
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], "model.dynamics=auto",
                                   f"paths.output_dir={tmp_path}"])
    validate_train(cfg)
    assert cfg.auto.share == 0.5 and cfg.auto.horizon == 50 and list(cfg.auto.references) == [
        "gns", "cranmer_gn"]
    with pytest.raises(ValueError, match="dynamics='auto'"):
        ModelConfig(dynamics="auto")
    for bad, key in (("auto.share=1.5", "auto.share"), ("auto.horizon=0", "auto.horizon"),
                     ("auto.references=[bgn]", "auto.references")):
        cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], "model.dynamics=auto",
                                       bad])
        with pytest.raises(ConfigError, match=key):
            validate_train(cfg)


# ----------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_auto_picks_the_structure_spring_was_made_with(tmp_path, shared_data_dir):
    """Tiny spring data (inertial pair forces): through the command line, each candidate a
    few hundred steps, the baselines off."""
    run = tmp_path / "run"
    proc = subprocess.run(command_line(
        "dataset=spring", *SMALL["spring"], f"paths.data_dir={shared_data_dir}",
        f"hydra.run.dir={run}", "model.dynamics=auto", "model.hidden=16",
        "model.decoder_hidden=16", "model.flow_hidden=16", "figures=false",
        "val_rollout_steps=0", "animation_every=0", "callbacks.progress_bar=null",
        "dataset.batch_size=16", "trainer.check_val_every_n_epoch=5", "trainer.max_epochs=-1",
        "trainer.max_steps=800", "auto.share=0.75", "auto.references=[]", "test=false"),
        env=CLI_ENV, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((run / "auto" / "auto.json").read_text())
    # the pair-force head, or its law as a formula (fine-tuned from it)
    assert record["choice"] in ("newton_inertial", "formula_newton_inertial")
    rows = {c["candidate"]: c for c in record["candidates"]}
    assert set(rows) == {"decoder", *PAIR_FORCE, "impulse", "soft_contact",
                         "formula_newton_inertial"}
    assert not rows["impulse"]["admitted"] and not rows["soft_contact"]["admitted"]
    assert all(rows[n]["steps"] == 120 for n in ("decoder", *PAIR_FORCE))  # 600 steps / 5
    inertial = rows["newton_inertial"]["val_err@50"]
    # spring's masses differ: neither masses at the source nor one mass for all make it
    assert inertial < min(rows[n]["val_err@50"] for n in ("decoder", "newton_source",
                                                          "newton_type"))
    assert rows["newton_inertial"]["mass_relative_r2"] > 0.9
    for name in ("report.md", "auto.csv", "figures/pair_law.png",
                 "figures/masses_newton_inertial.png", "figures/validation_error.png"):
        assert (run / "auto" / name).exists(), name
    top = json.loads((run / "metrics.json").read_text())
    assert top["auto"]["choice"] == record["choice"]
    # the winner's config beside its checkpoints (bgn.render and bgn.laws read it there)
    assert (run / "auto" / record["choice"] / "train_config.yaml").exists()
    print({n: (r["val_err@10"], r["val_err@50"]) for n, r in rows.items() if r["admitted"]})


@pytest.mark.slow
def test_auto_gives_centrally_damped_data_the_decoder(tmp_path):
    """Springs damped along the line between the particles keep momentum and angular
    momentum, so only the velocity test refuses the pair-force heads (a law of the
    distance): through the command line, the decoder is the one structure trained and chosen."""
    from bgn.data import from_arrays
    from tests.model.test_force_matching import damped_springs

    data, run = tmp_path / "data", tmp_path / "run"
    from_arrays(damped_springs(0.5, sims=5, frames=200), 0.02, name="damped", data_dir=data,
                splits={"train": [0, 1, 2], "val": [3], "test": [4]})
    proc = subprocess.run(command_line(
        "dataset=imported", "dataset.name=damped", f"paths.data_dir={data}",
        f"hydra.run.dir={run}", "model.hidden=16", "model.decoder_hidden=16",
        "model.flow_hidden=16", "figures=false", "val_rollout_steps=0", "animation_every=0",
        "callbacks.progress_bar=null", "dataset.batch_size=16", "trainer.max_epochs=-1",
        "trainer.max_steps=40", "auto.min_steps=10", "auto.references=[]", "test=false"),
        env=CLI_ENV, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    record = json.loads((run / "auto" / "auto.json").read_text())
    assert record["choice"] == "decoder"
    rows = {c["candidate"]: c for c in record["candidates"]}
    for name in PAIR_FORCE:
        assert not rows[name]["admitted"] and "depend on velocity" in rows[name]["reason"]
    velocity = record["protocol"]["velocity"]
    assert velocity["distance"] > 100 * velocity["velocity"]
    assert "Verdict: the forces depend on velocity" in (run / "auto" / "report.md").read_text()


@pytest.mark.parametrize("law_init", ["random", "match"])
def test_the_best_pair_force_law_becomes_a_formula_candidate(tmp_path, shared_data_dir,
                                                             law_init):
    """A tiny BGN pair-force run stands for the best candidate: its law read back, fine-tuned
    and scored as a candidate of its own, eligible, its formula in its label, and its
    checkpoint the one the winner would resume from (the composed config fits it). A matched
    law (law_init=match) trained in a second parameter group; the formula's has one."""
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.laws.options import DEFAULTS
    from bgn.laws.stage import law_stage
    from bgn.rollout import rollout_starts
    from bgn.studies.auto import formula_candidate
    from bgn.training.checkpoints import check_compatible
    from bgn.training.run import train

    auto_dir = tmp_path / "auto"
    base = ["dataset=spring", *SMALL["spring"], f"paths.data_dir={shared_data_dir}",
            "model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16",
            "figures=false", "val_rollout_steps=0", "callbacks.progress_bar=null",
            "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
            "trainer.limit_val_batches=1",
            # the network law: its own formula stage is not what is tested here (and the
            # stage's full fit took most of this test's time)
            "model.law=mlp"]
    best = Candidate("newton_inertial", ["model.dynamics=newton", "model.mass_law=inertial",
                                         f"model.law_init={law_init}"], pair_force=True)
    train(compose_candidate(base, best, auto_dir / best.name, {}), law_stage=law_stage)
    cfg = compose_config("train", base)
    dm = ParticleDataModule(cfg.dataset, cfg.fps, shared_data_dir, show_progress=False)
    dm.prepare_data()
    dm.setup()
    val = dm.datasets["val"]
    n_steps = 10
    result = formula_candidate([Result(best, errors={n_steps: 1.0}, steps=2)], auto_dir, val,
                               dm.datasets["train"], [0], rollout_starts(val, n_steps),
                               n_steps, [n_steps], {"max_steps": 6})
    assert result.candidate.eligible and result.candidate.pair_force and not result.error
    assert result.candidate.name == "formula_newton_inertial"
    assert math.isfinite(result.errors[n_steps]) and result.law is not None
    tuned = json.loads((auto_dir / result.candidate.name / "formula.json").read_text())
    # each form tuned in at most its share of the steps (half the candidates' max_steps) a
    # pass, a pass and its restarts (finetune_restarts)
    assert 0 < tuned["steps"] <= 3 * (1 + DEFAULTS.finetune_restarts) * tuned["tunings"]
    # named by its model's describe(): the formula written into the pair-force head
    assert result.label == result.model["label"] and "law a formula" in result.label
    # the job's deadline spent: its validation rollouts are not started (auto reports the
    # candidate as not scored, trainer.max_time cut it)
    from bgn.studies.auto import score_candidate
    from bgn.training.budget import Deadline, OutOfTime

    with pytest.raises(OutOfTime, match="the validation rollouts"):
        score_candidate(Result(best), auto_dir / best.name, val, dm.datasets["train"], [0],
                        rollout_starts(val, n_steps), n_steps, [n_steps],
                        Deadline(time.monotonic() - 1))
    final = compose_candidate(base, result.candidate, auto_dir / result.candidate.name, {})
    assert final.model.law == "formula"
    assert json.loads(final.model.law_formula) == tuned["model_tuned"]  # the model's scale
    check_compatible(auto_dir / result.candidate.name / "checkpoints" / "last.ckpt", {},
                     OmegaConf.to_container(final.model, resolve=True))
    ckpt = torch.load(auto_dir / best.name / "checkpoints" / "last.ckpt", weights_only=True)
    assert len(ckpt["optimizer_states"][0]["param_groups"]) == (2 if law_init == "match" else 1)
    # the formula's checkpoint is its own: no other candidate's callback state (its
    # ModelCheckpoint named that candidate's best.ckpt)
    own = torch.load(auto_dir / result.candidate.name / "checkpoints" / "last.ckpt",
                     weights_only=True)
    assert own["callbacks"] == {} and ckpt["callbacks"]


@pytest.mark.parametrize("carried", [False, True])
def test_a_winner_whose_budget_is_spent_is_tested_on_its_own_checkpoint(
        tmp_path, shared_data_dir, monkeypatch, carried):
    """The crash of issue 55: the winner (a formula candidate whose checkpoint was made from
    another candidate's) resumed from its own last.ckpt with no steps left, and was tested
    with the best.ckpt that the other candidate's ModelCheckpoint state named, whose network
    law does not load into the formula model. Its test must read its own weights, also where
    that state were still carried (``carried``: run.py's guard on its own)."""
    import lightning as L

    from bgn.laws.stage import law_stage
    from bgn.rollout import rollout_starts
    from bgn.studies.auto import formula_candidate
    from bgn.training.run import data_module, train

    auto_dir = tmp_path / "auto"
    base = ["dataset=spring", *SMALL["spring"], f"paths.data_dir={shared_data_dir}",
            "model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16",
            "figures=false", "val_rollout_steps=0", "callbacks.progress_bar=null",
            "+trainer.limit_train_batches=2", "trainer.limit_val_batches=1",
            "+trainer.limit_test_batches=1", "test_rollouts=false",
            "model.law=mlp"]  # the candidate's own formula stage is not what is tested here
    best = Candidate("newton_inertial", ["model.dynamics=newton", "model.mass_law=inertial"],
                     pair_force=True)
    spent = {"max_steps": 2, "max_epochs": -1}
    train(compose_candidate(base, best, auto_dir / best.name, spent), law_stage=law_stage)
    dm = data_module(compose_config("train", base))
    dm.prepare_data()
    dm.setup()
    val = dm.datasets["val"]
    formula = formula_candidate([Result(best, errors={10: 1.0}, steps=2)], auto_dir, val,
                                dm.datasets["train"], [0], rollout_starts(val, 10), 10, [10],
                                {"max_steps": 4})
    out_dir = auto_dir / formula.candidate.name
    last = out_dir / "checkpoints" / "last.ckpt"
    if carried:  # the other candidate's ModelCheckpoint state, as formula.ckpt carried it
        other = torch.load(auto_dir / best.name / "checkpoints" / "last.ckpt",
                           weights_only=True)
        ckpt = torch.load(last, weights_only=True)
        ckpt["callbacks"] = other["callbacks"]
        assert any(str(auto_dir / best.name) in str(v) for v in ckpt["callbacks"].values())
        torch.save(ckpt, last)
    final = compose_candidate(base, formula.candidate, out_dir, spent, test=True)
    final.ckpt_path = str(last)
    tested = []
    original = L.Trainer.test

    def spy(self, model=None, *args, ckpt_path=None, **kwargs):
        tested.append(ckpt_path)
        return original(self, model, *args, ckpt_path=ckpt_path, **kwargs)

    monkeypatch.setattr(L.Trainer, "test", spy)
    metrics = train(final, law_stage=law_stage)
    assert math.isfinite(metrics["test/nmse"])
    assert len(tested) == 1 and (tested[0] is None or str(out_dir) in str(tested[0]))


def test_imported_data_choose_their_structure_by_default(tmp_path) -> None:
    """dataset=imported composes with model.dynamics=auto (conf/dataset_model/imported_bgn.yaml),
    and train() alone refuses it with the way to run it (auto needs the run's overrides)."""
    from bgn.training.run import train

    cfg = compose_config("train", ["dataset=imported", "dataset.name=any",
                                   f"paths.output_dir={tmp_path}"])
    assert cfg.model.dynamics == "auto"
    with pytest.raises(ValueError, match="python -m bgn.train"):
        train(cfg)


# ----------------------------------------------------------------------------- a tiny run
TINY_AUTO = ["dataset=spring", *SMALL["spring"], "model.dynamics=auto", "model.hidden=16",
             "model.decoder_hidden=16", "model.flow_hidden=16", "figures=false",
             "val_rollout_steps=0", "callbacks.progress_bar=null", "dataset.batch_size=16",
             NETWORK_LAW,
             "trainer.max_steps=40", "auto.min_steps=4", "auto.references=[]",
             "auto.horizon=10", "test=false"]


@pytest.fixture(scope="module")
def tiny_auto(tmp_path_factory, shared_data_dir):
    """A whole model.dynamics=auto run in this process on SMALL spring data (the decoder and
    three pair-force candidates of 5 steps each, the formula candidate, the winner to 25
    steps): its run directory."""
    from bgn.studies.auto import run_auto

    run = tmp_path_factory.mktemp("tiny_auto") / "run"
    overrides = [*TINY_AUTO, f"paths.data_dir={shared_data_dir}", f"paths.output_dir={run}"]
    run_auto(compose_config("train", overrides), overrides)
    return run


@pytest.mark.slow
def test_every_candidate_is_named_by_its_models_description(tiny_auto):
    """The report's label of each candidate is its trained model's describe()["label"] (the
    record Table 1 reads), with what it was trained with, given and has written in."""
    from bgn.training.checkpoints import best_checkpoint
    from bgn.training.module import load_model

    record = json.loads((tiny_auto / "auto" / "auto.json").read_text())
    rows = {c["candidate"]: c for c in record["candidates"]}
    assert set(rows) - {"decoder", *PAIR_FORCE, "impulse", "soft_contact"} == {
        n for n in rows if n.startswith("formula_")}
    for name, row in rows.items():
        if not row["admitted"]:
            assert row["label"] == name and row["model"] is None
            continue
        about = load_model(best_checkpoint(tiny_auto / "auto" / name)).model.describe()
        assert row["label"] == about["label"], name
        assert row["model"] == json.loads(json.dumps(about)), name
        assert row["physics"] == about["physics"]
    formula = next(r for n, r in rows.items() if n.startswith("formula_"))
    assert "law a formula" in formula["label"]
    report = (tiny_auto / "auto" / "report.md").read_text()
    for row in rows.values():
        assert f"| {row['label']} |" in report
    top = json.loads((tiny_auto / "metrics.json").read_text())
    assert top["auto"]["label"] == rows[top["auto"]["choice"]]["label"]


@pytest.mark.slow
def test_the_runs_wall_time_is_the_whole_jobs(tiny_auto):
    """metrics.json's wall_time_s at the run folder counts the whole job (every candidate,
    the formula candidate, the winner's continuation); each candidate keeps its own, and its
    training alone (train_s: less than its own, which counts its scoring too); the closing
    summary states the whole job's time and its parts."""
    from bgn.training.budget import clock_text
    from bgn.training.run import summary

    top = json.loads((tiny_auto / "metrics.json").read_text())
    own = top["auto"]["wall_s"]
    record = json.loads((tiny_auto / "auto" / "auto.json").read_text())
    admitted = {c["candidate"]: c["wall_s"] for c in record["candidates"] if c["admitted"]}
    assert own == pytest.approx(admitted) and all(t > 0 for t in own.values())
    for c in record["candidates"]:
        if c["admitted"] and not c["candidate"].startswith("formula_"):
            assert 0 < c["train_s"] < c["wall_s"] and c["train_steps"] == c["steps"], c
    assert top["auto"]["train_s"] == pytest.approx(
        {c["candidate"]: c["train_s"] for c in record["candidates"] if c["admitted"]})
    job = top["metrics"]["wall_time_s"]
    assert job >= sum(own.values()) + top["auto"]["winner_wall_time_s"]
    winner = json.loads((tiny_auto / "auto" / top["auto"]["choice"] / "metrics.json")
                        .read_text())
    assert winner["metrics"]["wall_time_s"] == pytest.approx(top["auto"]["winner_wall_time_s"])
    assert top["auto"]["kept"] == []
    text = summary(top, tiny_auto)
    first = text.splitlines()[0]
    trained = [n for n in own if not n.startswith("formula_")]
    assert f"in {clock_text(job)} (the whole job: {len(trained)} candidates, the formula " \
        "candidate, the winner's continuation)" in first  # test=false: no test
    assert f"chose {top['auto']['choice']}" in text
    assert f"next: python -m bgn.evaluate {tiny_auto}" in text


@pytest.mark.slow
def test_a_stopped_auto_run_resumes_with_the_command_it_printed(tmp_path, shared_data_dir,
                                                                  tiny_auto):
    """SIGTERM once a candidate has finished; the command the run printed resumes it: the
    finished candidates are kept (result.json untouched, not retrained), the run completes
    with its metrics.json and chooses what the same command chose uninterrupted."""
    import os
    import shlex
    import signal
    import sys

    run = tmp_path / "run"
    proc = subprocess.Popen(command_line(*TINY_AUTO, f"paths.data_dir={shared_data_dir}",
                                         f"hydra.run.dir={run}"),
                            cwd=tmp_path, env=CLI_ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    first = run / "auto" / "decoder" / "result.json"
    deadline = time.monotonic() + 600
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()[1][-3000:]
    os.kill(proc.pid, signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err[-3000:]
    assert not (run / "metrics.json").exists()
    said = [line for line in (out + err).splitlines() if "resume with: " in line]
    assert len(said) == 1, (out + err)[-3000:]
    command = shlex.split(said[0].split("resume with: ", 1)[1])
    assert command[:3] == ["python", "-m", "bgn.train"] and f"hydra.run.dir={run}" in command
    finished = {p.parent.name: (p.read_bytes(), p.stat().st_mtime_ns)
                for p in (run / "auto").glob("*/result.json")}
    checkpoints = {name: (run / "auto" / name / "checkpoints" / "last.ckpt").stat().st_mtime_ns
                   for name in finished}
    assert "decoder" in finished
    resumed = subprocess.run([sys.executable, *command[1:]], cwd=tmp_path, env=CLI_ENV,
                             capture_output=True, text=True, timeout=900)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    for name, (content, mtime) in finished.items():
        path = run / "auto" / name / "result.json"
        assert (path.read_bytes(), path.stat().st_mtime_ns) == (content, mtime), name
    top = json.loads((run / "metrics.json").read_text())
    reference = json.loads((tiny_auto / "metrics.json").read_text())
    assert top["auto"]["choice"] == reference["auto"]["choice"]
    assert sorted(top["auto"]["kept"]) == sorted(finished)
    for name in finished:  # not retrained (the winner's last.ckpt is its continuation's)
        if name != top["auto"]["choice"]:
            last = run / "auto" / name / "checkpoints" / "last.ckpt"
            assert last.stat().st_mtime_ns == checkpoints[name], name
    assert set(top["auto"]["status"]) == set(reference["auto"]["status"])
    assert all(s in ("trained", "-") for s in top["auto"]["status"].values()), top["auto"]
    assert top["auto"]["steps"] == reference["auto"]["steps"]
    for name in finished:  # the same evidence as the uninterrupted run's
        assert top["auto"]["val_errors"][name] == pytest.approx(
            reference["auto"]["val_errors"][name], rel=1e-6), name
    assert "kept from an earlier attempt" in (resumed.stdout + resumed.stderr)
    assert (run / "auto" / "report.md").exists()


def test_a_candidate_is_described_by_the_model_its_config_builds(tmp_path, shared_data_dir):
    """Before it trains (kept where it fails before a checkpoint): the describe() of the
    model its config builds, untrained; None where that model cannot be built."""
    from bgn.studies.auto import described
    from bgn.training.run import data_module

    base = ["dataset=spring", *SMALL["spring"], f"paths.data_dir={shared_data_dir}",
            "model.hidden=16"]
    dm = data_module(compose_config("train", base))
    dm.prepare_data()
    dm.setup()
    pool = {c.name: c for c in candidates(dm.meta, dm.history, True, REFS)}
    decoder = described(compose_candidate(base, pool["decoder"], tmp_path / "d", {}), dm)
    assert decoder is not None and decoder["label"] == "BGN (paper decoder)"
    inertial = described(compose_candidate(base, pool["newton_inertial"], tmp_path / "n", {}),
                         dm)
    assert inertial is not None and "pair-force head (masses inertial" in inertial["label"]
    assert "mass_law=inertial" in inertial["physics"]
    gns = described(compose_candidate(base, pool["gns"], tmp_path / "g", {}), dm)
    assert gns is not None and gns["label"].startswith("GNS")
    # a config no model builds from: no description, so the report names it by its name
    bad = compose_candidate(base, pool["newton_source"], tmp_path / "b", {})
    bad.model.mass_law = "bogus"
    assert described(bad, dm) is None


def test_the_closing_summary_of_an_auto_run_states_the_whole_job():
    """bgn.training.run.summary of the run folder's record: the whole job's time and the
    parts of it that ran (the candidates that trained, the formula candidate, the winner's
    continuation and its test: a stopped run names neither), what was kept from an earlier
    attempt, a choice not made by evidence said so, the run's report and the winner's
    checkpoints."""
    from pathlib import Path

    from bgn.training.run import summary

    status = {"decoder": "trained", "newton_inertial": "trained",
              "newton_source": "not trained (3 steps of auto.min_steps=4 before "
                               "trainer.max_time)",
              "gns": "not scored (trainer.max_time was reached during its validation "
                     "rollouts)", "impulse": "-",
              "formula_newton_inertial": "not scored (trainer.max_time was reached during "
                                         "its validation rollouts)"}
    record = {"metrics": {"wall_time_s": 75.0}, "model": "bgn",
              "budget": {"steps": 5, "max_steps": None, "cut_by": "max_time",
                         "cut": ["the winner's continuation"]},
              "variant": {"label": "BGN (paper decoder)"},
              "auto": {"choice": "decoder", "report": "r/auto/report.md", "fallback": "",
                       "status": status, "continued": False,
                       "wall_s": dict.fromkeys(status, 3.0), "kept": ["decoder"]}}
    lines = summary(record, Path("r")).splitlines()
    assert lines[0] == ("trained BGN (paper decoder): 5 steps in 1 min 15 s (the whole job: "
                        "3 candidates; decoder kept from an earlier attempt), CUT SHORT by "
                        "trainer.max_time (the winner's continuation)")
    assert lines[1] == "model.dynamics=auto chose decoder on validation rollouts (report: " \
        "r/auto/report.md)"
    assert "run: r (metrics.json, auto/report.md, the model's checkpoints in auto/decoder/)" \
        in lines
    record["auto"]["fallback"] = "no candidate trained 100 steps"
    assert "chose decoder not by evidence" in summary(record, Path("r"))
    # a whole job: the formula candidate scored, the winner continued, tested or not
    status["formula_newton_inertial"] = "trained"
    record["auto"].update(continued=True, kept=[])
    record["budget"] = {"steps": 9, "max_steps": 9, "cut_by": None, "cut": []}
    first = summary(record, Path("r")).splitlines()[0]
    assert first.endswith("(the whole job: 3 candidates, the formula candidate, the winner's "
                          "continuation)")
    record["metrics"]["test/nmse"] = 0.1
    assert summary(record, Path("r")).splitlines()[0].endswith(
        "the formula candidate, the winner's continuation and its test)")
    for name in status:
        status[name] = "-" if name == "impulse" else "not trained (0 steps ...)"
    assert "(the whole job: no candidate trained, the winner's continuation and its test)" \
        in summary(record, Path("r"))


def test_no_formula_fits_gives_no_formula_candidate(tmp_path, monkeypatch) -> None:
    """Where the law search finds no formula within its tolerance, the formula stage tunes
    nothing and auto has no formula candidate (None), not a failed one."""
    import bgn.laws.finetune as finetune
    import bgn.studies.auto as auto
    import bgn.training.checkpoints as checkpoints
    from bgn.studies.auto import formula_candidate

    best = Result(Candidate("newton_inertial", [], pair_force=True), errors={10: 1.0}, steps=2)
    monkeypatch.setattr(auto, "best_pair_force", lambda results, n: best)
    monkeypatch.setattr(checkpoints, "best_checkpoint", lambda folder: folder / "best.ckpt")
    monkeypatch.setattr(finetune, "finetune_formula", lambda *a, **k: {
        "outcome": "no formula fits", "choice": "network", "tolerance": 0.02})
    assert formula_candidate([best], tmp_path, None, None, [0], [0], 10, [10], {}) is None
    assert not (tmp_path / "formula_newton_inertial" / "checkpoints").exists()
