"""examples/fluids/bgn_rollouts.py: bgn's rollouts of a LagrangeBench-layout test split start
from the same six frames LagrangeBench's models are given and cover the same frames.

(The engine and peer scripts of examples/fluids run in their own environment, not here.)"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import h5py
import numpy as np
import pytest

from bgn.data.datamodule import ParticleDataModule
from tests.conftest import TINY_RUN, compose_config

SCRIPT = Path(__file__).resolve().parents[1] / "examples" / "fluids" / "bgn_rollouts.py"


def load_script():
    spec = importlib.util.spec_from_file_location("bgn_rollouts", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def six_frame_run(shared_data_dir: Path, tmp_path_factory) -> Path:
    """The tiny run with a window of six frames (history 4), LagrangeBench's input."""
    from omegaconf import OmegaConf

    from bgn.training.run import train

    run = tmp_path_factory.mktemp("run6")
    cfg = compose_config("train", [*TINY_RUN, "dataset.history=4",
                                   f"paths.data_dir={shared_data_dir}", f"paths.output_dir={run}"])
    train(cfg)
    (run / ".hydra").mkdir()
    (run / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    return run


@pytest.fixture(scope="module")
def lagrangebench_folder(six_frame_run: Path, shared_data_dir: Path, tmp_path_factory) -> Path:
    """Two test trajectories of the tiny run's scene, written in LagrangeBench's layout."""
    from omegaconf import OmegaConf

    cfg = OmegaConf.load(six_frame_run / ".hydra" / "config.yaml")
    dm = ParticleDataModule(cfg.dataset, cfg.fps, shared_data_dir)
    dm.prepare_data()
    dm.setup()
    test = dm.datasets["test"]
    folder = tmp_path_factory.mktemp("lagrangebench")
    with h5py.File(folder / "test.h5", "w") as f:
        for i in range(2):
            pos = test.file.read("positions", i)[:30]
            g = f.create_group(f"{i:05d}")
            g.create_dataset("position", data=pos.astype(np.float32))
            g.create_dataset("particle_type", data=np.zeros(pos.shape[1], dtype=np.int64))
    return folder


def test_the_rollouts_start_from_the_six_given_frames_and_cover_the_rest(
        six_frame_run: Path, lagrangebench_folder: Path, tmp_path) -> None:
    run = six_frame_run
    out = tmp_path / "rollouts.npz"
    assert load_script().main([str(run), str(lagrangebench_folder), "--out", str(out)]) == 0
    r = np.load(out)
    with h5py.File(lagrangebench_folder / "test.h5", "r") as f:
        truth = np.stack([f[k]["position"][()] for k in sorted(f)])
    assert r["predicted"].shape == r["truth"].shape == truth.shape
    np.testing.assert_array_equal(r["truth"], truth)
    np.testing.assert_array_equal(r["predicted"][:, :6], truth[:, :6])   # given, not predicted
    assert np.isfinite(r["predicted"]).all()
    assert not np.array_equal(r["predicted"][:, 6:], truth[:, 6:])        # predicted, not copied
    assert int(r["start"]) == 5 and float(r["seconds_per_frame"]) > 0


def test_a_missing_split_or_a_longer_window_is_one_clear_error(
        trained_run, lagrangebench_folder: Path, tmp_path, capsys) -> None:
    run, _ = trained_run                                  # history 5: a window of 7 frames
    with pytest.raises(SystemExit):
        load_script().main([str(run), str(tmp_path), "--out", str(tmp_path / "r.npz")])
    assert "no test.h5" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        load_script().main([str(run), str(lagrangebench_folder), "--out", str(tmp_path / "r.npz")])
    assert "reads 7 frames, more than the 6" in capsys.readouterr().err
    assert not (tmp_path / "r.npz").exists()


def test_the_reference_keeps_each_particles_last_velocity_across_the_periodic_box(
        tmp_path) -> None:
    """Uniform motion through a periodic box: the constant-velocity reference is exact, the
    frames that wrap around included."""
    import json

    spec = importlib.util.spec_from_file_location(
        "reference_rollouts", SCRIPT.parent / "reference_rollouts.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rng = np.random.default_rng(0)
    x0, v = rng.random((5, 2)), rng.normal(0.0, 0.05, (5, 2))
    truth = np.mod(x0 + np.arange(20)[:, None, None] * v, 1.0)
    folder = tmp_path / "uniform"
    folder.mkdir()
    (folder / "metadata.json").write_text(json.dumps(
        {"bounds": [[0.0, 1.0], [0.0, 1.0]], "periodic_boundary_conditions": [True, True]}))
    with h5py.File(folder / "test.h5", "w") as f:
        g = f.create_group("00000")
        g.create_dataset("position", data=truth)
        g.create_dataset("particle_type", data=np.zeros(5, dtype=np.int64))
    out = tmp_path / "reference.npz"
    assert module.main([str(folder), "--out", str(out)]) == 0
    predicted = np.load(out)["predicted"][0]
    offset = predicted - truth
    np.testing.assert_allclose(offset - np.round(offset), 0.0, atol=1e-5)   # up to whole boxes
    assert np.abs(offset).max() > 0.5                                      # some did wrap


def test_the_speed_table_finds_where_the_measured_scalings_cross(tmp_path):
    """speed.py's table: seconds per unit simulated time from each side's rows, power fits in
    logs, the count where they cross; a one-count case takes another's exponents."""
    import json

    spec = importlib.util.spec_from_file_location("speed", SCRIPT.with_name("speed.py"))
    speed = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(speed)
    n = np.array([2500, 10000, 22500])
    engine = [{"particles": int(k), "dt": 1e-3, "seconds_per_step": 1e-7 * k} for k in n]
    learned = [{"particles": int(k), "dt_frame": 0.1, "seconds_per_frame": 1e-2 * k ** 0.5}
               for k in n]
    (tmp_path / "tgv_speed_engine.json").write_text(json.dumps({"rows": engine}))
    (tmp_path / "tgv_speed_bgn.json").write_text(json.dumps({"rows": learned}))
    for seed, mse in enumerate((1e-3, 3e-3)):
        (tmp_path / f"tgv_bgn_s{seed}").mkdir()
        (tmp_path / f"tgv_bgn_s{seed}" / "score.json").write_text(json.dumps({"mse20": mse}))
    # engine 1e-4 N, bgn 0.1 N^0.5 per unit time: equal at N = 1e6, bgn cheaper above
    text = speed.table(tmp_path, "tgv", None)
    assert "1,000,000 particles (bgn cheaper above)" in text and "over 2 seeds" in text
    assert "| 2500 | 0.25 | 5 | 0.05 |" in text
    for ext in ("md", "csv", "png"):
        assert (tmp_path / f"tgv_speed.{ext}").is_file()
    # one count, the tgv exponents: the same costs at 2500 particles give the same crossover
    (tmp_path / "dam_speed_engine.json").write_text(json.dumps({"rows": engine[:1]}))
    (tmp_path / "dam_speed_bgn.json").write_text(json.dumps({"rows": learned[:1]}))
    text = speed.table(tmp_path, "dam", "tgv")
    assert "1,000,000 particles (bgn cheaper above) (scaling exponents measured on tgv)" in text
