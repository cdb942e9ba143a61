"""Seeds, parallel cells, provenance and the results_md block of the study: the aggregation
over seeds from hand-made per-seed records, the seeded cell plan, a failed cell named while
the others are reported, the generated block rewritten in place."""

from __future__ import annotations

import csv
import json
import statistics
from pathlib import Path
from typing import Any

import pytest

from bgn.provenance import block_markers, replace_block
from bgn.studies.cells import Cell, cell_overrides, compose_train, plan_cells
from bgn.studies.grid import CellsFailed, run
from bgn.studies.report import (
    aggregate_rows,
    rollout_table,
    spread,
    table1,
    write_report,
)
from bgn.training.validate import ConfigError
from tests.conftest import compose_config

SEEDS = (0, 1, 2)
BGN = [Cell("spring", 50.0, "bgn", seed=s, seeded=True) for s in SEEDS]
GNS = [Cell("spring", 50.0, "gns_given", seed=s, seeded=True) for s in SEEDS]
NMSE = {"bgn": [0.1, 0.2, 0.6], "gns_given": [0.3, 0.3, 0.3]}
CAP = 10.0  # rollout_cap: a failed rollout counts at it (bgn.eval.evaluate)
# seed 2 of bgn: one of its three rollouts failed, counted at the cap in its mean
POS_ERR = {"bgn": [0.1, 0.2, (0.3 + 0.3 + CAP) / 3], "gns_given": [0.5, 0.5, 0.5]}
FAILED = {"bgn": [0.0, 0.0, 1 / 3], "gns_given": [0.0, 0.0, 0.0]}
LABELS = {"bgn": "BGN + pair-force head", "gns_given": "GNS + radii/types"}


def record(cell: Cell) -> dict[str, Any]:
    i = cell.seed
    metrics = {"mse": NMSE[cell.model][i] * 2, "nmse": NMSE[cell.model][i],
               "nmse_last_extrapolation": 1.5, "nmse_linear_extrapolation": 2.5,
               "rollout/pos_err_mean@all": POS_ERR[cell.model][i],
               "rollout/failed_share": FAILED[cell.model][i], "rollout/rollout_cap": CAP,
               "rollout_last/pos_err_mean@all": 4.0, "rollout_last/failed_share": 0.0}
    if not (cell.model == "bgn" and i == 1):  # absent in one seed: averaged over the others
        metrics["rollout/energy_err@all"] = 0.01 * (i + 1)
    return {"train": {"metrics": {"wall_time_s": 30.0}},
            "eval": {"metrics": metrics, "figure": None, "train_steps": 500,
                     "model": {"label": LABELS[cell.model], "given": ["radii"],
                               "physics": "none"}}}


CELLS = [*BGN, *GNS]
RESULTS = {c.name: record(c) for c in CELLS}


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_aggregate_rows_mean_spread_and_missing_values() -> None:
    rows = [{"seed": s, "model": "m", "x": x, "figure": f"f{s}.png"}
            for s, x in zip(SEEDS, [1.0, 2.0, 6.0])] + [{"seed": 0, "model": "n", "x": None}]
    m, n = aggregate_rows(rows, ["model"])
    assert (m["seeds"], m["x"], m["x_min"], m["x_max"], m["x_n"]) == (3, 3.0, 1.0, 6.0, 3)
    assert m["x_std"] == pytest.approx(statistics.stdev([1.0, 2.0, 6.0]))
    assert m["figure"] == "f0.png"  # a non-numeric column: the first seed's
    assert n["seeds"] == 1 and n["x"] is None
    nan = aggregate_rows([{"seed": 0, "x": 1.0}, {"seed": 1, "x": float("nan")}], [])[0]
    assert nan["x"] != nan["x"]  # a diverged seed makes the mean NaN, it is not dropped
    assert spread(nan, "x") == "nan (1–1)"
    inf = aggregate_rows([{"seed": 0, "x": 70.0}, {"seed": 1, "x": float("inf")}], [])[0]
    assert spread(inf, "x") == "inf (70–inf)"  # no finite std: the range shows the seed
    assert spread(m, "x") == "3 ± 2.646 (1–6)"


def test_table1_over_seeds_is_mean_and_spread_never_the_best(tmp_path: Path) -> None:
    text = table1(tmp_path, CELLS, RESULTS)
    rows = csv_rows(tmp_path / "table1.csv")  # one row per model, mean/std/min/max/n
    assert [(r["model"], r["seeds"]) for r in rows] == [(LABELS["bgn"], "3"),
                                                        (LABELS["gns_given"], "3")]
    bgn = rows[0]
    assert float(bgn["NMSE"]) == pytest.approx(0.3)  # mean, not the best seed's 0.1
    assert float(bgn["NMSE_std"]) == pytest.approx(statistics.stdev(NMSE["bgn"]))
    assert (float(bgn["NMSE_min"]), float(bgn["NMSE_max"]), bgn["NMSE_n"]) == (0.1, 0.6, "3")
    assert float(rows[1]["NMSE_std"]) == 0.0
    per_seed = csv_rows(tmp_path / "table1_per_seed.csv")
    assert [(r["seed"], float(r["NMSE"])) for r in per_seed] == [
        (str(s), v) for m in ("bgn", "gns_given") for s, v in zip(SEEDS, NMSE[m])]
    # each seed's steps and wall time, then the errors
    assert "| 3 | 500 | 30 | 0.6 ± 0.5292 (0.2–1.2) | 0.3 ± 0.2646 (0.1–0.6) |" in text
    assert "| 3 | 500 | 30 | 0.6 | 0.3 |" in text  # the seeds agree: the value alone
    assert "never the best seed" in text


def test_rollouts_over_seeds_count_the_failed_rollout(tmp_path: Path) -> None:
    rollout_table(tmp_path, CELLS, RESULTS)
    rows = {r["model"]: r for r in csv_rows(tmp_path / "rollouts.csv")}
    bgn = rows[LABELS["bgn"]]
    assert float(bgn["pos_err_mean@all"]) == pytest.approx(sum(POS_ERR["bgn"]) / 3)
    assert float(bgn["pos_err_mean@all_max"]) == pytest.approx((0.6 + CAP) / 3)
    assert float(bgn["failed_share"]) == pytest.approx(1 / 9)
    assert float(bgn["failed_share_max"]) == pytest.approx(1 / 3)
    assert float(bgn["energy_err@all"]) == pytest.approx(0.02)  # seeds 0 and 2 have it
    assert bgn["energy_err@all_n"] == "2"
    # the references learn nothing: one row from one seed's cell, not averaged over seeds
    assert rows["last extrapolation"]["seeds"] == "1"


def test_plan_cells_per_seed_and_the_seed_override() -> None:
    one = compose_config("experiments", ["preset=tiny"])
    two = compose_config("experiments", ["preset=tiny", "preset.seeds=[0,1]"])
    names = [c.name for c in plan_cells(one.preset)]
    seeded = plan_cells(two.preset)
    assert not any(n.endswith(("_s0", "_s1")) for n in names)  # one seed: names unchanged
    assert [c.name for c in seeded] == [f"{n}_s{s}" for s in (0, 1) for n in names]
    assert "seed=1" in cell_overrides(seeded[-1], two)
    assert not any(o.startswith("seed=") for o in cell_overrides(plan_cells(one.preset)[0],
                                                                   one))
    with pytest.raises(ConfigError, match="seeds"):
        plan_cells(compose_config("experiments", ["preset=tiny", "preset.seeds=[1,1]"]).preset)


def test_reproduce_cells_train_a_step_budget_per_scene_and_model() -> None:
    """preset=reproduce budgets every cell in optimiser steps (preset.max_steps), so a rerun
    trains the same steps whatever the machine's load; a bad budget is refused by name."""
    cfg = compose_config("experiments", ["preset=reproduce"])
    for cell in plan_cells(cfg.preset):
        steps = cfg.preset.max_steps[cell.scene][cell.model]
        assert compose_train(cell_overrides(cell, cfg)).trainer.max_steps == steps > 0
    bad = compose_config("experiments", ["preset=reproduce",
                                         "preset.max_steps.spring.bgn=0"])
    with pytest.raises(ConfigError, match=r"preset\.max_steps\.spring\.bgn"):
        cell_overrides(plan_cells(bad.preset)[0], bad)


def test_results_block_is_replaced_in_place_and_idempotent() -> None:
    begin, end = block_markers("reproduce")
    text = f"# Results\n\nintro\n\n{begin}\nold table\n{end}\n\nafter\n"
    once = replace_block(text, "reproduce", "new table")
    assert once == f"# Results\n\nintro\n\n{begin}\nnew table\n{end}\n\nafter\n"
    assert replace_block(once, "reproduce", "new table") == once
    other = replace_block(once, "standard", "std")  # another preset's block: appended
    assert other.startswith(once.rstrip("\n")) and other.endswith(
        "<!-- generated:standard:begin -->\nstd\n<!-- generated:standard:end -->\n")
    assert replace_block(other, "reproduce", "third").count("new table") == 0


def test_report_provenance_and_results_md(tmp_path: Path) -> None:
    provenance = {"command": "python -m bgn.experiments preset=reproduce workers=15",
                  "preset": "reproduce", "config_hash": "abc123", "git_commit": "f" * 40,
                  "git_dirty": False, "seeds": [0, 1, 2], "workers": 15,
                  "threads_per_worker": 1, "wall_time_s": 12.0}
    results_md = tmp_path / "docs" / "results.md"
    results_md.parent.mkdir()
    results_md.write_text("# Results\n\nhand-written\n")
    report_dir = tmp_path / "report"
    report = write_report(report_dir, "reproduce", "cells/", CELLS, RESULTS, provenance,
                          results_md)
    assert json.loads((report_dir / "provenance.json").read_text()) == provenance
    text = report.read_text()
    assert "## Provenance" in text and f"`{provenance['command']}`" in text
    regenerate = f"Regenerated by `{provenance['command']}`"
    assert text.count(regenerate) == 6  # under every table
    first = results_md.read_text()
    assert first.startswith("# Results\n\nhand-written\n") and regenerate in first
    assert "| 3 | 500 | 30 | 0.6 ± 0.5292 (0.2–1.2)" in first  # the aggregated Table 1
    write_report(report_dir, "reproduce", "cells/", CELLS, RESULTS, provenance, results_md)
    assert results_md.read_text() == first  # a second run leaves one block, the same


def test_a_failed_cell_is_named_and_the_others_reported(tmp_path: Path, monkeypatch,
                                                        capsys) -> None:
    """workers=1: a cell whose training raises is named, the others are evaluated and
    reported, and the command fails at the end."""
    import bgn.studies.grid as grid

    cfg = compose_config("experiments", [
        "preset=tiny", "preset.scenes=[spring]", "preset.fps=[50]",
        "preset.models=[bgn,gns]", "preset.seeds=[0,1]", "preset.ablations=null",
        "preset.sample_efficiency=null", f"cells_dir={tmp_path / 'cells'}",
        f"report_dir={tmp_path / 'report'}"])
    cells = plan_cells(cfg.preset)
    broken = cells[1].name

    def train_cell(cell: Cell, cfg: Any) -> tuple[dict[str, Any], bool]:
        if cell.name == broken:
            raise RuntimeError("diverged")
        run_dir = tmp_path / "cells" / cell.name
        run_dir.mkdir(parents=True)
        rec = {"metrics": {"wall_time_s": 1.0}}
        (run_dir / "metrics.json").write_text(json.dumps(rec))
        return rec, True

    def evaluate_cell(cell: Cell, cfg: Any) -> dict[str, Any]:
        return record(Cell("spring", 50.0, "bgn", seed=cell.seed, seeded=True))["eval"]

    monkeypatch.setattr(grid, "train_cell", train_cell)
    monkeypatch.setattr(grid, "evaluate_cell", evaluate_cell)
    with pytest.raises(CellsFailed) as err:
        run(cfg)
    assert err.value.failed == [broken] and broken in str(err.value)
    assert f"FAILED: {broken}" in capsys.readouterr().out
    provenance = json.loads((tmp_path / "report" / "provenance.json").read_text())
    assert provenance["failed_cells"] == [broken] and provenance["seeds"] == [0, 1]
    # what a run on another machine needs to know to expect the same digits or not
    assert provenance["processor"] and "torch " in provenance["libraries"]
    assert "zuko " in provenance["libraries"]
    listed = (tmp_path / "report" / "report.md").read_text()
    assert all((f"| {c.name} |" in listed) == (c.name != broken) for c in cells)


def test_tiny_preset_two_seeds_two_workers(tmp_path: Path) -> None:
    """Four tiny cells (2 models x 2 seeds) trained and evaluated in two worker processes,
    then one aggregated report with its provenance."""
    cfg = compose_config("experiments", [
        "preset=tiny", "preset.scenes=[spring]", "preset.fps=[50]",
        "preset.models=[bgn,gns]", "preset.seeds=[0,1]", "preset.ablations=null",
        "preset.sample_efficiency=null", "workers=2", f"paths.data_dir={tmp_path / 'data'}",
        f"cells_dir={tmp_path / 'cells'}", f"report_dir={tmp_path / 'report'}",
        f"results_md={tmp_path / 'results.md'}"])
    # the network law: the formula stage, not under test here, was most of this test's time
    # (tests/test_experiments.py runs the tiny preset with it)
    cfg.preset.model_overrides.bgn.append("model.law=mlp")
    report = run(cfg)
    cells = plan_cells(cfg.preset)
    assert len(cells) == 4 and {c.name[-3:] for c in cells} == {"_s0", "_s1"}
    for cell in cells:
        run_dir = tmp_path / "cells" / cell.name
        assert (run_dir / "metrics.json").exists() and (run_dir / "eval.json").exists()
        assert json.loads((run_dir / "job.json").read_text())["threads"] == 1
    table = csv_rows(tmp_path / "report" / "table1.csv")
    assert len(table) == 2 and {r["seeds"] for r in table} == {"2"}
    assert len(csv_rows(tmp_path / "report" / "table1_per_seed.csv")) == 4
    rollouts = csv_rows(tmp_path / "report" / "rollouts.csv")
    assert all(0 <= float(r["failed_share"]) <= 1 for r in rollouts)
    provenance = json.loads((tmp_path / "report" / "provenance.json").read_text())
    assert (provenance["workers"], provenance["seeds"], provenance["failed_cells"]) == (
        2, [0, 1], [])
    assert provenance["git_commit"] and provenance["config_hash"]
    assert "## Provenance" in report.read_text()
    assert "<!-- generated:tiny:begin -->" in (tmp_path / "results.md").read_text()


def test_seeds_of_one_model_config_are_one_row_whatever_their_fitted_law() -> None:
    """A formula law fitted per run names other constants in each seed's label and physics:
    the seeds of one model config are still one row (its texts merged), two configs two."""
    from bgn.studies.report import MODEL_ID, merged_text

    physics = ["pair forces; the law a formula -1.003*(r + 0.0107)**-2",
               "pair forces; the law a formula -0.9996*(r + 0.0097)**-2"]
    text = "physics written in"
    rows = [{"seed": s, MODEL_ID: "bgn/", "scene": "g", "model": "BGN", text: p, "x": x}
            for s, p, x in zip(SEEDS, physics, [1.0, 3.0])]
    rows.append({"seed": 0, MODEL_ID: "gns/", "scene": "g", "model": "BGN", text: "none",
                 "x": 5.0})
    one, other = aggregate_rows(rows, ["scene", "model", text])
    assert one["seeds"] == 2 and one["x"] == 2.0 and other["x"] == 5.0
    assert one[text] == ("pair forces; the law a formula (per seed: -1.003*(r + "
                         "0.0107)**-2; -0.9996*(r + 0.0097)**-2)")
    assert merged_text(["same", "same"]) == "same"
    # seeds that share a formula's start: the split stays outside its brackets
    assert merged_text(["law -1*(r + 0.009994)**-1", "law -1*(r + 0.009992)**-1"]) == (
        "law (per seed: -1*(r + 0.009994)**-1; -1*(r + 0.009992)**-1)")


def test_trained_steps_reads_the_record_then_the_last_checkpoint(tmp_path: Path) -> None:
    """A cell's budget in the report: the optimiser steps of its training record, else of its
    last checkpoint (the best one where there is no last), None where it has neither."""
    import torch

    from bgn.studies.grid import trained_steps

    assert trained_steps(tmp_path) is None
    (tmp_path / "checkpoints").mkdir()
    torch.save({"global_step": 40, "state_dict": {}}, tmp_path / "checkpoints" / "best.ckpt")
    assert trained_steps(tmp_path) == 40
    torch.save({"global_step": 55, "state_dict": {}}, tmp_path / "checkpoints" / "last.ckpt")
    assert trained_steps(tmp_path) == 55
    # the training record's count wins: a budget reached inside an epoch ends after the
    # last checkpoint (written at the end of the epoch before)
    (tmp_path / "metrics.json").write_text('{"budget": {"steps": 60}, "metrics": {}}')
    assert trained_steps(tmp_path) == 60
