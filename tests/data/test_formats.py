"""Foreign trajectory layouts: detection, faithful reading, periodic unwrapping, splits and the
one-line errors of bad input (file, trajectory, frame)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bgn.data import formats
from bgn.data.formats import (
    FORMATS,
    check_trajectories,
    detect_format,
    split_by_trajectory,
    unwrap_periodic,
)
from bgn.data.raw import IMPORT_SPLITS, DataImportError, RawTrajectories, SplitArrays
from tests.data.layouts import (
    damage_tfrecord_length,
    write_arrays_h5,
    write_arrays_npz,
    write_gns_npz,
    write_lagrangebench,
    write_tfrecord,
)


def read_trajectories(path: Path, **options) -> RawTrajectories:
    """The reader with unpickling allowed: these GNS files are the tests' own (the refusal
    without it: tests/data/test_bad_inputs.py)."""
    return formats.read_trajectories(path, allow_pickle=True, **options)


META = {"dt": 0.0025, "bounds": [[0.0, 1.0], [0.0, 1.0]], "default_connectivity_radius": 0.015,
        "dim": 2, "sequence_length": 11, "vel_mean": [0.0, 0.0], "vel_std": [1.0, 1.0],
        "acc_mean": [0.0, 0.0], "acc_std": [1.0, 1.0]}
LB_META = {"dt": 0.0004, "write_every": 100, "bounds": [[0.0, 1.0], [0.0, 1.0]],
           "periodic_boundary_conditions": [True, True], "default_connectivity_radius": 0.029,
           "dim": 2}


def walk(rng: np.random.Generator, t: int = 12, n: int = 6, d: int = 2,
         step: float = 0.005) -> np.ndarray:
    """A smooth random walk of n particles well inside the unit box (no jumps, no overlap)."""
    start = rng.uniform(0.3, 0.7, (1, n, d))
    return (start + np.cumsum(rng.normal(0.0, step, (t, n, d)), axis=0)).astype(np.float32)


def trajectories(seed: int, count: int, **kw) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        pos = walk(rng, **kw)
        out.append((pos, rng.integers(0, 4, pos.shape[1]).astype(np.int64)))
    return out


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def raises_naming(*parts: str):
    """pytest.raises for a one-line DataImportError naming every part."""
    return pytest.raises(DataImportError,
                         match="(?s)^(?!.*\n)" + "".join(f"(?=.*{re.escape(p)})" for p in parts))


# ---------------------------------------------------------------------------------------------
# Detection and reading each layout back


@pytest.fixture
def layouts(tmp_path: Path) -> dict[str, Path]:
    splits = {"train": trajectories(0, 3), "valid": trajectories(1, 1), "test": trajectories(2, 1)}
    s, t, n, d = 4, 12, 5, 2
    pos = np.stack([walk(np.random.default_rng(k), t, n, d) for k in range(s)]).astype(float)
    return {
        "gns-npz": write_gns_npz(tmp_path / "gns", splits, META),
        "lagrangebench-h5": write_lagrangebench(tmp_path / "lb", splits, LB_META),
        "tfrecord": write_tfrecord(tmp_path / "tf", splits, META),
        "arrays-npz": write_arrays_npz(tmp_path / "a.npz", positions=pos, dt=0.1),
        "arrays-h5": write_arrays_h5(tmp_path / "a.h5", positions=pos, dt=0.1),
    }


def test_every_format_is_detected(layouts: dict[str, Path]) -> None:
    assert set(layouts) == set(FORMATS)
    for fmt, path in layouts.items():
        assert detect_format(path) == fmt
        assert read_trajectories(path).source["format"] == fmt


def test_unknown_layouts_are_named(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("x")
    with raises_naming(str(tmp_path / "empty"), "unknown format", "notes.txt", "looked for"):
        detect_format(tmp_path / "empty")
    (tmp_path / "x.csv").write_text("1,2")
    with raises_naming("x.csv", "unknown format"):
        detect_format(tmp_path / "x.csv")
    np.savez(tmp_path / "other.npz", coords=np.zeros(3))
    with raises_naming("other.npz", "positions", "coords"):
        detect_format(tmp_path / "other.npz")
    with raises_naming("missing", "no such"):
        detect_format(tmp_path / "missing")
    with raises_naming("format='xyz'", "gns-npz, lagrangebench-h5"):
        read_trajectories(tmp_path / "other.npz", fmt="xyz")
    with raises_naming("other.npz", "gns-npz", "folder"):
        read_trajectories(tmp_path / "other.npz", fmt="gns-npz")


@pytest.mark.parametrize("fmt", ["gns-npz", "tfrecord"])
def test_gns_and_tfrecord_read_back(tmp_path: Path, fmt: str) -> None:
    splits = {"train": trajectories(0, 3), "valid": trajectories(1, 2), "test": trajectories(2, 1)}
    write = write_gns_npz if fmt == "gns-npz" else write_tfrecord
    folder = write(tmp_path / fmt, splits, META)
    raw = read_trajectories(folder)
    assert raw.dt == META["dt"] and raw.kinematic_types == (3,)
    assert raw.connectivity_radius == META["default_connectivity_radius"]
    np.testing.assert_array_equal(raw.bounds, META["bounds"])
    assert not raw.periodic.any()
    assert raw.metadata == META
    for split, stem in (("train", "train"), ("val", "valid"), ("test", "test")):
        got = raw.splits[split]
        assert got.positions.dtype == np.float64 and got.types.dtype == np.int64
        np.testing.assert_array_equal(got.positions, np.stack([p for p, _ in splits[stem]]))
        np.testing.assert_array_equal(got.types, np.stack([k for _, k in splits[stem]]))
        assert len(got.names) == len(splits[stem])
        suffix = ".npz" if fmt == "gns-npz" else ".tfrecord"
        assert raw.source["split_files"][split] == [stem + suffix]
    for name, digest in raw.source["files"].items():
        assert digest == sha(folder / name)
    assert set(raw.source["files"]) == {"metadata.json", "train" + suffix, "valid" + suffix,
                                        "test" + suffix}


def test_gns_material_property_is_recorded(tmp_path: Path) -> None:
    trajs = [(p, k, np.float64(0.5 + i)) for i, (p, k) in enumerate(trajectories(0, 3))]
    raw = read_trajectories(write_gns_npz(tmp_path, {"train": trajs, "valid": trajs[:1],
                                                     "test": trajs[:1]}, META))
    assert raw.metadata["material"]["train"] == [0.5, 1.5, 2.5]


def test_gns_data_key_and_scalar_particle_type(tmp_path: Path) -> None:
    """GNS also writes all trajectories under one ``gns_data`` key, and allows one particle
    type per trajectory (a scalar)."""
    trajs = trajectories(0, 4)
    data = np.empty(len(trajs), dtype=object)
    for i, (p, _) in enumerate(trajs):
        item = np.empty(2, dtype=object)
        item[0], item[1] = p, 5
        data[i] = item
    np.savez(tmp_path / "train.npz", gns_data=data)
    (tmp_path / "metadata.json").write_text(json.dumps(META))
    raw = read_trajectories(tmp_path)
    names = sorted(n for a in raw.splits.values() for n in a.names)
    assert names == [f"gns_data[{i}]" for i in range(4)]
    for a in raw.splits.values():
        assert (a.types == 5).all()
        rows = [int(n[9:-1]) for n in a.names]
        np.testing.assert_array_equal(a.positions, np.stack([trajs[i][0] for i in rows]))


def test_lagrangebench_reads_back_unwrapped(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    truth = [(0.5 + np.cumsum(rng.normal(0, 0.05, (30, 6, 2)), axis=0),
              np.array([0, 0, 0, 0, 1, 2])) for _ in range(3)]
    wrapped = [(np.mod(p, 1.0), k) for p, k in truth]
    assert any((p != w).any() for (p, _), (w, _) in zip(truth, wrapped))  # crosses the box
    folder = write_lagrangebench(tmp_path, {"train": wrapped[:1], "valid": wrapped[1:2],
                                            "test": wrapped[2:]}, LB_META)
    raw = read_trajectories(folder)
    assert raw.dt == pytest.approx(LB_META["dt"] * LB_META["write_every"], rel=1e-15)
    assert raw.kinematic_types == (1, 2) and raw.periodic.all()
    assert raw.connectivity_radius == LB_META["default_connectivity_radius"]
    for split, (p, k) in zip(IMPORT_SPLITS, truth):
        got = raw.splits[split]
        shift = got.positions[0] - p  # one whole-box shift per particle and dimension
        np.testing.assert_allclose(shift, shift[:1].repeat(len(p), 0), atol=1e-12)
        np.testing.assert_allclose(shift, np.rint(shift), atol=1e-12)
        np.testing.assert_array_equal(got.types[0], k)
        assert got.names == ["00000"]


def test_missing_splits_are_carved_by_trajectory(tmp_path: Path) -> None:
    folder = write_gns_npz(tmp_path, {"train": trajectories(0, 10)}, META)
    first, again = read_trajectories(folder, split_seed=4), read_trajectories(folder, split_seed=4)
    names = {s: first.splits[s].names for s in IMPORT_SPLITS}
    assert names == {s: again.splits[s].names for s in IMPORT_SPLITS}
    every = [n for s in IMPORT_SPLITS for n in names[s]]
    assert sorted(every) == sorted(f"simulation_trajectory_{i}" for i in range(10))
    assert [len(names[s]) for s in IMPORT_SPLITS] == [8, 1, 1]
    assert first.source["split_files"]["val"] == ["train.npz"]
    other = read_trajectories(folder, split_seed=5)
    assert any(other.splits[s].names != names[s] for s in IMPORT_SPLITS)
    # A given test file stays; only val is carved from train.
    folder = write_gns_npz(tmp_path / "b", {"train": trajectories(0, 5),
                                            "test": trajectories(1, 2)}, META)
    raw = read_trajectories(folder)
    assert len(raw.splits["test"].names) == 2 and len(raw.splits["val"].names) == 1
    with raises_naming("train.npz", "missing"):
        read_trajectories(write_gns_npz(tmp_path / "c", {"valid": trajectories(0, 2)}, META))


@pytest.mark.parametrize("writer", [write_arrays_npz, write_arrays_h5])
def test_arrays_read_back(tmp_path: Path, writer) -> None:
    rng = np.random.default_rng(5)
    s, t, n, d = 5, 20, 4, 3
    truth = 2.0 + np.cumsum(rng.uniform(-0.9, 0.9, (s, t, n, d)), axis=1)  # < half a box
    box = np.array([[0.0, 4.0], [-1.0, 3.0], [0.0, 10.0]])
    periodic = np.array([True, True, False])
    wrapped = truth.copy()
    wrapped[..., :2] = box[:2, 0] + np.mod(truth[..., :2] - box[:2, 0], box[:2, 1] - box[:2, 0])
    masses = rng.uniform(0.5, 2.0, (s, n))
    assert (wrapped != truth).any()  # the walks cross the periodic box
    split = np.array(["train", "test", "train", "val", "train"])
    suffix = writer.__name__.rsplit("_", 1)[1]
    path = writer(tmp_path / f"arrays.{suffix}", positions=wrapped, dt=0.05,
                  times=1.0 + 0.05 * np.arange(t), masses=masses, radii=np.full(n, 0.1),
                  types=np.arange(n), velocities=np.ones((s, t, n, d)), box=box,
                  periodic=periodic, split=split)
    raw = read_trajectories(path)
    assert raw.dt == 0.05 and raw.kinematic_types == () and raw.metadata == {}
    np.testing.assert_array_equal(raw.bounds, box)
    np.testing.assert_array_equal(raw.periodic, periodic)
    assert raw.source["files"] == {path.name: sha(path)}
    for name, rows in (("train", [0, 2, 4]), ("val", [3]), ("test", [1])):
        got = raw.splits[name]
        assert got.names == [str(i) for i in rows]
        shift = got.positions - truth[rows]
        np.testing.assert_allclose(shift, shift[:, :1].repeat(t, 1), atol=1e-9)
        np.testing.assert_array_equal(got.positions[..., 2], truth[rows][..., 2])
        np.testing.assert_array_equal(got.masses, masses[rows])
        np.testing.assert_array_equal(got.radii, np.full((len(rows), n), 0.1))
        np.testing.assert_array_equal(got.types, np.tile(np.arange(n), (len(rows), 1)))
        assert got.velocities.shape == (len(rows), t, n, d)


def test_arrays_box_lengths_and_dt_from_times(tmp_path: Path) -> None:
    pos = walk(np.random.default_rng(0), t=10, n=3)[None].repeat(3, 0).astype(float)
    raw = read_trajectories(write_arrays_npz(tmp_path / "a.npz", positions=pos,
                                             times=0.25 * np.arange(10), box=[1.0, 2.0]))
    assert raw.dt == 0.25
    np.testing.assert_array_equal(raw.bounds, [[0.0, 1.0], [0.0, 2.0]])
    assert sum(len(a.names) for a in raw.splits.values()) == 3


def _field(number: int, payload: bytes) -> bytes:
    """A length-delimited protobuf field (wire type 2), encoded by hand."""
    def varint(v: int) -> bytes:
        out = b""
        while v >= 0x80:
            out, v = out + bytes([v & 0x7F | 0x80]), v >> 7
        return out + bytes([v])

    return varint(number << 3 | 2) + varint(len(payload)) + payload


def test_tfrecord_reads_sequence_examples_encoded_by_hand(tmp_path: Path) -> None:
    """The wire format from TensorFlow's example.proto / feature.proto field numbers, written
    without the reader's protobuf declarations (so a wrong field number would fail here)."""
    from tensorboard.summary.writer.record_writer import RecordWriter

    pos, types = trajectories(7, 1)[0]
    def bytes_feature(b: bytes) -> bytes:
        return _field(1, _field(1, b))  # Feature.bytes_list(1).value(1)

    key = _field(3, _field(1, bytes([42])))  # Feature.int64_list(3), packed value(1) = 42
    context = (_field(1, _field(1, b"key") + _field(2, key))
               + _field(1, _field(1, b"particle_type") + _field(2, bytes_feature(
                   types.tobytes()))))
    steps = b"".join(_field(1, bytes_feature(frame.tobytes())) for frame in pos)
    lists = _field(1, _field(1, b"position") + _field(2, steps))
    with open(tmp_path / "train.tfrecord", "wb") as fh:
        RecordWriter(fh).write(_field(1, context) + _field(2, lists))
    (tmp_path / "metadata.json").write_text(json.dumps(META))
    raw = read_trajectories(tmp_path, split_fractions=(1.0, 0.0, 0.0))
    assert raw.splits["train"].names == ["42"]
    np.testing.assert_array_equal(raw.splits["train"].positions[0], pos)
    np.testing.assert_array_equal(raw.splits["train"].types[0], types)


def test_tfrecord_damage_is_reported(tmp_path: Path) -> None:
    folder = write_tfrecord(tmp_path, {"train": trajectories(0, 3)}, META)
    damage_tfrecord_length(folder / "train.tfrecord")
    with raises_naming("train.tfrecord", "record 0", "checksum"):
        read_trajectories(folder)


# ---------------------------------------------------------------------------------------------
# Periodic unwrapping and splits (properties)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), d=st.integers(1, 3), low=st.floats(-5, 5),
       length=st.floats(0.5, 20))
def test_unwrap_gives_minimum_image_differences(seed: int, d: int, low: float,
                                                length: float) -> None:
    rng = np.random.default_rng(seed)
    bounds = np.stack([np.full(d, low), np.full(d, low + length)], axis=1)
    periodic = rng.random(d) < 0.7
    steps = rng.uniform(-0.45, 0.45, (2, 40, 3, d)) * length  # below half a box per frame
    truth = low + length * rng.random((2, 1, 3, d)) + np.cumsum(steps, axis=1)
    wrapped = truth.copy()
    wrapped[..., periodic] = low + np.mod(truth[..., periodic] - low, length)
    out = unwrap_periodic(wrapped, bounds, periodic)
    diff = np.diff(wrapped, axis=1)
    image = diff - length * np.rint(diff / length)
    np.testing.assert_allclose(np.diff(out, axis=1)[..., periodic], image[..., periodic],
                               atol=1e-9 * length)
    np.testing.assert_allclose(np.diff(out, axis=1), np.diff(truth, axis=1), atol=1e-9 * length)
    np.testing.assert_array_equal(out[..., ~periodic], wrapped[..., ~periodic])
    np.testing.assert_array_equal(out[:, 0], wrapped[:, 0])
    np.testing.assert_array_equal(unwrap_periodic(out, bounds, periodic), out)


@settings(max_examples=40, deadline=None)
@given(s=st.integers(3, 40), seed=st.integers(0, 1000),
       fractions=st.tuples(st.floats(0.1, 1), st.floats(0, 1), st.floats(0, 1)))
def test_split_by_trajectory_is_a_partition(s: int, seed: int, fractions) -> None:
    arrays = SplitArrays(positions=np.arange(s, dtype=float).reshape(s, 1, 1, 1),
                         masses=np.arange(s, dtype=float)[:, None] + 1,
                         names=[f"t{i}" for i in range(s)])
    out = split_by_trajectory(arrays, fractions, seed)
    assert set(out) == {k for k, f in zip(IMPORT_SPLITS, fractions) if f > 0}
    rows = np.concatenate([a.positions[:, 0, 0, 0] for a in out.values()])
    assert sorted(rows.tolist()) == list(range(s))  # each trajectory in exactly one split
    for a in out.values():
        assert a.names == [f"t{int(i)}" for i in a.positions[:, 0, 0, 0]]
        np.testing.assert_array_equal(a.masses[:, 0], a.positions[:, 0, 0, 0] + 1)
    again = split_by_trajectory(arrays, fractions, seed)
    assert {k: a.names for k, a in out.items()} == {k: a.names for k, a in again.items()}


def test_split_by_trajectory_refuses_too_few() -> None:
    with raises_naming("2 trajectories", "more trajectories"):
        split_by_trajectory(SplitArrays(positions=np.zeros((2, 3, 1, 1))), (0.8, 0.1, 0.1), 0)


# ---------------------------------------------------------------------------------------------
# Bad input: one line naming the file, the trajectory and the frame


def gns_with(tmp_path: Path, change, meta: dict | None = None) -> Path:
    """A GNS folder whose train trajectory simulation_trajectory_1 is changed by ``change``."""
    trajs = trajectories(0, 3)
    trajs[1] = change(*trajs[1])
    return write_gns_npz(tmp_path, {"train": trajs, "valid": trajectories(1, 1),
                                    "test": trajectories(2, 1)}, META if meta is None else meta)


def test_nan_names_file_trajectory_and_frame(tmp_path: Path) -> None:
    def nan(p, k):
        p = p.copy()
        p[7, 2, 1] = np.nan
        return p, k

    with raises_naming("train.npz", "'simulation_trajectory_1'", "frame 7", "particle 2", "NaN"):
        read_trajectories(gns_with(tmp_path, nan))


def test_inf_velocity_in_arrays(tmp_path: Path) -> None:
    pos = walk(np.random.default_rng(0), t=10, n=3)[None].repeat(4, 0).astype(float)
    vel = np.zeros_like(pos)
    vel[2, 5, 1, 0] = np.inf
    path = write_arrays_npz(tmp_path / "a.npz", positions=pos, velocities=vel, dt=0.1,
                            split=[0, 0, 1, 2])
    with raises_naming("a.npz", "trajectory '2'", "frame 5", "velocities", "inf"):
        read_trajectories(path)


@pytest.mark.parametrize("axis,what", [(1, "particle counts"), (2, "dimensions"),
                                       (0, "frame counts")])
def test_unequal_shapes_in_one_split(tmp_path: Path, axis: int, what: str) -> None:
    def grow(p, k):
        extra = np.take(p, [0], axis=axis) + 0.01
        return np.concatenate([p, extra], axis=axis), (np.append(k, 0) if axis == 1 else k)

    with raises_naming("train.npz", "'simulation_trajectory_1'", what, "separately"):
        read_trajectories(gns_with(tmp_path, grow))


@pytest.mark.parametrize("dt", [None, 0.0, -0.1])
def test_missing_or_non_positive_dt(tmp_path: Path, dt) -> None:
    meta = {k: v for k, v in META.items() if k != "dt"} | ({} if dt is None else {"dt": dt})
    with raises_naming("metadata.json" if dt is None else str(tmp_path), "dt"):
        read_trajectories(gns_with(tmp_path, lambda p, k: (p, k), meta))
    pos = walk(np.random.default_rng(0), t=10, n=3)[None].repeat(3, 0).astype(float)
    arrays = {"positions": pos} | ({} if dt is None else {"dt": dt})
    with raises_naming("b.h5", "dt"):
        read_trajectories(write_arrays_h5(tmp_path / "b.h5", **arrays))


def test_lagrangebench_needs_write_every(tmp_path: Path) -> None:
    meta = {k: v for k, v in LB_META.items() if k != "write_every"}
    folder = write_lagrangebench(tmp_path, {"train": trajectories(0, 3)}, meta)
    with raises_naming("metadata.json", "write_every"):
        read_trajectories(folder)


def test_non_uniform_times(tmp_path: Path) -> None:
    pos = walk(np.random.default_rng(0), t=10, n=3)[None].repeat(3, 0).astype(float)
    times = 0.1 * np.arange(10)
    times[6:] += 0.01
    with raises_naming("a.npz", "frame 5 to 6", "not uniformly spaced", "resample"):
        read_trajectories(write_arrays_npz(tmp_path / "a.npz", positions=pos, times=times))
    with raises_naming("c.npz", "dt=0.2", "0.1 apart"):
        read_trajectories(write_arrays_npz(tmp_path / "c.npz", positions=pos, dt=0.2,
                                           times=0.1 * np.arange(10)))


def test_jump_of_half_a_box_without_periodic_boundary(tmp_path: Path) -> None:
    def jump(p, k):
        p = p.copy()
        p[4:, 3, 0] -= 1.0  # as if wrapped across a periodic box of length 1
        return p, k

    with raises_naming("train.npz", "'simulation_trajectory_1'", "frame 3 to 4", "particle 3",
                       "dimension 0", "declare"):
        read_trajectories(gns_with(tmp_path, jump))
    # The same data declared periodic are unwrapped and accepted.
    trajs = trajectories(0, 3)
    trajs[1] = jump(*trajs[1])
    meta = LB_META | {"periodic_boundary_conditions": [True, False]}
    folder = write_lagrangebench(tmp_path / "lb", {"train": trajs, "valid": trajs[:1],
                                                   "test": trajs[2:]}, meta)
    raw = read_trajectories(folder)
    assert np.abs(np.diff(raw.splits["train"].positions, axis=1)).max() < 0.5


def test_coincident_particles(tmp_path: Path) -> None:
    def overlap(p, k):
        p = p.copy()
        p[9:, 4] = p[9:, 1]
        return p, k

    with raises_naming("train.npz", "'simulation_trajectory_1'", "frame 9", "particles 1 and 4",
                       "coincide"):
        read_trajectories(gns_with(tmp_path, overlap))
    # Within the relative tolerance (not only bit-equal), and only then.
    pos = np.stack([walk(np.random.default_rng(k), t=10, n=4) for k in range(3)]).astype(float)
    near = pos.copy()
    near[2, 6, 3] = near[2, 6, 0] + 1e-14
    with raises_naming("n.npz", "trajectory '2'", "frame 6", "particles 0 and 3"):
        read_trajectories(write_arrays_npz(tmp_path / "n.npz", positions=near, dt=0.1))
    near[2, 6, 3] = near[2, 6, 0] + 1e-9
    read_trajectories(write_arrays_npz(tmp_path / "far.npz", positions=near, dt=0.1))


def test_masses_must_be_positive(tmp_path: Path) -> None:
    pos = walk(np.random.default_rng(0), t=10, n=3)[None].repeat(3, 0).astype(float)
    masses = np.ones((3, 3))
    masses[1, 2] = 0.0
    path = write_arrays_npz(tmp_path / "m.npz", positions=pos, dt=0.1, masses=masses,
                            split=["train", "train", "val"])
    with raises_naming("m.npz", "trajectory '1'", "particle 2", "mass", "positive"):
        read_trajectories(path)


def test_too_few_frames(tmp_path: Path) -> None:
    folder = write_gns_npz(tmp_path, {"train": trajectories(0, 3, t=2)}, META)
    with raises_naming("train.npz", "2 frames", "3"):
        read_trajectories(folder)
    raw = read_trajectories(write_gns_npz(tmp_path / "b", {"train": trajectories(0, 3, t=5)},
                                          META))
    with raises_naming(str(tmp_path / "b"), "5 frames", "fewer than the 7"):
        check_trajectories(raw, min_frames=7)


def test_metadata_dim_must_match(tmp_path: Path) -> None:
    with raises_naming("metadata.json", "dim=3", "2-dimensional"):
        read_trajectories(gns_with(tmp_path, lambda p, k: (p, k), META | {"dim": 3}))


def test_check_names_in_memory_trajectories() -> None:
    pos = np.zeros((1, 4, 2, 1))
    pos[0, :, 1] = 1.0 + 0.1 * np.arange(4)[:, None]  # one particle moves: something to learn
    raw = RawTrajectories(splits={"train": SplitArrays(positions=pos)}, dt=float("nan"))
    with raises_naming("my data", "dt=nan"):
        check_trajectories(raw, 3, where="my data")
    raw.dt = 0.1
    check_trajectories(raw, 3)
    raw.metadata = {"dim": 1}
    check_trajectories(raw, 3)
    assert json.dumps(raw.metadata)
