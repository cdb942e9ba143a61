"""Generation is deterministic, fps-consistent, cached by parameters and physically sound."""

import warnings

import h5py
import numpy as np
import pytest

from bgn.data.edges import radius_graph
from bgn.data.generate import (
    ALIASED_WARN,
    aliased_share,
    ensure_dataset,
    generate_file,
    simulate_one,
)
from bgn.data.spec import DatasetSpec
from bgn.train.generate import main

SCENES = ["spring", "gravity_r1", "gravity_r2", "collisions"]


def _arrays(path):
    with h5py.File(path, "r") as f:
        return {k: f[k][...] for k in f if isinstance(f[k], h5py.Dataset)}


@pytest.mark.slow  # a pool of two spawned simulation processes per scene
@pytest.mark.parametrize("scene", SCENES)
def test_same_seed_same_bits_whatever_the_workers(small_cfg, tmp_path, scene):
    cfg = small_cfg(scene)
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    one = _arrays(ensure_dataset(spec, tmp_path / "w1", workers=1))
    two = _arrays(ensure_dataset(spec, tmp_path / "w2", workers=2))
    assert one.keys() == two.keys()
    for name in one:
        assert np.array_equal(one[name], two[name]), name


@pytest.mark.parametrize("scene", SCENES)
def test_fps10_is_every_fifth_fps50_frame(small_cfg, scene):
    cfg50 = small_cfg(scene, "fps=50", "dataset.n_frames=50")
    cfg10 = small_cfg(scene, "fps=10", "dataset.n_frames=10")
    f50 = _arrays(ensure_dataset(DatasetSpec.from_config(cfg50.dataset, 50, "val"),
                                 cfg50.paths.data_dir, workers=1))
    f10 = _arrays(ensure_dataset(DatasetSpec.from_config(cfg10.dataset, 10, "val"),
                                 cfg10.paths.data_dir, workers=1))
    for name in ("positions", "velocities"):
        assert np.array_equal(f10[name], f50[name][:, ::5]), name
    for name in ("masses", "radii", "types"):
        assert np.array_equal(f10[name], f50[name]), name


def test_cache_key_follows_parameters_and_splits(small_cfg):
    base = small_cfg("spring")
    spec = DatasetSpec.from_config(base.dataset, 50, "train")
    changed = DatasetSpec.from_config(small_cfg("spring", "dataset.softening=0.02").dataset,
                                      50, "train")
    loader_only = DatasetSpec.from_config(small_cfg("spring", "dataset.batch_size=7").dataset,
                                          50, "train")
    assert spec.filename() != changed.filename()
    assert spec.filename() == loader_only.filename()
    assert len({spec.with_split(s).filename() for s in ("train", "val", "test")}) == 3
    assert spec.filename() != DatasetSpec.from_config(base.dataset, 10, "train").filename()


def test_splits_are_different_simulations(small_cfg):
    cfg = small_cfg("spring")
    spec = DatasetSpec.from_config(cfg.dataset, 50, "train")
    a = simulate_one(spec, 0)
    b = simulate_one(spec.with_split("test"), 0)
    assert not np.allclose(a.positions[0], b.positions[0])
    assert np.array_equal(simulate_one(spec, 1).positions, simulate_one(spec, 1).positions)


def test_bad_config_values_are_named(small_cfg):
    cfg = small_cfg("spring")
    with pytest.raises(ValueError, match="fps"):
        DatasetSpec.from_config(cfg.dataset, -5, "train")
    with pytest.raises(ValueError, match="n_sims"):
        DatasetSpec.from_config(small_cfg("spring", "dataset.n_sims=0").dataset, 50, "train")
    with pytest.raises(ValueError, match="no_such_param"):
        DatasetSpec.from_config(small_cfg("spring", "+dataset.no_such_param=1").dataset,
                                50, "train")


def test_every_recorded_contact_is_a_candidate_edge(small_cfg):
    cfg = small_cfg("collisions")
    path = ensure_dataset(DatasetSpec.from_config(cfg.dataset, cfg.fps, "train"),
                          cfg.paths.data_dir, workers=1)
    with h5py.File(path, "r") as f:
        x, radii, contacts = f["positions"][...], f["radii"][...], f["contacts"][...]
        margin = f.attrs["margin"]
    assert len(contacts) > 0
    for s, t, i, j in contacts:
        edges = radius_graph(x[s, t], radii=radii[s], margin=margin)
        assert ((edges[0] == i) & (edges[1] == j)).any()


def _margin(path) -> float:
    with h5py.File(path, "r") as f:
        return float(f.attrs["margin"])


def test_val_and_test_take_the_train_splits_margin(small_cfg):
    """No test ground truth in test inputs: a val or test file's radius graph is the train
    split's, whose file is written first even when the test split alone is asked for, and
    whose recorded contacts are all within it (above)."""
    cfg = small_cfg("collisions")
    train = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    test = ensure_dataset(train.with_split("test"), cfg.paths.data_dir, workers=1)
    assert train.path(cfg.paths.data_dir).exists()
    val = ensure_dataset(train.with_split("val"), cfg.paths.data_dir, workers=1)
    margin = _margin(train.path(cfg.paths.data_dir))
    assert margin > 0 and _margin(test) == margin and _margin(val) == margin


def test_contacts_outside_the_train_margin_are_counted_not_widened_for(small_cfg, tmp_path):
    """A test split whose recorded contacts the given margin misses says how many, and keeps
    the margin it was given."""
    cfg = small_cfg("collisions")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "test")
    path = tmp_path / "test.h5"
    with pytest.warns(UserWarning, match=r"\d+ of \d+ recorded contacts lie outside the train"):
        generate_file(spec, path, margin=0.0)
    assert _margin(path) == 0.0
    with pytest.raises(ValueError, match="train split's radius-graph margin"):
        generate_file(spec, tmp_path / "other.h5")


def test_a_test_file_of_another_margin_is_regenerated(small_cfg):
    """A cached test file written with its own split's margin (the old rule) is stale: it is
    replaced by one with the train split's margin, the same simulations."""
    cfg = small_cfg("collisions")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "test")
    path = ensure_dataset(spec, cfg.paths.data_dir, workers=1)
    margin = _margin(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # contacts outside a margin too small are warned of
        generate_file(spec, path, margin=0.5 * margin)
    before = _arrays(path)
    assert ensure_dataset(spec, cfg.paths.data_dir, workers=1) == path
    assert _margin(path) == margin
    after = _arrays(path)
    assert all(np.array_equal(before[k], after[k]) for k in before)


def test_main_generates_all_splits(small_cfg, capsys):
    paths = main(small_cfg("gravity_r2", "workers=1"))  # in-process: no spawned pool
    assert set(paths) == {"train", "val", "test"} and all(p.exists() for p in paths.values())
    assert "done in" in capsys.readouterr().out


@pytest.mark.parametrize("overrides", [["dataset.n_particles=6"], ["dataset.dim=3"]])
def test_size_and_dimension_are_config(small_cfg, overrides):
    cfg = small_cfg("gravity_r1", *overrides)
    path = ensure_dataset(DatasetSpec.from_config(cfg.dataset, cfg.fps, "train"),
                          cfg.paths.data_dir, workers=1)
    with h5py.File(path, "r") as f:
        n, d = f["positions"].shape[2:]
    assert (n, d) == ((6, 2) if "n_particles" in overrides[0] else (4, 3))


def test_three_types_by_config(small_cfg):
    cfg = small_cfg("collisions", "dataset.types=[{radius: 0.1, mass_mode: 0.001, "
                    "mass_log_std: 0.1, fraction: 0.4},{radius: 0.15, mass_mode: 0.05, "
                    "mass_log_std: 0.1, fraction: 0.3},{radius: 0.2, mass_mode: 0.4, "
                    "mass_log_std: 0.1, fraction: 0.3}]")
    path = ensure_dataset(DatasetSpec.from_config(cfg.dataset, cfg.fps, "train"),
                          cfg.paths.data_dir, workers=1)
    with h5py.File(path, "r") as f:
        assert set(np.unique(f["types"][...])) == {0, 1, 2}


def test_frames_too_slow_for_the_encounters_warn_and_resolved_ones_do_not(small_cfg):
    """gravity_r2 at fps 2: close passes turn a pair more than half a revolution between
    frames in many frames, which generation says; at fps 200 the same motion is resolved."""
    def generate(fps):
        cfg = small_cfg("gravity_r2", f"fps={fps}", "dataset.n_frames=40")
        spec = DatasetSpec.from_config(cfg.dataset, fps, "train")
        return ensure_dataset(spec, cfg.paths.data_dir, workers=1)

    with pytest.warns(UserWarning, match="revolution per frame"):
        slow = generate(2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast = generate(200)
    assert aliased_share(_arrays(slow), 1 / 2) > ALIASED_WARN
    assert aliased_share(_arrays(fast), 1 / 200) < ALIASED_WARN
