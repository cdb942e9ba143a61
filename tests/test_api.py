"""The Python API (``bgn.load``): its docstring examples run, its answers agree with the
simulator and the evaluation it wraps, and bad input is one ValueError naming the argument."""

from __future__ import annotations

import doctest
from pathlib import Path

import numpy as np
import pytest
import torch

import bgn
from bgn import api
from bgn.data.datamodule import ParticleDataModule
from bgn.rollout import rollout
from bgn.training.module import load_model


@pytest.fixture(scope="module")
def run_and_data(trained_run, shared_data_dir: Path):
    """(the tiny spring run, its test dataset, one test trajectory (T, N, D), its masses)."""
    from omegaconf import OmegaConf

    run, _ = trained_run
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    dm = ParticleDataModule(cfg.dataset, cfg.fps, shared_data_dir)
    dm.prepare_data()
    dm.setup()
    test = dm.datasets["test"]
    return run, test, test.file.read("positions", 0), test.file.read("masses", 0)


def test_the_docstring_examples_run(run_and_data) -> None:
    run, _, trajectory, _ = run_and_data
    result = doctest.testmod(api, extraglobs={"run": str(run), "trajectory": trajectory,
                                              "bgn": bgn}, optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 8 and result.failed == 0, result


def test_a_rollout_is_the_simulators_from_the_same_window(run_and_data) -> None:
    run, test, trajectory, _ = run_and_data
    model = bgn.load(run)
    k2 = model.window_length
    start = 20
    ours = model.rollout(trajectory[start - k2 + 1:start + 1], 15)
    theirs = rollout(load_model(model.source).model, test, 0, start, 15)["predicted"][1:]
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(model.predict_step(trajectory[start - k2 + 1:start + 1]),
                               ours[0], rtol=0, atol=1e-12)
    assert bgn.load(model.source).source == model.source  # a .ckpt as well as a run folder


def test_the_rollout_is_translation_invariant(run_and_data) -> None:
    run, _, trajectory, _ = run_and_data
    model = bgn.load(run)
    window = trajectory[:model.window_length]
    shift = np.array([0.37, -1.2])
    np.testing.assert_allclose(model.rollout(window + shift, 5) - shift,
                               model.rollout(window, 5), rtol=0, atol=1e-5)


def test_inference_reads_the_law_and_the_flow(run_and_data) -> None:
    run, _, trajectory, masses = run_and_data
    model = bgn.load(run)
    posterior = model.infer(trajectory, frames=8, samples=16)
    n = trajectory.shape[1]
    assert posterior.per_frame is not None and posterior.per_frame.shape == (8 * 16, n)
    assert posterior.frames == 8
    # spring's BGN has a pair-force head: its law fits the masses (a run of 2 steps
    # identifies none: NaN, and the answers come from the per-frame posterior)
    assert posterior.law is not None and posterior.law[0].shape == (n,)
    assert posterior.law_scale in ("per-frame", "physical", "relative")
    low, high = posterior.interval(0.9)
    median = posterior.median()
    assert median.shape == (n,) and np.all((low <= median) & (median <= high))
    assert np.all(posterior.log_std() >= 0) and "windows" in posterior.describe()
    assert len(masses) == n


def test_a_flow_only_posterior_reads_the_draws() -> None:
    draws = np.log(np.array([[1.0, 2.0], [1.2, 2.2], [0.8, 1.8]]))
    posterior = api.MassPosterior(draws, 3, None, None)
    np.testing.assert_allclose(posterior.median(), [1.0, 2.0])
    assert "posterior" in posterior.describe()
    with pytest.raises(ValueError, match="no masses"):
        api.MassPosterior(None, 3, (np.full(2, np.nan), np.full(2, np.nan)), "relative").median()


def test_the_law_is_the_heads_law(run_and_data) -> None:
    from bgn.laws.sample import sample_law

    run, _, _, _ = run_and_data
    model = bgn.load(run)
    law = model.law()
    r = np.array([0.3, 1.0, 2.5])
    np.testing.assert_allclose(law(r), sample_law(law.head, r, 2), rtol=0, atol=0)
    assert law(1.0).shape == () and law.formula is None and law.scale in ("physical", "shape")
    with pytest.raises(ValueError, match="distances > 0"):
        law([-1.0])


@pytest.mark.parametrize("call, match", [
    (lambda m, x: m.rollout(x[:2], 3), "at least"),
    (lambda m, x: m.rollout(x[:m.window_length, :, :1], 3), r"\(frames, N, 2\)"),
    (lambda m, x: m.rollout(x[:m.window_length] * np.nan, 3), "NaN"),
    (lambda m, x: m.rollout(x[:m.window_length], 0), "n_steps"),
    (lambda m, x: m.rollout(x[:m.window_length], 2.5), "n_steps"),
    (lambda m, x: m.rollout(x[:m.window_length], 3, masses=-np.ones(x.shape[1])), "> 0"),
    (lambda m, x: m.rollout(x[:m.window_length], 3, masses=np.ones(2)), "masses"),
    (lambda m, x: m.rollout(x[:m.window_length], 3, types=np.full(x.shape[1], 0.5)),
     "types"),
    (lambda m, x: m.infer(x[:m.window_length]), "at least"),
    (lambda m, x: m.infer(x, frames=0), "frames"),
    (lambda m, x: m.rollout(x[:m.window_length], 3, context=x[:4, :1]), "context"),
])
def test_bad_input_is_one_value_error(run_and_data, call, match) -> None:
    run, _, trajectory, _ = run_and_data
    model = bgn.load(run)
    with pytest.raises(ValueError, match=match) as err:
        call(model, trajectory)
    assert "\n" not in str(err.value)


def test_a_missing_path_and_a_model_without_a_law_are_refused(tmp_path: Path,
                                                              run_and_data) -> None:
    from bgn.model.newton import pair_force_head_of

    with pytest.raises(ValueError, match="does not exist"):
        bgn.load(tmp_path / "nothing")
    run, _, trajectory, _ = run_and_data
    model = bgn.load(run)
    head = pair_force_head_of(model.model)
    model.model.force_head = torch.nn.Identity()  # as a model without a pair-force head
    try:
        with pytest.raises(ValueError, match="no pair-force head"):
            model.law()
    finally:
        model.model.force_head = head


def test_import_bgn_stays_light() -> None:
    import subprocess
    import sys

    code = ("import sys, bgn; assert 'lightning' not in sys.modules and 'bgn.api' not in "
            "sys.modules; bgn.load; assert 'bgn.api' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_formula_law_is_called_as_its_text_reads(run_and_data) -> None:
    import sympy

    from bgn.model.formula_law import FormulaLaw
    from bgn.model.newton import pair_force_head_of

    run, _, _, _ = run_and_data
    model = bgn.load(run)
    head = pair_force_head_of(model.model)
    spec = ('[{"types": [0, 0], "terms": [{"kind": "const", "a": 1.5}, '
            '{"kind": "shifted", "power": -2, "a": -0.7, "c": 0.05}]}]')
    head.force_law = FormulaLaw(spec).to(next(head.parameters()).dtype)
    head.law_scale = -0.25  # a formula kept in the network's free scale (the formula stage)
    law = model.law()
    r = np.array([0.2, 0.9, 3.0])
    text = sympy.lambdify(sympy.Symbol("r"), sympy.sympify(law.formula))
    np.testing.assert_allclose(law(r), text(r), rtol=1e-3)
    assert law.scale == "physical"


def test_a_periodic_scenes_frames_may_come_wrapped_into_the_box() -> None:
    """Frames wrapped into a periodic box (LagrangeBench's layout) are joined by the minimum
    image before the model reads them: no velocity spans the box; open dimensions and open
    scenes are left as given."""
    from bgn.sim.scene import SceneMeta

    model = api.Model.__new__(api.Model)
    model.meta = SceneMeta(name="box", dim=2, n_particles=1, n_types=1,
                           interaction="pairwise", target="acceleration", graph="radius",
                           box=1.0, period=(1.0, 0.0))
    moving = np.array([[[0.95, 0.5]], [[0.99, 0.7]], [[1.03, 0.9]], [[1.07, 1.1]]])
    wrapped = moving.copy()
    wrapped[..., 0] %= 1.0                                    # x wraps, y (open) does not
    np.testing.assert_allclose(model._positions("window", wrapped, 2), moving, atol=1e-12)
    model.meta = SceneMeta(name="open", dim=2, n_particles=1, n_types=1,
                           interaction="pairwise", target="acceleration", graph="full")
    np.testing.assert_array_equal(model._positions("window", wrapped, 2), wrapped)


def test_a_contact_head_reads_the_masses_off_the_impacts_it_sees(shared_data_dir: Path) -> None:
    """A model with an impulse head and no pair law: ``infer`` reads each disc's mass off the
    momentum exchanged at the impacts its contact head sees over the trajectory, each type's
    mass law as prior (``bgn.eval.impact_posterior``); with the gates open on an exact
    event-driven trajectory the linked discs' ratios are exact, so each group's errors are one
    common shift within the posterior's spread. The types come from the type classifier when not
    given; a checkpoint without the scene's mass law gets no impact posterior."""
    from bgn.eval.mass_baselines import MassPrior
    from bgn.training.run import build
    from tests.conftest import SMALL, compose_config

    cfg = compose_config("train", ["dataset=collisions", *SMALL["collisions"],
                                   "model.hidden=8", "model.decoder_hidden=8",
                                   "model.flow_hidden=8", "model.mass_context=pairs",
                                   f"paths.data_dir={shared_data_dir}", "figures=false"])
    datamodule, module = build(cfg)
    test = datamodule.datasets["test"]
    head = module.model.force_head
    with torch.no_grad():  # gates that pass every impact of the rule
        head.gate[-1].bias.fill_(40.0)
    prior = MassPrior.of_scene(test.scene)
    model = api.Model(module.model, test.dt, test.margin, mass_prior=prior)
    x = test.file.read("positions", 0)
    masses, types = test.file.read("masses", 0), test.file.read("types", 0)
    posterior = model.infer(x, frames=len(x), radii=test.file.read("radii", 0), types=types)
    assert "impacts" in posterior.describe()
    mean, std = posterior.impacts
    err = mean - np.log(masses)
    seen = std < 0.9 * prior.type_law(types)[1]          # narrowed by an impact
    assert seen.sum() >= 2
    # the ratios exact: each disc's error is its impact partner's (one shift per linked group)
    same = np.abs(err[seen][:, None] - err[seen][None, :]) < 1e-6
    assert np.all(same.sum(axis=1) >= 2)
    assert np.all(np.abs(err[seen]) < 4 * std[seen])       # the shift: within its spread
    np.testing.assert_allclose(posterior.median(), np.exp(mean))
    model.mass_prior = None                                 # no mass law: the flow alone
    assert model.infer(x, frames=4, radii=test.file.read("radii", 0)).impacts is None


def test_a_checkpoint_carries_its_scenes_mass_law(run_and_data) -> None:
    """The record keeps the scene's parameters (``scene_config``), so the API rebuilds the
    scene's mass law from the checkpoint alone; the hash the resume check compares is theirs."""
    from bgn.eval.mass_baselines import MassPrior
    from bgn.training.checkpoints import params_hash, read, recorded_provenance, resolve_run

    run, test, _, _ = run_and_data
    record = recorded_provenance(read(resolve_run(str(run))[0]))
    assert record["scene_params"] == params_hash(record["scene_config"])
    assert bgn.load(run).mass_prior == MassPrior.of_scene(test.scene)
