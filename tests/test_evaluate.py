"""Evaluation: the inverse model beside its references on small real datasets with an
untrained BGN (every metric is there, the force-law estimator reads the masses off the
frames); ``python -m bgn.evaluate`` on a tiny
trained run, the training run's test-phase rollouts, failed rollouts counted at the cap, and
bad input refused in one line."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from bgn.data.datamodule import ParticleDataModule
from bgn.eval.evaluate import evaluate_model, mass_figure, matched_frames
from bgn.eval.evaluate import main as evaluate_main
from bgn.rollout import evaluate_rollouts, rollout_starts, rollout_summary
from bgn.training.run import build, train
from tests.conftest import REPORT_RECORD, SMALL, TINY_RUN, compose_config
from tests.test_simulator import Oracle

TINY_BGN = ["model.hidden=8", "model.decoder_hidden=8", "model.flow_hidden=8",
            "model.mass_context=pairs"]


@pytest.mark.parametrize("scene", ["spring", "gravity_r2", "collisions"])
def test_inverse_evaluation_with_references(scene: str, tmp_path: Path,
                                            shared_data_dir: Path) -> None:
    cfg = compose_config("train", [f"dataset={scene}", *SMALL[scene], *TINY_BGN,
                                   f"paths.data_dir={shared_data_dir}", "figures=false",
                                   "val_rollout_steps=0"])
    datamodule, module = build(cfg)
    metrics, arrays = evaluate_model(module.eval(), datamodule.datasets["test"], max_frames=4,
                                     mass_frames=6, mass_samples=16, batch_size=3)
    for key in ("coverage50", "coverage_max_dev", "sbc_p", "tarp_atc", "info_gain",
                "sim_mass_rel_err", "prior/coverage90", "physical/relmass_r2_estimate"):
        assert np.isfinite(metrics[key]), key
    if scene == "collisions":  # the contact head's per-simulation impact solve beside the flow's
        assert np.isfinite(metrics["sim_mass_rel_err_flow"])
        # the type-only reference: its gain over the mixture is what the type tells (two
        # types 400x apart, half each: ln 2), and the model's gain over it is its own gain
        # less that, on the same particles
        assert metrics["type_prior/info_gain"] == pytest.approx(np.log(2), abs=1e-3)
        assert metrics["info_gain_over_type"] == pytest.approx(
            metrics["info_gain"] - metrics["type_prior/info_gain"], rel=1e-9, abs=1e-9)
        assert 0.4 < metrics["type_prior/coverage50"] < 0.6
        # the estimator falls back to the disc's type's law, so it is never worse than that
        # by much; its shares of discs estimated are counted
        assert metrics["physical/mass_rel_err"] < 2 * metrics["type_prior/mass_rel_err"] < 0.5
        assert 0 <= metrics["physical/identified"] <= metrics["physical/sim_identified"] <= 1
        assert "coverage_type" in arrays
        # per simulation through the impacts the model's own contact head sees (no
        # validation split given: the noise from the equations' own scatter)
        for key in ("sim_mass_rel_err", "coverage50", "info_gain", "info_gain_over_type",
                    "identified", "physical_sim_mass_rel_err", "physical_relmass_r2_estimate"):
            assert np.isfinite(metrics[f"impact_posterior/{key}"]), key
        assert metrics["impact_posterior/noise_from"] == "residuals"
    else:  # one mass law for every particle: the type says nothing, no such reference
        assert not any(k.startswith("type_prior/") for k in metrics)
        assert "info_gain_over_type" not in metrics
    if scene != "collisions":  # O(dt^2) finite differences of the adaptive integrator's frames
        assert metrics["physical/mass_rel_err"] < 0.01
        assert metrics["physical/identified"] == 1.0
        # a pair-force head: the masses its (here untrained) law fits, beside the references
        for key in ("mass_rel_err", "sim_mass_rel_err", "relmass_r2_estimate"):
            assert np.isfinite(metrics[f"learned_law/{key}"]), key
        # and per simulation, all its evaluated frames in one fit (no validation split given:
        # the free scale placed by the prior; gravity's law is physical)
        for key in ("sim_mass_rel_err", "coverage50", "info_gain", "relmass_r2_estimate"):
            assert np.isfinite(metrics[f"law_posterior/{key}"]), key
        assert metrics["law_posterior/scale"] == ("prior" if scene == "spring" else "physical")
    else:  # the impulse head has no pair law to read masses through
        assert not any(k.startswith(("learned_law/", "law_posterior/")) for k in metrics)
    if scene != "collisions":  # no contact head: no impacts to read
        assert not any(k.startswith("impact_posterior/") for k in metrics)
    assert mass_figure(arrays, tmp_path / "mass.png").stat().st_size > 0


# spring's pair force at unit masses, 2 (1 - r) (positive: repulsive), as a formula spec
SPRING_LAW = json.dumps([{"types": [0, 0], "terms": [
    {"kind": "const", "power": 0.0, "a": 2.0, "c": None},
    {"kind": "power", "power": 1.0, "a": -2.0, "c": None}]}])


def test_through_the_true_law_the_law_estimator_reads_the_relative_masses(
        shared_data_dir: Path) -> None:
    """The law estimator is the physical estimator with the model's law in place of the
    scene's: given the true law (a formula), its relative masses are nearly as exact (the
    one shift the law's free scale leaves is placed by the prior, not by the true masses: on
    a few particles that shift is loose, so the absolute error is not asserted here)."""
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], *TINY_BGN,
                                   f"paths.data_dir={shared_data_dir}", "figures=false",
                                   "val_rollout_steps=0", "model.law=formula",
                                   f"model.law_formula='{SPRING_LAW}'"])
    datamodule, module = build(cfg)
    metrics, _ = evaluate_model(module.eval(), datamodule.datasets["test"], max_frames=4,
                                mass_frames=6, mass_samples=4, batch_size=3)
    # the head fits each window from fewer accelerations than the estimator's stencil reads
    assert metrics["learned_law/relmass_r2_estimate"] > 0.995
    assert metrics["learned_law/relmass_r2_estimate"] == pytest.approx(
        metrics["physical/relmass_r2_estimate"], abs=5e-3)
    assert np.isfinite(metrics["learned_law/sim_mass_rel_err"])


def test_the_relmass_point_is_the_median_unless_a_draw_is_asked(shared_data_dir: Path) -> None:
    """``relmass_decode=median`` decodes Eq. 9-10 at the flow's base draw 0: the same for any
    seed; ``draw`` at a random posterior sample: it moves with the seed."""
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], *TINY_BGN,
                                   f"paths.data_dir={shared_data_dir}", "figures=false",
                                   "val_rollout_steps=0"])
    datamodule, module = build(cfg)
    test = datamodule.datasets["test"]

    def r2(decode: str, seed: int) -> float:
        metrics, _ = evaluate_model(module.eval(), test, max_frames=4, mass_frames=2,
                                    mass_samples=2, batch_size=4, seed=seed,
                                    relmass_decode=decode)
        return metrics["relmass_r2"]

    assert r2("median", 0) == r2("median", 1)
    assert r2("draw", 0) != r2("draw", 1)
    assert r2("draw", 0) != r2("median", 0)


# ----------------------------------------------------------------------------- the command
FAST_EVAL = ["rollout.steps=20", "max_frames=8", "mass_frames=4", "mass_samples=8",
             "batch_size=4", "progress=false"]


def evaluate_cfg(*overrides: str):
    return compose_config("evaluate", [*FAST_EVAL, *overrides])


def test_the_training_test_phase_reports_rollouts_beside_one_step(trained_run) -> None:
    run, metrics = trained_run
    record = json.loads((run / "metrics.json").read_text())["metrics"]
    for key in ("test/nmse", "test/rollout_error@10", "test/rollout_error@50",
                "test/rollout_error_median@50", "test/rollout_mse@50",
                "test/rollout_failed_share", "test/energy_error@50",
                "test/rollout_error@50_last", "test/rollout_error@50_linear"):
        assert np.isfinite(metrics[key]) and record[key] == metrics[key], key
    assert "test/rollout_error@50_predictability" not in metrics  # python -m bgn.evaluate's
    assert 0 <= metrics["test/rollout_failed_share"] <= 1


def test_the_test_phase_rollouts_can_be_skipped(tmp_path: Path, shared_data_dir: Path) -> None:
    metrics = train(compose_config("train", [*TINY_RUN, f"paths.data_dir={shared_data_dir}",
                                             f"paths.output_dir={tmp_path}",
                                             "+trainer.fast_dev_run=true",
                                             "test_rollouts=false"]))
    assert "test/nmse" in metrics
    assert not [k for k in metrics if "rollout" in k]


def test_the_report_repeats_the_one_step_error_the_run_printed(trained_run,
                                                                tmp_path: Path) -> None:
    """By default the command scores the frames the run's test phase scored (its
    dataset.test_samples, 17 of the ~110 here), so the NMSE a user saw at the end of
    training is the report's; a fixed count scores other frames."""
    run, metrics = trained_run
    out = evaluate_main(evaluate_cfg(f"ckpt={run}", "max_frames=null", "figures=false",
                                     f"out_dir={tmp_path / 'eval'}"))
    report = json.loads((out / "metrics.json").read_text())["metrics"]
    assert report["n_frames"] == 17
    assert report["nmse"] == pytest.approx(metrics["test/nmse"], rel=1e-4)
    assert report["median_relative_error"] == pytest.approx(
        metrics["test/median_relative_error"], rel=1e-4)


@pytest.mark.parametrize("given", ["run", "checkpoint"])
def test_the_command_writes_report_csv_json_and_figures(trained_run, tmp_path: Path,
                                                        given: str) -> None:
    run, _ = trained_run
    path = run if given == "run" else run / "checkpoints" / "best.ckpt"
    out = evaluate_main(evaluate_cfg(f"ckpt={path}", f"out_dir={tmp_path / 'eval'}"))
    assert out == tmp_path / "eval"
    record = json.loads((out / "metrics.json").read_text())
    metrics = record["metrics"]
    for key in ("mse", "nmse", "nmse_last_extrapolation", "rollout/pos_err_mean@10",
                "rollout/pos_err_median@10", "rollout/pos_mse_mean@all",
                "rollout/failed_share", "rollout/rollout_cap", "rollout/energy_err@10",
                "rollout_last/pos_err_mean@10", "rollout_linear/pos_err_mean@10",
                "predictability/pos_err_mean@10", "coverage50", "info_gain",
                "mass_calibration_scale50", "prior/coverage50", "physical/mass_rel_err",
                "lb/mse@5", "lb/mse@10", "lb/mse@20", "lb/mse@all", "lb/mse_std@5",
                "lb/sinkhorn", "lb/e_kin_mse", "lb/failed_share", "lb_last/mse@5",
                "lb_linear/sinkhorn", "lb_predictability/e_kin_mse"):
        assert np.isfinite(metrics[key]), key
    assert "lb/mse@50" not in metrics  # 20 steps (FAST_EVAL)
    # over the whole rollout LagrangeBench's MSE is bgn's (the same rollouts, the same cap)
    assert metrics["lb/mse@all"] == pytest.approx(metrics["rollout/pos_mse_mean@all"], rel=1e-9)
    assert metrics["lb/sinkhorn_rollouts"] == min(4, metrics["lb/rollouts"])
    assert record["provenance"]["checkpoint"] == str((run / "checkpoints" / "best.ckpt").resolve())
    assert record["provenance"]["run_config"] == str((run / ".hydra" / "config.yaml").resolve())
    assert record["provenance"]["calibration_split"] == "val"
    with open(out / "metrics.csv", newline="") as fh:
        rows = {r["metric"]: r["value"] for r in csv.DictReader(fh)}
    assert float(rows["nmse"]) == metrics["nmse"]
    # the model's rollouts, for what bgn cannot score itself (an engine's own energy): the
    # recorded start frames are the truth's, and their errors are the report's
    with np.load(out / "rollouts.npz") as saved:
        predicted, true = saved["predicted"], saved["true"]
        assert predicted.shape == true.shape and len(saved["sims"]) == len(predicted)
        np.testing.assert_array_equal(predicted[:, :2], true[:, :2])
        err = np.linalg.norm(predicted[:, 11] - true[:, 11], axis=-1).mean()
        assert err == pytest.approx(metrics["rollout/pos_err_mean@10"], rel=1e-6)
    report = (out / "report.md").read_text()
    for text in ("best.ckpt", record["provenance"]["run_config_hash"], "git commit",
                 "torch threads", "- libraries: torch ", "## Rollouts", "## Inverse model",
                 "rollout_error.png",
                 "## LagrangeBench metrics", "| mse@5 | mse@10 | mse@20 | mse@all | sinkhorn",
                 "## The learned pair law (bgn on spring)", "f(r) = ",
                 "![learned law, formula and truth](law.png)"):
        assert text in report, text  # BGN's default on spring: the pair-force head
    for figure in ("rollout_error.png", "energy_drift.png", "mass.png", "law.png"):
        assert (out / figure).stat().st_size > 0, figure
    assert not list(out.glob(".*tmp*"))  # nothing half-written


def test_rollout_masses_changes_the_rollouts_alone_and_the_label_says_so(trained_run,
                                                                       tmp_path: Path) -> None:
    """``rollout.masses=held`` on a checkpoint trained with the window's fit: one-step metrics
    as before (the first window's fit is the window's), the rollouts after the first step
    not, and the record's label says the masses are held."""
    run, _ = trained_run
    records = {}
    for masses in ("window", "held"):
        out = evaluate_main(evaluate_cfg(f"ckpt={run}", f"out_dir={tmp_path / masses}",
                                         f"rollout.masses={masses}", "figures=false",
                                         "rollout.steps=10"))
        records[masses] = json.loads((out / "metrics.json").read_text())
    window, held = (records[k]["metrics"] for k in ("window", "held"))
    assert window["nmse"] == held["nmse"]
    assert window["rollout/pos_err_mean@10"] != held["rollout/pos_err_mean@10"]
    assert "held" in records["held"]["provenance"]["model"]["label"]
    assert "held" not in records["window"]["provenance"]["model"]["label"]


def test_rollout_masses_is_refused_for_a_model_without_a_pair_force_head(
        shared_data_dir: Path) -> None:
    from bgn.eval.evaluate import set_rollout_masses
    from bgn.training.validate import ConfigError

    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], "model=gns",
                                   f"paths.data_dir={shared_data_dir}"])
    _, module = build(cfg)
    with pytest.raises(ConfigError, match="no pair-force head"):
        set_rollout_masses(module.model, "held")


def test_the_default_output_folder_is_beside_the_run(trained_run) -> None:
    run, _ = trained_run
    out = evaluate_main(evaluate_cfg(f"ckpt={run}", "split=val", "calibration_split=train",
                                     "figures=false", "rollout.steps=5"))
    assert out == run / "eval" / "val"
    assert (out / "report.md").is_file() and not list(out.glob("*.png"))


def test_a_failed_rollout_counts_at_the_cap_where_the_median_hides_it(
        shared_data_dir: Path) -> None:
    """Three test simulations, an exact model that blows up in the first: the median of the
    position error stays 0, the mean counts the failed rollout at 10 scene scales."""
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], "dataset.n_sims=3",
                                   f"paths.data_dir={shared_data_dir}"])
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, generate_workers=1)
    dm.prepare_data()
    dm.setup()
    ds = dm.datasets["test"]
    n = 20
    start = rollout_starts(ds, n)[0]
    out = rollout_summary(evaluate_rollouts(Oracle(ds, poison=(0, start + 2)), ds, n))
    x = ds.file.read("positions", (0, slice(start - 1, start + n + 1)))
    cap = 10 * np.linalg.norm(x - x.mean(axis=(0, 1)), axis=-1).max()
    assert out["test/rollout_failed_share"] == pytest.approx(1 / 3)
    assert out["test/rollout_error@10"] == pytest.approx(cap / 3, rel=1e-9)
    assert out["test/rollout_error_median@10"] < 1e-9      # the median alone would hide it
    assert out["test/rollout_mse@10"] == pytest.approx(cap**2 / 2 / 3, rel=1e-9)


def test_bad_input_is_one_line(trained_run, tmp_path: Path, capsys) -> None:
    run, _ = trained_run
    empty = tmp_path / "empty_run"
    empty.mkdir()
    foreign = tmp_path / "foreign.ckpt"
    ckpt = torch.load(run / "checkpoints" / "best.ckpt", weights_only=True)
    ckpt["hyper_parameters"]["model_config"]["name"] = "mystery"
    torch.save(ckpt, foreign)
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_text((run / ".hydra" / "config.yaml").read_text())
    for path, code, words in ((tmp_path / "nope", 2, "no such file"),
                              (empty, 2, "no checkpoint"),
                              (foreign, 1, "'mystery'")):
        with pytest.raises(SystemExit) as exit_:
            evaluate_main(evaluate_cfg(f"ckpt={path}"))
        err = capsys.readouterr().err
        assert exit_.value.code == code, path
        assert len(err.strip().splitlines()) == 1 and words in err, err
    for key, value, words in (("relmass_decode", "mean", "median"),
                              ("rollout.masses", "fixed", "held")):
        with pytest.raises(SystemExit) as exit_:
            evaluate_main(evaluate_cfg(f"ckpt={run}", f"{key}={value}"))
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and key in err and words in err, err


def test_a_larger_split_scores_more_simulations_the_runs_first(trained_run, tmp_path: Path,
                                                               capsys) -> None:
    """``sims=``: the scored split with more simulations, the run's first ones unchanged (each
    simulation a pure function of the seed, the split and its index), the training file the
    run's; on imported data, or a count below 1, one line."""
    from omegaconf import OmegaConf

    run, _ = trained_run
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir)
    dm.prepare_data()
    dm.setup()
    n = dm.datasets["test"].file.n_sims
    larger = dm.larger_split("test", n + 2)
    assert larger.file.n_sims == n + 2 and larger.file.path != dm.datasets["test"].file.path
    np.testing.assert_array_equal(larger.file.read("positions", n - 1),
                                  dm.datasets["test"].file.read("positions", n - 1))
    out = evaluate_main(evaluate_cfg(f"ckpt={run}", f"out_dir={tmp_path / 'eval'}",
                                     f"sims={n + 2}", "rollout.max_sims=1"))
    metrics = json.loads((out / "metrics.json").read_text())["metrics"]
    base = evaluate_main(evaluate_cfg(f"ckpt={run}", f"out_dir={tmp_path / 'base'}",
                                      "rollout.max_sims=1"))
    fewer = json.loads((base / "metrics.json").read_text())["metrics"]
    # the same frame count spread over more simulations: more distinct particles
    assert metrics["law_posterior/windows"] < fewer["law_posterior/windows"]
    # calibration_sims=: the calibration split enlarged the same way, said in the provenance
    calibrated = evaluate_main(evaluate_cfg(
        f"ckpt={run}", f"out_dir={tmp_path / 'calibrated'}", f"calibration_sims={n + 2}",
        "rollout.max_sims=1", "figures=false"))
    record = json.loads((calibrated / "metrics.json").read_text())["provenance"]
    assert record["sims"] == {"split": n, "calibration": n + 2}
    assert f"({n} simulations scored, {n + 2} calibrated on)" in (
        calibrated / "report.md").read_text()
    with pytest.raises(SystemExit) as exit_:
        evaluate_main(evaluate_cfg(f"ckpt={run}", "sims=0"))
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "sims" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(SystemExit) as exit_:
        evaluate_main(evaluate_cfg(f"ckpt={run}", "calibration_sims=-1"))
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and "calibration_sims" in err


def test_the_relmass_decode_recheck_writes_both_decodes_into_its_block(trained_run, tmp_path,
                                                                      monkeypatch) -> None:
    """``examples/recheck/relmass_decode.py`` on a run: both decodes evaluated on validation,
    each in its own report folder, and the seeds' table written into the results file's
    block (whatever else the file holds is kept)."""
    run, _ = trained_run
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples" / "recheck"))
    import relmass_decode

    results = tmp_path / "results.md"
    results.write_text("# Results\n\nkept\n")
    text = relmass_decode.main([str(run), "--out", str(tmp_path / "out"),
                                "--results-md", str(results)])
    rows = [line for line in text.splitlines() if line.startswith("| spring")]
    assert [row.split(" | ")[2] for row in rows] == ["median", "draw"]
    for decode in ("median", "draw"):
        metrics = json.loads((run / "eval" / f"val_relmass_decode_{decode}" / "metrics.json")
                             .read_text())
        assert metrics["provenance"]["split"] == "val"
        assert metrics["provenance"]["calibration_split"] == "train"
    written = results.read_text()
    assert "kept" in written and "<!-- generated:recheck_relmass_decode_val:begin -->" in written
    assert rows[0] in written and (tmp_path / "out" / "table.csv").exists()


def test_the_rollout_masses_recheck_evaluates_both_fits_of_the_same_checkpoint(
        trained_run, tmp_path, monkeypatch) -> None:
    """``examples/recheck/rollout_masses.py``: the same checkpoint rolled out on validation
    with the window's fit and with the held one, a row each, labelled by what it holds."""
    run, _ = trained_run
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "examples" / "recheck"))
    import rollout_masses

    text = rollout_masses.main([str(run), "--out", str(tmp_path / "out")])
    rows = [line.split(" | ") for line in text.splitlines() if line.startswith("| spring")]
    assert [row[2] for row in rows] == ["window", "held"]
    assert "held" in rows[1][1] and "held" not in rows[0][1]
    assert rows[0][3:] != rows[1][3:]  # the rollouts differ
    metrics = json.loads((run / "eval" / "val_masses_held" / "metrics.json").read_text())
    assert metrics["provenance"]["split"] == "val"
    assert metrics["provenance"]["calibration_split"] == "train"


def test_the_path_is_the_first_positional_argument() -> None:
    from bgn.training.validate import positional_override

    assert positional_override(["runs/a", "split=val"], "ckpt") == ["ckpt=runs/a", "split=val"]
    assert positional_override(["-cn", "evaluate", "r"], "ckpt") == ["-cn", "evaluate", "ckpt=r"]
    assert positional_override(["my run,1"], "ckpt") == ["ckpt='my run,1'"]
    assert positional_override(["a", "b"], "ckpt") == ["ckpt=a", "b"]  # Hydra refuses b


def test_the_command_line_refuses_a_missing_path(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-m", "bgn.evaluate", str(tmp_path / "nope")],
                          capture_output=True, text=True, cwd=tmp_path, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "nope" in done.stderr
    assert not list(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize("model", ["newton", "decoder"])
def test_the_report_reads_the_pair_law_of_a_pair_force_head(model: str, tmp_path: Path,
                                                            shared_data_dir: Path) -> None:
    """model=newton has a pair-force head: its formula (bgn.laws) and figure go into the
    report; BGN with the paper's decoder has none, and the report says so."""
    from bgn.eval.evaluate import law_text, report_text

    overrides = (["model=newton", "model.hidden=8"] if model == "newton"
                 else [*TINY_BGN, "model.dynamics=decoder"])
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"], *overrides,
                                   f"paths.data_dir={shared_data_dir}", "figures=false",
                                   "val_rollout_steps=0"])
    datamodule, module = build(cfg)
    text, figure = law_text(module.eval(), datamodule.datasets["train"], "law.png")
    record = REPORT_RECORD
    report = report_text(record, {}, ["rollout_error.png", "law.png"], text)
    if model == "newton":
        assert "## The learned pair law (newton on spring)" in text and "f(r) = " in text
        assert "![learned law, formula and truth](law.png)" in report
        assert figure is not None and len(figure.axes) >= 3
        assert "![law](law.png)" not in report           # shown once, in its section
    else:
        assert figure is None and "has no pair-force head" in report
        assert "f(r) = " not in report


def test_the_lagrangebench_metrics_take_the_source_periodic_box() -> None:
    """Imported data record which dimensions are periodic and the box: the metrics' minimum
    image reads that box's sides, inf along the others; built-in scenes have none."""
    from types import SimpleNamespace

    from bgn.rollout import lb_prefix, scene_period
    from bgn.sim.imported import ImportedScene

    scene = ImportedScene(dim=2, periodic=(True, False), bounds=((0.0, 2.0), (-1.0, 1.0)))
    assert scene_period(SimpleNamespace(scene=scene)).tolist() == [2.0, np.inf]
    assert scene_period(SimpleNamespace(scene=ImportedScene(dim=2))) is None
    assert scene_period(SimpleNamespace(scene=object())) is None
    assert [lb_prefix(k) for k in ("rollout", "rollout_last", "predictability")] \
        == ["lb", "lb_last", "lb_predictability"]


def test_an_auto_run_resolves_to_its_chosen_structure(tmp_path: Path) -> None:
    """``python -m bgn.evaluate <run>`` on a model.dynamics=auto run scores the structure
    that auto chose (``auto/auto.json``), with that candidate's own run config."""
    from bgn.training.checkpoints import resolve_run

    for name in ("decoder", "newton_source"):
        (tmp_path / "auto" / name / "checkpoints").mkdir(parents=True)
        (tmp_path / "auto" / name / "checkpoints" / "best.ckpt").write_bytes(b"")
        (tmp_path / "auto" / name / "train_config.yaml").write_text("{}")
    (tmp_path / "auto" / "auto.json").write_text(json.dumps({"choice": "newton_source"}))
    ckpt, run_dir, config = resolve_run(str(tmp_path))
    assert ckpt == tmp_path / "auto" / "newton_source" / "checkpoints" / "best.ckpt"
    assert config == tmp_path / "auto" / "newton_source" / "train_config.yaml"


def test_data_without_masses_build_no_inverse_model_and_score_no_masses(tmp_path: Path) -> None:
    """Imported data without masses: the model is built without the mass flow (nothing
    records what it would learn: docs/design.md#the-scene-record), so the evaluation reports
    no posterior and scores nothing against the stand-in unit masses."""
    from bgn.data import from_arrays
    from bgn.eval.evaluate import evaluate_model
    from tests.test_train import SMALL_MODELS

    rng = np.random.default_rng(0)
    walk = np.cumsum(rng.normal(scale=0.01, size=(5, 30, 4, 2)), axis=1)
    x = walk + rng.normal(size=(5, 1, 4, 2))
    from_arrays(x, 0.02, name="nomass", data_dir=tmp_path / "data",
                splits={"train": [0, 1, 2], "val": [3], "test": [4]})
    cfg = compose_config("train", [
        "dataset=imported", "dataset.name=nomass", f"paths.data_dir={tmp_path / 'data'}",
        f"paths.output_dir={tmp_path / 'out'}", "model=bgn", *SMALL_MODELS["bgn"],
        "model.dynamics=decoder", "rollout_steps=3", "val_rollout_steps=0"])
    datamodule, module = build(cfg)
    metrics, arrays = evaluate_model(module, datamodule.datasets["test"], max_frames=8,
                                     mass_frames=4, mass_samples=16, batch_size=2)
    assert module.model.heads == frozenset({"dynamics"})
    assert not any(k.startswith("posterior/") for k in metrics)
    assert not arrays and "coverage50" not in metrics and "relmass_r2" not in metrics


class _Split:
    """A split's shape alone: its simulations and its windows (``frames`` per simulation)."""

    def __init__(self, n_sims: int, frames: int) -> None:
        self.sims, self.frames_per_sim = list(range(n_sims)), frames

    def __len__(self) -> int:
        return len(self.sims) * self.frames_per_sim


def test_the_calibration_split_is_read_with_as_many_frames_per_simulation() -> None:
    """A posterior's noise is chosen on the calibration split with the scored split's frames
    per simulation, whatever the two splits' sizes (sims=, calibration_sims=)."""
    scored, indices = _Split(40, 100), list(range(0, 4000, 100))  # one frame per simulation
    for n_sims in (10, 40, 160):
        chosen = matched_frames(scored, _Split(n_sims, 100), indices)
        assert len(chosen) == n_sims  # one each
        assert sorted({i // 100 for i in chosen}) == list(range(n_sims))  # every simulation
    assert len(matched_frames(_Split(10, 100), _Split(40, 100), list(range(0, 1000, 25)))) \
        == 160  # four per simulation
    assert len(matched_frames(_Split(10, 5), _Split(10, 5), list(range(50)))) == 50  # all
