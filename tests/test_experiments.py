"""The experiments command: the tiny preset end to end (every report file, one row per cell)
and resumability; a cell the wall-clock cap cut is continued on a resume, never kept, and
named in the report and its provenance (fake cell folders: no training)."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from bgn.studies.cells import Cell, plan_cells, train_cell
from bgn.studies.grid import run
from bgn.studies.report import INVERSE_REFERENCES
from tests.conftest import compose_config


def tiny_cfg(tmp_path: Path):
    return compose_config("experiments", [
        "preset=tiny", f"paths.data_dir={tmp_path / 'data'}", f"cells_dir={tmp_path / 'cells'}",
        f"report_dir={tmp_path / 'report'}"])


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def finished_record(max_steps: int, steps: int | None = None,
                    wall: float = 100.0) -> dict[str, Any]:
    """A cell's metrics.json as ``bgn.training.run.train`` writes it, nothing cut."""
    return {"metrics": {"wall_time_s": wall, "test/nmse": 0.5},
            "budget": {"max_steps": max_steps, "steps": max_steps if steps is None else steps,
                       "cut_by": None, "cut": [], "max_time_s": 300.0}}


def cut_record(max_steps: int | None, steps: int, wall: float = 300.0,
               cut: tuple[str, ...] = ("training",)) -> dict[str, Any]:
    """A cell's metrics.json where the wall-clock cap cut ``cut``."""
    return {"metrics": {"wall_time_s": wall, "test/nmse": 0.9},
            "budget": {"max_steps": max_steps, "steps": steps, "cut_by": "max_time",
                       "cut": list(cut), "max_time_s": 300.0}}


def fake_cell(cells_dir: Path, cell: Cell, record: dict[str, Any]) -> Path:
    """A cell folder with a last.ckpt and ``record`` as its metrics.json."""
    run_dir = cells_dir / cell.name
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    (run_dir / "checkpoints" / "last.ckpt").write_bytes(b"")
    (run_dir / "metrics.json").write_text(json.dumps(record))
    return run_dir


def test_a_cell_the_cap_cut_continues_from_its_last_checkpoint(tmp_path: Path, monkeypatch,
                                                                capsys) -> None:
    """A cut cell's metrics.json is not kept: the cell continues from its last.ckpt toward
    its step budget, each attempt the cap cut recorded and its time counted in the cell's
    wall time; a record that trained its budget (or stopped early on its own) is kept."""
    import bgn.training.run as run_module

    cfg = tiny_cfg(tmp_path)
    cell = Cell("spring", 50.0, "gns")
    run_dir = fake_cell(tmp_path / "cells", cell, cut_record(2, 1, wall=300.0))
    outcomes = [cut_record(2, 1, wall=200.0, cut=("test",)), finished_record(2, wall=50.0)]
    resumed = []

    def train(train_cfg, law_stage=None) -> None:  # writes metrics.json, as the real one
        resumed.append(train_cfg.ckpt_path)
        (run_dir / "metrics.json").write_text(json.dumps(outcomes.pop(0)))

    monkeypatch.setattr(run_module, "train", train)
    record, trained = train_cell(cell, cfg)  # cut again, in its test this time
    assert trained and resumed == [str(run_dir / "checkpoints" / "last.ckpt")]
    assert "cut by trainer.max_time: training; trained 1 of 2 steps; continuing from its " \
        "last checkpoint" in capsys.readouterr().out
    record, trained = train_cell(cell, cfg)  # then finished
    assert trained and len(resumed) == 2
    assert record["budget"]["attempts"] == [
        {"steps": 1, "wall_time_s": 300.0, "cut": ["training"]},
        {"steps": 1, "wall_time_s": 200.0, "cut": ["test"]}]
    assert record["metrics"]["wall_time_s"] == 550.0  # every attempt's together
    assert json.loads((run_dir / "metrics.json").read_text()) == record
    assert train_cell(cell, cfg) == (record, False) and len(resumed) == 2  # kept now

    early = fake_cell(tmp_path / "cells", Cell("spring", 10.0, "gns"),
                      finished_record(2, steps=1))
    assert train_cell(Cell("spring", 10.0, "gns"), cfg)[1] is False  # early stopping
    assert json.loads((early / "metrics.json").read_text())["budget"]["steps"] == 1
    # a cell without a step budget (a Pareto cell: its time schedule ends it) is kept as it is
    scheduled = Cell("collisions", 50.0, "gns")
    fake_cell(tmp_path / "cells", scheduled, cut_record(None, 7))
    assert train_cell(scheduled, cfg)[1] is False and len(resumed) == 2


def test_the_cut_cells_are_named_in_the_report_and_its_provenance(tmp_path: Path,
                                                                 monkeypatch) -> None:
    """A study whose cells the cap cut (faked: no training) names each in report.md, in
    provenance.json and in the results_md block, with what was cut and the steps trained."""
    import bgn.studies.grid as grid
    from tests.test_experiments_seeds import record as eval_record

    cfg = tiny_cfg(tmp_path)
    for key in ("scenes", "fps", "models"):
        cfg.preset[key] = {"scenes": ["spring"], "fps": [50], "models": ["bgn", "gns"]}[key]
    cfg.preset.ablations = cfg.preset.sample_efficiency = None
    cfg.results_md = str(tmp_path / "results.md")
    bgn_cell, gns_cell = plan_cells(cfg.preset)

    def train_cell(cell: Cell, cfg) -> tuple[dict[str, Any], bool]:
        rec = cut_record(2, 1, cut=("training", "formula stage")) if cell.model == "bgn" \
            else finished_record(2)
        fake_cell(tmp_path / "cells", cell, rec)
        return rec, True

    def evaluate_cell(cell: Cell, cfg) -> dict[str, Any]:
        return eval_record(Cell("spring", 50.0, "bgn", seed=0, seeded=True))["eval"]

    monkeypatch.setattr(grid, "train_cell", train_cell)
    monkeypatch.setattr(grid, "evaluate_cell", evaluate_cell)
    report = run(cfg)
    named = (f"{bgn_cell.name} (cut by trainer.max_time: training, formula stage; trained 1 "
             "of 2 steps)")
    provenance = json.loads((tmp_path / "report" / "provenance.json").read_text())
    assert provenance["cut_cells"] == [named]
    text = report.read_text()
    assert "**1 cell(s) cut by the wall-clock cap**" in text and named in text
    assert gns_cell.name not in text.split("## Cells")[0]  # the other is not named as cut
    assert "cells cut by the wall-clock cap (trainer.max_time" in (
        tmp_path / "results.md").read_text()
    assert named in (tmp_path / "results.md").read_text()


def test_parallel_workers_continue_a_cut_cell_and_skip_a_finished_one(
        tmp_path: Path, monkeypatch) -> None:
    """workers > 1: a cell whose record the cap cut gets a process (which continues it) even
    where its evaluation is cached; a finished, evaluated cell does not."""
    import bgn.studies.grid as grid

    cfg = tiny_cfg(tmp_path)
    cut, done = Cell("spring", 50.0, "bgn"), Cell("spring", 50.0, "gns")
    fake_cell(tmp_path / "cells", cut, cut_record(2, 1))
    fake_cell(tmp_path / "cells", done, finished_record(2))
    started = []
    monkeypatch.setattr(grid, "prepare_datasets", lambda cells, cfg: None)
    monkeypatch.setattr(grid, "cached_eval", lambda cell, cfg: {"metrics": {}})
    monkeypatch.setattr(grid, "cell_process",
                        lambda cell, cfg, threads: (started.append(cell.name), (True, None))[1])
    assert grid.train_all([cut, done], cfg, workers=2, threads=1) == []
    assert started == [cut.name]


@pytest.mark.slow  # the tiny study end to end: every cell trained, evaluated, reported
def test_tiny_preset_end_to_end_and_resumes(tmp_path: Path, capsys) -> None:
    cfg = tiny_cfg(tmp_path)
    cells = plan_cells(cfg.preset)
    report = run(cfg)
    out = tmp_path / "report"
    assert report == out / "report.md"
    for name in ("report.md", "table1.md", "table1.csv", "rollouts.md", "rollouts.csv",
                 "inverse.md", "inverse.csv",
                 "types.md", "ablations.md", "sample_efficiency.md", "sample_efficiency.csv",
                 "sample_efficiency.png"):
        assert (out / name).stat().st_size > 0, name
    text = report.read_text()
    for name in ("table1", "rollouts", "inverse", "types", "ablations", "sample_efficiency"):
        table = (out / f"{name}.md").read_text()  # report.md embeds every table whole
        assert "\n#" + table.rstrip("\n") in text, name
    for cell in cells:  # every cell trained, evaluated and listed
        assert (tmp_path / "cells" / cell.name / "metrics.json").exists()
        assert f"| {cell.name} |" in text

    preset = cfg.preset
    table1 = csv_rows(out / "table1.csv")  # one row per main cell, labelled by its variant
    assert len(table1) == len(preset.scenes) * len(preset.fps) * len(preset.models)
    assert {(r["scene"], float(r["fps"])) for r in table1} == {
        (s, float(f)) for s in preset.scenes for f in preset.fps}
    for row in table1:
        assert float(row["NMSE"]) >= 0 and float(row["MSE"]) >= 0
        # what the model is, every row: trained with, given at inference, physics
        assert row["trained with"] and row["given at inference"] and row["physics written in"]
        assert int(row["train steps"]) > 0 and float(row["train s"]) > 0  # its budget
        # the baselines' loss reads the frames alone; BGN's the recorded masses too (its
        # flow), and on collisions the recorded contacts
        if row["model"].startswith(("GNS", "Cranmer")):
            assert row["trained with"] == "-"
        else:
            assert "recorded masses" in row["trained with"]
            assert ("recorded contacts" in row["trained with"]) == (row["scene"] == "collisions")
        assert float(row["repeat-last NMSE"]) >= 0  # no-learning references, every row
        assert float(row["linear-extrapolation NMSE"]) >= 0
        # 10 and 50 fps are in the paper; its baselines are the plain ones
        assert bool(row["paper (metric unstated)"]) == (row["model"] in ("GNS", "Cranmer GN"))
    rollouts = csv_rows(out / "rollouts.csv")
    assert {(r["scene"], float(r["fps"]), r["model"]) for r in rollouts} == {
        (r["scene"], float(r["fps"]), r["model"]) for r in table1} | {
        (s, float(f), m) for s in preset.scenes for f in preset.fps
        for m in ["last extrapolation", "predictability limit (simulator, 1e-6 off)"]
        + (["linear extrapolation"] if s != "collisions" else [])}
    for row in rollouts:
        assert 0 <= float(row["failed_share"]) <= 1
        assert float(row["pos_err_mean@1"]) >= 0
        if not row["model"].startswith("predictability"):
            assert float(row["seconds_per_step"]) > 0
    inverse = csv_rows(out / "inverse.csv")
    references = set(INVERSE_REFERENCES.values())
    models = [r for r in inverse if r["model"] not in references]  # each with its references
    assert len(models) == len(preset.scenes) * len(preset.fps)
    assert all(r["model"].startswith("BGN") and r["given at inference"]
               and "recorded masses" in r["trained with"] for r in models)  # labelled
    # the prior-only sampler and the physical estimator under every model, the type-only
    # sampler where each type has its own mass law (collisions), the law estimator per window
    # and the per-simulation posterior through the learned law where the model has a
    # pair-force head, the per-simulation posterior through the impacts where it has a contact
    # head (collisions)
    assert len(inverse) == 3 * len(models) + 2 * sum(r["scene"] == "collisions" for r in models) \
        + 2 * sum("pair-force head" in r["model"] for r in models)
    for row in models:
        assert 0 <= float(row["coverage90"]) <= 1
        assert float(row["info_gain"]) == float(row["info_gain"])  # a number, not blank
        assert (out / row["figure"]).exists()
        assert f"({row['figure']})" in (out / "inverse.md").read_text()
    assert {r["model"] for r in inverse} - {r["model"] for r in models} == references
    types = (out / "types.md").read_text()
    assert types.count("| collisions |") == len(preset.fps)
    ablations = (out / "ablations.md").read_text()
    for variant in ["full", *preset.ablations.variants]:
        assert f"| {variant} |" in ablations
    efficiency = csv_rows(out / "sample_efficiency.csv")
    assert len(efficiency) == len(preset.sample_efficiency.models) * len(
        preset.sample_efficiency.train_sims)

    # a second invocation retrains (and re-evaluates) nothing, and rewrites the report
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "cells").rglob("*")
              if p.name in ("metrics.json", "eval.json") or p.suffix == ".ckpt"}
    capsys.readouterr()
    run(tiny_cfg(tmp_path))
    assert "  trained\n" not in capsys.readouterr().out
    assert stamps == {p: p.stat().st_mtime_ns for p in stamps}

    # an interrupted cell (checkpoints but no metrics.json) is the only one trained again
    interrupted = tmp_path / "cells" / cells[0].name / "metrics.json"
    interrupted.unlink()
    run(tiny_cfg(tmp_path))
    assert capsys.readouterr().out.count("  trained\n") == 1
    assert interrupted.exists()


def test_a_damaged_study_file_is_named_and_its_cell_redone(tmp_path: Path, shared_data_dir,
                                                           caplog) -> None:
    """A half-written eval.json (or metrics.json) is named in a warning and the cell is
    evaluated (trained) again, instead of a JSONDecodeError that blocks the study."""
    from bgn.studies.grid import evaluate_cell

    cfg = tiny_cfg(tmp_path)
    cfg.paths.data_dir = str(shared_data_dir)
    cfg.preset.overrides.append("+dataset.generate_workers=1")
    cell = Cell("spring", 50.0, "cranmer_gn")
    record, trained = train_cell(cell, cfg)
    assert trained and "test/nmse" in record["metrics"]
    # the preset's step budget ended the cell, not its wall-time cap (nothing "cut short")
    assert record["budget"]["steps"] == record["budget"]["max_steps"] == \
        cfg.preset.max_steps.spring.cranmer_gn
    assert record["budget"]["cut_by"] is None
    first = evaluate_cell(cell, cfg)
    run_dir = tmp_path / "cells" / cell.name
    for name in ("eval.json", "metrics.json", "cell.json"):
        json.loads((run_dir / name).read_text())  # whole files
    assert not list(run_dir.glob(".*.tmp*"))  # no temporary file left behind

    eval_path = run_dir / "eval.json"
    text = eval_path.read_text()
    eval_path.write_text(text[: len(text) // 2])  # a writer killed half-way (older bgn)
    with caplog.at_level("WARNING"):
        again = evaluate_cell(cell, cfg)
    assert f"{eval_path} is damaged" in caplog.text
    rewritten = json.loads(eval_path.read_text())  # whole again
    assert rewritten["metrics"].keys() == again["metrics"].keys() == first["metrics"].keys()
    assert rewritten["checkpoint"] == again["checkpoint"]

    metrics_path = run_dir / "metrics.json"
    metrics_path.write_text('{"metrics": {"test/nmse": 0.')
    caplog.clear()
    with caplog.at_level("WARNING"):
        record, trained = train_cell(cell, cfg)
    assert trained and f"{metrics_path} is damaged" in caplog.text
    assert json.loads(metrics_path.read_text())["metrics"]["test/nmse"] >= 0
