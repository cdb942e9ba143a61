"""examples/charges/make.py: charged bodies of hidden masses in the plain-arrays layout, the
truth kept beside the file, and the file imported as a user's would be."""

from __future__ import annotations

import csv
import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bgn.eval.law_posterior import Spread
from bgn.sim.nbody import NBodyScene

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "charges" / "make.py"


def test_the_charge_data_hide_masses_and_charges_and_follow_the_charged_law(tmp_path) -> None:
    out = tmp_path / "charges"
    res = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), "--sims", "4",
                          "--frames", "40"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    data = np.load(out / "charges.npz")
    assert set(data.files) == {"positions", "dt", "split"}  # nothing hidden in the file
    assert data["positions"].shape == (4, 40, 4, 2)
    assert set(data["split"].tolist()) == {"train", "val", "test"}
    truth = np.load(out / "_hidden" / "truth.npz")
    assert truth["masses"].shape == truth["charges"].shape == (4, 4)
    assert (truth["masses"] > 0).all() and (truth["charges"] < 0).any() \
        and (truth["charges"] > 0).any()
    # the recorded motion is the charged law's: finite differences against its accelerations
    x, dt = data["positions"][0], float(data["dt"])
    scene = NBodyScene("r2")
    fd = (x[2:] - 2 * x[1:-1] + x[:-2]) / dt**2
    law = scene.accelerations(x[1:-1], truth["masses"][0], truth["charges"][0])
    assert np.median(np.abs(fd - law)) < 0.05 * np.median(np.abs(law))
    assert json.loads((out / "make.json").read_text())["params"]["bodies"] == 4
    # a second run into the same folder is refused without --overwrite, and keeps the data
    again = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out)],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode != 0 and "--overwrite" in again.stderr
    assert np.array_equal(np.load(out / "charges.npz")["positions"], data["positions"])


def test_a_simulations_frames_identify_its_masses_and_charge_signs_with_the_true_law(
        tmp_path) -> None:
    """identify.py on small data: pooled over each simulation's frames, the fit with the true
    law recovers the relative masses and every clear charge's sign (the best a learned law can
    reach); its table is written."""
    data, out = tmp_path / "charges", tmp_path / "identify"
    for cmd in ([str(SCRIPT), "--out", str(data), "--sims", "5", "--frames", "160"],
                [str(SCRIPT.parent / "identify.py"), str(data), "--out", str(out)]):
        res = subprocess.run([sys.executable, *cmd], capture_output=True, text=True,
                             timeout=300)
        assert res.returncode == 0, res.stderr
    rows = {r["fit"]: r for r in csv.DictReader(open(out / "identify.csv"))}
    pooled = rows["per simulation"]
    assert float(pooled["identified"]) == 1.0
    assert float(pooled["log-mass R^2"]) > 0.99
    assert float(pooled["charge signs right"]) == 1.0
    assert float(pooled["charge R^2"]) > 0.99
    assert "per window" in rows and (out / "identify.md").exists()
    resolved = rows["per simulation, frames turning < 0.02"]  # frames a pair turns fast in: out
    assert float(resolved["charge signs right"]) == 1.0


def test_a_fits_posterior_misses_are_zero_at_the_truth_and_its_coverage_counts_them() -> None:
    """score.py's posterior: the true couplings (``k = q / m``, ``c`` the charges at unit rms,
    in any global sign) miss nothing; a simulation with a particle whose ``k`` came out 0 (its
    own accelerations all left out) has no masses but keeps its charges, and a simulation
    whose fit failed (NaN) is left out of the charges' scores."""
    spec = importlib.util.spec_from_file_location("charges_score",
                                                  SCRIPT.with_name("score.py"))
    score = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(score)
    scores, coverage, misses = score.scores, score.coverage, score.misses

    rng = np.random.default_rng(0)
    masses = np.exp(rng.normal(size=(3, 4)))
    charges = rng.choice([-1.0, 1.0], (3, 4)) * np.exp(0.5 * rng.normal(size=(3, 4)))
    c = -charges / np.sqrt((charges ** 2).mean(1, keepdims=True))       # the other sign
    k = c / masses
    got = misses(k, c, np.full_like(k, 0.01), np.full_like(c, 0.01), masses, charges)
    assert np.allclose(got["log-mass"][0], 0) and np.allclose(got["charge"][0], 0)
    miss, sd = np.array([0.0, 0.5, 2.0, np.nan]), np.ones(4)
    # two simulations of two particles: |z| 0 and 0.5 within, 2 without, one not identified;
    # resampling the simulations gives any share from none (the second twice) to all
    share, low, high = coverage(miss, sd, Spread(), 0.5, 2, rng)
    assert (share, low, high) == (pytest.approx(2 / 3), 0.0, 1.0)
    k[1, 2] = 0.0                     # no mass for simulation 1, its charges still read
    c[2] = np.nan                     # simulation 2's fit failed
    k[2] = np.nan
    table = scores(k, c, masses, charges, 0.2)
    assert table["identified"] == pytest.approx(1 / 3)
    assert table["charges fitted"] == pytest.approx(2 / 3)
    assert table["charge signs right"] == 1.0 and table["charge R^2"] == pytest.approx(1.0)
