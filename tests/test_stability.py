"""The hard-case stability suite (``python -m bgn.stability``): the tiny preset end to end,
every case config loads and builds, checkpoints are wired per scene."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from bgn.sim.nbody import NYQUIST_TURN
from bgn.studies.stability import CONF_DIR, build, load_case, run, simulate, simulator_checks


def compose_stability(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="stability", overrides=overrides)


def test_tiny_preset_runs_end_to_end(tmp_path):
    cfg = compose_stability(["preset=tiny", f"report_dir={tmp_path}"])
    report = run(cfg)
    for name in ("report.md", "simulator.csv", "model.csv", "stability.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    with (tmp_path / "simulator.csv").open() as f:
        sim_rows = list(csv.DictReader(f))
    assert [r["case"] for r in sim_rows] == list(cfg.preset.cases)
    assert all(r["passed"] == "True" for r in sim_rows), sim_rows
    # the frame rate of every tiny n-body case carries its rotations; discs have no such row
    for r in sim_rows:
        assert (r["aliased_frames"] == "") == (r["scene"] == "collisions"), r
        if r["scene"] != "collisions":
            assert float(r["aliased_frames"]) == 0 < float(r["max_turns_per_frame"]) < NYQUIST_TURN
    with (tmp_path / "model.csv").open() as f:
        model_rows = list(csv.DictReader(f))
    refs = [r for r in model_rows if r["model"].startswith(("frame oracle", "predictability"))]
    learned = [r for r in model_rows if r not in refs]
    # one row per case and dtype (the float32-vs-float64 case has two)
    assert len(learned) == len(sim_rows) + 1
    assert {r["dtype"] for r in learned} == {"float32", "float64"}
    assert all(r["one_step_rel_error"] not in ("", "nan") for r in learned)
    # force scenes: the true physics fed frames, and chaos alone from 1e-6
    force_cases = {r["case"] for r in learned if r["scene"] != "collisions"}
    oracle = {r["case"]: r for r in refs if r["model"].startswith("frame oracle")}
    chaos = {r["case"]: r for r in refs if r["model"].startswith("predictability")}
    assert set(oracle) == set(chaos) == force_cases
    assert float(oracle["spring_6_bodies"]["one_step_rel_error"]) < 1e-4
    assert all(float(r["error_1"]) < 1e-5 for r in chaos.values())
    text = report.read_text()
    assert "untrained" in text and "| spring_6_bodies |" in text
    assert all(r["aliased_frames"] == "0.0" for r in model_rows if r["scene"] != "collisions")
    assert "aliased_frames" in text


def test_the_frames_of_the_heavy_centre_case_alias_and_its_resolved_twin_do_not():
    """Masses 1000, 1, 1, 1 at fps 50: a light body turns more than half a revolution in some
    frames (what no model fed frames can follow); masses 1, 1e-3, 1e-3, 1e-3 never do."""
    rows = {}
    for name in ("gravity_r2_mass_ratio_1e3", "gravity_r2_mass_ratio_1e3_resolved"):
        case = load_case(name)
        scene, state, _, _ = build(case)
        traj, log = simulate(scene, state, np.arange(20) / case.fps)
        rows[name] = simulator_checks(case, scene, traj, log, 0.0)
    fast, resolved = rows["gravity_r2_mass_ratio_1e3"], rows["gravity_r2_mass_ratio_1e3_resolved"]
    assert fast["aliased_frames"] > 0 and fast["max_turns_per_frame"] > 1
    assert resolved["aliased_frames"] == 0 and resolved["max_turns_per_frame"] < 0.1


def test_without_checkpoints_the_model_part_is_skipped(tmp_path):
    cfg = compose_stability(["preset=tiny", f"report_dir={tmp_path}",
                             "preset.cases=[spring_6_bodies]", "preset.untrained_model=null"])
    report = run(cfg)
    assert "skipped" in report.read_text()
    assert (tmp_path / "model.csv").read_text().count("\n") == 1  # the header only


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF_DIR / "case").glob("*.yaml")))
def test_every_case_loads_and_builds(name):
    case = load_case(name)
    scene, state, _, base = build(case)
    assert state.positions.shape == (scene.meta.n_particles, scene.meta.dim)
    assert case.n_frames > 2 and case.fps > 0
    if case.transform:
        assert not np.array_equal(state.positions, base.positions)


def test_every_case_is_in_the_all_cases_preset():
    cfg = compose_stability(["preset=all_cases"])
    assert sorted(cfg.preset.cases) == sorted(p.stem for p in (CONF_DIR / "case").glob("*.yaml"))


def test_the_old_quick_name_is_gone():
    from hydra.errors import MissingConfigException

    with pytest.raises(MissingConfigException):
        compose_stability(["preset=quick"])


def test_unknown_case_keys_are_errors(tmp_path):
    (tmp_path / "case").mkdir()
    (tmp_path / "case" / "bad.yaml").write_text("scene: spring\nfsp: 10\n")
    with pytest.raises(ValueError, match="fsp"):
        load_case("bad", tmp_path)
    with pytest.raises(ValueError, match="known"):
        load_case("missing", tmp_path)
def test_a_checkpoint_per_scene_is_used_and_must_match_its_scene(tmp_path, monkeypatch):
    """``checkpoints.<scene>`` is loaded with ``bgn.training.module.load_model`` (stubbed here with
    a small untrained model) and used for that scene's cases only."""
    import types

    import bgn.training.module
    from bgn.studies.stability import model_for

    cfg = compose_stability(["preset=tiny", f"report_dir={tmp_path}",
                             "preset.cases=[spring_6_bodies]"])
    case = load_case("spring_6_bodies")
    scene, state, _, _ = build(case)
    traj = scene.simulate_from(state, np.arange(30) / case.fps)
    untrained, _ = model_for(case, scene, traj, cfg)
    monkeypatch.setattr(bgn.training.module, "load_model",
                        lambda path: types.SimpleNamespace(model=untrained))
    cfg.checkpoints.spring = "spring.ckpt"
    _, label = model_for(case, scene, traj, cfg)
    assert label == "spring.ckpt"
    run(cfg)
    assert "spring: `spring.ckpt`" in (tmp_path / "report.md").read_text()
    cfg.checkpoints.spring = None
    cfg.checkpoints.gravity_r2 = "spring.ckpt"  # a spring model given for gravity_r2
    gcase = load_case("gravity_r2_6_bodies")
    gscene, gstate, _, _ = build(gcase)
    with pytest.raises(ValueError, match="spring model"):
        model_for(gcase, gscene, gscene.simulate_from(gstate, np.arange(10) / 50), cfg)
