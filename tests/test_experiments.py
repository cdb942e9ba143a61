"""The experiments command: the tiny preset end to end (every report file, one row per cell),
resumability, and the inverse metrics on synthetic samples."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from bgn.evaluate import inverse_metrics, kde_modes, r2_score, recovered_modes
from bgn.experiments import plan_cells, run
from tests.conftest import compose_config


def tiny_cfg(tmp_path: Path):
    return compose_config("experiments", [
        "preset=tiny", f"data_dir={tmp_path / 'data'}", f"cells_dir={tmp_path / 'cells'}",
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
    for name in ("report.md", "table1.md", "table1.csv", "inverse.md", "inverse.csv",
                 "types.md", "ablations.md", "sample_efficiency.md", "sample_efficiency.csv",
                 "sample_efficiency.png"):
        assert (out / name).stat().st_size > 0, name
    text = report.read_text()
    for name in ("table1", "inverse", "types", "ablations", "sample_efficiency"):
        table = (out / f"{name}.md").read_text()  # report.md embeds every table whole
        assert "\n#" + table.rstrip("\n") in text, name
    for cell in cells:  # every cell trained, evaluated and listed
        assert (tmp_path / "cells" / cell.name / "metrics.json").exists()
        assert f"| {cell.name} |" in text

    preset = cfg.preset
    table1 = csv_rows(out / "table1.csv")
    assert {(r["scene"], float(r["fps"])) for r in table1} == {
        (s, float(f)) for s in preset.scenes for f in preset.fps}
    for row in table1:
        for model in preset.models:
            assert float(row[f"{model} NMSE"]) >= 0 and float(row[f"{model} MSE"]) >= 0
        assert row["BGN paper (metric unstated)"]  # 10 and 50 fps are in the paper
        assert float(row["repeat-last NMSE"]) >= 0  # no-learning references, every row
        assert float(row["linear-extrapolation NMSE"]) >= 0
    inverse = csv_rows(out / "inverse.csv")
    assert len(inverse) == len(preset.scenes) * len(preset.fps)
    for row in inverse:
        assert 0 <= float(row["coverage90"]) <= 1
        assert (out / row["figure"]).exists()
        assert f"({row['figure']})" in (out / "inverse.md").read_text()
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


# ----------------------------------------------------------------------------- metrics
def bimodal_log_masses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Two types, as in collisions: log-masses around log 0.001 and log 0.4."""
    centre = np.where(rng.random(n) < 0.5, np.log(0.001), np.log(0.4))
    return centre + 0.1 * rng.standard_normal(n)


def test_perfect_samples_are_calibrated() -> None:
    rng = np.random.default_rng(0)
    n, s = 400, 64
    centre = np.where(rng.random(n) < 0.5, np.log(0.001), np.log(0.4))
    true = centre + 0.1 * rng.standard_normal(n)
    # each particle's samples from the same distribution its true value came from
    samples = centre + 0.1 * rng.standard_normal((s, n))
    m = inverse_metrics(true, samples)
    assert m["coverage50"] == pytest.approx(0.5, abs=0.08)
    assert m["coverage90"] == pytest.approx(0.9, abs=0.05)
    assert m["wasserstein1"] < 0.1
    assert m["welch_p"] > 0.01
    assert m["modes_true"] == 2 and m["modes_recovered"] == 2


def test_shifted_samples_are_not() -> None:
    rng = np.random.default_rng(1)
    true = bimodal_log_masses(rng, 400)
    samples = true[None, :] + 2.0 + 0.1 * rng.standard_normal((64, 400))
    m = inverse_metrics(true, samples)
    assert m["coverage50"] < 0.05 and m["coverage90"] < 0.05
    assert m["wasserstein1"] == pytest.approx(2.0, abs=0.1)
    assert m["welch_p"] < 1e-6
    assert m["modes_recovered"] == 0


def test_collapsed_samples_lose_a_mode() -> None:
    rng = np.random.default_rng(2)
    true = bimodal_log_masses(rng, 400)
    samples = np.log(0.4) + 0.1 * rng.standard_normal((32, 400))  # every particle "heavy"
    n_true, n_matched = recovered_modes(true, samples)
    assert (n_true, n_matched) == (2, 1)


def test_kde_modes_and_r2() -> None:
    grid = np.linspace(-5, 5, 501)
    values = np.concatenate([np.full(50, -2.0), np.full(50, 2.0)])
    values = values + 0.05 * np.random.default_rng(3).standard_normal(100)
    assert np.allclose(kde_modes(values, grid), [-2, 2], atol=0.1)
    x = np.arange(10.0)
    assert r2_score(x, x) == 1.0 and r2_score(np.full(10, x.mean()), x) == pytest.approx(0.0)
    assert np.isnan(r2_score(x, np.ones(10)))


def test_bad_sample_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="n_samples"):
        inverse_metrics(np.zeros(5), np.zeros((3, 4)))
