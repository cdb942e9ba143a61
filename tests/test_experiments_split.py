"""A study scored on the validation split (``preset.eval.split=val``) and the
grid's ``variants`` (the same scene and model with overrides A against B): the recheck
preset's plan, its keys refused one at a time before any cell trains, every table and the
provenance naming the split, a validation study's results_md block apart from the test one,
and a tiny study of two variants scored on validation end to end."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from bgn.provenance import block_markers
from bgn.studies.cells import Cell, cell_overrides, compose_train, plan_cells
from bgn.studies.grid import check_variant_cells, validate_grid
from bgn.studies.report import write_report
from bgn.training.validate import ConfigError, validate_train
from tests.conftest import compose_config
from tests.test_experiments_seeds import CELLS, RESULTS

PAIRS = "model.mass_context=pairs"


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_recheck_preset_is_the_default_against_its_alternative_on_validation() -> None:
    cfg = compose_config("experiments", ["preset=recheck"])
    validate_grid(cfg.preset)
    assert cfg.preset.eval.split == "val" and cfg.preset.seeds == [0, 1, 2]
    cells = plan_cells(cfg.preset)
    assert len(cells) == 2 * 3 and {c.extra for c in cells} == {(), (PAIRS,)}
    for cell in cells:
        overrides = cell_overrides(cell, cfg)
        assert "test=false" in overrides  # the test split is not read by the re-check
        # the variant's override after the preset's (it wins), before the paths
        assert (PAIRS in overrides) == (cell.tag == "pairs")
        model = compose_train(overrides).model
        validate_train(compose_train(overrides))
        assert model.mass_context == ("pairs" if cell.tag == "pairs" else "fit")
    # another row from the command line: a new variant in place of the shipped one
    other = compose_config("experiments", [
        "preset=recheck", "preset.scenes=[gravity_r2]", "~preset.variants.pairs",
        '+preset.variants.frames1=["model.mass_context_frames=1"]'])
    validate_grid(other.preset)
    assert {c.name for c in plan_cells(other.preset) if c.seed == 0} == {
        "gravity_r2_fps50_bgn_full_default_s0", "gravity_r2_fps50_bgn_full_frames1_s0"}


@pytest.mark.parametrize(("preset", "key", "value", "named"), [
    ("tiny", "preset.eval.split", "train", "preset.eval.split"),
    ("tiny", "preset.eval.split", "testing", "preset.eval.split"),
    ("reproduce", "preset.eval.split", "val", "preset.stability=null"),  # headline stages
    ("tiny", "preset.variants", ["model.mass_context=pairs"], "preset.variants"),
    ("tiny", "preset.variants", {"a/b": []}, "preset.variants.a/b"),
    ("tiny", "preset.variants", {"pairs": "model.mass_context=pairs"},
     "preset.variants.pairs"),
    ("reproduce", "preset.variants", {"pairs": [PAIRS]}, "preset.pareto=null"),
])
def test_a_bad_split_or_variant_is_one_error_naming_it(preset: str, key: str, value: object,
                                                      named: str) -> None:
    cfg = compose_config("experiments", [f"preset={preset}"])
    OmegaConf.update(cfg, key, value, force_add=True)
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        validate_grid(cfg.preset)


def test_a_variant_renamed_to_other_overrides_is_refused(tmp_path: Path) -> None:
    """A trained cell is not retrained: the same variant name with other overrides would
    report the old cells under the new overrides, so it is refused before any training."""
    cfg = compose_config("experiments", ["preset=recheck", f"cells_dir={tmp_path}"])
    check_variant_cells(cfg)  # nothing trained yet
    cell = next(c for c in plan_cells(cfg.preset) if c.tag == "pairs")
    (tmp_path / cell.name).mkdir()
    (tmp_path / cell.name / "cell.json").write_text(json.dumps({"extra": [PAIRS]}))
    check_variant_cells(cfg)  # the same overrides: resumed
    OmegaConf.update(cfg, "preset.variants.pairs", ["model.mass_context=node"])
    with pytest.raises(ConfigError, match=f"cell {cell.name}.*trained with"):
        check_variant_cells(cfg)


def test_a_validation_report_says_so_everywhere_and_never_fills_a_test_block(
        tmp_path: Path) -> None:
    provenance = {"command": "python -m bgn.experiments preset=reproduce preset.eval.split=val",
                  "preset": "reproduce", "config_hash": "abc", "git_commit": "f" * 40,
                  "seeds": [0, 1, 2], "eval_split": "val", "calibration_split": "train"}
    results_md = tmp_path / "results.md"
    begin, end = block_markers("reproduce")
    test_block = f"{begin}\nthe test tables\n{end}"
    results_md.write_text(f"# Results\n\n{test_block}\n")
    report = write_report(tmp_path / "report", "reproduce", "cells/", CELLS, RESULTS,
                          provenance, results_md, split="val")
    text = report.read_text()
    assert text.startswith("# Experiments report: preset `reproduce`, scored on the "
                           "validation split")
    headings = [line for line in text.splitlines() if line.startswith("## ")
                and line not in ("## Provenance", "## Cells")]
    assert len(headings) == 6 and all("validation split" in h for h in headings), headings
    assert "test split" not in "\n".join(headings) and "| val NMSE |" in text
    assert "- split scored (every table): val" in text
    assert "- mass flow recalibrated on: train" in text
    written = results_md.read_text()
    assert test_block in written  # the test block untouched
    begin_val, end_val = block_markers("reproduce_val")
    block = written[written.index(begin_val):written.index(end_val)]
    assert "Table 1: one-step error on the validation split" in block


def test_tiny_study_of_two_variants_on_validation(tmp_path: Path, shared_data_dir) -> None:
    """Two tiny BGN cells (mass_context fit and pairs) trained with test=false and scored on
    validation, the flow recalibrated on train; the rows labelled by their overrides."""
    from bgn.eval.evaluate import evaluate_split
    from bgn.studies.cells import cell_datamodule
    from bgn.studies.grid import run
    from bgn.training.module import load_model

    cfg = compose_config("experiments", [
        "preset=tiny", "preset.scenes=[spring]", "preset.fps=[50]", "preset.models=[bgn]",
        "preset.ablations=null", "preset.sample_efficiency=null", "preset.eval.split=val",
        "+preset.variants={default:[],pairs:[\"model.mass_context=pairs\"]}",
        f"paths.data_dir={shared_data_dir}", f"cells_dir={tmp_path / 'cells'}",
        f"report_dir={tmp_path / 'report'}", f"results_md={tmp_path / 'results.md'}"])
    cfg.preset.overrides.extend(["test=false", "+dataset.generate_workers=1"])
    # the network law: the formula stage, not under test here, was most of this test's time
    # (tests/test_experiments.py runs the tiny preset with it)
    cfg.preset.model_overrides.bgn.append("model.law=mlp")
    validate_grid(cfg.preset)
    report = run(cfg)
    cells = plan_cells(cfg.preset)
    assert [c.tag for c in cells] == ["default", "pairs"]
    for cell in cells:
        run_dir = tmp_path / "cells" / cell.name
        assert not (run_dir / "eval.json").exists()  # the test record is another file
        result = json.loads((run_dir / "eval_val.json").read_text())
        assert (result["split"], result["calibration_split"]) == ("val", "train")
        assert not any(k.startswith("test/") for k in
                       json.loads((run_dir / "metrics.json").read_text())["metrics"])
    # the numbers are the validation split's (python -m bgn.evaluate split=val's code)
    cell = cells[1]
    datamodule = cell_datamodule(tmp_path / "cells" / cell.name, str(shared_data_dir))
    e = cfg.preset.eval
    module = load_model(json.loads((tmp_path / "cells" / cell.name / "eval_val.json")
                                   .read_text())["checkpoint"])
    scored = {}
    for split, calibration in (("val", "train"), ("test", "val")):
        scored[split], _ = evaluate_split(
            module, datamodule.datasets[split], datamodule.datasets[calibration],
            max_frames=e.max_frames, mass_frames=e.mass_frames,
            mass_samples=e.mass_samples, batch_size=e.batch_size, rollout_steps=2)
    table = csv_rows(tmp_path / "report" / "table1.csv")
    assert [r["overrides"] for r in table] == ["default: none", f"pairs: {PAIRS}"]
    assert float(table[1]["NMSE"]) == pytest.approx(scored["val"]["nmse"], rel=1e-3)
    assert float(table[1]["NMSE"]) != pytest.approx(scored["test"]["nmse"], rel=1e-3)
    provenance = json.loads((tmp_path / "report" / "provenance.json").read_text())
    assert (provenance["eval_split"], provenance["calibration_split"]) == ("val", "train")
    assert "scored on the validation split" in report.read_text()
    written = (tmp_path / "results.md").read_text()
    assert block_markers("tiny_val")[0] in written and block_markers("tiny")[0] not in written
    assert Cell("spring", 50.0, "bgn", tag="pairs", extra=(PAIRS,)).name == cell.name
