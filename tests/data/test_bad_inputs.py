"""Every bad input of the data commands, one row of docs/usage.md's "Bad input" table each:
refused with one line on stderr, a non-zero exit and nothing written under the data dir.

The table is the specification: its ids are this file's cases (one to one), its exit codes are
asserted, and every word it puts in backticks in the message column must be in the line. The
commands run in-process (the ``cli`` entry called with a composed config) to keep this fast;
one run of the real command line is in the slow tier.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bgn.data import from_arrays
from bgn.data.formats import read_trajectories
from bgn.data.importing import main as import_main
from bgn.data.raw import DataImportError, DataImportWarning
from bgn.training.validate import cli
from tests.conftest import compose_config
from tests.data.layouts import (
    damage_tfrecord_length,
    write_arrays_h5,
    write_arrays_npz,
    write_gns_npz,
    write_lagrangebench,
    write_tfrecord,
)

ROOT = Path(__file__).resolve().parents[2]
USAGE = ROOT / "docs" / "usage.md"
S, T, N, D = 10, 16, 6, 2
DT = 0.01
META = {"dt": DT, "bounds": [[0.0, 1.0], [0.0, 1.0]], "dim": D}
LB_META = {**META, "write_every": 1, "periodic_boundary_conditions": [False, False]}


# ---------------------------------------------------------------------------------------------
# Sources: small, good trajectories and ways to spoil them


def positions(s: int = S, t: int = T, n: int = N, seed: int = 0) -> np.ndarray:
    """(s, t, n, D) particles drifting with small accelerations inside (0.2, 0.8)^D."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.3, 0.7, size=(s, 1, n, D))
    velocity = rng.normal(scale=0.5, size=(s, 1, n, D))
    accel = rng.normal(scale=0.5, size=(s, 1, n, D))
    time = np.arange(t)[None, :, None, None] * DT
    return start + velocity * time + 0.5 * accel * time**2


def arrays(where: Path, name: str = "a.npz", **changes) -> Path:
    """A plain-array file (npz or h5 by ``name``) of good data with ``changes`` (None drops a
    key)."""
    data = {"positions": positions(), "dt": DT} | changes
    data = {k: v for k, v in data.items() if v is not None}
    write = write_arrays_h5 if name.endswith(".h5") else write_arrays_npz
    return write(where / name, **data)


def spoiled(change: Callable[[np.ndarray], None], **changes) -> Callable[[Path], Path]:
    """An arrays file whose positions ``change`` edits in place."""
    def make(where: Path) -> Path:
        x = positions()
        change(x)
        return arrays(where, positions=x, **changes)
    return make


def gns(where: Path, trajectories: list | None = None, meta: dict | None = None) -> Path:
    """A GNS folder (pickled tuples, as GNS writes them) with one training file."""
    if trajectories is None:
        trajectories = [(x, np.zeros(N, dtype=np.int64)) for x in positions(s=3)]
    return write_gns_npz(where / "gns", {"train": trajectories}, META if meta is None else meta)


def gns_meta(meta: dict | str) -> Callable[[Path], Path]:
    def make(where: Path) -> Path:
        folder = gns(where)
        text = meta if isinstance(meta, str) else json.dumps(meta)
        (folder / "metadata.json").write_text(text)
        return folder
    return make


def file_with(content: bytes, name: str) -> Callable[[Path], Path]:
    def make(where: Path) -> Path:
        (where / name).write_bytes(content)
        return where / name
    return make


def cut(make: Callable[[Path], Path], keep: float = 0.5) -> Callable[[Path], Path]:
    """The file ``make`` writes, cut to ``keep`` of its bytes (an interrupted copy)."""
    def cut_make(where: Path) -> Path:
        path = make(where)
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])
        return path
    return cut_make


def damaged_npz_member(where: Path) -> Path:
    """A compressed npz whose first member's deflated bytes are overwritten (zip intact)."""
    path = where / "damaged.npz"
    np.savez_compressed(path, positions=positions(), dt=DT)
    with zipfile.ZipFile(path) as z:
        info = z.infolist()[0]
    data = bytearray(path.read_bytes())
    start = info.header_offset + 30 + len(info.filename) + len(info.extra) + 64
    data[start:start + 256] = bytes(256)
    path.write_bytes(bytes(data))
    return path


def ragged(where: Path) -> Path:
    frames = np.empty(T, dtype=object)
    x = positions(s=1)[0]
    for i in range(T):
        frames[i] = x[i, :-1] if i == 4 else x[i]  # frame 4 lost a particle
    return gns(where, [(frames, np.zeros(N, dtype=np.int64))] * 3)


def two_counts(where: Path) -> Path:
    x = positions(s=3)
    return gns(where, [(x[0], np.zeros(N, np.int64)), (x[1, :, :-1], np.zeros(N - 1, np.int64)),
                       (x[2], np.zeros(N, np.int64))])


def text_types(where: Path) -> Path:
    return gns(where, [(x, np.array(["water"] * N)) for x in positions(s=3)])


def lagrangebench_without_write_every(where: Path) -> Path:
    trajs = [(x, np.zeros(N, np.int64)) for x in positions(s=3)]
    return write_lagrangebench(where / "lb", {"train": trajs}, META)


def damaged_tfrecord(where: Path) -> Path:
    folder = write_tfrecord(where / "tf", {"train": [(x, np.zeros(N, np.int64))
                                                      for x in positions(s=3)]}, META)
    damage_tfrecord_length(folder / "train.tfrecord")
    return folder


def folder_of(*names: str) -> Callable[[Path], Path]:
    def make(where: Path) -> Path:
        folder = where / "folder"
        folder.mkdir()
        for name in names:
            (folder / name).write_text("{}" if name.endswith(".json") else "x")
        return folder
    return make


def set_at(index: tuple, value: float) -> Callable[[np.ndarray], None]:
    def change(x: np.ndarray) -> None:
        x[index] = value
    return change


def static(x: np.ndarray) -> None:
    x[:] = x[:, :1]


def jump(x: np.ndarray) -> None:
    x[0, 8:, 2, 0] += 5.0  # half the data's extent in one frame, no periodic box


def coincide(x: np.ndarray) -> None:
    x[0, :, 1] = x[0, :, 0]  # a duplicated particle


def imported(where: Path, data: Path) -> None:
    """A good import named ``x`` under ``data`` (for the training command's cases)."""
    from_arrays(positions(), DT, name="x", data_dir=data, splits={
        "train": range(8), "val": [8], "test": [9]})


def h5_of_import(change: Callable[[Path], None]) -> Callable[[Path, Path], None]:
    def make(where: Path, data: Path) -> None:
        imported(where, data)
        change(data / "imported" / "x" / "train.h5")
    return make


def garble(path: Path) -> None:
    path.write_text("not HDF5")


def halve(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


# ---------------------------------------------------------------------------------------------
# The cases: id -> (command, source maker or None, overrides, setup of the data dir or None)

Source = Callable[[Path], Path] | None
Setup = Callable[[Path, Path], None] | None
CASES: dict[str, tuple[str, Source, dict[str, str | None], Setup]] = {
    # the import's config (exit 2)
    "no-path": ("import", None, {}, None),
    "no-name": ("import", arrays, {"name": None}, None),
    "bad-name": ("import", arrays, {"name": "'my data'"}, None),
    "unknown-format": ("import", arrays, {"format": "gns_zip"}, None),
    "negative-split-seed": ("import", arrays, {"split_seed": "-1"}, None),
    "negative-history": ("import", arrays, {"history": "-1"}, None),
    "unknown-target": ("import", arrays, {"target": "force"}, None),
    "bad-radii-by-type": ("import", arrays, {"radii_by_type": "[0.1,-1]"}, None),
    "data-dir-is-file": ("import", arrays, {"paths.data_dir": "{file}"}, None),
    "data-dir-under-file": ("import", arrays, {"paths.data_dir": "{file}/data"}, None),
    # the source: files (exit 1)
    "no-such-path": ("import", lambda w: w / "missing.npz", {}, None),
    "wrong-format-for-path": ("import", arrays, {"format": "gns-npz"}, None),
    "unknown-suffix": ("import", file_with(b"1,2,3\n", "x.csv"), {}, None),
    "empty-folder": ("import", folder_of(), {}, None),
    "folder-without-split-files": ("import", folder_of("metadata.json", "notes.txt"), {},
                                   None),
    "empty-file": ("import", file_with(b"", "empty.npz"), {}, None),
    "text-file-named-npz": ("import", file_with(b"hello\n", "text.npz"), {}, None),
    "truncated-npz": ("import", cut(arrays), {}, None),
    "damaged-npz-member": ("import", damaged_npz_member, {}, None),
    "text-file-named-h5": ("import", file_with(b"hello\n", "text.h5"), {}, None),
    "truncated-h5": ("import", cut(lambda w: arrays(w, "a.h5")), {}, None),
    "damaged-tfrecord": ("import", damaged_tfrecord, {}, None),
    "no-positions": ("import", lambda w: write_arrays_npz(w / "c.npz", coords=positions()), {},
                     None),
    "gns-pickle-not-allowed": ("import", gns, {}, None),
    # the source: keys and values (exit 1)
    "pickled-array": ("import", lambda w: arrays(w, masses=np.array([1.0, "a"] * 3,
                                                                    dtype=object)), {}, None),
    "text-positions": ("import", lambda w: arrays(w, positions=positions().astype(str)), {},
                       None),
    "text-types": ("import", text_types, {"allow_pickle": "true"}, None),
    "negative-types": ("import", lambda w: arrays(w, types=np.full(N, -1)), {}, None),
    "fractional-types": ("import", lambda w: arrays(w, types=np.full(N, 0.5)), {}, None),
    "huge-positions": ("import", spoiled(set_at((2, 5, 1, 0), 1e200)), {}, None),
    "nan-positions": ("import", spoiled(set_at((3, 7, 2, 1), np.nan)), {}, None),
    "inf-velocities": ("import", lambda w: arrays(w, velocities=np.where(
        np.arange(S * T * N * D).reshape(S, T, N, D) == 100, np.inf, 0.0)), {}, None),
    "all-static": ("import", spoiled(static), {}, None),
    "implausible-dt": ("import", lambda w: arrays(w, dt=1e30), {}, None),
    "negative-dt": ("import", lambda w: arrays(w, dt=-0.01), {}, None),
    "no-dt": ("import", lambda w: arrays(w, dt=None), {}, None),
    "two-dt": ("import", lambda w: arrays(w, dt=[0.01, 0.02]), {}, None),
    "uneven-times": ("import", lambda w: arrays(w, dt=None, times=np.cumsum(
        np.r_[0.0, np.full(T - 1, DT)] + np.eye(T)[5] * DT)), {}, None),
    "masses-shape": ("import", lambda w: arrays(w, masses=np.ones(N + 1)), {}, None),
    "velocities-shape": ("import", lambda w: arrays(w, velocities=np.zeros((S, T, N, 3))), {},
                         None),
    "negative-mass": ("import", lambda w: arrays(w, masses=np.r_[np.ones(N - 1), -1.0]), {},
                      None),
    "bad-box": ("import", lambda w: arrays(w, box=np.array([[0.0, 1.0], [1.0, 0.0]])), {},
                None),
    "periodic-without-box": ("import", lambda w: arrays(w, periodic=True), {}, None),
    "unknown-split-label": ("import", lambda w: arrays(w, split=np.array(["training"] * S)),
                            {}, None),
    "split-length": ("import", lambda w: arrays(w, split=np.array(["train"] * (S - 1))), {},
                     None),
    "too-few-trajectories": ("import", lambda w: arrays(w, positions=positions(s=2)), {}, None),
    "too-few-frames": ("import", lambda w: arrays(w, positions=positions(t=6)), {}, None),
    "half-box-jump": ("import", spoiled(jump), {}, None),
    "coincident-particles": ("import", spoiled(coincide), {}, None),
    "ragged-frames": ("import", ragged, {"allow_pickle": "true"}, None),
    "particle-counts-in-one-split": ("import", two_counts, {"allow_pickle": "true"}, None),
    "metadata-no-dt": ("import", gns_meta({"bounds": META["bounds"]}), {"allow_pickle": "true"},
                       None),
    "metadata-not-json": ("import", gns_meta("{dt: 0.01"), {"allow_pickle": "true"}, None),
    "metadata-dt-text": ("import", gns_meta({**META, "dt": "fast"}), {"allow_pickle": "true"},
                         None),
    "metadata-bad-bounds": ("import", gns_meta({**META, "bounds": [[1.0, 0.0], [0.0, 1.0]]}),
                            {"allow_pickle": "true"}, None),
    "metadata-wrong-dim": ("import", gns_meta({**META, "dim": 3}), {"allow_pickle": "true"},
                           None),
    "lagrangebench-no-write-every": ("import", lagrangebench_without_write_every, {}, None),
    "radii-by-type-too-short": ("import", lambda w: arrays(w, types=np.r_[np.zeros(N - 1), 1]),
                                {"radii_by_type": "[0.1]"}, None),
    "import-exists": ("import", arrays, {}, lambda w, data: imported(w, data)),
    "imports-folder-is-a-file": ("import", arrays, {}, lambda w, data: (
        data.mkdir(), (data / "imported").write_text("x"))),
    # the training command on imported data (exit 2: its config; 1: its files)
    "train-data-dir-is-file": ("train", None, {"paths.data_dir": "{file}"}, None),
    "generate-data-dir-is-file": ("generate", None, {"paths.data_dir": "{file}"}, None),
    "train-import-without-name": ("train", None, {"dataset": "imported"}, None),
    "train-import-missing": ("train", None, {"dataset": "imported", "dataset.name": "nowhere"},
                             imported),
    "train-import-split-missing": ("train", None, {"dataset": "imported", "dataset.name": "x"},
                                   lambda w, data: (imported(w, data), (
                                       data / "imported/x/val.h5").unlink())),
    "train-history-too-long": ("train", None, {"dataset": "imported", "dataset.name": "x",
                                               "dataset.history": "20"}, imported),
    "train-negative-history": ("train", None, {"dataset": "imported", "dataset.name": "x",
                                               "dataset.history": "-1"}, imported),
    "train-val-rollouts-too-many": ("train", None, {"dataset": "imported", "dataset.name": "x",
                                                    "val_rollout_sims": "3",
                                                    "val_rollout_steps": "4"}, imported),
    "train-sims-too-many": ("train", None, {"dataset": "imported", "dataset.name": "x",
                                            "dataset.train_sims": "9"}, imported),
    "train-import-not-hdf5": ("train", None, {"dataset": "imported", "dataset.name": "x"},
                              h5_of_import(garble)),
    "train-import-truncated": ("train", None, {"dataset": "imported", "dataset.name": "x"},
                               h5_of_import(halve)),
}


# ---------------------------------------------------------------------------------------------
# The table in docs/usage.md


def table() -> dict[str, tuple[list[str], int]]:
    """``id -> (the words in backticks of the message column, the exit code)`` of the rows of
    the bad-input table in docs/usage.md (the rows whose first cell is an id in backticks)."""
    text = USAGE.read_text().split("## Bad input", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and re.fullmatch(r"`[a-z0-9-]+`", cells[0]):
            rows[cells[0].strip("`")] = (re.findall(r"`([^`]+)`", cells[2]), int(cells[3]))
    return rows


TABLE = table()


def test_the_table_and_the_cases_agree():
    assert len(TABLE) >= 40
    assert sorted(TABLE) == sorted(CASES), (set(TABLE) ^ set(CASES))
    assert all(words for words, _ in TABLE.values())  # every row says what the line names


def run(case: str, tmp_path: Path) -> int:
    """Run ``case``'s command in-process and return its exit code; asserts that nothing under
    the data dir changed."""
    command, source, overrides, setup = CASES[case]
    where, data = tmp_path / "src", tmp_path / "data"
    where.mkdir()
    (where / "afile").write_text("a file, not a folder")
    if setup is not None:
        setup(where, data)
    given: dict[str, str | None] = {"paths.data_dir": str(data)}
    if command == "import":
        given |= {"name": "x"}
        if source is not None:
            given["path"] = f"'{source(where)}'"
    given |= overrides
    given = {k: None if v is None else v.replace("{file}", str(where / "afile"))
             for k, v in given.items()}
    before = snapshot(data)
    if command == "import":
        cfg = compose_config("import", [f"{k}={v}" for k, v in given.items() if v is not None])
        entry = cli("import")(import_main)
    elif command == "generate":
        from bgn.train.generate import main as generate

        cfg = compose_config("generate", [f"{k}={v}" for k, v in given.items() if v is not None])
        entry = cli("generate")(generate)
    else:
        from bgn.train.__main__ import main as entry

        cfg = compose_config("train", [f"{k}={v}" for k, v in given.items() if v is not None])
    with pytest.raises(SystemExit) as exit_info:
        entry(cfg)
    assert snapshot(data) == before, "something was written under the data dir"
    return int(exit_info.value.code)


def snapshot(folder: Path) -> dict[str, bytes | None]:
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): None if p.is_dir() else p.read_bytes()
            for p in sorted(folder.rglob("*"))}


@pytest.mark.parametrize("case", sorted(CASES))
def test_every_bad_input_is_refused_in_one_line(case, tmp_path, capsys):
    code = run(case, tmp_path)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    words, expected = TABLE[case]
    assert code == expected, lines[0]
    for word in words:
        assert word in lines[0], (word, lines[0])
    assert "Traceback" not in err and ".tmp" not in lines[0]  # the source, not a temporary
    # text.npz: no word of pickles; a pickled plain array: no offer to unpickle it
    assert ("pickle" in lines[0]) == (case in ("gns-pickle-not-allowed", "pickled-array"))
    assert ("allow_pickle" in lines[0]) == (case == "gns-pickle-not-allowed")


# ---------------------------------------------------------------------------------------------
# What is warned about, and what an explicit statement allows


def test_a_misspelt_key_is_named_with_the_key_it_resembles(tmp_path, capsys):
    source = arrays(tmp_path, masse=np.ones(N), colour=np.zeros(N))
    cfg = compose_config("import", [f"path={source}", "name=m",
                                    f"paths.data_dir={tmp_path / 'data'}"])
    cli("import")(import_main)(cfg)
    err = capsys.readouterr().err
    assert "'masse' (did you mean 'masses'?)" in err and "'colour'" in err
    assert len(err.strip().splitlines()) == 1  # one warning line


def test_a_near_miss_in_metadata_is_warned_about_and_its_own_keys_are_not(tmp_path):
    folder = gns(tmp_path, meta={**META, "defualt_connectivity_radius": 0.1, "vel_mean": [0, 0]})
    with pytest.warns(DataImportWarning, match="defualt_connectivity_radius") as record:
        read_trajectories(folder, allow_pickle=True)
    assert "vel_mean" not in str(record[0].message)


def test_good_data_import_without_a_warning(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataImportWarning)
        read_trajectories(arrays(tmp_path, masses=np.ones(N)))


def test_a_pickled_gns_file_is_read_only_with_allow_pickle(tmp_path):
    folder = gns(tmp_path)
    with pytest.raises(DataImportError, match="pickled Python objects.*allow_pickle=true"):
        read_trajectories(folder)
    raw = read_trajectories(folder, allow_pickle=True)
    assert raw.splits["train"].positions.shape[1:] == (T, N, D)


def test_the_documented_format_names_are_accepted(tmp_path):
    source = arrays(tmp_path)
    for name in ("arrays", "arrays_npz", "arrays-npz"):
        assert read_trajectories(source, fmt=name).source["format"] == "arrays-npz"
    folder = gns(tmp_path)
    for name in ("gns_npz", "gns", "GNS-npz"):
        assert read_trajectories(folder, fmt=name, allow_pickle=True).source["format"] \
            == "gns-npz"


def test_whole_number_types_as_floats_are_accepted(tmp_path):
    raw = read_trajectories(arrays(tmp_path, types=np.r_[np.zeros(N - 2), 2.0, 2.0]))
    assert raw.splits["train"].types.dtype == np.int64 and raw.splits["train"].types.max() == 2


def test_a_refused_import_leaves_an_existing_data_dir_as_it_was(tmp_path):
    data = tmp_path / "data"
    (data / "spring").mkdir(parents=True)
    x = positions()
    x[0, 2, 1, 0] = np.nan
    with pytest.raises(DataImportError):
        from_arrays(x, DT, name="y", data_dir=data)
    assert sorted(p.name for p in data.iterdir()) == ["spring"]


@pytest.mark.slow
def test_the_command_line_refuses_in_one_line(tmp_path):
    source = arrays(tmp_path, types=np.full(N, 0.5))
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run(
        [sys.executable, "-m", "bgn.data.import", str(source), "name=x",
         f"paths.data_dir={tmp_path / 'data'}"], capture_output=True, text=True, env=env,
        cwd=tmp_path, timeout=300)
    assert result.returncode == 1
    assert result.stderr.strip().count("\n") == 0 and "0.5" in result.stderr
    assert not (tmp_path / "data").exists()


def test_a_file_failing_the_checks_on_open_names_the_source_and_leaves_nothing(tmp_path,
                                                                              monkeypatch):
    """The last line of defence: a file the source's checks passed but the dataset file's
    checks refuse is reported against the source (never the temporary file), and the folders
    the import made are gone."""
    from bgn.data import importing
    from bgn.data.files import DatasetFileError

    def refuse(path, *args, **kwargs):
        raise DatasetFileError(path, "array 'types' holds types outside 0..0", "regenerate")

    monkeypatch.setattr(importing, "DatasetFile", refuse)
    raw = read_trajectories(arrays(tmp_path))
    with pytest.raises(DataImportError) as err:
        importing.import_dataset(raw, "x", tmp_path / "data")
    assert str(tmp_path / "a.npz") in str(err.value) and "fix the source data" in str(err.value)
    assert ".tmp" not in str(err.value) and "regenerate" not in str(err.value)
    assert not (tmp_path / "data").exists()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.one_of(st.integers(-3, 5), st.floats(-3, 5), st.just(np.nan)), min_size=1,
                max_size=8))
def test_types_are_accepted_exactly_when_whole_and_not_negative(values):
    from bgn.data.formats import types_of

    v = np.asarray(values)
    ok = bool(np.all(np.isfinite(v) & (v == np.round(v)) & (v >= 0)))
    if ok:
        np.testing.assert_array_equal(types_of(v, "types"), v.astype(np.int64))
    else:
        with pytest.raises(DataImportError, match="types: entry"):
            types_of(v, "types")


def test_an_unread_key_of_a_gns_trajectory_is_warned_about(tmp_path):
    folder = tmp_path / "gns"
    folder.mkdir()
    items = {}
    for i, x in enumerate(positions(s=3)):
        item = np.empty((), dtype=object)
        item[()] = {"positions": x, "particle_type": np.zeros(N, np.int64), "velocity": x}
        items[f"trajectory_{i}"] = item
    np.savez(folder / "train.npz", **items)
    (folder / "metadata.json").write_text(json.dumps(META))
    with pytest.warns(DataImportWarning, match=r"trajectories\): ignored 'velocity'") as record:
        raw = read_trajectories(folder, allow_pickle=True)
    assert len([w for w in record if w.category is DataImportWarning]) == 1  # once per file
    assert raw.splits["train"].positions.shape[1:] == (T, N, D)
