"""The study presets' step budgets: every cell of every grid preset (main grid, ablations,
sample efficiency) gets a ``trainer.max_steps`` override, so the same command trains the same
cells on any machine, under a wall-clock cap set by one rule; the baselines' budgets keep
BGN's wall time across the presets; a cell the preset's table leaves out trains its scene's
default, said before training; a step table of the wrong shape, or a step budget set beside
the table, is refused in one line; the report's sentence on the budgets is built from the
cells' records; the study reads its data folder by one name, ``paths.data_dir``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from bgn.coerce import ConfigError, seconds
from bgn.studies import grid
from bgn.studies.cells import (
    Cell,
    cell_overrides,
    compose_train,
    default_steps,
    plan_cells,
    preset_steps,
    step_budget,
    unnamed_budgets,
)
from bgn.studies.headline import training_budget
from tests.conftest import compose_config
from tests.test_commands import run_app
from tests.test_experiments import cut_record, finished_record

GRID_PRESETS = ("tiny", "first_look", "standard", "full", "recheck", "reproduce")
STEPS = re.compile(r"\+\+trainer\.max_steps=(\d+)$")
BASELINES = ("gns", "cranmer_gn")


def preset(name: str, *overrides: str):
    return compose_config("experiments", [f"preset={name}", *overrides])


def budgets(name: str) -> dict[tuple[str, str], int]:
    """(scene, model) -> the steps the preset's cells of them train."""
    p = preset(name).preset
    return {(c.scene, c.model): preset_steps(p, c.scene, c.model)[0] for c in plan_cells(p)}


def measured_caps() -> list[tuple[float, dict[str, int]]]:
    """The wall-clock caps set from measurements, each with the BGN step budget per scene it
    was set for: reproduce's (about three times an idle cell's whole run: docs/results.md,
    "Budgets") and the default job's (conf/trainer/default.yaml, for conf/budget/)."""
    rep = preset("reproduce").preset
    scenes = list(rep.max_steps)
    default = seconds(compose_train(["dataset=spring"]).trainer.max_time)
    return [(seconds(rep.max_time), {s: preset_steps(rep, s, "bgn")[0] for s in scenes}),
            (default, {s: default_steps(s) for s in scenes})]


@pytest.mark.parametrize("name", GRID_PRESETS)
def test_every_cell_of_a_grid_preset_gets_a_step_budget(name: str) -> None:
    cfg = preset(name)
    cells = plan_cells(cfg.preset)
    for cell in cells:
        found = [int(m.group(1)) for o in cell_overrides(cell, cfg) if (m := STEPS.match(o))]
        assert found == [preset_steps(cfg.preset, cell.scene, cell.model)[0]], cell.name
        assert found[0] > 0
        # the wall time is a cap only: nothing of the preset sets a shorter one per scene
        assert not any("max_time" in o for o in (cfg.preset.get("scene_overrides") or {})
                       .get(cell.scene, []))
    assert unnamed_budgets(cfg.preset) == []  # every shipped preset names its budgets
    groups = {g for c in cells for g in c.groups}
    if cfg.preset.get("ablations"):
        assert "ablation" in groups
    if cfg.preset.get("sample_efficiency"):
        assert "sample_efficiency" in groups
    # the override reaches the composed train config (one cell: composing is slow)
    last = cells[-1]
    train = compose_train(cell_overrides(last, cfg))
    assert train.trainer.max_steps == preset_steps(cfg.preset, last.scene, last.model)[0]
    if name == "tiny":  # its cap is for the tests' tiny cells
        return
    # One rule for the cap, so that the steps, not the clock, end a cell: at least the cap
    # measured for cells as large or larger, i.e. of a reference whose BGN budget is at
    # least the preset's on each of its scenes (a baseline's budget is BGN's whole wall
    # time: the next test), the shortest such cap where several are.
    mine = {c.scene: preset_steps(cfg.preset, c.scene, "bgn")[0] for c in cells}
    larger = [cap for cap, steps in measured_caps()
              if all(n <= steps[scene] for scene, n in mine.items())]
    assert larger, f"{name}: cells larger than any measured cap's; measure them"
    assert seconds(train.trainer.max_time) >= min(larger), name


def test_the_baselines_keep_bgns_wall_time_across_the_presets() -> None:
    """standard's budgets are reproduce's (its plain baselines as the *_given ones); first_look's
    BGN is standard's x 30/80; full's and recheck's BGN the default job's; and per scene each
    baseline's steps lie on one line through the presets' BGN steps (its steps/s relative to
    BGN's times BGN's fit plus its formula stage, which does not scale with BGN's steps), within
    the rounding of the configs."""
    rep, std, first, full = (budgets(n) for n in ("reproduce", "standard", "first_look",
                                                   "full"))
    rec = preset("recheck").preset  # its cells are spring's; its table names every scene
    for scene in ("spring", "gravity_r1", "gravity_r2", "collisions"):
        assert std[scene, "bgn"] == rep[scene, "bgn"]
        assert first[scene, "bgn"] == pytest.approx(std[scene, "bgn"] * 30 / 80, abs=5)
        assert full[scene, "bgn"] == preset_steps(rec, scene, "bgn")[0] == default_steps(scene)
        for model in BASELINES:
            assert std[scene, model] == rep[scene, f"{model}_given"]
            (s1, b1), (s2, b2) = [(b[scene, "bgn"], b[scene, model]) for b in (first, std)]
            predicted = b2 + (b2 - b1) / (s2 - s1) * (full[scene, "bgn"] - s2)
            assert full[scene, model] == pytest.approx(predicted, rel=0.01), (scene, model)
            assert b1 < b2 < full[scene, model]  # more BGN steps, more baseline steps
            assert preset_steps(rec, scene, model) == (full[scene, model], True)  # as full's
    # collisions: no formula stage, so the line runs through zero (steps in proportion)
    ratio = [b["collisions", "gns"] / b["collisions", "bgn"] for b in (first, std, full)]
    assert max(ratio) / min(ratio) < 1.05


def test_a_cell_the_table_leaves_out_trains_its_scenes_default_and_says_so(
        monkeypatch, capsys) -> None:
    cfg = preset("first_look", "~preset.max_steps.spring.gns",
                 "preset.max_steps.gravity_r1.bgn=default")
    p = cfg.preset
    assert preset_steps(p, "spring", "gns") == (default_steps("spring"), False)
    assert preset_steps(p, "gravity_r1", "bgn") == (default_steps("gravity_r1"), True)
    assert unnamed_budgets(p) == [f"spring/gns: {default_steps('spring')} "
                                  "(conf/budget/spring.yaml)"]
    cell = next(c for c in plan_cells(p) if (c.scene, c.model) == ("spring", "gns"))
    assert f"++trainer.max_steps={default_steps('spring')}" in cell_overrides(cell, cfg)

    def stop(*_args):
        raise RuntimeError("stopped before training")

    monkeypatch.setattr(grid, "train_all", stop)
    with pytest.raises(RuntimeError, match="stopped"):
        grid.run(cfg)
    out = capsys.readouterr().out
    assert "preset.max_steps does not name these cells' step budgets" in out
    assert f"spring/gns: {default_steps('spring')}" in out


def test_the_budget_sentence_is_built_from_the_cells_records() -> None:
    """"Every cell trained its step budget" only where every record says so; else each cell
    the cap cut is named (its rows depend on the load), and one that stopped before its
    budget on its own (early stopping) too."""
    cells = [Cell("spring", 50.0, m, seed=s, seeded=True) for m in ("bgn", "gns")
             for s in (0, 1)]
    whole = {c.name: {"train": finished_record(1500 if c.model == "bgn" else 2780)}
             for c in cells}
    text = training_budget(cells, whole)
    assert text.startswith("Every cell trained its step budget")
    assert "spring: bgn 1500, gns 2780;" in text  # per scene and model, once for the seeds
    cut, early = cells[1].name, cells[3].name
    records = {**whole, cut: {"train": cut_record(1500, 900)},
               early: {"train": finished_record(2780, steps=2000)}}
    text = training_budget(cells, records)
    assert "Every cell" not in text and "not every cell trained it" in text
    assert (f"cut {cut} (cut by trainer.max_time: training; trained 900 of 1500 steps)"
            in text)
    assert f"max_epochs (the same on any machine): {early} (stopped early (early stopping " \
        "or trainer.max_epochs) at 2000 of 2780 steps)" in text
    assert cells[0].name not in text


@pytest.mark.parametrize(("value", "key"), [
    (1500, "preset.max_steps"),                     # one number for the whole study
    ({"spring": 1500}, "preset.max_steps.spring"),  # one per scene
    ([1500, 2000], "preset.max_steps"),              # a list
    ({"spring": [1500]}, "preset.max_steps.spring"),
])
def test_a_step_table_of_the_wrong_shape_is_one_error_naming_it(value, key: str) -> None:
    cfg = preset("standard")
    OmegaConf.update(cfg, "preset.max_steps", value, merge=False)
    cell = next(c for c in plan_cells(cfg.preset) if c.scene == "spring")
    with pytest.raises(ConfigError, match=r"mapping scene -> model -> optimiser steps") as err:
        cell_overrides(cell, cfg)
    assert err.value.key == key


def test_a_wrongly_shaped_step_table_on_the_command_line_is_one_line(
        monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.chdir(tmp_path)
    code = run_app(monkeypatch, "bgn.experiments", "preset=standard", "preset.max_steps=1500")
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "preset.max_steps=1500: must be a mapping scene -> model" in err


@pytest.mark.parametrize("key", ["overrides", "model_overrides.gns", "scene_overrides.spring",
                                 "sample_efficiency.overrides"])
@pytest.mark.parametrize("override", ["trainer.max_steps=50", "++trainer.max_steps=50",
                                      "~trainer.max_steps"])
def test_a_step_budget_beside_the_table_is_refused(key: str, override: str) -> None:
    """A trainer.max_steps in the preset's override lists would silently beat the cell's
    budget that cell.json and the report state: refused, pointing to preset.max_steps."""
    cfg = preset("first_look")
    OmegaConf.update(cfg, f"preset.{key}", [override], merge=False, force_add=True)
    cell = next(c for c in plan_cells(cfg.preset) if (c.scene, c.model) == ("spring", "gns")
                and c.train_sims is not None)  # a cell that reads every list
    with pytest.raises(ConfigError, match=r"belongs in preset\.max_steps") as err:
        cell_overrides(cell, cfg)
    assert err.value.key == f"preset.{key}"


@pytest.mark.parametrize("value", ["0", "-3", "1.5", "many", "true"])
def test_a_bad_step_budget_is_refused_by_its_key(value: str) -> None:
    cfg = preset("standard", f"preset.max_steps.spring.gns={value}")
    cell = next(c for c in plan_cells(cfg.preset) if (c.scene, c.model) == ("spring", "gns"))
    with pytest.raises(ConfigError, match=r"preset\.max_steps\.spring\.gns"):
        cell_overrides(cell, cfg)


def test_a_scene_without_a_default_budget_needs_a_number() -> None:
    p = OmegaConf.create({"scenes": ["nowhere"], "fps": [10], "models": ["bgn"],
                          "max_steps": {"nowhere": {"bgn": "default"}}})
    with pytest.raises(ConfigError, match=r"conf/budget/nowhere\.yaml"):
        step_budget(Cell("nowhere", 10.0, "bgn"), p)
    p.max_steps.nowhere.bgn = 7
    assert step_budget(Cell("nowhere", 10.0, "bgn"), p) == ["++trainer.max_steps=7"]


def test_a_time_scheduled_cell_keeps_its_own_step_limit() -> None:
    """A Pareto cell's schedule ends it (trainer.max_steps=-1): no preset budget is added."""
    from bgn.studies import pareto

    cfg = preset("pareto_tiny")
    for cell in pareto.plan_cells(cfg):
        steps = [o for o in cell_overrides(cell, cfg) if "trainer.max_steps" in o]
        assert steps == ["trainer.max_steps=-1"], cell.name


def test_the_study_reads_its_data_folder_as_paths_data_dir(tmp_path: Path) -> None:
    cfg = preset("tiny", f"paths.data_dir={tmp_path / 'mine'}")
    assert "data_dir" not in cfg  # one name: no alias beside paths.data_dir
    cell = plan_cells(cfg.preset)[0]
    assert f"paths.data_dir={tmp_path / 'mine'}" in cell_overrides(cell, cfg)


def test_the_old_data_dir_name_is_refused_in_one_line(monkeypatch, capsys, tmp_path) -> None:
    """``python -m bgn.experiments data_dir=/x``: exit 2, one line naming paths.data_dir,
    nothing written (no log folder, no data, no cells)."""
    monkeypatch.chdir(tmp_path)
    code = run_app(monkeypatch, "bgn.experiments", f"data_dir={tmp_path / 'x'}")
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert "data_dir is not a key of python -m bgn.experiments" in err
    assert "paths.data_dir" in err
    assert list(tmp_path.iterdir()) == []
