"""Writers of the foreign trajectory layouts ``bgn.data.formats`` reads, for round-trip tests.

``splits`` map a split (bgn's ``train``/``val``/``test`` or the files' ``valid``) to a list of
trajectories ``(positions (T, N, D), particle_type (N,))``, GNS also ``(..., material)``.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bgn.data.formats import SPLIT_STEMS, _sequence_example_class

Trajectory = tuple[np.ndarray, ...]


def _stem(split: str) -> str:
    return SPLIT_STEMS.get(split, split)


def _write_metadata(folder: Path, metadata: dict[str, Any] | None) -> None:
    if metadata is not None:
        (folder / "metadata.json").write_text(json.dumps(metadata))


def write_gns_npz(folder: str | Path, splits: dict[str, list[Trajectory]],
                  metadata: dict[str, Any] | None) -> Path:
    """GNS layout: one ``simulation_trajectory_<i>`` key per trajectory holding the tuple as an
    object array (what GNS's tfrecord-to-npz conversion writes)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for split, trajs in splits.items():
        entries = {}
        for i, traj in enumerate(trajs):
            item = np.empty(len(traj), dtype=object)
            for k, part in enumerate(traj):
                item[k] = part
            entries[f"simulation_trajectory_{i}"] = item
        np.savez_compressed(folder / f"{_stem(split)}.npz", **entries)
    _write_metadata(folder, metadata)
    return folder


def write_lagrangebench(folder: str | Path, splits: dict[str, list[Trajectory]],
                        metadata: dict[str, Any] | None) -> Path:
    """LagrangeBench layout: ``{train,valid,test}.h5`` with groups ``00000``, ..."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for split, trajs in splits.items():
        with h5py.File(folder / f"{_stem(split)}.h5", "w") as f:
            for i, (pos, ptype) in enumerate(trajs):
                g = f.create_group(f"{i:05d}")
                g.create_dataset("position", data=pos)
                g.create_dataset("particle_type", data=ptype)
    _write_metadata(folder, metadata)
    return folder


def write_arrays_npz(path: str | Path, **arrays: Any) -> Path:
    path = Path(path)
    path = path if path.suffix == ".npz" else path.with_name(path.name + ".npz")  # as np.savez
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return path


def write_arrays_h5(path: str | Path, **arrays: Any) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            v = np.asarray(value)
            f.create_dataset(key, data=v.astype("S") if v.dtype.kind == "U" else v)
    return path


def write_tfrecord(folder: str | Path, splits: dict[str, list[Trajectory]],
                   metadata: dict[str, Any] | None) -> Path:
    """learning_to_simulate layout: SequenceExamples (context ``key``, ``particle_type`` bytes;
    feature list ``position``, float32 bytes per step) framed by TensorBoard's RecordWriter."""
    from tensorboard.summary.writer.record_writer import RecordWriter

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    sequence_example = _sequence_example_class()
    key = 0
    for split, trajs in splits.items():
        with open(folder / f"{_stem(split)}.tfrecord", "wb") as fh:
            writer = RecordWriter(fh)
            for pos, ptype in trajs:
                ex = sequence_example()
                ex.context.feature["key"].int64_list.value.append(key)
                ex.context.feature["particle_type"].bytes_list.value.append(
                    np.asarray(ptype, dtype=np.int64).tobytes())
                steps = ex.feature_lists.feature_list["position"].feature
                for frame in np.asarray(pos, dtype=np.float32):
                    steps.add().bytes_list.value.append(frame.tobytes())
                writer.write(ex.SerializeToString())
                key += 1
    _write_metadata(folder, metadata)
    return folder


def damage_tfrecord_length(path: str | Path) -> None:
    """Flip a bit of the first record's length, so its checksum fails."""
    data = bytearray(Path(path).read_bytes())
    (length,) = struct.unpack("<Q", data[:8])
    data[:8] = struct.pack("<Q", length ^ 1)
    Path(path).write_bytes(bytes(data))
