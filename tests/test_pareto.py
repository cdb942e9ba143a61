"""The Pareto study (``bgn.studies.pareto``, ``preset=pareto_*``): the front, the time-schedule
callback, the cells of the presets, and the tiny preset end to end (slow tier)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bgn.studies import pareto
from bgn.studies.cells import plan_cells
from bgn.studies.dispatch import is_pareto
from tests.conftest import compose_config


def preset_cfg(name: str, tmp_path: Path | None = None):
    paths = [] if tmp_path is None else [
        f"paths.data_dir={tmp_path / 'data'}", f"cells_dir={tmp_path / 'cells'}",
        f"report_dir={tmp_path / 'report'}"]
    return compose_config("experiments", [f"preset={name}", *paths])


# ----------------------------------------------------------------------------- the front
def test_the_front_holds_exactly_the_undominated_points() -> None:
    rng = np.random.default_rng(0)
    points = [{"cost": float(c), "rollout_error": float(e)}
              for c, e in rng.lognormal(size=(60, 2))]
    points.append({"cost": 0.5, "rollout_error": math.inf})  # a failed rollout: never on it
    front = pareto.pareto_front(points, "cost")
    costs = [p["cost"] for p in front]
    errors = [p["rollout_error"] for p in front]
    assert costs == sorted(costs) and errors == sorted(errors, reverse=True)
    for p in points:
        dominated = any(q["cost"] <= p["cost"] and q["rollout_error"] < p["rollout_error"]
                        or q["cost"] < p["cost"] and q["rollout_error"] <= p["rollout_error"]
                        for q in points if math.isfinite(q["rollout_error"]))
        assert (p in front) == (not dominated and math.isfinite(p["rollout_error"]))


def point(model: str, cost: float, error: float) -> dict:
    return {"model": model, "size": "default", "fps": 10.0, "minutes": 1.0,
            "seconds_per_time_unit": cost, "rollout_error": error}


def test_goal_check_names_a_baseline_that_beats_bgn_at_similar_cost() -> None:
    fine = [point("bgn", 1.0, 0.1), point("gns", 0.8, 0.5), point("gns", 0.1, 0.3)]
    text = pareto.goal_check(fine, "seconds_per_time_unit")
    # the GNS point 10x cheaper is not of similar cost: it shares the front with BGN
    assert text.startswith("BGN on the front: yes") and text.endswith("none.")
    beaten = [point("bgn", 1.0, 0.1), point("cranmer_gn", 0.8, 0.05)]
    text = pareto.goal_check(beaten, "seconds_per_time_unit")
    assert "BGN on the front: no" in text and "cranmer_gn fps10 1min beats bgn" in text


def test_size_grid_is_every_combination_with_each_axis_keys_set_together() -> None:
    cfg = preset_cfg("pareto_full")
    grid = pareto.size_grid(cfg.preset.sizes.grid.bgn)
    assert len(grid) == 4 * 3
    tag, overrides = grid[0]
    assert tag == "hidden32_layers1"
    assert overrides == ["model.hidden=32", "model.decoder_hidden=32", "model.node_layers=1",
                         "model.edge_layers=1"]


# ----------------------------------------------------------------------------- the schedule
class FakeTrainer:
    """What ``TimeSchedule`` uses of a Lightning trainer."""

    def __init__(self) -> None:
        self.global_step, self.should_stop, self.interrupted, self.saved = 0, False, False, []

    def save_checkpoint(self, path: Path) -> None:
        Path(path).write_text("weights")
        self.saved.append(Path(path).name)


def test_time_schedule_saves_at_each_mark_keeps_its_clock_and_stops(tmp_path, monkeypatch) -> None:
    clock = SimpleNamespace(now=100.0)
    monkeypatch.setattr(pareto.time, "perf_counter", lambda: clock.now)
    cb, trainer = pareto.TimeSchedule(str(tmp_path), [2, 1, 4]), FakeTrainer()
    cb.on_train_start(trainer, None)
    for now in (100.5, 101.2, 101.5, 104.5):  # the last step passes 2 s and 4 s at once
        clock.now = now
        trainer.global_step += 1
        cb.on_train_batch_end(trainer)
    assert trainer.saved == ["t1s.ckpt", "t2s.ckpt", "t4s.ckpt"] and trainer.should_stop
    side = json.loads((tmp_path / "t2s.json").read_text())
    assert side == {"seconds": 4.5, "step": 4}  # the time really trained, not the mark

    # a resumed run continues the clock of its checkpoint
    state = cb.state_dict()
    again = pareto.TimeSchedule(str(tmp_path / "resumed"), [6])
    again.load_state_dict(state)
    (tmp_path / "resumed").mkdir()
    again.on_train_start(trainer, None)
    clock.now = 106.0  # 1.5 s in this sitting: 6 s in all
    again.on_train_batch_end(trainer)
    assert (tmp_path / "resumed" / "t6s.ckpt").exists()


def test_a_fit_ended_early_keeps_its_last_weights_under_the_next_mark(tmp_path,
                                                                      monkeypatch) -> None:
    clock = SimpleNamespace(now=0.0)
    monkeypatch.setattr(pareto.time, "perf_counter", lambda: clock.now)
    cb, trainer = pareto.TimeSchedule(str(tmp_path), [1, 10]), FakeTrainer()
    cb.on_train_start(trainer, None)
    clock.now = 3.0
    cb.on_train_batch_end(trainer)
    cb.on_train_end(trainer, None)  # max_epochs, before the 10 s mark
    assert trainer.saved == ["t1s.ckpt", "t10s.ckpt"]
    run_dir = tmp_path.parent
    (run_dir / "checkpoints").mkdir(exist_ok=True)
    for name in ("t1s.ckpt", "t1s.json", "t10s.ckpt", "t10s.json"):
        (tmp_path / name).rename(run_dir / "checkpoints" / name)
    assert [s for _, s in pareto.checkpoints(run_dir)] == [3.0, 3.0]  # the real time


# ----------------------------------------------------------------------------- the presets
@pytest.mark.parametrize("name", ["pareto_tiny", "pareto_first_look", "pareto_full"])
def test_pareto_presets_plan_schedule_and_size_cells(name: str) -> None:
    cfg = preset_cfg(name)
    assert is_pareto(cfg)
    p = cfg.preset
    cells = pareto.plan_cells(cfg)
    schedule = [c for c in cells if pareto.SCHEDULE in c.groups]
    sizes = [c for c in cells if pareto.SIZES in c.groups]
    assert len(schedule) == len(p.scenes) * len(p.fps) * len(p.models)
    n_sizes = sum(len(pareto.size_grid(axes)) for axes in p.sizes.grid.values())
    assert len(sizes) == len(p.sizes.scenes) * len(p.sizes.fps) * n_sizes
    assert len({c.name for c in cells}) == len(cells)  # every cell its own directory
    for cell in schedule:
        assert f"+callbacks.time_schedule.seconds=[{','.join(f'{s:g}' for s in p.schedule_s)}]" \
            in cell.extra and "test=false" in cell.extra


def test_the_issue_cells_are_in_the_full_pareto_preset() -> None:
    p = preset_cfg("pareto_full").preset
    assert preset_cfg("pareto").preset == p  # the issue's name for it, one study behind both
    assert set(p.scenes) == {"spring", "gravity_r2", "collisions"}
    assert list(p.fps) == [10, 50] and list(p.schedule_s) == [60, 120, 240, 480]
    assert list(p.sizes.grid.bgn.hidden["values"]) == [32, 64, 128, 256]
    assert list(p.sizes.grid.bgn.layers["values"]) == [1, 2, 4]
    assert list(p.simulator.collisions_n) == [2000, 20000]


@pytest.mark.parametrize("name,fps", [("first_look", [10, 50]), ("standard", [10, 30, 50, 100])])
def test_table1_presets_cover_the_four_scenes(name: str, fps: list[int]) -> None:
    cfg = preset_cfg(name)
    assert not is_pareto(cfg)
    main = [c for c in plan_cells(cfg.preset) if "main" in c.groups]
    assert {(c.scene, c.fps, c.model) for c in main} == {
        (s, float(f), m) for s in ("spring", "gravity_r1", "gravity_r2", "collisions")
        for f in fps for m in ("bgn", "cranmer_gn", "gns")}


# ----------------------------------------------------------------------------- end to end
def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # every cell of the tiny Pareto study trained, evaluated, timed, reported
def test_pareto_tiny_end_to_end_and_resumes(tmp_path: Path) -> None:
    cfg = preset_cfg("pareto_tiny", tmp_path)
    cells = pareto.plan_cells(cfg)
    report = pareto.run(cfg)
    out = tmp_path / "report"
    points = csv_rows(out / "points.csv")
    schedule = [c for c in cells if pareto.SCHEDULE in c.groups]
    assert len(points) == len(schedule) * len(cfg.preset.schedule_s) + len(cells) - len(schedule)
    for p in points:
        assert float(p["seconds_per_time_unit"]) > 0 and float(p["nmse"]) >= 0
        assert float(p["rollout_error"]) >= 0
    for scene in cfg.preset.scenes:
        assert (out / f"pareto_{scene}.png").stat().st_size > 0
        for cost in pareto.COSTS:
            front = csv_rows(out / f"front_{scene}_{cost}.csv")
            assert front and all(r["scene"] == scene for r in front)
    sim = csv_rows(out / "simulator.csv")
    assert {(r["scene"], float(r["fps"])) for r in sim} == {
        (s, float(f)) for s in cfg.preset.scenes for f in cfg.preset.fps}
    scaling = csv_rows(out / "scaling.csv")
    assert {int(r["N"]) for r in scaling} == set(cfg.preset.simulator.collisions_n)
    assert [r["model"] for r in scaling] == ["exact simulator", *cfg.preset.models,
                                             pareto.REFERENCE]
    text = report.read_text()
    assert "torch threads" in text and text.count("BGN on the front:") == 2 * len(
        cfg.preset.scenes)

    # resumed: nothing trained or evaluated again, the same points
    def stamps() -> dict[str, float]:
        return {f"{c.name}/{f}": (tmp_path / "cells" / c.name / f).stat().st_mtime
                for c in cells for f in ("metrics.json", "pareto_eval.json")}

    before = stamps()
    pareto.run(cfg)
    assert stamps() == before
    assert csv_rows(out / "points.csv") == points
