"""Each report table from synthetic cell records (no training): rows, columns, the paper's
values, figures and report.md embedding every table."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

from bgn.eval.columns import (
    GIVEN,
    INVERSE_REFERENCES,
    NO_LEARNING,
    PHYSICS,
    TRAINED_WITH,
    inverse_reference_variant,
)
from bgn.studies.cells import Cell
from bgn.studies.report import (
    PAPER_LABEL,
    ablations_table,
    inverse_table,
    paper_value,
    rollout_table,
    sample_efficiency_table,
    table1,
    types_table,
    write_report,
)

MAIN = [Cell("collisions", 10.0, "bgn"), Cell("collisions", 10.0, "gns"),
        Cell("spring", 25.0, "bgn")]
ABLATION = [Cell("collisions", 10.0, "bgn", "no_contact", groups=("ablation",))]
EFFICIENCY = [Cell("spring", 25.0, "gns", "full", n, groups=("sample_efficiency",))
              for n in (1, 3)]
CELLS = MAIN + ABLATION + EFFICIENCY


def record(cell: Cell) -> dict[str, Any]:
    metrics: dict[str, Any] = {"mse": 0.1, "nmse": 0.2, "median_relative_error": 0.3,
                               "n_frames": 256, "nmse_last_extrapolation": 1.5,
                               "nmse_linear_extrapolation": 2.5}
    figure = None
    if cell.scene == "collisions":
        metrics.update(type_accuracy=0.9, type_auroc=0.95)
    if cell.model == "bgn":
        metrics.update({"welch_p": 0.5, "wasserstein1": 0.1, "coverage50": 0.5,
                        "coverage90": 0.9, "info_gain": 1.5, "prior/coverage50": 0.5,
                        "prior/info_gain": 0.0, "physical/sim_mass_rel_err": 0.001})
        figure = f"/elsewhere/figures/mass_{cell.name}.png"
        if cell.scene == "collisions":  # each type its own mass law: the type-only sampler
            metrics.update({"info_gain_over_type": 0.81, "type_prior/info_gain": 0.69,
                            "physical/identified": 0.2})
    if cell.train_sims is not None:
        metrics["nmse"] = 1.0 / cell.train_sims
    for key, err in (("rollout", 0.01), ("rollout_last", 0.5), ("rollout_linear", 0.2),
                     ("predictability", 1e-6)):
        metrics.update({f"{key}/pos_err_mean@10": err, f"{key}/failed_share": 0.0})
    out = {"train": {"metrics": {"wall_time_s": 60.0, "test/contact_f1": 0.7}},
           "eval": {"metrics": metrics, "figure": figure, "train_steps": 300}}
    if cell.scene == "collisions":  # what bgn.studies.grid records (older records lack it)
        out["eval"]["model"] = VARIANTS[cell.model]
    return out


VARIANTS = {  # PhysicsModel.describe of the collisions cells
    "bgn": {"label": "BGN + impulse head (radii)", "given": ["radii"],
            "trained_with": ["contacts", "masses"],
            "supervision": {"contacts": ["contact"], "masses": ["mass_nll", "impulse_mass"]},
            "physics": "impulses at the time of impact"},
    "gns": {"label": "GNS + radii/types", "given": ["radii", "types"], "trained_with": [],
            "supervision": {}, "physics": "none"}}
BGN_TRAINED = "recorded contacts (contact); recorded masses (mass_nll, impulse_mass)"


RESULTS = {c.name: record(c) for c in CELLS}


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


LIMIT = "predictability limit (simulator, 1e-6 off)"


def test_rollout_table(tmp_path: Path) -> None:
    """One row per model of the main grid, per no-learning reference and for the scene's
    predictability limit, per scene x fps."""
    rollout_table(tmp_path, CELLS, RESULTS)
    rows = csv_rows(tmp_path / "rollouts.csv")
    bgn, gns = VARIANTS["bgn"]["label"], VARIANTS["gns"]["label"]
    assert [(r["scene"], r["model"]) for r in rows] == [
        ("collisions", bgn), ("collisions", gns), ("collisions", "last extrapolation"),
        ("collisions", "linear extrapolation"), ("collisions", LIMIT), ("spring", "bgn"),
        ("spring", "last extrapolation"), ("spring", "linear extrapolation"), ("spring", LIMIT)]
    assert [float(r["pos_err_mean@10"]) for r in rows[:3]] == [0.01, 0.01, 0.5]
    assert rows[0]["pos_err_mean@100"] == ""  # not evaluated: blank, not zero
    assert [(r[TRAINED_WITH], r[GIVEN], r[PHYSICS]) for r in rows[:3]] == [
        (BGN_TRAINED, "radii", "impulses at the time of impact"), ("-", "radii, types", "none"),
        (NO_LEARNING, "-", "none")]
    assert (rows[5][GIVEN], rows[5][PHYSICS]) == ("", "")  # an older record


def test_paper_values() -> None:
    assert paper_value("BGN", "collisions", 10.0) == 0.003
    assert paper_value("BGN", "spring", 25.0) is None  # not a paper frame rate
    assert paper_value("BGN", "spring", 12.5) is None
    assert paper_value("Cranmer et al.", "spring", 25.0) == 0.047


def test_table1(tmp_path: Path) -> None:
    """One row per main cell: its variant, what it is given, the physics written in; the
    paper's value beside the paper's variant only."""
    plain = {"bgn_decoder": {"name": "bgn", "label": "BGN (paper decoder)", "given": [],
                             "physics": "none"},  # an older record: no supervision
             "gns": {"label": "GNS", "given": [], "physics": "none"}}
    cells, results = [*CELLS], {**RESULTS}
    for model, about in plain.items():  # model=bgn_decoder: the paper's BGN by its name
        cells.append(Cell("spring", 10.0, model))
        results[cells[-1].name] = {**record(cells[-1])}
        results[cells[-1].name]["eval"]["model"] = about
    table1(tmp_path, cells, results)
    rows = csv_rows(tmp_path / "table1.csv")
    assert [(r["scene"], r["fps"], r["model"], r[TRAINED_WITH], r[GIVEN]) for r in rows] == [
        ("collisions", "10", "BGN + impulse head (radii)", BGN_TRAINED, "radii"),
        ("collisions", "10", "GNS + radii/types", "-", "radii, types"),
        ("spring", "25", "bgn", "", ""),  # an older record: the cell's model name
        ("spring", "10", "BGN (paper decoder)", "not recorded", "-"),
        ("spring", "10", "GNS", "not recorded", "-")]
    assert rows[1]["NMSE"] == "0.2" and rows[1][PHYSICS] == "none"
    # every cell's budget: its steps and its whole run's wall time
    assert {(r["train steps"], r["train s"]) for r in rows} == {("300", "60.0")}
    # the steps are the training record's where it has them: the last checkpoint (the
    # evaluation's train_steps) lags the budget's end by up to a validation interval
    results[cells[0].name] = {**results[cells[0].name],
                              "train": {**results[cells[0].name]["train"],
                                        "budget": {"steps": 310, "max_steps": 310}}}
    table1(tmp_path, cells, results)
    assert csv_rows(tmp_path / "table1.csv")[0]["train steps"] == "310"
    assert rows[1]["frames"] == "256"  # NMSE is heavy-tailed: the frames it averages
    assert rows[0]["repeat-last NMSE"] == "1.5"
    # the paper's BGN is its decoder, its GNS reads no radii or types
    assert [r[PAPER_LABEL] for r in rows] == ["", "", "", "0.0007", "0.734"]


def test_inverse_table_lists_full_cells_with_a_figure(tmp_path: Path) -> None:
    text = inverse_table(tmp_path, CELLS, RESULTS)
    rows = csv_rows(tmp_path / "inverse.csv")
    # each model row, then its references on the same particles: the type-only sampler
    # only where it was evaluated (each type its own mass law)
    # (the model's label says what it is: older records without it show the cell's model)
    assert [(r["scene"], r["fps"], r["model"]) for r in rows] == [
        ("collisions", "10", label) for label in (VARIANTS["bgn"]["label"], *(
            INVERSE_REFERENCES[k] for k in ("prior", "type_prior", "physical")))] + [
        ("spring", "25", label) for label in ("bgn", INVERSE_REFERENCES["prior"],
                                              INVERSE_REFERENCES["physical"])]
    assert [r[GIVEN] for r in rows[:4]] == ["radii", "-", "types", "recorded contacts, types"]
    assert [r[TRAINED_WITH] for r in rows[:4]] == [BGN_TRAINED, *[NO_LEARNING] * 3]
    # the force-law estimator on a force scene reads nothing but the window
    assert rows[-1][GIVEN] == "-" == inverse_reference_variant("physical", False)[GIVEN]
    assert rows[0]["figure"] == f"figures/mass_{MAIN[0].name}.png"
    assert (rows[0]["info_gain"], rows[1]["info_gain"]) == ("1.5", "0.0")
    assert (rows[0]["info_gain_over_type"], rows[2]["info_gain"]) == ("0.81", "0.69")
    assert rows[3]["sim_mass_rel_err"] == "0.001" and rows[3]["figure"] == ""
    assert rows[3]["identified"] == "0.2"
    assert f"![mass_{MAIN[0].name}](figures/mass_{MAIN[0].name}.png)" in text


def test_types_and_ablations(tmp_path: Path) -> None:
    types = types_table(tmp_path, CELLS, RESULTS)
    assert types.count("| collisions |") == 2  # bgn and gns, not the ablation
    ablations = ablations_table(tmp_path, CELLS, RESULTS)
    assert "| no_contact |" in ablations and "| 0.7 |" in ablations  # contact from training
    assert not (tmp_path / "types.csv").exists() and not (tmp_path / "ablations.csv").exists()


def test_sample_efficiency_table_and_plot(tmp_path: Path) -> None:
    sample_efficiency_table(tmp_path, CELLS, RESULTS)
    rows = csv_rows(tmp_path / "sample_efficiency.csv")
    assert [(r["train_sims"], float(r["nmse"])) for r in rows] == [("1", 1.0), ("3", 1 / 3)]
    assert (tmp_path / "sample_efficiency.png").stat().st_size > 0


def test_empty_table_says_so(tmp_path: Path) -> None:
    assert "(no cells of this kind in the preset)" in ablations_table(tmp_path, MAIN, RESULTS)


def test_report_md_embeds_every_table(tmp_path: Path) -> None:
    report = write_report(tmp_path, "synthetic", "cells/", CELLS, RESULTS)
    text = report.read_text()
    assert text.startswith("# Experiments report: preset `synthetic`")
    for name in ("table1", "rollouts", "inverse", "types", "ablations", "sample_efficiency"):
        assert "\n#" + (tmp_path / f"{name}.md").read_text().rstrip("\n") in text, name
    for cell in CELLS:
        assert f"| {cell.name} | {', '.join(cell.groups)} | 300 | 60 |" in text  # steps, s
    assert "total training wall time 6.0 min" in text


def test_the_laws_prose_is_written_from_the_table_rows() -> None:
    """The laws block's findings (``law_stage.findings``) quote the rows beside them: the
    seeds whose fitted form is the truth's, the worst constants and errors, the choice and
    the failed rollouts, never a figure of another run."""
    from bgn.studies.laws_study import findings

    def row(scene: str, truth_form: float, constants: float, chosen: float) -> dict[str, Any]:
        return {"scene": scene, "form is the truth's": truth_form,
                "constants vs truth": constants, "fitted vs truth": 2 * constants,
                "fitted vs truth 1-99%": constants / 2, "network vs truth": 1.3,
                "network vs truth 1-99%": 0.03, "formula chosen": chosen,
                "network val error": 4e-3, "formula val error": 1e-5,
                "network failed": 1.0, "formula failed": 0.0}

    rows = [row("spring", 1.0, 4e-5, 1.0), row("spring", 1.0, 6e-5, 1.0),
            row("gravity_r2", 0.0, 8e-3, 0.0)]
    text = "\n".join(findings(rows, "50"))
    assert "truth's form in 2 of 3 cells** (spring 2 of 2, gravity_r2 0 of 1)" in text
    assert "within 0.006 % (spring), 0.8 % (gravity_r2)" in text  # the worst seed's
    assert "0.00012 (spring), 0.016 (gravity_r2)" in text
    assert "chosen over the network law in 2 of 3 cells" in text
    assert "after 50 steps" in text and "formula 0, network 3" in text
    assert findings([], "50") == []
