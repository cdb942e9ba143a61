"""The engine examples (examples/engines): each script at a tiny size writes the layout bgn's
importer reads, with finite values, and the engine's energy where it conserves one. Each test
skips when its engine is not installed (pip install -e ".[engines]")."""

import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

ENGINES = Path(__file__).resolve().parents[1] / "examples" / "engines"


def run(script: str, out: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    return subprocess.run([sys.executable, str(ENGINES / script), "--out", str(out), *args],
                          capture_output=True, text=True, env=env, timeout=300)


@pytest.fixture
def engine_energy(monkeypatch):
    monkeypatch.syspath_prepend(str(ENGINES))
    import engine_energy

    return engine_energy


def check_split(split: np.ndarray, n: int) -> None:
    assert split.shape == (n,)
    assert set(split.tolist()) == {"train", "val", "test"}


def test_rebound_nbody_plain_arrays(tmp_path, engine_energy):
    pytest.importorskip("rebound")
    out = tmp_path / "nbody"
    res = run("rebound_nbody.py", out, "--sims", "4", "--frames", "30", "--bodies", "3")
    assert res.returncode == 0, res.stderr
    with np.load(out / "nbody.npz") as f:
        assert set(f.files) == {"positions", "velocities", "masses", "dt", "split"}
        pos, vel, masses, dt = f["positions"], f["velocities"], f["masses"], float(f["dt"])
        check_split(f["split"], 4)
    assert pos.shape == vel.shape == (4, 30, 3, 3) and masses.shape == (4, 3)
    assert np.isfinite(pos).all() and np.isfinite(vel).all() and (masses > 0).all() and dt > 0
    # the stored velocities are the positions' time derivative
    fd = np.stack([engine_energy.frame_velocities(p, dt) for p in pos])
    np.testing.assert_allclose(fd[:, 2:-2], vel[:, 2:-2], atol=1e-4 * np.abs(vel).max())
    with np.load(out / "energy.npz") as e:
        energy, momentum = e["energy"], e["momentum"]
    assert energy.shape == (4, 30) and momentum.shape == (4, 30, 3)
    # IAS15 conserves the softened energy to round-off; the helper rebuilds the same number
    np.testing.assert_allclose(energy, energy[:, :1].repeat(30, 1), rtol=1e-9)
    again = engine_energy.rebound_energy(pos[0], vel[0], masses[0], 1.0, 0.1)["energy"]
    np.testing.assert_allclose(again, energy[0], rtol=1e-12)
    rec = json.loads((out / "engine.json").read_text())
    assert rec["engine"] == "rebound" and rec["params"]["softening"] == 0.1


def test_an_existing_output_is_kept_and_nothing_half_written(tmp_path):
    pytest.importorskip("rebound")
    out = tmp_path / "nbody"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    res = run("rebound_nbody.py", out, "--sims", "3", "--frames", "5")
    assert res.returncode != 0 and "--overwrite" in res.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["nbody"]
    assert [p.name for p in out.iterdir()] == ["mine.txt"]


def test_ase_morse_gas_lagrangebench_layout(tmp_path, engine_energy):
    pytest.importorskip("ase")
    out = tmp_path / "gas"
    res = run("ase_morse_gas.py", out, "--sims", "3", "--frames", "12", "--atoms", "16",
              "--burn-in", "10")
    assert res.returncode == 0, res.stderr
    meta = json.loads((out / "metadata.json").read_text())
    box = np.asarray(meta["bounds"])[:, 1]
    assert meta["periodic_boundary_conditions"] == [True, True] and meta["dim"] == 2
    assert meta["dt"] > 0 and meta["write_every"] >= 1 and meta["num_particles_max"] == 16
    assert meta["default_connectivity_radius"] < box.min() / 2
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        assert len(meta[key]) == 2 and np.isfinite(meta[key]).all()
    positions = {}
    for stem in ("train", "valid", "test"):
        with h5py.File(out / f"{stem}.h5", "r") as f:
            assert sorted(f) == [str(j).zfill(5) for j in range(len(f))] and len(f) >= 1
            for g in f.values():
                assert g["position"].shape == (12, 16, 2) and g["particle_type"].shape == (16,)
                p = g["position"][()]
                assert np.isfinite(p).all() and (p >= 0).all() and (p <= box).all()  # wrapped
            positions[stem] = np.stack([g["position"][()] for g in f.values()])
    with np.load(out / "energy.npz") as e:
        check_split(e["split"], 3)
        energy, index = e["energy"], e["index"]
        test_energy = energy[e["split"] == "test"][np.argsort(index[e["split"] == "test"])]
    # velocity Verlet keeps the energy up to a small fluctuation
    assert np.abs(energy - energy[:, :1]).max() < 0.02 * np.abs(energy).min()
    # the helper gives the engine's energy back from positions alone, inside the stencil
    again = engine_energy.dataset_energy(out, positions["test"], None, "test")
    for e_again, e_true in zip(again, test_energy):
        np.testing.assert_allclose(e_again["energy"][2:-2], e_true[2:-2], rtol=0.02)


def test_pymunk_granular_gns_layout(tmp_path):
    pytest.importorskip("pymunk")
    out = tmp_path / "granular"
    res = run("pymunk_granular.py", out, "--sims", "3", "--frames", "20", "--discs", "10")
    assert res.returncode == 0, res.stderr
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["dim"] == 2 and meta["dt"] > 0 and meta["sequence_length"] == 19
    train = []
    for stem in ("train", "valid", "test"):
        with np.load(out / f"{stem}.npz", allow_pickle=True) as f:
            assert f.files == [f"simulation_trajectory_{j}" for j in range(len(f.files))]
            for key in f.files:
                positions, types = f[key]
                assert positions.shape == (20, 10, 2) and positions.dtype == np.float32
                assert types.shape == (10,) and set(types.tolist()) == {0, 1}
                assert np.isfinite(positions).all()
                assert (positions > -0.01).all() and (positions < 1.01).all()  # in the box
                if stem == "train":
                    train.append(positions.astype(np.float64))
    vel = np.concatenate([np.diff(p, axis=0).reshape(-1, 2) for p in train])
    np.testing.assert_allclose(meta["vel_std"], vel.std(0), rtol=1e-6)  # from the train split
    with np.load(out / "energy.npz") as e:
        check_split(e["split"], 3)
        energy = e["energy"]
    assert np.isfinite(energy).all() and (energy[:, -1] < energy[:, 0]).all()  # dissipative


def test_summary_aggregates_seeds_and_keeps_failures(tmp_path, monkeypatch):
    """examples/engines/summary.py on two seeds' auto runs (files written by hand in the
    layout bgn.train and bgn.evaluate write): the mean over seeds, the candidates beside the
    winner, a failed share that is not hidden."""
    monkeypatch.syspath_prepend(str(ENGINES))
    import summary

    def write(path: Path, text: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)

    runs = []
    for seed, (err, failed) in enumerate(((0.01, 0.0), (0.03, 0.5))):
        run = tmp_path / f"s{seed}"
        write(run / ".hydra" / "config.yaml", f"seed: {seed}\ndataset:\n  name: gas\n")
        write(run / "auto" / "auto.json", json.dumps({
            "choice": "newton_source", "margin": 2.0,
            "protocol": {"horizon": 50, "balance": {"linear": 1e-9}},
            "candidates": [{"candidate": c, "admitted": True, "val_err@50": v, "wall_s": 5.0,
                            "train_s": 4.0}
                           for c, v in (("decoder", 0.2), ("newton_source", 0.1))]}))
        for cand, scale in (("newton_source", 1.0), ("decoder", 10.0)):
            write(run / "auto" / cand / "eval" / "test" / "metrics.json", json.dumps({
                "metrics": {"rollout/pos_err_mean@100": err * scale,
                            "rollout/pos_err_mean@50": err * scale / 2,
                            "rollout/failed_share": failed,
                            "rollout_last/pos_err_mean@100": 1.0,
                            "rollout_linear/pos_err_mean@100": 2.0}}))
        write(run / "auto" / "newton_source" / "metrics.json", json.dumps({  # bgn.train's
            "variant": {"label": "BGN + pair-force head", "given": [],
                        "supervision": {"masses": ["mass_nll", "relmass"]},
                        "physics": "central pair forces"}}))
        for key, worst in (("predicted", 0.02 * (seed + 1)), ("true", 1e-6)):
            write(run / f"energy_{key}.json", json.dumps({  # engine_energy.py --json
                "after": [10, 50, 100], "relative_change": [[0.0, 0.0, worst / 2],
                                                            [0.0, 0.0, worst]]}))
        runs.append(run)
    tests, choices = [], []
    for run in runs:
        rows, choice = summary.rows_of(run)
        tests += rows
        choices.append(choice)
    assert [r["model"] for r in tests[:2]] == ["chosen (newton)", "decoder (candidate)"]
    assert tests[0]["ratio @100"] == pytest.approx(0.01)
    # what each model was trained with and is given, from its run's record (none: blank)
    assert (tests[0]["trained with"], tests[0]["given at inference"]) == (
        "recorded masses (mass_nll, relmass)", "-")
    assert tests[1]["trained with"] == "" and tests[1]["steps"] is None
    assert tests[1]["budget s"] == 4.0  # a candidate's training, not auto's scoring of it
    md, _ = summary.table([r for r in tests if r["model"].startswith("chosen")],
                          ["data", "model"])
    assert "0.02 ± 0.01414 (0.01–0.03)" in md          # @100 over the two seeds
    assert "0.25 ± 0.3536 (0–0.5)" in md               # the failed share, not hidden
    md, _ = summary.table(choices, ["data"])
    assert "newton_source" in md and "| 2 |" in md
    # --results-md: the same tables, the command and the runs' evaluation commits, in the block
    for run in runs:
        path = run / "auto" / "decoder" / "eval" / "test" / "metrics.json"
        record = json.loads(path.read_text())
        path.write_text(json.dumps({**record, "provenance": {"git_commit": "a" * 40}}))
    results = tmp_path / "results.md"
    results.write_text("intro\n")
    text = summary.main([*map(str, runs), "--out", str(tmp_path / "out"),
                         "--results-md", str(results)])
    block = results.read_text()
    assert block.startswith("intro\n") and "<!-- generated:engines:begin -->" in block
    assert "python examples/engines/summary.py" in block and "aaaaaaaaaa (2)" in block
    assert "### rollouts" in block and text.split("## rollouts")[1].strip()[:200] in block
    # the engine's energy: the worst trajectory per seed, the recorded frames beside it,
    # kept out of the rollout tables
    energy = text.split("## energy")[1]
    assert ("| gas | chosen (newton) |  |  |  | 2 | 0 | 0 | 0.03 ± 0.01414 (0.02–0.04) |"
            in energy)
    assert "| gas | recorded frames |  |  |  | 2 | 0 | 0 | 1e-06 |" in energy
    rollouts = text.split("## rollouts")[1].split("##")[0]
    assert ("| gas | chosen (newton) | recorded masses (mass_nll, relmass) | - | central pair "
            "forces | 2 |") in rollouts
    assert "recorded frames" not in text.split("## energy")[0]


# ----------------------------------------------------------------------------- equal_time.py
def equal_time(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ENGINES / "equal_time.py"), *args],
                          capture_output=True, text=True, timeout=60)


def fake_bgn_run(run: Path, job_s: float | None, candidates: dict[str, tuple]) -> Path:
    """A BGN auto run folder with what equal_time.py reads: job_time.json (``job_s``; None:
    absent) and auto/auto.json's candidates (name: (steps, train_s[, wall_s]); its training
    alone trained all its steps; wall_s, its training and scoring, default train_s + 30)."""
    (run / "auto").mkdir(parents=True)
    if job_s is not None:
        (run / "job_time.json").write_text(json.dumps({"wall_s": job_s}))
    (run / "auto" / "auto.json").write_text(json.dumps({
        "choice": "decoder", "margin": 2.0, "protocol": {"horizon": 50},
        "candidates": [{"candidate": c, "admitted": True, "val_err@50": 0.1, "steps": s[0],
                        "train_steps": s[0], "train_s": s[1],
                        "wall_s": s[2] if len(s) > 2 else s[1] + 30, "status": "trained"}
                       for c, s in candidates.items()]}))
    return run


def test_equal_time_gives_a_baseline_the_steps_of_bgns_wall_time(tmp_path):
    run = fake_bgn_run(tmp_path / "rebound_s0", 300.0,
                       {"decoder": (400, 40.0), "gns": (400, 50.0), "cranmer_gn": (400, 80.0)})
    out = tmp_path / "gns.json"
    res = equal_time("steps", str(run), "gns", "--json", str(out))
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "2400"  # 400 steps / 50 s x 300 s
    # one line of reasoning for the baseline's log, and the record summary.py states
    assert res.stderr.count("\n") == 1 and "2400 steps" in res.stderr and "300.0 s" in res.stderr
    record = json.loads(out.read_text())
    assert (record["steps"], record["bgn_job_s"], record["steps_per_s"]) == (2400, 300.0, 8.0)
    assert equal_time("steps", str(run), "cranmer_gn").stdout.strip() == "1500"


def test_equal_time_rates_a_candidate_by_its_training_alone(tmp_path, monkeypatch):
    """A candidate's wall_s also counts auto's scoring of it (its validation rollouts, the
    law and the masses): the rate is its training's (train_steps over train_s), and a record
    without that time (a run from before it was recorded) is refused in one line."""
    monkeypatch.syspath_prepend(str(ENGINES))
    import equal_time as et

    run = fake_bgn_run(tmp_path / "run", 300.0, {"gns": (400, 50.0, 80.0)})
    record = et.equal_steps(run, "gns")
    assert (record["steps"], record["steps_per_s"], record["candidate_train_s"]) == (
        2400, 8.0, 50.0)                                # not 400 / 80 s x 300 s = 1500
    assert "in 50.0 s of training" in record["reason"]
    auto = run / "auto" / "auto.json"
    old = json.loads(auto.read_text())
    for c in old["candidates"]:
        del c["train_s"], c["train_steps"]
    auto.write_text(json.dumps(old))
    res = equal_time("steps", str(run), "gns")
    assert res.returncode == 1 and res.stdout == "" and res.stderr.count("\n") == 1
    assert "records no training time (train_s" in res.stderr and "Traceback" not in res.stderr


def test_equal_time_steps_follow_the_rate_and_the_job(tmp_path_factory, monkeypatch):
    """Property: the steps are the candidate's rate times the job's wall time (at least 1),
    and grow with it."""
    hypothesis = pytest.importorskip("hypothesis")
    st = hypothesis.strategies
    monkeypatch.syspath_prepend(str(ENGINES))
    import equal_time as et

    @hypothesis.settings(max_examples=40, deadline=None)
    @hypothesis.given(steps=st.integers(1, 10**5), wall=st.floats(0.5, 1e4),
                      job=st.floats(1.0, 1e5))
    def check(steps: int, wall: float, job: float) -> None:
        run = fake_bgn_run(tmp_path_factory.mktemp("run"), job, {"gns": (steps, wall)})
        got = et.equal_steps(run, "gns")["steps"]
        assert got == max(1, round(steps / wall * job))
        (run / "job_time.json").write_text(json.dumps({"wall_s": 2 * job}))
        assert et.equal_steps(run, "gns")["steps"] >= got

    check()


@pytest.mark.parametrize("job_s, candidates, model, names", [
    (None, {"gns": (400, 50.0)}, "gns", "job_time.json"),            # the job was not timed
    (300.0, {"gns": (400, 50.0)}, "cranmer_gn", "no candidate cranmer_gn"),
    (300.0, {"gns": (0, 50.0)}, "gns", "no rate"),                   # never trained
    (300.0, {"gns": (400, float("nan"))}, "gns", "no rate"),
])
def test_equal_time_refuses_a_run_without_the_record_in_one_line(tmp_path, job_s, candidates,
                                                                 model, names):
    run = fake_bgn_run(tmp_path / "run", job_s, candidates)
    out = tmp_path / "record.json"
    res = equal_time("steps", str(run), model, "--json", str(out))
    assert res.returncode == 1 and res.stdout == "" and not out.exists()
    assert res.stderr.count("\n") == 1 and names in res.stderr and str(run) in res.stderr
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize("record, names", [
    (json.dumps({"wall_s": 10.0}), "auto/auto.json"),   # a folder that is no auto run
    ("{truncated", "job_time.json: unreadable"),
    (json.dumps({"seconds": 10.0}), "job_time.json: unreadable"),
])
def test_equal_time_refuses_a_folder_that_is_no_timed_auto_run(tmp_path, record, names):
    (tmp_path / "job_time.json").write_text(record)
    res = equal_time("steps", str(tmp_path), "gns")
    assert res.returncode == 1 and res.stdout == "" and res.stderr.count("\n") == 1
    assert names in res.stderr and "Traceback" not in res.stderr


def test_equal_time_times_the_job_and_records_only_a_success(tmp_path):
    run = tmp_path / "run"
    make = f"import pathlib, time; time.sleep(0.3); pathlib.Path({str(run)!r}).mkdir()"
    res = equal_time("time", str(run), "--", sys.executable, "-c", make)
    assert res.returncode == 0, res.stderr
    record = json.loads((run / "job_time.json").read_text())
    assert 0.3 <= record["wall_s"] < 30 and "time.sleep(0.3)" in record["command"]
    failed = tmp_path / "failed"
    failed.mkdir()
    res = equal_time("time", str(failed), "--", sys.executable, "-c", "raise SystemExit(3)")
    assert res.returncode == 3 and list(failed.iterdir()) == []  # no budget from a failure


# ----------------------------------------------------------------------------- regenerate.sh
FAKE_PYTHON = """#!/usr/bin/env bash
# a stand-in for python: the BGN job and every evaluation succeed, a baseline's training fails
case "$1 $2" in
  "examples/engines/equal_time.py time") mkdir -p "$3" ;;
  "examples/engines/equal_time.py steps") echo '{"steps": 5}' > "$6"; echo 5 ;;
  "-m bgn.train") exit 1 ;;
esac
exit 0
"""


def regenerate(tmp_path: Path, **env: str) -> subprocess.CompletedProcess:
    """regenerate.sh with a stand-in ``python`` first on the PATH (nothing trains)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    (bin_dir / "python").write_text(FAKE_PYTHON)
    (bin_dir / "python").chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}",
           "OUT": str(tmp_path / "out"), "NAMES": "gas", "BASELINES": "gns", "JOBS": "1",
           "RESULTS_MD": str(tmp_path / "results.md"), **env}
    return subprocess.run(["bash", str(ENGINES / "regenerate.sh")], capture_output=True,
                          text=True, env=env, timeout=120)


def test_regenerate_refuses_seeds_without_the_one_that_gives_the_budget(tmp_path):
    """Every baseline's budget is the seed-0 BGN job's: SEEDS without 0 is refused in one
    line before anything runs."""
    res = regenerate(tmp_path, SEEDS="1 2")
    assert res.returncode == 2 and res.stderr.count("\n") == 1
    assert 'SEEDS="1 2" lacks seed 0' in res.stderr and "add 0 to SEEDS" in res.stderr
    assert not (tmp_path / "out").exists()


def test_regenerate_without_baselines_runs_the_bgn_jobs_alone(tmp_path):
    """BASELINES="" means none (not the default pair), and then no seed gives a budget."""
    res = regenerate(tmp_path, SEEDS="1", BASELINES="")
    out = tmp_path / "out"
    assert res.returncode == 0, res.stderr
    assert (out / "gas_s1" / "regenerate.done").exists()
    assert "gns" not in res.stdout and not list(out.glob("gas_*_s0*"))


def test_regenerate_a_failed_baseline_leaves_no_budget_record_behind(tmp_path):
    res = regenerate(tmp_path, SEEDS="0")
    out = tmp_path / "out"
    assert res.returncode != 0 and f"FAILED {out}/gas_gns_s0" in res.stdout, res.stdout
    assert (out / "gas_s0" / "regenerate.done").exists()  # the BGN job: done
    assert not (out / "gas_gns_s0.equal_time.json").exists()
    assert not (tmp_path / "results.md").exists()  # no tables from a failed set


def test_summary_states_each_baselines_budget(tmp_path, monkeypatch):
    """A baseline run with equal_time.py's record is labelled as given BGN's wall time, with
    that time beside its own; the winner's row carries its whole job's time; a run the cap
    cut has a row of its own."""
    monkeypatch.syspath_prepend(str(ENGINES))
    import summary

    metrics = {"metrics": {"rollout/pos_err_mean@100": 0.5, "rollout/failed_share": 0.0}}
    bgn = fake_bgn_run(tmp_path / "gas_s0", 300.0, {"gns": (400, 50.0)})
    (bgn / ".hydra").mkdir()
    (bgn / ".hydra" / "config.yaml").write_text("seed: 0\ndataset:\n  name: gas\n")
    (bgn / "auto" / "decoder" / "eval" / "test").mkdir(parents=True)
    (bgn / "auto" / "decoder" / "eval" / "test" / "metrics.json").write_text(
        json.dumps(metrics))
    base = tmp_path / "gas_gns_s0"
    (base / "eval" / "test").mkdir(parents=True)
    (base / "train_config.yaml").write_text("seed: 0\ndataset:\n  name: gas\nmodel:\n"
                                            "  name: gns\n")
    (base / "eval" / "test" / "metrics.json").write_text(json.dumps(metrics))
    (base / "metrics.json").write_text(json.dumps({"wall_time_s": 290.0}))
    import equal_time as et

    (base / "equal_time.json").write_text(json.dumps(et.equal_steps(bgn, "gns")))
    chosen = summary.rows_of(bgn)[0][0]
    assert (chosen["model"], chosen["BGN job s"]) == ("chosen (decoder)", 300.0)
    row = summary.rows_of(base)[0][0]
    assert (row["model"], row["budget s"], row["BGN job s"]) == (
        "gns (BGN's wall time)", 290.0, 300.0)
    (base / "equal_time.json").unlink()
    (base / "metrics.json").write_text(json.dumps({"wall_time_s": 290.0,
                                                   "budget": {"cut_by": "max_time"}}))
    row = summary.rows_of(base)[0][0]
    assert (row["model"], row["BGN job s"]) == (
        "gns (default budget) (cut by trainer.max_time)", None)


def test_the_engines_law_reads_the_masses_off_rebounds_frames(tmp_path, monkeypatch):
    """engine_masses.py's law is REBOUND's Plummer-softened gravity: bgn's gravity estimator
    reads the masses of REBOUND's own frames through it (to the frames' finite differences),
    and a law of another softening reads them worse."""
    pytest.importorskip("rebound")
    monkeypatch.syspath_prepend(str(ENGINES))
    from engine_masses import PlummerLaw

    from bgn.eval.mass_baselines import gravity_log_mass

    out = tmp_path / "nbody"
    assert run("rebound_nbody.py", out, "--sims", "3", "--frames", "40", "--bodies",
               "4").returncode == 0
    data = np.load(out / "nbody.npz")
    params = json.loads((out / "engine.json").read_text())["params"]
    x, masses = data["positions"][0], data["masses"][0]
    windows = np.stack([x[s:s + 8] for s in range(0, 32, 8)])
    right = gravity_log_mass(PlummerLaw(params["G"], params["softening"]), windows,
                             params["frame_dt"])
    wrong = gravity_log_mass(PlummerLaw(params["G"], 3 * params["softening"]), windows,
                             params["frame_dt"])
    err_right = np.abs(np.exp(right) / masses - 1)
    assert np.all(err_right < 0.01)
    assert np.median(np.abs(np.exp(wrong) / masses - 1)) > np.median(err_right)


def test_engine_law_reads_rebounds_force_off_the_engine(tmp_path, monkeypatch):
    """engine_law.py's engine force for REBOUND data is the engine's own Plummer-softened
    gravity (a leapfrog kick from rest), G and b from the dataset's engine.json."""
    pytest.importorskip("rebound")
    monkeypatch.syspath_prepend(str(ENGINES))
    import engine_law

    (tmp_path / "engine.json").write_text(json.dumps(
        {"engine": "rebound", "version": "test", "params": {"G": 2.0, "softening": 0.3}}))
    r = np.geomspace(0.05, 20.0, 25)
    force, text = engine_law.engine_force(tmp_path, r)
    assert "Plummer" in text
    np.testing.assert_allclose(force, -2.0 * r / (r**2 + 0.09) ** 1.5, rtol=1e-6)
