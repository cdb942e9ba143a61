"""The experiments command: the tiny preset end to end (every report file, one row per cell)
and resumability."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from bgn.studies.cells import plan_cells
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
    # sampler where each type has its own mass law (collisions)
    assert len(inverse) == 3 * len(models) + sum(r["scene"] == "collisions" for r in models)
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
    from bgn.studies.cells import Cell, train_cell
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
