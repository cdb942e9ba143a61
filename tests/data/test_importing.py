"""Imported trajectories -> bgn's dataset files -> training, rollouts (bgn.data.importing)."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from bgn.data import from_arrays
from bgn.data.datamodule import ParticleDataModule
from bgn.data.files import DatasetFile, DatasetFileError
from bgn.data.formats import read_trajectories
from bgn.data.generate import ensure_splits
from bgn.data.importing import import_dataset
from bgn.data.raw import DataImportError
from bgn.data.spec import DatasetSpec
from bgn.model.noise import add_random_walk_noise
from bgn.rollout import rollout
from bgn.training.run import build, data_module, train
from bgn.training.unroll import advance
from bgn.training.validate import ConfigError, positional_override, validate_train
from tests.conftest import SMALL, compose_config
from tests.data.layouts import (
    write_arrays_h5,
    write_arrays_npz,
    write_gns_npz,
    write_lagrangebench,
    write_tfrecord,
)
from tests.test_train import SMALL_MODELS

ROOT = Path(__file__).resolve().parents[2]
T, N, D = 16, 6, 2
DT = 0.01


def _trajectory(rng: np.random.Generator, kinematic: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth (T, N, D) trajectory of N particles in (0.2, 0.8)^2 and its types (the first
    ``kinematic`` particles are type 3 and stand still)."""
    start = rng.uniform(0.3, 0.7, size=(N, D))
    velocity = rng.normal(scale=0.5, size=(N, D))
    times = np.arange(T)[:, None, None] * DT
    x = start + velocity * times + 0.5 * rng.normal(size=(N, D)) * times**2
    types = np.zeros(N, dtype=np.int64)
    types[:kinematic] = 3
    x[:, :kinematic] = start[:kinematic]
    return x, types


def _splits(seed: int = 0, kinematic: int = 0) -> dict[str, list]:
    rng = np.random.default_rng(seed)
    return {split: [_trajectory(rng, kinematic) for _ in range(n)]
            for split, n in (("train", 3), ("valid", 1), ("test", 1))}


META = {"dt": DT, "bounds": [[0.0, 1.0], [0.0, 1.0]], "dim": D, "sequence_length": T}


def _write(fmt: str, where: Path) -> Path:
    """A small dataset in layout ``fmt``."""
    if fmt == "gns-npz":
        return write_gns_npz(where / "gns", _splits(kinematic=2),
                             {**META, "default_connectivity_radius": 0.5})
    if fmt == "lagrangebench-h5":
        return write_lagrangebench(where / "lb", _splits(),
                                   {**META, "write_every": 1,
                                    "periodic_boundary_conditions": [False, False]})
    if fmt == "tfrecord":
        return write_tfrecord(where / "tf", _splits(kinematic=2), META)
    trajs = [t for ts in _splits().values() for t in ts]
    arrays = {"positions": np.stack([x for x, _ in trajs]), "dt": DT,
              "masses": np.random.default_rng(1).uniform(0.5, 2.0, size=(len(trajs), N)),
              "split": np.array(["train"] * 3 + ["val", "test"])}
    if fmt == "arrays-npz":
        return write_arrays_npz(where / "arrays.npz", **arrays)
    return write_arrays_h5(where / "arrays.h5", **arrays)


def _train_cfg(name: str | list[str], data_dir: Path, out: Path, model: str, *overrides: str):
    """A tiny training run on the import ``name`` (or, with ``name`` a list of overrides, on
    that dataset)."""
    dataset = ["dataset=imported", f"dataset.name={name}"] if isinstance(name, str) else name
    return compose_config("train", [
        *dataset, f"paths.data_dir={data_dir}",
        f"paths.output_dir={out}", f"model={model}", *SMALL_MODELS[model], "rollout_steps=3",
        "val_rollout_steps=4", "val_rollout_sims=1", "dataset.batch_size=8",
        "+trainer.fast_dev_run=true", "test=false",
        # imported data default to model.dynamics=auto (a study of its own, bgn/studies/auto.py)
        *(["model.dynamics=decoder"] if model == "bgn" else []), *overrides])


FORMATS = ["gns-npz", "lagrangebench-h5", "arrays-npz", "arrays-h5", "tfrecord"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_format_imports_trains_and_rolls_out(tmp_path, fmt):
    source = _write(fmt, tmp_path)
    raw = read_trajectories(source, allow_pickle=True)  # the test's own GNS files
    paths = import_dataset(raw, "tiny", tmp_path / "data")
    train_file = DatasetFile(paths["train"])
    assert train_file.n_sims == 3 and train_file.n_frames == T
    assert json.loads(train_file.attrs["source"])["format"] == fmt
    assert bool(train_file.attrs["masses_known"]) == fmt.startswith("arrays")
    kinematic = train_file.read("kinematic", ...)
    assert kinematic.sum() == (3 * 2 if fmt in ("gns-npz", "tfrecord") else 0)
    np.testing.assert_allclose(train_file.read("positions", 0), raw.splits["train"].positions[0])
    for model in ("bgn", "gns"):
        cfg = _train_cfg("tiny", tmp_path / "data", tmp_path / model, model)
        metrics = train(cfg)
        assert np.isfinite(metrics["train/loss"]), model
        if model == "bgn":  # the mass posterior is scored only against recorded masses
            assert ("val/relmass_r2" in metrics) == fmt.startswith("arrays")
        record = json.loads((tmp_path / model / "metrics.json").read_text())
        assert record["dataset"] == "imported"
        assert record["fps"] == pytest.approx(1 / DT)  # the files' rate, not the top-level fps
    datamodule, module = build(cfg)
    result = rollout(module.model, datamodule.datasets["test"], sim=0, n_steps=3)
    assert result["predicted"].shape == (4, N, D) and int(result["first_non_finite"]) == -1


def _small_spring(tmp_path: Path) -> tuple[DatasetSpec, dict[str, Path]]:
    cfg = compose_config("generate", ["dataset=spring", *SMALL["spring"],
                                      f"paths.data_dir={tmp_path / 'data'}"])
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    return spec, ensure_splits(spec, tmp_path / "data", workers=1, show_progress=False)


def test_a_generated_dataset_imported_from_arrays_gives_identical_inputs_and_metrics(tmp_path):
    spec, generated = _small_spring(tmp_path)
    files = {s: DatasetFile(p) for s, p in generated.items()}
    stack = {key: np.concatenate([f.read(key, ...) for f in files.values()])
             for key in ("positions", "velocities", "masses", "radii", "types")}
    counts = np.cumsum([0] + [f.n_sims for f in files.values()])
    splits = {s: list(range(counts[i], counts[i + 1])) for i, s in enumerate(files)}
    assert (stack["radii"] == 0).all()  # point masses: an import without radii has zeros
    from_arrays(stack["positions"], 1.0 / spec.fps, masses=stack["masses"],
                types=stack["types"], velocities=stack["velocities"],
                name="spring_copy", data_dir=tmp_path / "data", splits=splits)

    spring = ["dataset=spring", *SMALL["spring"]]

    def datasets(name):
        cfg = _train_cfg(name, tmp_path / "data", tmp_path / "run", "gns")
        dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, show_progress=False)
        dm.prepare_data()
        dm.setup()
        return dm.datasets

    original, imported = datasets(spring), datasets("spring_copy")
    for split in ("train", "val", "test"):
        a, b = original[split], imported[split]
        assert len(a) == len(b)
        for i in (0, len(a) // 2, len(a) - 1):
            ga, gb = a[i], b[i]
            for key in ("pos", "vel", "edge_index", "target", "mass", "edge_rel_log_mass",
                        "types", "radius"):
                assert torch.equal(getattr(ga, key), getattr(gb, key)), (split, i, key)
    stats_a, stats_b = original["train"].file.stats(), imported["train"].file.stats()
    for group in stats_a:
        if group != "contact":  # the true force magnitudes against unknown (zeros)
            for key in stats_a[group]:
                np.testing.assert_array_equal(stats_a[group][key], stats_b[group][key])
    # the same model on both: spring's scene defaults (conf/dataset_model/spring_gns.yaml)
    # are not an import's
    metrics = [train(_train_cfg(name, tmp_path / "data", tmp_path / f"run{i}", "gns",
                                "model.target_prior=none"))
               for i, name in enumerate([spring, "spring_copy"])]
    keys = {k for k in metrics[0] if k != "wall_time_s"}
    assert keys == {k for k in metrics[1] if k != "wall_time_s"}
    assert {k: metrics[0][k] for k in keys} == {k: metrics[1][k] for k in keys}


def test_bad_input_writes_nothing_and_an_existing_import_survives(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 1, size=(10, 12, 3, 2)) * 0.01 + rng.uniform(0, 1, size=(1, 1, 3, 2))
    from_arrays(x, 0.1, name="walk", data_dir=tmp_path / "data")
    before = {p.name: p.read_bytes() for p in (tmp_path / "data/imported/walk").iterdir()}
    bad = x.copy()
    bad[7, 5, 1, 0] = np.nan  # one trajectory, whichever split it falls in
    for name, overwrite in (("fresh", False), ("walk", True)):
        with pytest.raises(DataImportError, match="NaN|finite"):
            from_arrays(bad, 0.1, name=name, data_dir=tmp_path / "data", overwrite=overwrite)
    assert sorted(p.name for p in (tmp_path / "data/imported").iterdir()) == ["walk"]
    after = {p.name: p.read_bytes() for p in (tmp_path / "data/imported/walk").iterdir()}
    assert after == before
    with pytest.raises(DataImportError, match="frames"):  # shorter than one window
        from_arrays(x[:, :7], 0.1, name="short", data_dir=tmp_path / "data")
    assert not (tmp_path / "data/imported/short").exists()


def test_an_existing_import_is_replaced_only_with_overwrite(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(10, 12, 3, 2)) * 0.01 + rng.normal(size=(1, 1, 3, 2))
    paths = from_arrays(x, 0.1, name="a", data_dir=tmp_path)
    with pytest.raises(DataImportError, match="overwrite=true"):
        from_arrays(x + 1.0, 0.1, name="a", data_dir=tmp_path)
    np.testing.assert_array_equal(DatasetFile(paths["train"]).read("positions", 0)[0],
                                  x[np.sort(np.random.default_rng(0).permutation(10))[0], 0])
    first = json.loads(DatasetFile(paths["train"]).attrs["config"])["params"]["data_sha256"]
    from_arrays(x + 1.0, 0.1, name="a", data_dir=tmp_path, overwrite=True)
    second = json.loads(DatasetFile(paths["train"]).attrs["config"])["params"]["data_sha256"]
    assert first != second
    assert [p.name for p in tmp_path.joinpath("imported").iterdir()] == ["a"]  # no leftovers


def test_what_the_source_lacks_is_recorded_as_unknown(tmp_path):
    rng = np.random.default_rng(2)
    x = rng.normal(size=(6, 10, 4, 3)) * 0.01 + rng.normal(size=(1, 1, 4, 3))
    paths = from_arrays(x, 0.5, name="bare", data_dir=tmp_path, splits={
        "train": [0, 1, 2, 3], "val": [4], "test": [5]})
    f = DatasetFile(paths["train"])
    assert not f.attrs["masses_known"] and (f.read("masses", ...) == 1).all()
    assert (f.read("radii", ...) == 0).all() and (f.read("types", ...) == 0).all()
    assert f.meta.interaction == "unknown" and f.meta.graph == "full" and f.meta.box is None
    assert "accelerations" not in f.handle  # no law to take them from
    assert (f.stats()["contact"]["max"] == 0).all()
    # velocities: central differences inside, one-sided at the ends
    v = f.read("velocities", 0)
    np.testing.assert_allclose(v[3], (x[0, 4] - x[0, 2]) / 1.0)
    np.testing.assert_allclose(v[0], (x[0, 1] - x[0, 0]) / 0.5)


def test_periodic_positions_are_unwrapped_before_differences(tmp_path):
    t = np.arange(12) * 0.1
    x = np.zeros((3, 12, 2, 1))
    x[:, :, 0, 0] = (0.9 + 0.5 * t) % 1.0  # crosses x = 1 once
    x[:, :, 1, 0] = 0.3
    paths = from_arrays(x, 0.1, box=1.0, periodic=True, name="ring", data_dir=tmp_path,
                        splits={"train": [0], "val": [1], "test": [2]})
    f = DatasetFile(paths["train"])
    np.testing.assert_allclose(f.read("velocities", 0)[:, 0, 0], 0.5, atol=1e-12)
    assert f.meta.box is None  # a periodic box has no walls
    assert json.loads(f.attrs["config"])["params"]["periodic"] == [True]


def test_a_missing_import_is_refused_in_one_line_naming_the_command(tmp_path):
    cfg = _train_cfg("nowhere", tmp_path / "data", tmp_path / "run", "gns")
    with pytest.raises(ConfigError, match="python -m bgn.data.import"):
        validate_train(cfg)


def test_the_command_line_imports_and_reports_the_next_command(tmp_path):
    source = _write("lagrangebench-h5", tmp_path)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, "-m", "bgn.data.import", str(source), "name=lb",
                          f"paths.data_dir={tmp_path / 'data'}"], capture_output=True,
                         text=True, env=env, cwd=tmp_path, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "dataset=imported dataset.name=lb" in run.stdout and "6 particles" not in run.stderr
    assert "3 x 16 x 6 x 2" in run.stdout
    again = subprocess.run([sys.executable, "-m", "bgn.data.import", str(source), "name=lb",
                            f"paths.data_dir={tmp_path / 'data'}"], capture_output=True,
                           text=True, env=env, cwd=tmp_path, timeout=300)
    assert again.returncode != 0 and len(again.stderr.strip().splitlines()) == 1
    assert "overwrite=true" in again.stderr


def test_the_path_argument_becomes_an_override():
    assert positional_override(["/a b/c's", "name=x"], "path") == ["path='/a b/c\\'s'", "name=x"]
    assert positional_override(["name=x", "path=y"], "path") == ["name=x", "path=y"]


def test_import_files_pass_the_checks_on_open(tmp_path):
    rng = np.random.default_rng(3)
    x = rng.normal(size=(10, 12, 3, 2)) * 0.01 + rng.normal(size=(1, 1, 3, 2))
    paths = from_arrays(x, 0.1, name="c", data_dir=tmp_path)
    with h5py.File(paths["train"], "r+") as f:
        f["stats/velocity/std"][...] *= 1.5
    with pytest.raises(DatasetFileError, match="do not match.*from_arrays"):
        DatasetFile(paths["train"])


def test_kinematic_particles_are_inputs_never_predicted_or_scored(tmp_path):
    raw = read_trajectories(_write("gns-npz", tmp_path), allow_pickle=True)
    import_dataset(raw, "kin", tmp_path / "data")
    datamodule, module = build(_train_cfg("kin", tmp_path / "data", tmp_path / "run", "gns"))
    model, data = module.model, datamodule.datasets["train"]
    g = data[0]
    assert g.kinematic.tolist() == [True, True] + [False] * (N - 2)  # type 3: particles 0, 1
    out = model(g)
    moved = out.target.clone()
    moved[g.kinematic] += 100.0  # what the model says of kinematic particles is not scored
    assert torch.equal(model.loss_terms(g, out)["dynamics"],
                       model.loss_terms(g, type(out)(moved))["dynamics"])
    moved[~g.kinematic] = model.target_coder.encode(g)[~g.kinematic]  # exact where scored
    assert model.loss_terms(g, type(out)(moved))["dynamics"] == 0.0
    noisy = add_random_walk_noise(g, 1.0, "acceleration")  # training noise: free particles
    for key in ("pos", "vel", "target"):
        assert torch.equal(getattr(noisy, key)[g.kinematic], getattr(g, key)[g.kinematic])
        assert not torch.equal(getattr(noisy, key)[~g.kinematic], getattr(g, key)[~g.kinematic])
    unrolled = dataclasses.replace(g, future_vel=torch.zeros(N, 1, D))  # unrolled training
    ahead = advance(unrolled, torch.full_like(g.target, 100.0), "acceleration", 0)
    x = datamodule.datasets["train"].file.read("positions", int(g.sim))
    np.testing.assert_allclose(ahead.pos[g.kinematic].numpy(),
                               x[int(g.frame) + 1][g.kinematic.numpy()], atol=1e-6)
    result = rollout(model, datamodule.datasets["test"], sim=0, n_steps=5)
    kinematic = g.kinematic.numpy()
    np.testing.assert_array_equal(result["predicted"][:, kinematic], result["true"][:, kinematic])
    # the others are the model's own (not copied from the record)
    assert (result["predicted"][1:, ~kinematic] != result["true"][1:, ~kinematic]).all()


def test_checkpoints_record_the_import_and_its_data(tmp_path):
    from bgn.training.run import run_provenance

    rng = np.random.default_rng(4)
    x = rng.normal(size=(10, 12, 3, 2)) * 0.01 + rng.normal(size=(1, 1, 3, 2))
    cfg = _train_cfg("p", tmp_path, tmp_path / "run", "gns")
    from_arrays(x, 0.1, name="p", data_dir=tmp_path)
    first = run_provenance(cfg, data_module(cfg))
    from_arrays(x * 1.01, 0.1, name="p", data_dir=tmp_path, overwrite=True)
    second = run_provenance(cfg, data_module(cfg))
    assert first["scene"] == second["scene"] == "imported" and first["fps"] == 10.0
    assert first["scene_params"] != second["scene_params"]  # same name, other data


def test_dataset_imported_needs_a_name(tmp_path):
    cfg = compose_config("train", ["dataset=imported", f"paths.data_dir={tmp_path}"])
    with pytest.raises(ConfigError, match="dataset.name is missing"):
        validate_train(cfg)


def test_each_split_keeps_its_own_sizes(tmp_path):
    from bgn.data.raw import RawTrajectories, SplitArrays

    rng = np.random.default_rng(5)

    def part(s, t):
        return SplitArrays(rng.normal(size=(s, t, 3, 2)) * 0.01 + rng.normal(size=(1, 1, 3, 2)))

    raw = RawTrajectories({"train": part(4, 20), "val": part(2, 12), "test": part(1, 9)}, 0.5)
    import_dataset(raw, "sizes", tmp_path)
    cfg = _train_cfg("sizes", tmp_path, tmp_path / "run", "gns")
    datamodule = data_module(cfg)
    datamodule.setup()
    lengths = {s: (d.file.n_sims, d.file.n_frames, len(d)) for s, d in
               datamodule.datasets.items()}
    assert lengths == {"train": (4, 20, 4 * 13), "val": (2, 12, 2 * 5), "test": (1, 9, 2)}
    assert datamodule.dt == 0.5
    with pytest.raises(ConfigError, match="test split"):  # 9 frames: history 7 needs 10
        validate_train(_train_cfg("sizes", tmp_path, tmp_path / "run", "gns",
                                  "dataset.history=7"))


def test_radii_by_type_gives_the_discs_their_radii_and_contact_metrics(tmp_path):
    from bgn.data.importing import radii_from_types, validate_import
    from bgn.rollout import evaluate_rollouts

    raw = read_trajectories(_write("lagrangebench-h5", tmp_path))
    for part in raw.splits.values():          # two types of disc
        part.types = np.tile(np.arange(N) % 2, (len(part.positions), 1))
    paths = import_dataset(radii_from_types(raw, [0.02, 0.03]), "discs", tmp_path / "data")
    radii, types = (DatasetFile(paths["test"]).read(k, ...) for k in ("radii", "types"))
    np.testing.assert_array_equal(radii, np.where(types == 0, 0.02, 0.03))
    cfg = _train_cfg("discs", tmp_path / "data", tmp_path / "run", "gns")
    datamodule, module = build(cfg)
    metrics = evaluate_rollouts(module.model, datamodule.datasets["test"], n_steps=3,
                                references=False)
    assert {"rollout/speed_w1_type0", "rollout/speed_w1_type1",
            "rollout/collision_rate_ratio"} <= set(metrics)
    # without radii, no contact metrics
    plain = import_dataset(raw, "plain", tmp_path / "data")
    assert not DatasetFile(plain["test"]).read("radii", ...).any()
    # bad input: each one error naming the fix
    with pytest.raises(DataImportError, match="one radius per type"):
        radii_from_types(raw, [0.02])
    with pytest.raises(DataImportError, match="records its own radii"):
        radii_from_types(radii_from_types(raw, [0.02, 0.03]), [0.02, 0.03])
    for bad in ([], [0.02, -1.0], [float("nan")]):
        with pytest.raises(ConfigError, match="radii_by_type"):
            validate_import({"path": "x", "name": "discs", "target": "acceleration",
                             "radii_by_type": bad})
