"""Files that used to pass the check: corrupt statistics or masses, a file opened for another
config; the regenerate hint; a killed writer's temporary file; workers of a killed generator."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from bgn.data.files import DatasetFile, DatasetFileError
from bgn.data.generate import ensure_dataset, ensure_splits
from bgn.data.spec import DatasetSpec
from tests.conftest import compose_config

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def train_file(small_cfg, tmp_path):
    cfg = small_cfg("spring")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    path = ensure_dataset(spec, cfg.paths.data_dir, workers=1)
    copy = tmp_path / "copy.h5"
    shutil.copy(path, copy)
    return copy, spec


def refused(path: Path, spec: DatasetSpec) -> str:
    with pytest.raises(DatasetFileError) as err:
        DatasetFile(path, spec)
    message = str(err.value)
    assert str(path) in message and "\n" not in message
    return message


def overwrite_bytes(path: Path, dataset: str, data: bytes) -> None:
    """Overwrite the stored bytes of a small (contiguous, uncompressed) array in place."""
    with h5py.File(path, "r") as f:
        offset = f[dataset].id.get_offset()
    assert offset is not None
    with open(path, "r+b") as fh:
        fh.seek(offset)
        fh.write(data)


@pytest.mark.parametrize("entry", ["std", "mean", "robust_scale", "median"])
def test_nan_statistics_are_refused(train_file, entry):
    path, spec = train_file
    with h5py.File(path, "r+") as f:
        f[f"stats/target/{entry}"][0] = np.nan
    message = refused(path, spec)
    assert f"stats/target/{entry}" in message and "non-finite" in message


def test_overwritten_statistics_bytes_are_refused(train_file):
    path, spec = train_file
    overwrite_bytes(path, "stats/target/std", b"\xde\xad\xbe\xef" * 4)
    assert "stats/target/std" in refused(path, spec)


def test_plausible_but_wrong_statistics_are_refused(train_file):
    path, spec = train_file
    with h5py.File(path, "r+") as f:
        f["stats/target/std"][...] = f["stats/target/std"][...] * 1.5  # finite, positive
    message = refused(path, spec)
    assert "stats/target/std" in message and "do not match the arrays" in message


def test_missing_or_misshapen_statistics_are_refused(train_file, tmp_path):
    path, spec = train_file
    other = tmp_path / "other.h5"
    shutil.copy(path, other)
    with h5py.File(path, "r+") as f:
        del f["stats/velocity/std"]
        f["stats/velocity"].create_dataset("std", data=np.ones(3))
    assert "stats/velocity/std" in refused(path, spec)
    with h5py.File(other, "r+") as f:
        del f["stats/log_mass"]
    assert "stats/log_mass" in refused(other, spec)


@pytest.mark.parametrize("how", ["negative", "bytes", "scaled"])
def test_corrupt_masses_are_refused(train_file, how):
    path, spec = train_file
    if how == "bytes":
        overwrite_bytes(path, "masses", b"\xde\xad\xbe\xef" * 2)
    else:
        with h5py.File(path, "r+") as f:
            m = f["masses"][...]
            m[0, 0] = -1.0 if how == "negative" else 2 * m[0, 0]  # scaled: log_mass stats
            f["masses"][...] = m
    message = refused(path, spec)
    assert "masses" in message or "log_mass" in message


def test_file_written_for_another_config_is_refused(small_cfg, tmp_path):
    cfg = small_cfg("spring")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    path = ensure_dataset(spec, cfg.paths.data_dir, workers=1)
    for other in (DatasetSpec(spec.scene, spec.n_sims, 61, spec.seed, spec.fps, "train",
                              spec.params),
                  DatasetSpec(spec.scene, spec.n_sims, spec.n_frames, spec.seed, 10.0, "train",
                              spec.params),
                  spec.with_split("val")):
        target = other.path(tmp_path / "data")
        shutil.copy(path, target)  # a file copied or renamed under another config's name
        message = refused(target, other)
        assert "was not written for this config" in message
    # same sizes, other scene parameters
    other = DatasetSpec(spec.scene, spec.n_sims, spec.n_frames, spec.seed, spec.fps, "train",
                        {**spec.params, "softening": 0.02})
    shutil.copy(path, other.path(tmp_path / "data"))
    assert "generating parameters" in refused(other.path(tmp_path / "data"), other)


def test_regenerate_hint_carries_overrides_and_data_dir(tmp_path):
    data = tmp_path / "my data"
    cfg = compose_config("generate", ["dataset=collisions", "dataset.n_sims=2",
                                      "dataset.n_frames=40", "dataset.n_particles=30",
                                      "dataset.box=4.0", "fps=10", f"paths.data_dir={data}"])
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    path = ensure_dataset(spec, data, workers=1)
    with h5py.File(path, "r+") as f:
        f["stats/target/std"][0] = np.nan
    for message in (refused(path, spec), str(_error(path))):  # with and without the config
        for part in ("python -m bgn.train.generate dataset=collisions fps=10",
                     "dataset.n_sims=2", "dataset.n_frames=40", "dataset.n_particles=30",
                     "dataset.box=4.0", f"'paths.data_dir={data}'"):
            assert part in message, message
    # the hint is a command that composes: every override is accepted by the schema
    hint = message.split("`")[1]
    overrides = [a.strip("'") for a in hint.split("python -m bgn.train.generate ")[1].split(" ")
                 if "=" in a]
    compose_config("generate", [o for o in overrides if not o.startswith("paths.data_dir")])


def _error(path: Path) -> DatasetFileError:
    with pytest.raises(DatasetFileError) as err:
        DatasetFile(path)
    return err.value


def test_stale_temporary_file_is_removed_under_the_lock(small_cfg):
    cfg = small_cfg("spring")
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    path = spec.path(cfg.paths.data_dir)
    path.parent.mkdir(parents=True)
    stale = path.with_name(f"{path.name}.tmp999999")  # what a writer killed mid-write leaves
    stale.write_bytes(b"\x89HDF partial")
    unrelated = path.with_name("other_scene_fps50_train.h5.tmp1")
    unrelated.write_bytes(b"another file's writer")
    ensure_dataset(spec, cfg.paths.data_dir, workers=1)
    assert not stale.exists() and path.exists()
    assert unrelated.exists()  # only this file's temporaries: their writer held this lock


def _children(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and PR_SET_PDEATHSIG")
def test_kill_9_during_generation_leaves_no_worker_and_no_temporary(tmp_path):
    data = tmp_path / "data"
    overrides = ["dataset=spring", "fps=10", "dataset.n_sims=2", "dataset.n_frames=2000",
                 f"paths.data_dir={data}"]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "bgn.train.generate", *overrides,
                             "workers=2", f"hydra.run.dir={tmp_path / 'run'}"],
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 90
        workers: list[int] = []
        while time.time() < deadline and len(workers) < 2:
            time.sleep(0.2)
            workers = [p for p in _children(proc.pid)
                       if b"multiprocessing" in Path(f"/proc/{p}/cmdline").read_bytes()
                       and b"resource_tracker" not in Path(f"/proc/{p}/cmdline").read_bytes()]
            assert proc.poll() is None, "generation ended before its workers were seen"
        assert len(workers) >= 2, "no generation workers appeared"
        time.sleep(0.5)  # the workers are simulating
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.time() + 15
        while time.time() < deadline and any(map(_alive, workers)):
            time.sleep(0.2)
        assert not any(map(_alive, workers)), "generation workers outlived their parent"
    finally:
        if proc.poll() is None:
            proc.kill()
    # a writer killed while writing leaves <file>.tmp<pid>: the next run removes it
    cfg = compose_config("generate", overrides)
    spec = DatasetSpec.from_config(cfg.dataset, cfg.fps, "train")
    data.mkdir(exist_ok=True)
    spec.path(data).with_name(f"{spec.filename()}.tmp{proc.pid}").write_bytes(b"partial")
    ensure_splits(spec, data, workers=1, show_progress=False)
    assert not list(data.glob("*.tmp*"))
    for split in ("train", "val", "test"):
        DatasetFile(spec.with_split(split).path(data), spec.with_split(split)).close()
