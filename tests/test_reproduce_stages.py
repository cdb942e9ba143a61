"""The grid study's stability and Pareto stages (``bgn.studies.headline``):
their config keys refused one at a time, the front from seed means, and a tiny
reproduce-like preset with both stages that writes every table and fills each generated
block of a copy of docs/results.md."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from bgn.provenance import block_markers
from bgn.studies.headline import mark_fronts, validate_stages
from bgn.training.validate import ConfigError
from tests.conftest import CONF_DIR, compose_config

RESULTS_MD = CONF_DIR.parent / "docs" / "results.md"


def reproduce(**updates: object):
    cfg = compose_config("experiments", ["preset=reproduce"])
    for key, value in updates.items():
        OmegaConf.update(cfg, key, value, force_add=True)
    return cfg


def test_reproduce_preset_has_its_stages_and_their_blocks_exist() -> None:
    preset = reproduce().preset
    validate_stages(preset)
    assert preset.stability.model in preset.models and preset.pareto is not None
    assert preset.laws.model in preset.models
    text = RESULTS_MD.read_text()
    for stage in ("stability", "pareto", "laws"):
        begin, end = block_markers(f"reproduce_{stage}")
        assert text.count(begin) == 1 and text.index(begin) < text.index(end)


@pytest.mark.parametrize(("key", "value", "named"), [
    ("preset.stability.cases", ["spring_fps10"], "preset.stability.cases"),
    ("preset.stability.preset", "no_such_preset", "preset.stability.preset"),
    ("preset.stability.model", "gns", "preset.stability.model"),
    ("preset.stability.fps", 10, "preset.stability.fps"),
    ("preset.stability.seeds", [7], "preset.stability.seeds"),
    ("preset.pareto.simulator_repeats", 0, "preset.pareto.simulator_repeats"),
    ("preset.pareto.timing", 1, "preset.pareto.timing"),
    ("preset.eval.rollout_steps", 20, "pos_err_mean@50"),  # no error after one time unit
    ("preset.laws.model", "gns", "preset.laws.model"),
    ("preset.laws.seeds", [7], "preset.laws.seeds"),
    ("preset.laws.max_seconds", 0, "preset.laws.max_seconds"),
    ("preset.laws.horizon", 50, "preset.laws.horizon"),
])
def test_a_bad_stage_key_is_one_error_naming_it(key: str, value: object, named: str) -> None:
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        validate_stages(reproduce(**{key: value}).preset)


def test_the_front_is_of_the_seed_means() -> None:
    """A model faster than another on every seed but worse on average is on the front only
    where no model is both faster and better in the mean."""
    def row(seed: int, model: str, error: float, seconds: float) -> dict:
        return {"seed": seed, "scene": "s", "fps": 50.0, "model": model,
                "rollout_error": error, "seconds_per_time_unit": seconds}

    rows = [row(0, "fast", 0.9, 1.0), row(1, "fast", 0.1, 1.0),     # mean 0.5
            row(0, "slow", 0.3, 5.0), row(1, "slow", 0.3, 5.0),     # mean 0.3: on the front
            row(0, "worse", 0.6, 6.0), row(1, "worse", 0.2, 6.0)]   # mean 0.4, slower: off
    means = {m["model"]: m for m in mark_fronts(rows)}
    assert {k: m["on front"] for k, m in means.items()} == {"fast": "yes", "slow": "yes",
                                                            "worse": "no"}
    assert all(r["on front"] == means[r["model"]]["on front"] for r in rows)
    assert means["fast"]["rollout_error"] == pytest.approx(0.5)


def csv_rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.slow  # 8 tiny cells in two workers, the tiny stability suite, Pareto and laws
def test_tiny_reproduce_with_its_stages(tmp_path: Path) -> None:
    from bgn.studies.grid import run

    results_md = tmp_path / "results.md"
    shutil.copy(RESULTS_MD, results_md)
    before = results_md.read_text()
    cfg = compose_config("experiments", [
        "preset=tiny", "preset.name=reproduce", "preset.scenes=[spring,collisions]",
        "preset.fps=[10]", "preset.models=[bgn,gns]", "preset.seeds=[0,1]",
        "preset.ablations=null", "preset.sample_efficiency=null", "workers=2",
        f"paths.data_dir={tmp_path / 'data'}", f"cells_dir={tmp_path / 'cells'}",
        f"report_dir={tmp_path / 'report'}", f"results_md={results_md}"])
    OmegaConf.update(cfg, "preset.stability", {"preset": "tiny", "model": "bgn", "fps": None,
                                               "seeds": None}, force_add=True)
    OmegaConf.update(cfg, "preset.pareto", {"simulator_repeats": 1}, force_add=True)
    OmegaConf.update(cfg, "preset.laws", {"model": "bgn", "seeds": [0], "max_seconds": 5},
                     force_add=True)
    validate_stages(cfg.preset)
    run(cfg)

    report = tmp_path / "report"
    stability, pareto = report / "stability", report / "pareto"
    for path in ["table1.csv", "rollouts.csv", "inverse.csv", "report.md",
                 "stability/report.md", "stability/simulator.csv", "stability/model.csv",
                 "stability/model_per_seed.csv", "stability/stability.png",
                 "pareto/report.md", "pareto/points.csv", "pareto/points_per_seed.csv",
                 "pareto/simulator.csv", "pareto/pareto_spring.png",
                 "pareto/pareto_collisions.png", "laws/report.md", "laws/laws.csv",
                 "laws/formulas.csv", "laws/spring_fps10_bgn_full_s0/law.png",
                 "laws/spring_fps10_bgn_full_s0/formula.json"]:
        assert (report / path).is_file(), path

    # stability: every case of the tiny stability preset, model rows of both seeds where the
    # grid has a BGN cell of the case's scene, none for gravity_r2 (no cell)
    cases = OmegaConf.load(CONF_DIR / "stability" / "preset" / "tiny.yaml").cases
    sim = csv_rows(stability / "simulator.csv")
    assert [r["case"] for r in sim] == list(cases)
    per_seed = csv_rows(stability / "model_per_seed.csv")
    learned = [r for r in per_seed if r["model"].startswith("BGN")]
    assert {r["scene"] for r in learned} == {"spring", "collisions"}
    scenes = {c: OmegaConf.load(CONF_DIR / "stability" / "case" / f"{c}.yaml").scene
              for c in cases}
    for case in (c for c in cases if scenes[c] != "gravity_r2"):
        assert {r["seed"] for r in learned if r["case"] == case} == {"0", "1"}, case
    model = csv_rows(stability / "model.csv")
    assert {r["seeds"] for r in model if r["model"].startswith("BGN")} == {"2"}
    assert all(float(r["non_finite"]) in (0.0, 0.5, 1.0) for r in model)

    # pareto: per scene both models per seed and the extrapolations (no linear one on
    # collisions: its target is a velocity), every error after one time unit (fps steps)
    points = csv_rows(pareto / "points_per_seed.csv")
    cells = {json.loads((p / "eval.json").read_text())["metrics"]["rollout/pos_err_mean@10"]
             for p in (tmp_path / "cells").iterdir()}
    learned = [p for p in points if "extrapolation" not in p["model"]]
    assert len(learned) == 2 * 2 * 2 and {float(p["rollout_error"]) for p in learned} == cells
    assert sum("extrapolation" in p["model"] for p in points) == 3
    assert all(float(p["seconds_per_time_unit"]) > 0 for p in points)
    fronts = {(p["scene"], p["on front"]) for p in csv_rows(pareto / "points.csv")}
    assert ("spring", "yes") in fronts and ("collisions", "yes") in fronts
    assert {r["scene"] for r in csv_rows(pareto / "simulator.csv")} == {"spring", "collisions"}

    # laws: spring's BGN cell of seed 0 (its pair-force head), scored against the truth;
    # collisions' impulse head has no law to read and is named as left out
    laws = csv_rows(report / "laws" / "formulas.csv")
    assert [(r["scene"], r["seed"]) for r in laws] == [("spring", "0")]
    assert "r" in laws[0]["fitted to the frames"] and "r" in laws[0]["truth"]
    (scored,) = csv_rows(report / "laws" / "laws.csv")
    assert float(scored["network vs truth"]) >= float(scored["network vs truth 1-99%"]) >= 0
    assert float(scored["form is the truth's"]) in (0.0, 1.0)
    assert "collisions: the" in (report / "laws" / "formulas.md").read_text()

    # the same provenance, and each generated block filled in place
    grid = json.loads((report / "provenance.json").read_text())
    for stage in (stability, pareto, report / "laws"):
        own = json.loads((stage / "provenance.json").read_text())
        assert {k: own[k] for k in grid} == grid and own["stage_wall_time_s"] >= 0
        assert f"`{grid['command']}`" in (stage / "report.md").read_text()
    after = results_md.read_text()
    for name, inside in [("reproduce", "Table 1"), ("reproduce_stability", "hard cases"),
                         ("reproduce_pareto", "Speed against error"),
                         ("reproduce_laws", "against the truth")]:
        begin, end = block_markers(name)
        assert after.count(begin) == 1 and after.count(end) == 1, name
        block = after[after.index(begin):after.index(end)]
        assert inside in block and "Not generated yet" not in block, name
        assert "Regenerated by" in block and "config hash" in block, name
    outside = before[:before.index(block_markers("reproduce")[0])]
    assert after.startswith(outside)  # the text before the blocks is left as it was
    assert after.rstrip().endswith(before.rstrip()[-200:])  # and the text after them
    rel = Path("report") / "pareto" / "pareto_spring.png"
    assert f"]({rel.as_posix()})" in after  # figure links relative to the results file


def test_a_cell_whose_law_stage_fails_is_named_and_fails_the_stage(tmp_path: Path,
                                                                   monkeypatch) -> None:
    """The other cells' tables are written; the failed cell is named in them and the stage
    raises, so the command exits non-zero."""
    from bgn.studies import laws_study
    from bgn.studies.cells import Cell

    cells = [Cell("spring", 50.0, "bgn", seed=s, seeded=True) for s in (0, 1)]
    done = iter([{"failed": "ValueError: boom"}, {"left_out": "no pair-force head"}])
    monkeypatch.setattr(laws_study, "_law_job", lambda *job: next(done))
    cfg = OmegaConf.create({"preset": {"name": "p", "seeds": [0, 1], "laws": {
        "model": "bgn", "seeds": None, "max_seconds": None}},
        "cells_dir": str(tmp_path / "cells"), "report_dir": str(tmp_path / "report"),
        "paths": {"data_dir": str(tmp_path / "data")}, "results_md": None})
    results = {c.name: {"eval": {"model": {"label": "BGN"}}} for c in cells}
    with pytest.raises(RuntimeError, match=r"1 cell\(s\) failed \(spring_fps50_bgn_full_s0\)"):
        laws_study.laws_stage(cfg, cells, results, {"command": "c", "preset": "p"}, 1, None)
    text = (tmp_path / "report" / "laws" / "formulas.md").read_text()
    assert "FAILED (not in the tables): spring_fps50_bgn_full_s0: ValueError: boom" in text
    assert "spring: no pair-force head" in text
