"""Bad files give one clear error; concurrent generators leave one valid file."""

import multiprocessing as mp
import shutil

import h5py
import numpy as np
import pytest

from bgn.data.files import DatasetFile, DatasetFileError
from bgn.data.generate import ensure_dataset, ensure_splits
from bgn.data.spec import DatasetSpec


@pytest.fixture
def train_file(small_cfg, tmp_path):
    cfg = small_cfg("spring")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    return ensure_dataset(spec, cfg.paths.data_dir, workers=1), spec


def _copy(path, tmp_path, name="copy.h5"):
    target = tmp_path / name
    shutil.copy(path, target)
    return target


def test_valid_file_opens_with_metadata(train_file):
    path, spec = train_file
    f = DatasetFile(path, spec)
    assert f.meta.name == "spring" and f.n_sims == 2 and f.n_frames == 60
    assert f.dt == pytest.approx(1 / 50)
    stats = f.stats()
    assert np.all(stats["target"]["std"] > 0)
    assert np.all(stats["velocity"]["std"] >= 0)


def test_truncated_file_names_file_and_fix(train_file, tmp_path):
    path, spec = train_file
    bad = _copy(path, tmp_path)
    with open(bad, "r+b") as fh:
        fh.truncate(bad.stat().st_size // 2)
    with pytest.raises(DatasetFileError) as err:
        DatasetFile(bad, spec)
    message = str(err.value)
    assert str(bad) in message and "truncated or corrupt" in message
    assert "python -m bgn.train.generate dataset=spring fps=50" in message
    assert bad.exists()  # never deleted behind the user's back


def test_garbage_file(tmp_path):
    bad = tmp_path / "garbage.h5"
    bad.write_bytes(b"not an hdf5 file at all" * 100)
    with pytest.raises(DatasetFileError, match="truncated or corrupt"):
        DatasetFile(bad)


def test_a_missing_file_says_how_to_make_it_not_to_delete_it(tmp_path):
    with pytest.raises(DatasetFileError) as err:
        DatasetFile(tmp_path / "spring_x_fps50_test.h5")
    assert "does not exist. Make it with `python -m bgn.train.generate`" in str(err.value)
    assert "Delete" not in str(err.value)
    # an imported dataset's file: made by the import, named by its folder
    with pytest.raises(DatasetFileError, match=r"Make it with `python -m bgn\.data\.import "
                       r"<your trajectories> name=charges`"):
        DatasetFile(tmp_path / "imported" / "charges" / "test.h5")


def test_wrong_schema_version(train_file, tmp_path):
    path, spec = train_file
    bad = _copy(path, tmp_path)
    with h5py.File(bad, "r+") as f:
        f.attrs["schema_version"] = 999
    with pytest.raises(DatasetFileError, match="schema version 999"):
        DatasetFile(bad, spec)


def test_nan_values(train_file, tmp_path):
    path, spec = train_file
    bad = _copy(path, tmp_path)
    with h5py.File(bad, "r+") as f:
        f["positions"][0, 3, 1, 0] = np.nan
    with pytest.raises(DatasetFileError, match="'positions' holds 1 non-finite"):
        DatasetFile(bad, spec)


def test_wrong_shape(train_file, tmp_path):
    path, spec = train_file
    bad = _copy(path, tmp_path)
    with h5py.File(bad, "r+") as f:
        del f["masses"]
        f["masses"] = np.ones((2, 3))
    with pytest.raises(DatasetFileError, match="'masses' has shape"):
        DatasetFile(bad, spec)


def test_bad_file_in_cache_is_reported_not_overwritten(small_cfg):
    cfg = small_cfg("spring")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "val")
    path = spec.path(cfg.paths.data_dir)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 64)
    with pytest.raises(DatasetFileError, match=str(path.name)):
        ensure_splits(spec, cfg.paths.data_dir, workers=1, show_progress=False)
    assert path.read_bytes().startswith(b"\x89HDF")


def _generate(args):
    spec, data_dir = args
    return str(ensure_dataset(spec, data_dir, workers=1))


@pytest.mark.slow  # two spawned processes
def test_concurrent_generators_leave_one_valid_file(small_cfg):
    cfg = small_cfg("spring", "dataset.n_frames=400")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    with mp.get_context("spawn").Pool(2) as pool:
        paths = pool.map(_generate, [(spec, cfg.paths.data_dir)] * 2)
    assert paths[0] == paths[1]
    data_dir = spec.path(cfg.paths.data_dir).parent
    assert sorted(p.name for p in data_dir.glob("*.h5")) == [spec.filename()]
    assert not list(data_dir.glob("*.tmp*"))  # no half-written leftovers
    DatasetFile(paths[0], spec)  # validates
