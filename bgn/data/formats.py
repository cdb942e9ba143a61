"""Readers of trajectory files in other projects' layouts, and the checks every import passes.

Each layout reduces to one :class:`bgn.data.raw.RawTrajectories` (float64 positions, int64
types, the frame spacing, the box, the kinematic types, the source files and their sha256):

- ``gns-npz``: a folder with ``{train,valid,test}.npz`` (GNS, geoelements/gns
  ``data_loader.load_npz_data``): one key per trajectory holding ``(positions (T, N, D),
  particle_type (N,) [, material_property])``, or one ``gns_data`` key holding them all; plus
  ``metadata.json`` (``dt``, ``bounds``, ``default_connectivity_radius``, ``dim``, ...).
- ``lagrangebench-h5``: a folder with ``{train,valid,test}.h5`` (tumaer/lagrangebench
  ``data/data.py``): groups ``"00000"``, ... with ``position (T, N, D)`` and ``particle_type
  (N,)``; ``metadata.json`` with ``dt``, ``write_every``, ``bounds``,
  ``periodic_boundary_conditions``, ``default_connectivity_radius``.
- ``arrays-npz`` / ``arrays-h5``: one file with ``positions (S, T, N, D)`` and ``dt``, optionally
  ``masses``, ``radii``, ``types`` ((S, N) or (N,)), ``velocities (S, T, N, D)``, ``box`` ((D,)
  lengths or (D, 2) bounds), ``periodic (D,)``, ``times (T,)`` and ``split (S,)``.
- ``tfrecord``: DeepMind's learning_to_simulate ``{train,valid,test}.tfrecord`` and
  ``metadata.json`` (``reading_utils.py``): SequenceExamples with context ``key`` (int64) and
  ``particle_type`` (bytes of int64), feature list ``position`` (bytes of float32 (N * D) per
  step). Read without TensorFlow: the record framing is parsed here and the protobuf messages
  are declared here from TensorFlow's ``feature.proto``/``example.proto``. The optional
  per-step ``step_context`` (a global input of some datasets) is not read.

Periodic data come back unwrapped (continuous positions, :func:`unwrap_periodic`), so finite
differences are minimum-image displacements. Files are opened without unpickling: a GNS ``.npz``
whose trajectories are pickled Python objects (GNS writes them so) is read only when the caller
says ``allow_pickle`` (unpickling can run code). Keys a layout does not read are named in a
``DataImportWarning`` (with the known key they are closest to: a misspelt ``masse``).
"""

from __future__ import annotations

import difflib
import hashlib
import json
import struct
import warnings
import zipfile
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bgn.data.raw import (
    IMPORT_SPLITS,
    DataImportError,
    DataImportWarning,
    RawTrajectories,
    SplitArrays,
)

FORMATS = ("gns-npz", "lagrangebench-h5", "arrays-npz", "arrays-h5", "tfrecord")
# Other names of the layouts (underscores, the projects' names); "arrays" is told by the suffix
FORMAT_ALIASES = {"gns": "gns-npz", "lagrangebench": "lagrangebench-h5", "lagrangebench-hdf5":
                  "lagrangebench-h5", "learning-to-simulate": "tfrecord", "arrays-hdf5":
                  "arrays-h5"}
# The file stems of the folder layouts for bgn's splits (all three projects say "valid").
SPLIT_STEMS = {"train": "train", "val": "valid", "test": "test"}
FOLDER_SUFFIX = {"gns-npz": ".npz", "lagrangebench-h5": ".h5", "tfrecord": ".tfrecord"}
# learning_to_simulate and GNS: type 3 is the kinematic (obstacle/boundary) particle
# (learning_to_simulate/train.py KINEMATIC_PARTICLE_ID = 3).
GNS_KINEMATIC_TYPES = (3,)
# LagrangeBench NodeType: 0 fluid, 1 solid wall, 2 moving wall, 3 rigid body; its
# lagrangebench/utils.py get_kinematic_mask marks SOLID_WALL and MOVING_WALL as kinematic.
LAGRANGEBENCH_KINEMATIC_TYPES = (1, 2)
COINCIDENT_RTOL = 1e-12  # two particles closer than this times the coordinates' scale
TIMES_RTOL = 1e-6  # allowed relative spread of the spacing of given times
ARRAY_KEYS = ("positions", "dt", "masses", "radii", "types", "velocities", "box", "periodic",
              "times", "split")
# metadata.json keys some reader uses: a near miss of one of them is warned about
GNS_ITEM_KEYS = ("positions", "position", "particle_type", "particle_types", "material_property")
METADATA_KEYS = ("dt", "bounds", "dim", "default_connectivity_radius", "write_every",
                 "periodic_boundary_conditions")
# The models compute in float32 (largest 3.4e38, smallest normal 1.2e-38): positions and the
# typical velocity and acceleration of the frames (finite differences over dt) must lie well
# inside, or squared distances overflow and targets vanish
PLAUSIBLE = (1e-30, 1e30)
SPLIT_CODES = {"train": "train", "val": "val", "valid": "val", "validation": "val",
               "test": "test", 0: "train", 1: "val", 2: "test"}


def format_name(fmt: str, path: str | Path | None = None) -> str:
    """The layout ``fmt`` names (``gns_npz``, ``lagrangebench``: other spellings accepted;
    ``arrays``: npz or h5 by the suffix of ``path``); refused with the choices."""
    name = str(fmt).strip().lower().replace("_", "-")
    name = FORMAT_ALIASES.get(name, name)
    if name == "arrays":
        name = "arrays-h5" if path is not None and Path(path).suffix in (".h5", ".hdf5") \
            else "arrays-npz"
    if name not in FORMATS:
        raise DataImportError(f"format={fmt!r} is not a layout bgn reads; choose one of "
                              f"{', '.join(FORMATS)}, or leave it out (null) to detect it")
    return name


# ---------------------------------------------------------------------------------------------
# Detection and the entry point


def detect_format(path: str | Path) -> str:
    """The layout of ``path`` (a folder or a file), told from its files."""
    p = Path(path)
    looked_for = ("a folder with train/valid/test .npz (GNS), .h5 with groups holding "
                  "'position' (LagrangeBench) or .tfrecord (learning_to_simulate), or one "
                  ".npz/.h5 file with a 'positions' array (plain arrays)")
    if not p.exists():
        raise DataImportError(f"{p}: no such file or folder; give the folder or file that "
                              f"holds the trajectories ({looked_for})")
    if p.is_file():
        if p.suffix == ".npz":
            with open_npz(p) as f:
                if "positions" in f.files:
                    return "arrays-npz"
                found = ", ".join(f.files[:8])
        elif p.suffix in (".h5", ".hdf5"):
            with open_h5(p) as f:
                if isinstance(f.get("positions"), h5py.Dataset):
                    return "arrays-h5"
                found = ", ".join(list(f.keys())[:8])
        else:
            raise DataImportError(f"{p}: unknown format (suffix '{p.suffix}'); looked for "
                                  f"{looked_for}")
        raise DataImportError(f"{p}: no 'positions' array (found {found or 'nothing'}); "
                              f"looked for {looked_for}")
    for fmt, suffix in FOLDER_SUFFIX.items():
        files = [p / f"{stem}{suffix}" for stem in SPLIT_STEMS.values()]
        present = [f for f in files if f.is_file()]
        if not present:
            continue
        if fmt == "lagrangebench-h5":
            with open_h5(present[0]) as f:
                groups = [k for k in f if isinstance(f[k], h5py.Group)]
                if not groups or "position" not in f[groups[0]]:
                    raise DataImportError(
                        f"{present[0]}: not LagrangeBench's layout (no groups holding "
                        f"'position'); give a LagrangeBench folder or one plain-array file")
        return fmt
    contents = ", ".join(sorted(q.name for q in p.iterdir())[:10])
    raise DataImportError(f"{p}: unknown format (holds {contents or 'nothing'}); looked for "
                          f"{looked_for}")


def read_trajectories(path: str | Path, fmt: str | None = None, split_seed: int = 0,
                      split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1),
                      allow_pickle: bool = False) -> RawTrajectories:
    """Read ``path`` in layout ``fmt`` (detected when None; other spellings:
    :func:`format_name`) into checked ``RawTrajectories``.

    Splits the files lack are carved from the training trajectories by
    :func:`split_by_trajectory` with ``split_seed``. A ``gns-npz`` file of pickled tuples (GNS
    writes them so) is refused unless ``allow_pickle``: unpickling a file can run code, so only
    files you trust."""
    p = Path(path)
    if not p.exists():
        raise DataImportError(f"{p}: no such file or folder; give the path of the trajectories")
    fmt = detect_format(p) if fmt is None else format_name(fmt, p)
    if p.is_dir() != (fmt in FOLDER_SUFFIX):
        raise DataImportError(f"{p}: format {fmt} is read from a "
                              f"{'folder' if fmt in FOLDER_SUFFIX else 'file'}, and this is "
                              f"{'a folder' if p.is_dir() else 'not one'}; give the right path "
                              f"or leave the format out to detect it")
    try:
        if fmt == "gns-npz":  # the one layout that may hold pickled objects
            raw, split_files = _read_gns(p, split_seed, split_fractions, allow_pickle)
        else:
            reader = {"lagrangebench-h5": _read_lagrangebench, "arrays-npz": _read_arrays,
                      "arrays-h5": _read_arrays, "tfrecord": _read_tfrecord}[fmt]
            raw, split_files = reader(p, fmt, split_seed, split_fractions)
    except DataImportError as err:  # every message names the source (splitting's do not)
        if str(p) in str(err):
            raise
        raise DataImportError(f"{p}: {err}") from None
    root = p if p.is_dir() else p.parent
    used = sorted({f for files in split_files.values() for f in files}
                  | ({p / "metadata.json"} if (p / "metadata.json").is_file() else set()))
    raw.source = {"format": fmt, "path": str(p),
                  "files": {str(f.relative_to(root)): _sha256(f) for f in used},
                  "split_files": {k: [str(f.relative_to(root)) for f in v]
                                  for k, v in split_files.items()}}
    if raw.periodic is not None and raw.periodic.any():
        for split in raw.splits.values():
            split.positions = unwrap_periodic(split.positions, raw.bounds, raw.periodic)
    check_trajectories(raw, min_frames=3)
    return raw


# ---------------------------------------------------------------------------------------------
# Layout readers: each returns the trajectories and, per split, the files it came from


Read = tuple[RawTrajectories, dict[str, list[Path]]]


def _read_gns(p: Path, seed: int, fractions: Sequence[float], allow_pickle: bool) -> Read:
    meta = _metadata(p)
    splits, files, material = {}, {}, {}
    for split, stem in SPLIT_STEMS.items():
        f = p / f"{stem}.npz"
        if not f.is_file():
            continue
        names, trajs, mats, unread = [], [], [], set()
        for name, item in _gns_items(f, allow_pickle):
            pos, ptype, mat = _gns_trajectory(item, f, name, unread)
            names.append(name)
            trajs.append((pos, ptype))
            mats.append(mat)
        warn_ignored(sorted(unread), GNS_ITEM_KEYS, f"{f} (its trajectories)")
        splits[split] = _stack(trajs, names, f)
        files[split] = [f]
        if any(m is not None for m in mats):
            material[split] = [None if m is None else _jsonable(m) for m in mats]
    if material:
        # Recorded for provenance; no bgn model reads a per-particle material yet.
        meta = {**meta, "material": material}
    raw = RawTrajectories(splits=splits, dt=_meta_dt(meta, p), metadata=meta,
                          bounds=_meta_bounds(meta, p), kinematic_types=GNS_KINEMATIC_TYPES,
                          connectivity_radius=_meta_float(meta, "default_connectivity_radius"))
    raw.periodic = None if raw.bounds is None else np.zeros(len(raw.bounds), dtype=bool)
    return _fill_splits(raw, files, p / "train.npz", seed, fractions)


def _gns_items(f: Path, allow_pickle: bool) -> Iterator[tuple[str, Any]]:
    """(name, trajectory) of a GNS npz, unpickled only with ``allow_pickle``."""
    with open_npz(f, allow_pickle) as data:
        if "gns_data" in data.files:
            for i, item in enumerate(_npz_member(data, "gns_data", f)):
                yield f"gns_data[{i}]", item
        else:
            for name in data.files:
                yield name, _npz_member(data, name, f)


@contextmanager
def open_npz(f: Path, allow_pickle: bool = False) -> Iterator[Any]:
    """``np.load`` of a ``.npz`` archive, refused in one line when it is none (empty, cut
    short, text): numpy would take such a file for a pickle."""
    size = f.stat().st_size
    if size == 0:
        raise DataImportError(f"{f}: the file is empty (0 bytes); copy it again or give the "
                              f"file that holds the trajectories")
    if not zipfile.is_zipfile(f):
        with open(f, "rb") as fh:
            head = fh.read(4)
        what = ("a zip archive cut short (its directory at the end is missing)"
                if head.startswith(b"PK") else "not a .npz archive (no zip signature)")
        raise DataImportError(f"{f}: {what}; the file is damaged or incomplete, or not numpy's "
                              f".npz: copy it again or write it with numpy.savez")
    try:
        data = np.load(f, allow_pickle=allow_pickle)
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise DataImportError(f"{f}: cannot be read as a .npz archive ({err}); copy it "
                              f"again or write it with numpy.savez") from None
    with data:
        yield data


def _npz_member(data: Any, key: str, f: Path, may_pickle: bool = True) -> Any:
    """One array of an open ``.npz``; damaged bytes and pickled objects refused in one line
    (``may_pickle``: the layout may hold them, with ``allow_pickle``)."""
    try:
        return data[key]
    except ValueError as err:
        if "allow_pickle" not in str(err):
            raise DataImportError(f"{f}: key '{key}' cannot be read ({err}); the file is "
                                  f"damaged: copy it again") from None
        if not may_pickle:
            raise DataImportError(f"{f}: key '{key}' holds pickled Python objects, which "
                                  f"plain-array files do not; save it as numbers (numpy.savez "
                                  f"of a float or int array)") from None
        raise DataImportError(
            f"{f}: key '{key}' holds pickled Python objects, and unpickling a file can run "
            f"code; if you trust the file, import it with allow_pickle=true") from None
    except (OSError, EOFError, zlib.error, zipfile.BadZipFile) as err:
        raise DataImportError(f"{f}: key '{key}' cannot be read ({err}); the file is damaged "
                              f"or incomplete: copy it again") from None


@contextmanager
def open_h5(f: Path) -> Iterator[h5py.File]:
    """``h5py.File(f, "r")``, refused in one line when it is no readable HDF5 file."""
    try:
        handle = h5py.File(f, "r")
    except OSError as err:
        raise DataImportError(f"{f}: not a readable HDF5 file ({err}); the file is damaged, "
                              f"incomplete or not HDF5: copy it again") from None
    with handle:
        try:
            yield handle
        except OSError as err:  # a damaged dataset inside a file that opens
            raise DataImportError(f"{f}: cannot be read ({err}); the file is damaged or "
                                  f"incomplete: copy it again") from None


def _gns_trajectory(item: Any, f: Path, name: str, unread: set[str]
                    ) -> tuple[np.ndarray, np.ndarray, Any]:
    """One GNS trajectory: (positions, types, material); keys of a dict item that are not read
    go to ``unread`` (warned about once per file)."""
    if isinstance(item, np.ndarray) and item.dtype == object and item.ndim == 0:
        item = item.item()
    if isinstance(item, dict):
        pos = item.get("positions", item.get("position"))
        ptype = item.get("particle_type", item.get("particle_types"))
        mat = item.get("material_property")
        unread.update(str(k) for k in item if k not in GNS_ITEM_KEYS)
    elif len(item) in (2, 3):
        pos, ptype = item[0], item[1]
        mat = item[2] if len(item) == 3 else None
    else:
        pos = None
    if pos is None or ptype is None:
        raise DataImportError(f"{f}: trajectory '{name}' is not (positions, particle_type "
                              f"[, material_property]); write each key as that tuple")
    if isinstance(pos, list | tuple) or (isinstance(pos, np.ndarray) and pos.dtype.kind == "O"
                                         and pos.ndim == 1):  # frames one by one
        _equal_counts(pos, f, name)
        pos = np.stack([np.asarray(x) for x in pos]) if len(pos) else np.zeros((0, 0, 0))
    pos = floats(pos, f"{f}: trajectory '{name}' positions")
    if pos.ndim != 3:
        raise DataImportError(f"{f}: trajectory '{name}' positions have shape {pos.shape}, "
                              f"not (T, N, D); write positions per frame, particle, dimension")
    return pos, _per_particle(ptype, pos.shape[1], f, name, "particle_type"), mat


def _read_lagrangebench(p: Path, fmt: str, seed: int, fractions: Sequence[float]) -> Read:
    meta = _metadata(p)
    splits, files = {}, {}
    for split, stem in SPLIT_STEMS.items():
        f = p / f"{stem}.h5"
        if not f.is_file():
            continue
        names, trajs = [], []
        with open_h5(f) as h:
            for name in sorted(h.keys()):
                g = h[name]
                if not isinstance(g, h5py.Group) or "position" not in g:
                    raise DataImportError(f"{f}: '{name}' is not a trajectory group with "
                                          f"'position'; LagrangeBench files hold only those")
                pos = floats(g["position"][()], f"{f}: trajectory '{name}' position")
                if pos.ndim != 3:
                    raise DataImportError(f"{f}: trajectory '{name}' position has shape "
                                          f"{pos.shape}, not (T, N, D)")
                if "particle_type" not in g:
                    raise DataImportError(f"{f}: trajectory '{name}' has no particle_type; "
                                          f"add one per particle (0 for fluid)")
                names.append(name)
                trajs.append((pos, _per_particle(g["particle_type"][()], pos.shape[1], f,
                                                 name, "particle_type")))
        splits[split] = _stack(trajs, names, f)
        files[split] = [f]
    if "write_every" not in meta:
        raise DataImportError(f"{p / 'metadata.json'}: no write_every; LagrangeBench frames "
                              f"are dt * write_every apart: add it (1 if every step was kept)")
    dt = _meta_dt(meta, p) * float(meta["write_every"])
    bounds = _meta_bounds(meta, p)
    periodic = meta.get("periodic_boundary_conditions")
    if periodic is not None:
        periodic = np.asarray(periodic, dtype=bool)
        if bounds is None and periodic.any():
            raise DataImportError(f"{p / 'metadata.json'}: periodic_boundary_conditions "
                                  f"without bounds; add bounds [[low, high], ...] per dimension")
    elif bounds is not None:
        periodic = np.zeros(len(bounds), dtype=bool)
    if periodic is not None and bounds is not None and len(periodic) != len(bounds):
        raise DataImportError(f"{p / 'metadata.json'}: periodic_boundary_conditions has "
                              f"{len(periodic)} entries but bounds {len(bounds)}; one per "
                              f"dimension in both")
    raw = RawTrajectories(splits=splits, dt=dt, bounds=bounds, periodic=periodic,
                          kinematic_types=LAGRANGEBENCH_KINEMATIC_TYPES, metadata=meta,
                          connectivity_radius=_meta_float(meta, "default_connectivity_radius"))
    return _fill_splits(raw, files, p / "train.h5", seed, fractions)


def _read_arrays(p: Path, fmt: str, seed: int, fractions: Sequence[float]) -> Read:
    arrays = _load_arrays(p, fmt)
    pos = floats(arrays["positions"], f"{p}: positions")
    if pos.ndim == 3:
        pos = pos[None]  # one trajectory given as (T, N, D)
    if pos.ndim != 4:
        raise DataImportError(f"{p}: positions have shape {pos.shape}, not (S, T, N, D) or "
                              f"(T, N, D); reshape them to trajectories, frames, particles, dims")
    s, t, n, d = pos.shape
    dt = _arrays_dt(arrays, p, t)
    per_particle = {}
    for key, dtype in (("masses", np.float64), ("radii", np.float64), ("types", np.int64)):
        if key in arrays:
            per_particle[key] = _per_trajectory_particles(arrays[key], s, n, p, key, dtype)
    vel = None
    if "velocities" in arrays:
        vel = floats(arrays["velocities"], f"{p}: velocities")
        vel = vel[None] if vel.ndim == 3 else vel
        if vel.shape != pos.shape:
            raise DataImportError(f"{p}: velocities have shape {vel.shape}, positions "
                                  f"{pos.shape}; give one velocity per position")
    bounds, periodic = _arrays_box(arrays, p, d)
    names = [str(i) for i in range(s)]
    whole = SplitArrays(positions=pos, velocities=vel, names=names, **per_particle)
    raw = RawTrajectories(splits={}, dt=dt, bounds=bounds, periodic=periodic)
    if "split" in arrays:
        labels = np.asarray(arrays["split"]).reshape(-1)
        if labels.dtype.kind in "SU":
            labels = labels.astype(str)
        if len(labels) != s:
            raise DataImportError(f"{p}: split has {len(labels)} entries for {s} trajectories; "
                                  f"give one split per trajectory")
        codes = [SPLIT_CODES.get(v.item() if hasattr(v, "item") else v) for v in labels]
        bad = [i for i, c in enumerate(codes) if c is None]
        if bad:
            raise DataImportError(f"{p}: trajectory {bad[0]} has split '{labels[bad[0]]}'; "
                                  f"use train/val/test (or 0/1/2)")
        for split in IMPORT_SPLITS:
            idx = [i for i, c in enumerate(codes) if c == split]
            if idx:
                raw.splits[split] = _take(whole, np.asarray(idx))
        return raw, {k: [p] for k in raw.splits}
    raw.splits = split_by_trajectory(whole, fractions, seed)
    return raw, {k: [p] for k in raw.splits}


def _load_arrays(p: Path, fmt: str) -> dict[str, Any]:
    if fmt == "arrays-npz":
        with open_npz(p) as f:
            arrays = {k: _npz_member(f, k, p, may_pickle=False) for k in f.files
                      if k in ARRAY_KEYS}
            ignored = [k for k in f.files if k not in ARRAY_KEYS]
    else:
        with open_h5(p) as f:
            arrays = {k: f[k][()] for k in ARRAY_KEYS if isinstance(f.get(k), h5py.Dataset)}
            ignored = [k for k in f if k not in arrays]
            if "dt" not in arrays and "dt" in f.attrs:
                arrays["dt"] = f.attrs["dt"]  # bgn's own files keep dt as an attribute
            if "split" in arrays and arrays["split"].dtype.kind == "O":
                arrays["split"] = np.asarray([v.decode() if isinstance(v, bytes) else v
                                              for v in arrays["split"]])
    if "positions" not in arrays:
        raise DataImportError(f"{p}: no 'positions' array; write positions (S, T, N, D)")
    warn_ignored(ignored, ARRAY_KEYS, str(p))
    return arrays


def warn_ignored(keys: Sequence[str], known: Sequence[str], where: str,
                 near_misses_only: bool = False) -> None:
    """A ``DataImportWarning`` naming the ``keys`` no reader uses, each with the known key it
    is closest to (a misspelling would otherwise drop the data: ``masse``). Sources with
    many keys of their own (metadata.json) warn only of near misses."""
    notes = []
    for key in keys:
        close = difflib.get_close_matches(str(key), known, n=1, cutoff=0.75)
        if close:
            notes.append(f"'{key}' (did you mean '{close[0]}'?)")
        elif not near_misses_only:
            notes.append(f"'{key}'")
    if notes:
        warnings.warn(f"{where}: ignored {', '.join(notes)}; bgn reads {', '.join(known)}",
                      DataImportWarning, stacklevel=2)


def _arrays_dt(arrays: dict[str, Any], p: Path, n_frames: int) -> float:
    dt = float(floats(arrays["dt"], f"{p}: dt").reshape(-1)[0]) if "dt" in arrays else None
    if "dt" in arrays and np.size(arrays["dt"]) != 1:
        raise DataImportError(f"{p}: dt has {np.size(arrays['dt'])} values; give one frame "
                              f"spacing (a scalar)")
    if "times" in arrays:
        times = floats(arrays["times"], f"{p}: times").reshape(-1, n_frames) \
            if np.size(arrays["times"]) % n_frames == 0 else None
        if times is None or n_frames < 2:
            raise DataImportError(f"{p}: times have shape {np.shape(arrays['times'])} for "
                                  f"{n_frames} frames; give one time per frame")
        steps = np.diff(times, axis=1)
        spacing = float(np.median(steps))
        tol = TIMES_RTOL * abs(spacing) + 8 * np.finfo(np.float64).eps * np.abs(times).max()
        off = np.abs(steps - spacing) > tol
        if off.any():
            traj, frame = (int(i) for i in np.argwhere(off)[0])
            raise DataImportError(
                f"{p}: times are not uniformly spaced: trajectory {traj}, frame {frame} to "
                f"{frame + 1} is {steps[traj, frame]:.6g} apart, not {spacing:.6g}; resample "
                f"the trajectories to a uniform spacing")
        if dt is None:
            dt = spacing
        elif not np.isclose(dt, spacing, rtol=TIMES_RTOL, atol=0.0):
            raise DataImportError(f"{p}: dt={dt:.6g} but the times are {spacing:.6g} apart; "
                                  f"fix dt or the times")
    if dt is None:
        raise DataImportError(f"{p}: no dt (and no times); add the time between frames as "
                              f"'dt'")
    return dt


def _arrays_box(arrays: dict[str, Any], p: Path, d: int) -> tuple[Any, Any]:
    bounds = None
    if "box" in arrays:
        box = floats(arrays["box"], f"{p}: box")
        if box.shape == (d,):
            bounds = np.stack([np.zeros(d), box], axis=1)
        elif box.shape == (d, 2):
            bounds = box
        else:
            raise DataImportError(f"{p}: box has shape {box.shape}; give ({d},) lengths or "
                                  f"({d}, 2) lower/upper bounds")
        if not (np.isfinite(bounds).all() and (bounds[:, 1] > bounds[:, 0]).all()):
            raise DataImportError(f"{p}: box {bounds.tolist()} is not a finite box with "
                                  f"upper > lower in every dimension")
    periodic = None
    if "periodic" in arrays:
        periodic = np.broadcast_to(np.asarray(arrays["periodic"], dtype=bool), (d,)).copy()
        if periodic.any() and bounds is None:
            raise DataImportError(f"{p}: periodic dimensions without a box; add 'box'")
    elif bounds is not None:
        periodic = np.zeros(d, dtype=bool)
    return bounds, periodic


def _read_tfrecord(p: Path, fmt: str, seed: int, fractions: Sequence[float]) -> Read:
    meta = _metadata(p)
    sequence_example = _sequence_example_class()
    splits, files = {}, {}
    for split, stem in SPLIT_STEMS.items():
        f = p / f"{stem}.tfrecord"
        if not f.is_file():
            continue
        names, trajs = [], []
        for i, record in enumerate(_tfrecords(f)):
            ex = sequence_example.FromString(record)
            context = ex.context.feature
            name = str(context["key"].int64_list.value[0]) if "key" in context and \
                context["key"].int64_list.value else str(i)
            if "particle_type" not in context or "position" not in ex.feature_lists.feature_list:
                raise DataImportError(f"{f}: record {i} (key {name}) lacks particle_type or "
                                      f"position; not a learning_to_simulate trajectory")
            types = np.frombuffer(b"".join(context["particle_type"].bytes_list.value),
                                  dtype=np.int64)
            steps = ex.feature_lists.feature_list["position"].feature
            flat = np.frombuffer(b"".join(b"".join(s.bytes_list.value) for s in steps),
                                 dtype=np.float32)
            t, n = len(steps), len(types)
            if n == 0 or t == 0 or flat.size % (t * n):
                raise DataImportError(f"{f}: trajectory {name} holds {flat.size} position "
                                      f"values for {t} steps of {n} particles; the record is "
                                      f"damaged or not learning_to_simulate's layout")
            names.append(name)
            trajs.append((flat.reshape(t, n, -1).astype(np.float64), types.astype(np.int64)))
        if not trajs:
            raise DataImportError(f"{f}: no records; write at least one trajectory")
        splits[split] = _stack(trajs, names, f)
        files[split] = [f]
    raw = RawTrajectories(splits=splits, dt=_meta_dt(meta, p), metadata=meta,
                          bounds=_meta_bounds(meta, p), kinematic_types=GNS_KINEMATIC_TYPES,
                          connectivity_radius=_meta_float(meta, "default_connectivity_radius"))
    raw.periodic = None if raw.bounds is None else np.zeros(len(raw.bounds), dtype=bool)
    return _fill_splits(raw, files, p / "train.tfrecord", seed, fractions)


def _tfrecords(f: Path) -> Iterator[bytes]:
    """Records of a TFRecord file: uint64 length, uint32 masked crc32c of the length, the
    data, uint32 masked crc32c of the data (little-endian). The length's checksum is verified;
    the data's is not (pure-Python crc32c would dominate the import); a damaged record fails
    to parse or to reshape instead."""
    from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c

    with open(f, "rb") as fh:
        i = 0
        while header := fh.read(12):
            if len(header) < 12:
                raise DataImportError(f"{f}: record {i} is truncated (header); the file is "
                                      f"incomplete: copy it again")
            (length,), (crc,) = struct.unpack("<Q", header[:8]), struct.unpack("<I", header[8:])
            if masked_crc32c(header[:8]) != crc:
                raise DataImportError(f"{f}: record {i} fails its length checksum; the file is "
                                      f"damaged or not a TFRecord (compressed files are not "
                                      f"read: decompress them first)")
            data = fh.read(length)
            if len(data) < length or len(fh.read(4)) < 4:
                raise DataImportError(f"{f}: record {i} is truncated; the file is incomplete: "
                                      f"copy it again")
            yield data
            i += 1


_SEQUENCE_EXAMPLE = None


def _sequence_example_class() -> Any:
    """tensorflow.SequenceExample, declared from TensorFlow's feature.proto and example.proto
    in a private descriptor pool (no TensorFlow needed, no clash with it when installed)."""
    global _SEQUENCE_EXAMPLE
    if _SEQUENCE_EXAMPLE is not None:
        return _SEQUENCE_EXAMPLE
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fdp = descriptor_pb2.FieldDescriptorProto
    file = descriptor_pb2.FileDescriptorProto(name="bgn_tf_example.proto", package="tensorflow",
                                              syntax="proto3")

    def message(name: str, fields: list[tuple], nested: Any = None) -> Any:
        m = file.message_type.add(name=name) if nested is None else nested.nested_type.add(
            name=name)
        for fname, number, ftype, label, type_name, oneof in fields:
            field = m.field.add(name=fname, number=number, type=ftype, label=label)
            if type_name:
                field.type_name = type_name
            if oneof is not None:
                field.oneof_index = oneof
        return m

    rep, opt = fdp.LABEL_REPEATED, fdp.LABEL_OPTIONAL
    msg, string = fdp.TYPE_MESSAGE, fdp.TYPE_STRING
    message("BytesList", [("value", 1, fdp.TYPE_BYTES, rep, None, None)])
    message("FloatList", [("value", 1, fdp.TYPE_FLOAT, rep, None, None)])
    message("Int64List", [("value", 1, fdp.TYPE_INT64, rep, None, None)])
    feature = message("Feature", [("bytes_list", 1, msg, opt, ".tensorflow.BytesList", 0),
                                  ("float_list", 2, msg, opt, ".tensorflow.FloatList", 0),
                                  ("int64_list", 3, msg, opt, ".tensorflow.Int64List", 0)])
    feature.oneof_decl.add(name="kind")
    for outer, entry, value in (("Features", "FeatureEntry", "Feature"),
                                ("FeatureLists", "FeatureListEntry", "FeatureList")):
        if outer == "FeatureLists":
            message("FeatureList", [("feature", 1, msg, rep, ".tensorflow.Feature", None)])
        m = message(outer, [("feature" if outer == "Features" else "feature_list", 1, msg, rep,
                             f".tensorflow.{outer}.{entry}", None)])
        e = message(entry, [("key", 1, string, opt, None, None),
                            ("value", 2, msg, opt, f".tensorflow.{value}", None)], nested=m)
        e.options.map_entry = True
    message("SequenceExample", [("context", 1, msg, opt, ".tensorflow.Features", None),
                                ("feature_lists", 2, msg, opt, ".tensorflow.FeatureLists",
                                 None)])
    pool = descriptor_pool.DescriptorPool()
    pool.Add(file)
    _SEQUENCE_EXAMPLE = message_factory.GetMessageClass(
        pool.FindMessageTypeByName("tensorflow.SequenceExample"))
    return _SEQUENCE_EXAMPLE


# ---------------------------------------------------------------------------------------------
# Shared pieces of the readers


def _metadata(folder: Path) -> dict[str, Any]:
    f = folder / "metadata.json"
    if not f.is_file():
        return {}
    try:
        meta = json.loads(f.read_text())
    except json.JSONDecodeError as e:
        raise DataImportError(f"{f}: not valid JSON ({e.msg}, line {e.lineno}); fix the file")\
            from None
    if not isinstance(meta, dict):
        raise DataImportError(f"{f}: holds {type(meta).__name__}, not an object of keys")
    warn_ignored([k for k in meta if k not in METADATA_KEYS], METADATA_KEYS, str(f),
                 near_misses_only=True)
    return meta


def _meta_dt(meta: dict[str, Any], folder: Path) -> float:
    if "dt" not in meta:
        raise DataImportError(f"{folder / 'metadata.json'}: no dt; add the time between frames "
                              f"as \"dt\" (create metadata.json if it is missing)")
    try:
        return float(meta["dt"])
    except (TypeError, ValueError):
        raise DataImportError(f"{folder / 'metadata.json'}: dt is {meta['dt']!r}, not a "
                              f"number; give the time between frames") from None


def _meta_bounds(meta: dict[str, Any], folder: Path) -> np.ndarray | None:
    if meta.get("bounds") is None:
        return None
    b = floats(meta["bounds"], f"{folder / 'metadata.json'}: bounds")
    if b.ndim != 2 or b.shape[1] != 2 or not np.isfinite(b).all() or (b[:, 1] <= b[:, 0]).any():
        raise DataImportError(f"{folder / 'metadata.json'}: bounds {meta['bounds']} are not "
                              f"[[low, high], ...] with high > low per dimension")
    return b


def _meta_float(meta: dict[str, Any], key: str) -> float | None:
    return None if meta.get(key) is None else float(meta[key])


def _per_particle(value: Any, n: int, f: Path, name: str, key: str) -> np.ndarray:
    v = types_of(value, f"{f}: trajectory '{name}' {key}")
    if v.size not in (1, n):
        raise DataImportError(f"{f}: trajectory '{name}' has {v.size} {key} values for {n} "
                              f"particles; give one per particle")
    return np.broadcast_to(v.reshape(-1), (n,)).copy()


def _equal_counts(frames: Any, f: Path, name: str) -> None:
    """Frames given one by one (an object array or list) must hold one particle count."""
    shapes = [np.shape(np.asarray(x, dtype=object)) for x in frames]
    for frame, shape in enumerate(shapes):
        if shape != shapes[0]:
            raise DataImportError(
                f"{f}: trajectory '{name}', frame {frame} holds {shape[0] if shape else 0} "
                f"particles where frame 0 holds {shapes[0][0] if shapes[0] else 0}: a "
                f"trajectory keeps its particles in every frame; cut it where the count changes "
                f"and import parts of one count (padding with still kinematic particles fits "
                f"trajectories of different constant counts, not a changing one: the "
                f"equal-count rule, docs/usage.md 'Your own trajectories')")


def floats(value: Any, what: str) -> np.ndarray:
    """``value`` as float64, refused in one line naming ``what`` when it is no numbers."""
    try:
        v = np.asarray(value)
        if v.dtype.kind not in "biufO":  # text is refused, even "0.5"
            raise TypeError(v.dtype)
        return v.astype(np.float64)
    except (TypeError, ValueError):
        example = np.asarray(value, dtype=object).reshape(-1)[:1]
        raise DataImportError(f"{what} are not numbers (e.g. {example[0]!r}); write them as "
                              f"floats") from None


def types_of(value: Any, what: str) -> np.ndarray:
    """Particle types as int64: integers >= 0 (or floats of whole values), refused in one line
    naming ``what`` otherwise (text, fractions and negatives were once cast silently)."""
    v = np.asarray(value)
    if v.dtype.kind not in "biuf":
        first = v.reshape(-1)[0].item() if v.size else None
        kind = "text" if v.dtype.kind in "US" else v.dtype.name
        raise DataImportError(f"{what} are {kind} (e.g. {first!r}), not integers; "
                              f"number the particle types 0, 1, 2, ... in the source data "
                              f"(GNS: 3 marks kinematic particles)")
    for bad, problem in ((~np.isfinite(v) | (v != np.round(v)) if v.dtype.kind == "f"
                          else np.zeros(v.shape, bool), "not a whole number"),
                         (v < 0, "negative")):
        if bad.any():
            k = tuple(int(i) for i in np.argwhere(bad)[0])
            raise DataImportError(f"{what}: entry {k if len(k) > 1 else k[0]} is "
                                  f"{v[k].item()!r}, {problem}; particle types are integers "
                                  f"0, 1, 2, ...: fix the source data")
    return v.astype(np.int64)


def _per_trajectory_particles(value: Any, s: int, n: int, p: Path, key: str,
                              dtype: Any) -> np.ndarray:
    v = types_of(value, f"{p}: {key}") if dtype == np.int64 else floats(value, f"{p}: {key}")
    if v.shape not in ((n,), (s, n)):
        raise DataImportError(f"{p}: {key} have shape {v.shape}; give ({n},) or ({s}, {n}) "
                              f"(one per particle, optionally per trajectory)")
    return np.broadcast_to(v, (s, n)).copy()


def _stack(trajs: list[tuple[np.ndarray, np.ndarray]], names: list[str], f: Path) -> SplitArrays:
    """One split's trajectories as (S, T, N, D); they must agree in T, N and D."""
    if not trajs:
        raise DataImportError(f"{f}: no trajectories; write at least one")
    shape0 = trajs[0][0].shape
    for (pos, _), name in zip(trajs, names):
        if pos.shape == shape0:
            continue
        what, fix = (("particle counts", "pad the smaller ones with kinematic particles "
                      "standing still far from the rest") if pos.shape[1] != shape0[1] else
                     ("dimensions", "import each dimension separately")
                     if pos.shape[2] != shape0[2] else
                     ("frame counts", "cut them to one length"))
        raise DataImportError(
            f"{f}: trajectory '{name}' has shape {pos.shape} (T, N, D) but '{names[0]}' has "
            f"{shape0}: different {what} in one split; bgn's files hold one (T, N, D) per "
            f"split: import groups of equal shape separately, or {fix} (the equal-count rule, "
            f"docs/usage.md 'Your own trajectories')")
    return SplitArrays(positions=np.stack([t[0] for t in trajs]),
                       types=np.stack([t[1] for t in trajs]), names=list(names))


def _take(arrays: SplitArrays, idx: np.ndarray) -> SplitArrays:
    def pick(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[idx]

    return SplitArrays(positions=arrays.positions[idx], masses=pick(arrays.masses),
                       radii=pick(arrays.radii), types=pick(arrays.types),
                       velocities=pick(arrays.velocities),
                       names=[arrays.names[i] for i in idx] if arrays.names else [])


def _fill_splits(raw: RawTrajectories, files: dict[str, list[Path]], train_file: Path,
                 seed: int, fractions: Sequence[float]) -> Read:
    """Carve the splits the files lack from the training trajectories."""
    missing = [s for s in IMPORT_SPLITS if s not in raw.splits]
    if not missing:
        return raw, files
    if "train" not in raw.splits:
        raise DataImportError(f"{train_file}: missing; the training split is required (the "
                              f"other splits can be carved from it)")
    share = [f if (s == "train" or s in missing) else 0.0
             for s, f in zip(IMPORT_SPLITS, fractions)]
    carved = split_by_trajectory(raw.splits["train"], share, seed)
    raw.splits.update(carved)
    for s in carved:
        files[s] = [train_file]
    return raw, files


def _jsonable(value: Any) -> Any:
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    return float(v[0]) if v.size == 1 or (v == v[0]).all() else v.tolist()


def _sha256(f: Path) -> str:
    h = hashlib.sha256()
    with open(f, "rb") as fh:
        while block := fh.read(1 << 20):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------
# Splits and periodic boundaries


def split_by_trajectory(arrays: SplitArrays, fractions: Sequence[float],
                        seed: int) -> dict[str, SplitArrays]:
    """Whole trajectories to train/val/test in proportion to ``fractions`` (a split with
    fraction 0 is left out), shuffled by ``seed``; never frames of one trajectory in two."""
    s = arrays.positions.shape[0]
    fr = np.asarray(fractions, dtype=np.float64)
    if fr.shape != (3,) or (fr < 0).any() or fr[0] <= 0:
        raise DataImportError(f"split fractions {list(fractions)}: give three non-negative "
                              f"shares (train, val, test) with train > 0")
    fr = fr / fr.sum()
    counts = [0, *(max(1, round(f * s)) if f > 0 else 0 for f in fr[1:])]
    while s - sum(counts[1:]) < 1 and max(counts[1:]) > 1:  # rounding must leave train some
        counts[int(np.argmax(counts[1:])) + 1] -= 1
    counts[0] = s - sum(counts[1:])
    if counts[0] < 1:
        raise DataImportError(
            f"{s} trajectories cannot fill {sum(c > 0 for c in counts[1:]) + 1} splits without "
            f"putting frames of one trajectory in two; supply more trajectories, or the "
            f"val/test files")
    order = np.random.default_rng(seed).permutation(s)
    out, start = {}, 0
    for split, count in zip(IMPORT_SPLITS, counts):
        if count:
            out[split] = _take(arrays, np.sort(order[start:start + count]))
        start += count
    return out


def unwrap_periodic(positions: np.ndarray, bounds: np.ndarray, periodic: np.ndarray) -> np.ndarray:
    """Continuous (S, T, N, D) positions from positions wrapped into a periodic box: each frame
    moves by the minimum-image displacement from the previous one. Exact whole box lengths are
    added, so unwrapping continuous positions changes nothing."""
    out = np.array(positions, dtype=np.float64)
    dims = np.flatnonzero(np.asarray(periodic, dtype=bool))
    if dims.size == 0:
        return out
    length = (np.asarray(bounds, dtype=np.float64)[:, 1] - bounds[:, 0])[dims]
    for s in range(out.shape[0]):  # one trajectory at a time bounds the temporary memory
        x = out[s][..., dims]  # (T, N, P)
        images = -np.rint(np.diff(x, axis=0) / length)
        shift = np.concatenate([np.zeros_like(x[:1]), np.cumsum(images, axis=0)]) * length
        out[s][..., dims] = x + shift
    return out


# ---------------------------------------------------------------------------------------------
# Checks


def check_trajectories(raw: RawTrajectories, min_frames: int, where: str = "") -> None:
    """Every check of imported trajectories; the first failure raises ``DataImportError``
    naming the file, split, trajectory and frame, and the fix. Positions must be unwrapped
    (periodic dimensions skip the half-box jump check)."""
    src = raw.source or {}
    where = where or str(src.get("path", "the trajectories"))
    split_files = src.get("split_files", {})

    def fail(split: str | None, problem: str) -> DataImportError:
        file = ", ".join(split_files.get(split, [])) if split else ""
        head = f"{where}/{file}" if file and Path(where).name != file else where
        return DataImportError(f"{head}: {problem}")

    if raw.dt is None or not np.isfinite(raw.dt) or raw.dt <= 0:
        raise fail(None, f"dt={raw.dt} is not a positive time between frames; give the "
                         f"frame spacing")
    if not raw.splits:
        raise fail(None, "no trajectories; give at least a training split")
    dims = {split: a.positions.shape[-1] for split, a in raw.splits.items()}
    meta_dim = raw.metadata.get("dim") if isinstance(raw.metadata, dict) else None
    for split, a in raw.splits.items():
        pos = a.positions
        if pos.ndim != 4:
            raise fail(split, f"split {split}: positions have shape {pos.shape}, not "
                              f"(S, T, N, D)")
        s, t, n, d = pos.shape
        if meta_dim is not None and int(meta_dim) != d:
            raise fail(split, f"metadata.json says dim={meta_dim} but split {split} holds "
                              f"{d}-dimensional positions; fix dim in metadata.json")
        if d != dims.get("train", d):
            raise fail(split, f"split {split} is {d}-dimensional, train "
                              f"{dims['train']}-dimensional; import data of one dimension")
        if s < 1 or n < 1:
            raise fail(split, f"split {split} has {s} trajectories of {n} particles; give "
                              f"at least one of each")
        if t < min_frames:
            raise fail(split, f"split {split}, trajectory {_name(a, 0)}: {t} frames, fewer "
                              f"than the {min_frames} one window needs; give longer "
                              f"trajectories")
        for key in ("bounds", "periodic"):
            v = getattr(raw, key)
            if v is not None and np.shape(v)[0] != d:
                raise fail(split, f"{key} has {np.shape(v)[0]} dimensions, positions {d}; "
                                  f"give one per dimension")
        _check_particles(a, split, fail)
        _check_motion(raw, a, split, fail)
    _check_scales(raw, "train" if "train" in raw.splits else next(iter(raw.splits)), fail)


def _name(a: SplitArrays, i: int) -> str:
    return f"'{a.names[i]}'" if a.names and i < len(a.names) else str(i)


def _check_particles(a: SplitArrays, split: str, fail: Any) -> None:
    s, t, n, d = a.positions.shape
    for key in ("masses", "radii", "types"):
        v = getattr(a, key)
        if v is not None and np.shape(v) != (s, n):
            raise fail(split, f"split {split}: {key} have shape {np.shape(v)}, not ({s}, {n})")
    for key in ("masses", "radii"):
        v = getattr(a, key)
        if v is None:
            continue
        bad = ~(np.isfinite(v) & (v > 0))
        if bad.any():
            i, j = (int(k) for k in np.argwhere(bad)[0])
            raise fail(split, f"split {split}, trajectory {_name(a, i)}, particle {j}: "
                              f"{'radius' if key == 'radii' else 'mass'} {v[i, j].item()!r} is not "
                              f"positive and finite; give {key} > 0 or leave them out")
    if a.types is not None and (np.asarray(a.types) < 0).any():
        i, j = (int(k) for k in np.argwhere(np.asarray(a.types) < 0)[0])
        raise fail(split, f"split {split}, trajectory {_name(a, i)}, particle {j}: type "
                          f"{a.types[i, j]} is negative; particle types are integers 0, 1, "
                          f"2, ...: fix the source data")
    if a.velocities is not None and a.velocities.shape != a.positions.shape:
        raise fail(split, f"split {split}: velocities have shape {a.velocities.shape}, "
                          f"positions {a.positions.shape}; give one per position")


def _check_scales(raw: RawTrajectories, split: str, fail: Any) -> None:
    """Something moves, and the frames' typical speed and acceleration (median finite
    differences of the moving particles over ``dt``) lie in ``PLAUSIBLE``: a dt in the wrong
    unit (1e30) leaves targets that float32 rounds to zero."""
    a = raw.splits[split]
    steps, bends = [], []
    for x in a.positions:  # one trajectory at a time: bounded memory
        d1 = np.abs(np.diff(x, axis=0))
        d2 = np.abs(np.diff(x, n=2, axis=0))
        if (d1 > 0).any():
            steps.append(float(np.median(d1[d1 > 0])))
        if (d2 > 0).any():
            bends.append(float(np.median(d2[d2 > 0])))
    if not steps:
        raise fail(split, f"split {split}: no particle moves in any trajectory (every frame "
                          f"equals the first): nothing to learn; check that the positions are "
                          f"the trajectories' frames (not one frame repeated)")
    low, high = PLAUSIBLE
    dt = np.float64(raw.dt)
    with np.errstate(over="ignore", divide="ignore", under="ignore"):
        scales = (("speed", np.median(steps) / dt, "dt"),
                  ("acceleration", np.median(bends or [0.0]) / dt**2, "dt^2"))
    for what, value, unit in scales:
        if value and not low <= value <= high:
            raise fail(None, f"dt={raw.dt:g} makes the frames' typical {what} {value:.3g} "
                             f"(median change per frame over {unit}), outside {low:g}.."
                             f"{high:g} where the models' float32 arithmetic resolves it; dt "
                             f"is likely in the wrong unit: give the time between frames in "
                             f"the unit of the source")


def _check_motion(raw: RawTrajectories, a: SplitArrays, split: str, fail: Any) -> None:
    """Per trajectory (bounded memory): finite values, no half-box jumps in non-periodic
    dimensions, no coincident particles."""
    from scipy.spatial import cKDTree

    s, t, n, d = a.positions.shape
    periodic = np.zeros(d, bool) if raw.periodic is None else np.asarray(raw.periodic, bool)
    direction = np.random.default_rng(0).normal(size=d)  # generic: no lattice row lines up
    direction /= np.linalg.norm(direction)
    for i in range(s):
        x = a.positions[i]
        for key, arr in (("positions", x),
                         ("velocities", None if a.velocities is None else a.velocities[i])):
            if arr is None:
                continue
            ok = np.isfinite(arr)
            if not ok.all():
                frame, particle, dim = (int(k) for k in np.argwhere(~ok)[0])
                raise fail(split, f"split {split}, trajectory {_name(a, i)}, frame {frame}, "
                                  f"particle {particle}: {key} hold {arr[frame, particle, dim]} "
                                  f"(NaN or inf); remove or repair that trajectory")
            big = np.abs(arr) > PLAUSIBLE[1]
            if big.any():
                frame, particle, dim = (int(k) for k in np.argwhere(big)[0])
                raise fail(split, f"split {split}, trajectory {_name(a, i)}, frame {frame}, "
                                  f"particle {particle}: {key} hold "
                                  f"{arr[frame, particle, dim]:.3g}, beyond the "
                                  f"{PLAUSIBLE[1]:g} the models' float32 arithmetic holds "
                                  f"(squared distances overflow); fix the source data (a stray "
                                  f"value or a wrong unit)")
        lo, hi = x.min(axis=(0, 1)), x.max(axis=(0, 1))
        if raw.bounds is not None:
            length, told = raw.bounds[:, 1] - raw.bounds[:, 0], "the box"
        else:
            length, told = hi - lo, "the data's extent (no box given)"
        free = ~periodic & (length > 0)
        if t > 1 and free.any():
            jump = np.abs(np.diff(x[..., free], axis=0)) > 0.5 * length[free]
            if jump.any():
                frame, particle, k = (int(v) for v in np.argwhere(jump)[0])
                dim = int(np.flatnonzero(free)[k])
                raise fail(split, f"split {split}, trajectory {_name(a, i)}, frame {frame} to "
                                  f"{frame + 1}, particle {particle}: jumps more than half of "
                                  f"{told} in dimension {dim} with no periodic boundary "
                                  f"declared; likely periodic data: declare that dimension "
                                  f"periodic (with its box)")
        scale = max(float(np.abs(x).max()), float((hi - lo).max()), np.finfo(float).tiny)
        tol = COINCIDENT_RTOL * scale
        # Exact and cheap: two particles within tol are within tol along any unit direction,
        # so only frames whose sorted projections on one generic direction have a gap that
        # small (plus rounding) can hold a coincident pair; those get an exact tree search.
        proj = np.sort(x @ direction, axis=1)
        near = np.diff(proj, axis=1) <= tol + 16 * np.finfo(float).eps * scale
        for frame in np.flatnonzero(near.any(axis=1)):
            pairs = cKDTree(x[frame]).query_pairs(tol, output_type="ndarray")
            if len(pairs):
                p, q = sorted(int(v) for v in pairs[0])
                raise fail(split, f"split {split}, trajectory {_name(a, i)}, frame {frame}: "
                                  f"particles {p} and {q} coincide (within {tol:.2g}); remove "
                                  f"duplicated particles")
