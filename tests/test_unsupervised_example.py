"""examples/unsupervised/summary.py: one row per run from its evaluation (what it was trained
with, the law posterior's figures), and a run not yet evaluated named in one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "unsupervised" / "summary.py"


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True,
                          text=True, timeout=120)


def test_the_table_reads_each_runs_evaluation(tmp_path: Path) -> None:
    folder = tmp_path / "spring_s0" / "eval400"
    folder.mkdir(parents=True)
    metrics = {"law_posterior/relmass_r2_estimate": 0.99, "law_posterior/scale": "prior",
               "law_posterior/sim_mass_rel_err": 0.05, "law_posterior/coverage50": 0.5,
               "law_posterior/coverage90": 0.9, "law_posterior/tail_share": 0.2,
               "law_posterior/tail_width": 4.0, "nmse": 1e-5}
    record = {"provenance": {"model": {"supervision": {"pair forces": ["contact"]}}},
              "metrics": metrics}
    (folder / "metrics.json").write_text(json.dumps(record))
    res = run(str(tmp_path / "spring_s0"))
    assert res.returncode == 0, res.stderr
    row = res.stdout.strip().splitlines()[-1]
    assert row.startswith("| spring_s0 | pair forces (contact) | learned law | 0.99 | 0.05 |")
    assert "| prior |" in row and "| 0.5 / 0.9 |" in row and "| 0.2 x 4 |" in row


def test_a_run_with_an_impulse_head_reads_its_impact_posterior(tmp_path: Path) -> None:
    folder = tmp_path / "collisions_s0" / "eval400"
    folder.mkdir(parents=True)
    metrics = {"impact_posterior/sim_mass_rel_err": 0.01,
               "impact_posterior/info_gain_over_type": 2.5,
               "impact_posterior/coverage50": 0.4, "impact_posterior/coverage90": 0.8}
    (folder / "metrics.json").write_text(json.dumps({"provenance": {}, "metrics": metrics}))
    res = run(str(tmp_path / "collisions_s0"))
    assert res.returncode == 0, res.stderr
    row = res.stdout.strip().splitlines()[-1]
    assert "| contact head's impacts |" in row and "| 0.01 |" in row
    assert "| 2.5 |" in row and "| 0.4 / 0.8 |" in row


def test_a_run_without_its_evaluation_is_named(tmp_path: Path) -> None:
    res = run(str(tmp_path), "--eval", "elsewhere")
    assert res.returncode == 2 and "no elsewhere/metrics.json" in res.stderr
    assert "Traceback" not in res.stderr
