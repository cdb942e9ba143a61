"""Writers for the foreign layouts bgn imports (DESIGN.md section 11), shared by the engine
scripts in this folder: plain arrays (npz), LagrangeBench HDF5 and GNS / learning_to_simulate npz.

Every writer fills a temporary folder beside the target and renames it at the end, so an
interrupted run leaves nothing half-written under the target name.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np

SPLITS = ("train", "val", "test")
# file stems of the two published layouts (they call the validation split "valid")
FILE_STEMS = {"train": "train", "val": "valid", "test": "test"}


def assign_splits(n_sims: int, seed: int, fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
                  ) -> np.ndarray:
    """Split name per trajectory (whole trajectories only), shuffled with ``seed``; at least one
    trajectory in each split."""
    if n_sims < 3:
        raise SystemExit(f"--sims {n_sims}: need at least 3 trajectories (one per split)")
    n_val = max(1, round(fractions[1] * n_sims))
    n_test = max(1, round(fractions[2] * n_sims))
    names = np.array(["train"] * (n_sims - n_val - n_test) + ["val"] * n_val + ["test"] * n_test)
    return names[np.random.default_rng(seed).permutation(n_sims)]


@contextmanager
def output_dir(out: str | Path, overwrite: bool) -> Iterator[Path]:
    """A temporary folder that becomes ``out`` when the block ends without error."""
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise SystemExit(f"{out} exists and is not empty: pass --overwrite or choose another --out")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)


def minimum_image(d: np.ndarray, box: np.ndarray | None) -> np.ndarray:
    """Displacements wrapped into [-box/2, box/2) where ``box`` (D,) is periodic (None: as is)."""
    if box is None:
        return d
    return d - box * np.round(d / box)


def frame_statistics(trajectories: list[np.ndarray], box: np.ndarray | None = None
                     ) -> dict[str, list[float]]:
    """vel/acc mean and std per dimension as learning_to_simulate and LagrangeBench define them:
    per-frame position differences (not divided by dt), minimum image where periodic, over all
    frames and particles of the given (training) trajectories."""
    vels = [minimum_image(np.diff(p.astype(np.float64), axis=0), box) for p in trajectories]
    accs = [np.diff(v, axis=0) for v in vels]
    v = np.concatenate([x.reshape(-1, x.shape[-1]) for x in vels])
    a = np.concatenate([x.reshape(-1, x.shape[-1]) for x in accs])
    return {"vel_mean": v.mean(0).tolist(), "vel_std": v.std(0).tolist(),
            "acc_mean": a.mean(0).tolist(), "acc_std": a.std(0).tolist()}


def write_energy(out: Path, split: np.ndarray, series: list[dict[str, np.ndarray]]) -> None:
    """``energy.npz``: the engine's own per-frame series (energy, momenta...) of every
    trajectory, its split and ``index``, its number within its split's file (the layouts
    with one file per split)."""
    index = np.empty(len(split), dtype=np.int64)
    for name in ("train", "val", "test"):
        index[split == name] = np.arange((split == name).sum())
    np.savez(out / "energy.npz", split=split.astype("U5"), index=index,
             **{k: np.stack([e[k] for e in series]) for k in series[0]})


def write_json(path: Path, obj: dict[str, Any]) -> None:
    path.write_text(json.dumps(obj, indent=2) + "\n")


def write_plain_npz(path: Path, *, positions: np.ndarray, dt: float, split: np.ndarray,
                    **arrays: np.ndarray) -> None:
    """Plain arrays: positions (S, T, N, D), dt, split (S,) names and optional per-trajectory
    arrays (masses (S, N), velocities (S, T, N, D), ...)."""
    np.savez(path, positions=positions, dt=np.float64(dt), split=split.astype("U5"), **arrays)


def write_lagrangebench(out: Path, trajectories: list[np.ndarray], types: list[np.ndarray],
                        split: np.ndarray, metadata: dict[str, Any]) -> None:
    """LagrangeBench HDF5: {train,valid,test}.h5, groups "00000".. with ``position`` (T, N, D)
    float32 and ``particle_type`` (N,); metadata.json gets the split sizes and the statistics."""
    for name in SPLITS:
        idx = np.flatnonzero(split == name)
        with h5py.File(out / f"{FILE_STEMS[name]}.h5", "w") as f:
            for j, i in enumerate(idx):
                g = f.create_group(str(j).zfill(5))
                g.create_dataset("particle_type", data=types[i])
                g.create_dataset("position", data=trajectories[i].astype(np.float32),
                                 compression="gzip")
    train = [trajectories[i] for i in np.flatnonzero(split == "train")]
    box = None
    if any(metadata["periodic_boundary_conditions"]):
        bounds = np.asarray(metadata["bounds"], dtype=np.float64)
        box = np.where(metadata["periodic_boundary_conditions"], bounds[:, 1] - bounds[:, 0],
                       np.inf)
    metadata = dict(metadata)
    seq = trajectories[0].shape[0] - 1  # positions per trajectory minus the last target
    metadata.update(sequence_length_train=seq, num_trajs_train=int((split == "train").sum()),
                    sequence_length_test=seq, num_trajs_test=int((split == "test").sum()),
                    **frame_statistics(train, box))
    write_json(out / "metadata.json", metadata)


def write_gns(out: Path, trajectories: list[np.ndarray], types: list[np.ndarray],
              split: np.ndarray, metadata: dict[str, Any]) -> None:
    """GNS npz: {train,valid,test}.npz, key ``simulation_trajectory_<j>`` holding the object
    pair (positions (T, N, D) float32, particle_type (N,)); metadata.json with statistics from
    the training split and ``sequence_length`` = frames - 1 (learning_to_simulate's count)."""
    for name in SPLITS:
        entries = {}
        for j, i in enumerate(np.flatnonzero(split == name)):
            pair = np.empty(2, dtype=object)
            pair[0] = trajectories[i].astype(np.float32)
            pair[1] = types[i].astype(np.int64)
            entries[f"simulation_trajectory_{j}"] = pair
        np.savez_compressed(out / f"{FILE_STEMS[name]}.npz", **entries)
    train = [trajectories[i] for i in np.flatnonzero(split == "train")]
    metadata = dict(metadata, sequence_length=trajectories[0].shape[0] - 1,
                    **frame_statistics(train))
    write_json(out / "metadata.json", metadata)


def engine_record(engine: str, version: str, params: dict[str, Any], seed: int,
                  seconds: float) -> dict[str, Any]:
    """What engine.json says about a dataset: engine, parameters, seed and the command line."""
    return {"engine": engine, "version": version, "params": params, "seed": seed,
            "command": "python " + " ".join(sys.argv), "generation_seconds": round(seconds, 2)}
