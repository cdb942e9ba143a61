"""Trajectories from outside bgn -> bgn's validated dataset files
(docs/design.md#imported-files).

``python -m bgn.data.import <path> name=<name>`` reads a file or directory in any layout
``bgn.data.formats`` knows (detected from the files), checks it, and writes
``<data_dir>/imported/<name>/{train,val,test}.h5``; ``python -m bgn.train dataset=imported
dataset.name=<name>`` then trains on them like on a generated scene. ``from_arrays`` does the
same for arrays already in memory. What is written:

- the frames as recorded (periodic data unwrapped by the reader), at the source's spacing dt;
- velocities: the source's where it gives them, else central finite differences of the
  positions (one-sided at the first and last frame); the models never read them (their inputs
  are backward differences of positions), they serve the exact-state tools;
- masses: the source's, else ones and the attribute ``masses_known`` False (the inverse model
  still trains and reports a posterior, but nothing scores it); radii and types: the source's,
  else zeros;
- ``kinematic`` (S, N): particles of the source's kinematic types (inputs, never predicted);
- the scene (``bgn.sim.imported.ImportedScene``): a complete graph, or GNS's radius graph
  ``|x_i - x_j| <= r_i + r_j + R`` with R the source's connectivity radius; walls only where
  the source declares a non-periodic box ``[0, L]^D``; the pair force law is unknown;
- normalisation statistics from the training split only (``bgn.data.stats``);
- the source (format, files, their sha256) and its own metadata as JSON attributes.

Every split is checked before the first file is written, the files are written into a
temporary directory and moved into place at once: bad input leaves nothing on disk (not even
the folders above the import, where the import made them).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import sys
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from bgn.coerce import ConfigError, need_int
from bgn.data.files import DatasetFile, DatasetFileError, write_dataset
from bgn.data.raw import (
    IMPORT_SPLITS,
    DataImportError,
    DataImportWarning,
    RawTrajectories,
    SplitArrays,
)
from bgn.data.spec import IMPORTED, SPLITS, DatasetSpec, data_dir_problem, imported_dir
from bgn.data.stats import compute_stats
from bgn.sim.imported import TARGETS, ImportedScene

NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")
DEFAULT_FRACTIONS = (0.8, 0.1, 0.1)


def _json(value: Any) -> str:
    """JSON of source metadata (numpy scalars and arrays as lists)."""
    def plain(v: Any) -> Any:
        if isinstance(v, np.ndarray | np.generic):
            return v.tolist()
        if isinstance(v, Path):
            return str(v)
        raise TypeError(f"{type(v).__name__} is not JSON serialisable")

    return json.dumps(value, sort_keys=True, default=plain)


def central_velocities(positions: np.ndarray, dt: float) -> np.ndarray:
    """(S, T, N, D) positions -> velocities by central differences over frames (second order
    inside, first order at the first and last frame); unwrapped positions, so periodic
    crossings are already the minimum image."""
    return np.gradient(positions, dt, axis=1, edge_order=1)


def walls(raw: RawTrajectories) -> float | None:
    """The side L of reflecting walls ``[0, L]^D`` where the source declares such a box (bounds
    from 0 to the same L in every dimension, none periodic), else None: bgn's walls are that
    box only, other bounds are recorded but not modelled as walls."""
    if raw.bounds is None:
        return None
    bounds = np.asarray(raw.bounds, dtype=np.float64)
    if raw.periodic is not None and np.any(raw.periodic):
        return None
    if np.allclose(bounds[:, 0], 0.0) and np.allclose(bounds[:, 1], bounds[0, 1]) \
            and bounds[0, 1] > 0:
        return float(bounds[0, 1])
    return None


def data_hash(arrays: Mapping[str, Mapping[str, np.ndarray]], dt: float) -> str:
    """sha256 of every split's arrays and the frame spacing (the checkpoints' provenance)."""
    h = hashlib.sha256(np.float64(dt).tobytes())
    for split in SPLITS:
        for key in sorted(arrays[split]):
            value = np.ascontiguousarray(arrays[split][key])
            h.update(f"{split}/{key}{value.dtype.str}{value.shape}".encode())
            h.update(value.tobytes())
    return h.hexdigest()


def split_arrays(part: SplitArrays, dt: float, kinematic_types: Sequence[int],
                 masses_known: bool) -> dict[str, np.ndarray]:
    """One split's file arrays (float64 states, (S, N) particle arrays)."""
    x = np.asarray(part.positions, dtype=np.float64)
    s, _, n, _ = x.shape
    types = (np.zeros((s, n), dtype=np.int64) if part.types is None
             else np.asarray(part.types, dtype=np.int64))
    return {
        "positions": x,
        "velocities": (central_velocities(x, dt) if part.velocities is None
                       else np.asarray(part.velocities, dtype=np.float64)),
        "masses": (np.asarray(part.masses, dtype=np.float64) if masses_known
                   else np.ones((s, n))),
        "radii": np.zeros((s, n)) if part.radii is None else np.asarray(part.radii, np.float64),
        "types": types,
        "kinematic": np.isin(types, np.asarray(kinematic_types, dtype=np.int64)),
    }


def _check_shapes(raw: RawTrajectories) -> tuple[int, int]:
    """Every split present, one particle count and dimension for all (the scene's)."""
    missing = [s for s in IMPORT_SPLITS if s not in raw.splits]
    if missing:
        raise DataImportError(f"the import has no {', '.join(missing)} split; give the "
                              "source all three, or none (they are then drawn by trajectory)")
    shapes = {s: raw.splits[s].positions.shape for s in IMPORT_SPLITS}
    n, d = shapes["train"][2:]
    for split, shape in shapes.items():
        if shape[2:] != (n, d):
            raise DataImportError(
                f"split {split!r} has {shape[2]} particles in {shape[3]} dimensions, the train "
                f"split {n} in {d}: one dataset holds one particle count and dimension; import "
                "the others under another name")
    return n, d


def import_dataset(raw: RawTrajectories, name: str, data_dir: str | Path, history: int = 5,
                   overwrite: bool = False, target: str = "acceleration") -> dict[str, Path]:
    """Check ``raw`` and write ``<data_dir>/imported/<name>/{train,val,test}.h5`` (see the
    module doc). ``history``: the window every trajectory must hold with its next frame;
    ``target``: the model's forward target (``velocity`` for contact data). Raises
    ``DataImportError`` before anything is written."""
    from bgn.data.formats import check_trajectories

    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise DataImportError(f"name={name!r}: use letters, digits, '.', '_' and '-' (it names "
                              "the directory data/imported/<name>)")
    if target not in TARGETS:
        raise DataImportError(f"target={target!r}: choose one of {TARGETS}")
    if problem := data_dir_problem(data_dir):
        raise DataImportError(problem)
    directory = imported_dir(data_dir, name)
    if directory.parent.exists() and not directory.parent.is_dir():
        raise DataImportError(f"{directory.parent} is a file, not the folder of imports; move "
                              "it away, or give another paths.data_dir")
    if directory.exists() and not overwrite:
        raise DataImportError(f"an import named {name!r} exists in {directory}; pass "
                              "overwrite=true to replace it, or choose another name")
    check_trajectories(raw, min_frames=history + 3)
    n, d = _check_shapes(raw)
    if not raw.dt > 0:
        raise DataImportError(f"dt={raw.dt}: the frame spacing must be positive")
    fps = 1.0 / float(raw.dt)
    dt = 1.0 / fps  # the files' spacing (DatasetSpec.dt): the one every check recomputes with
    masses_known = all(raw.splits[s].masses is not None for s in IMPORT_SPLITS)
    arrays = {s: split_arrays(raw.splits[s], dt, raw.kinematic_types, masses_known)
              for s in IMPORT_SPLITS}
    n_types = max(int(a["types"].max()) for a in arrays.values()) + 1
    radius = raw.connectivity_radius
    source = raw.source or {"format": "arrays"}
    scene = ImportedScene(
        name=name, n_particles=n, dim=d, n_types=max(n_types, 1),
        graph="full" if radius is None else "radius", target=target, interaction="unknown",
        box=walls(raw), connectivity_radius=None if radius is None else float(radius),
        periodic=() if raw.periodic is None else tuple(bool(p) for p in raw.periodic),
        bounds=() if raw.bounds is None else tuple(map(tuple, np.asarray(raw.bounds).tolist())),
        kinematic_types=tuple(int(t) for t in raw.kinematic_types), masses_known=masses_known,
        source=str(source.get("path", "")),  # "": from memory (from_arrays)
        data_sha256=data_hash(arrays, dt))
    params = {f.name: getattr(scene, f.name) for f in fields(scene)}
    sizes = tuple(arrays[s]["positions"].shape[:2] for s in SPLITS)
    train = DatasetSpec(IMPORTED, *sizes[0], 0, fps, "train", params, sizes)
    stats = compute_stats(scene, arrays["train"], dt, scene.margin)  # the training split only
    attrs = {"source": _json(source), "source_metadata": _json(raw.metadata),
             "masses_known": masses_known}

    made = [q for q in (directory.parent, *directory.parent.parents) if not q.exists()]
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = directory.parent / f".{name}.tmp{os.getpid()}"
    old = directory.parent / f".{name}.old{os.getpid()}"
    done = False
    try:
        for split in SPLITS:
            spec = train.with_split(split)
            write_dataset(tmp / f"{split}.h5", spec, scene.meta, arrays[split],
                          margin=scene.margin, stats=stats if split == "train" else None,
                          attrs=attrs)
            try:
                DatasetFile(tmp / f"{split}.h5", replace(spec)).close()  # the checks on open
            except DatasetFileError as err:  # the source's fault: name it, not the temporary
                problem = str(err).split(": ", 1)[-1].split(". Delete it")[0]
                raise DataImportError(f"{source.get('path') or 'the trajectories'}: its "
                                      f"{split} split fails bgn's checks of a dataset file "
                                      f"({problem}); fix the source data") from None
        if directory.exists():  # overwrite: swap the directories, then drop the old one
            os.replace(directory, old)
        os.replace(tmp, directory)
        done = True
    finally:
        for leftover in (tmp, old):
            if leftover.exists():
                shutil.rmtree(leftover)
        if not done:  # the folders this import made, innermost first, if still empty
            for q in made:
                if q.is_dir() and not any(q.iterdir()):
                    q.rmdir()
    return {split: directory / f"{split}.h5" for split in SPLITS}


def _per_trajectory(value: Any, s: int, shape: tuple[int, ...], key: str,
                    dtype: Any) -> np.ndarray | None:
    """A per-particle array given once (N,) or per trajectory (S, N) -> (S, N)."""
    from bgn.data.formats import floats

    if value is None:
        return None
    a = floats(value, key) if dtype == np.float64 else np.asarray(value, dtype=dtype)
    if a.shape == shape[1:]:
        a = np.broadcast_to(a, shape).copy()
    if a.shape != shape:
        raise DataImportError(f"{key} has shape {a.shape}; expected (N,) = {shape[1:]} or "
                              f"(S, N) = {shape}")
    return a


def from_arrays(positions: np.ndarray, dt: float, masses: np.ndarray | None = None,
                radii: np.ndarray | None = None, types: np.ndarray | None = None,
                velocities: np.ndarray | None = None, box: Any = None, periodic: Any = None,
                name: str = "arrays", data_dir: str | Path = "data", split_seed: int = 0,
                splits: Mapping[str, Sequence[int]] | None = None, history: int = 5,
                overwrite: bool = False, kinematic_types: Sequence[int] = (),
                connectivity_radius: float | None = None,
                target: str = "acceleration") -> dict[str, Path]:
    """Import trajectories already in memory: ``positions`` (S, T, N, D), frames ``dt`` apart;
    ``masses``, ``radii``, ``types`` (N,) or (S, N); ``velocities`` (S, T, N, D); ``box`` a
    side L (the box ``[0, L]^D``) or (D, 2) bounds; ``periodic`` a bool or one per dimension
    (positions are then unwrapped by the minimum image). ``splits`` maps train/val/test to
    trajectory indices; None splits the trajectories 80/10/10 with ``split_seed``, never frames
    of one trajectory into two splits. Returns the three files' paths (``import_dataset``)."""
    from bgn.data.formats import floats, split_by_trajectory, types_of, unwrap_periodic

    x = floats(positions, "positions")
    if x.ndim != 4:
        raise DataImportError(f"positions have shape {x.shape}; expected (S, T, N, D) "
                              "(trajectories, frames, particles, dimensions)")
    s, t, n, d = x.shape
    bounds = None
    if box is not None:
        bounds = np.asarray(box, dtype=np.float64)
        if bounds.ndim == 0:
            bounds = np.column_stack([np.zeros(d), np.full(d, float(bounds))])
        if bounds.shape != (d, 2):
            raise DataImportError(f"box has shape {bounds.shape}; give a side length or "
                                  f"(D, 2) = ({d}, 2) bounds")
    flags = None
    if periodic is not None:
        flags = np.broadcast_to(np.asarray(periodic, dtype=bool), (d,)).copy()
        if flags.any():
            if bounds is None:
                raise DataImportError("periodic=true needs the box (box=L or (D, 2) bounds)")
            x = unwrap_periodic(x, bounds, flags)
    whole = SplitArrays(
        positions=x,
        masses=_per_trajectory(masses, s, (s, n), "masses", np.float64),
        radii=_per_trajectory(radii, s, (s, n), "radii", np.float64),
        types=None if types is None else _per_trajectory(types_of(types, "types"), s, (s, n),
                                                         "types", np.int64),
        velocities=None if velocities is None else floats(velocities, "velocities"),
        names=[f"trajectory {i}" for i in range(s)])
    if whole.velocities is not None and whole.velocities.shape != x.shape:
        raise DataImportError(f"velocities have shape {whole.velocities.shape}; expected the "
                              f"positions' {x.shape}")
    if splits is None:
        parts = split_by_trajectory(whole, DEFAULT_FRACTIONS, split_seed)
    else:
        parts = {key: _take(whole, list(splits.get(key, ()))) for key in IMPORT_SPLITS}
    raw = RawTrajectories(splits=parts, dt=float(dt), bounds=bounds, periodic=flags,
                          kinematic_types=tuple(kinematic_types),
                          connectivity_radius=connectivity_radius,
                          source={"format": "arrays"})
    return import_dataset(raw, name, data_dir, history, overwrite, target)


def _take(whole: SplitArrays, rows: list[int]) -> SplitArrays:
    """The trajectories ``rows`` of ``whole``."""
    if not rows:
        raise DataImportError("splits: every split (train, val, test) needs at least one "
                              "trajectory index")
    def pick(a: np.ndarray | None) -> np.ndarray | None:
        return None if a is None else a[rows]

    return SplitArrays(whole.positions[rows], pick(whole.masses), pick(whole.radii),
                       pick(whole.types), pick(whole.velocities),
                       [whole.names[i] for i in rows] if whole.names else [])


# ----------------------------------------------------------------------------- the command
def radii_from_types(raw: RawTrajectories, radii_by_type: Sequence[float] | None
                     ) -> RawTrajectories:
    """``raw`` with each particle's radius that of its type (``radii_by_type[k]``: type k's),
    for a source that records types and no radii; unchanged for None."""
    if radii_by_type is None:
        return raw
    table = np.asarray(list(radii_by_type), dtype=np.float64)
    for split, part in raw.splits.items():
        if part.radii is not None:
            raise DataImportError(f"radii_by_type: the {split} split records its own "
                                  "radii; drop radii_by_type")
        if part.types is None:
            raise DataImportError(f"radii_by_type: the {split} split records no particle "
                                  "types; give radii in the source (plain arrays: 'radii')")
        types = np.asarray(part.types)
        if types.max() >= len(table):
            raise DataImportError(f"radii_by_type has {len(table)} entries but the {split} "
                                  f"split has particles of type {int(types.max())}: give one "
                                  "radius per type")
    return replace(raw, splits={split: replace(part, radii=table[np.asarray(part.types)])
                                for split, part in raw.splits.items()})


def validate_import(cfg: Any) -> None:
    """The import's config, before any file is read."""
    from omegaconf import OmegaConf

    for key, what in (("path", "the file or folder to import, the first argument"),
                      ("name", "the dataset's name, e.g. name=my_water")):
        if OmegaConf.is_config(cfg) and OmegaConf.is_missing(cfg, key) or not cfg.get(key):
            raise ConfigError(key, message=f"{key} is missing: {what} (python -m "
                              "bgn.data.import <path> name=<name>)")
    if cfg.get("format") is not None:
        from bgn.data.formats import format_name

        try:
            format_name(cfg.get("format"), cfg.get("path"))
        except DataImportError as err:
            raise ConfigError("format", message=str(err)) from None
    data_dir = (cfg.get("paths") or {}).get("data_dir") or "data"
    if problem := data_dir_problem(data_dir):
        raise ConfigError("paths.data_dir", message=problem)
    need_int(cfg.get("split_seed", 0), "split_seed", 0, 2**32 - 1)
    need_int(cfg.get("history", 5), "history", 0)
    if not NAME.fullmatch(str(cfg.get("name"))):
        raise ConfigError("name", cfg.get("name"), "use letters, digits, '.', '_' and '-'")
    if cfg.get("target") not in TARGETS:
        raise ConfigError("target", cfg.get("target"), f"choose one of {TARGETS}")
    radii = cfg.get("radii_by_type")
    if radii is not None and (not len(radii) or not all(
            isinstance(r, (int, float)) and math.isfinite(r) and r > 0 for r in radii)):
        raise ConfigError("radii_by_type", radii, "give one positive radius per particle type, "
                          "e.g. radii_by_type=[0.02,0.03]")


def describe(paths: Mapping[str, Path], seconds: float) -> str:
    """What an import wrote, and the command that trains on it."""
    lines = []
    for split, path in paths.items():
        f = DatasetFile(path, check_values=False)
        lines.append(f"{split:>5}: {path}  ({path.stat().st_size / 1e6:.2f} MB, {f.n_sims} x "
                     f"{f.n_frames} x {f.attrs['n_particles']} x {f.attrs['dim']} "
                     "trajectories x frames x particles x dims)")
        if split == "train":
            types = f.read("types", ...)
            kinematic = f.read("kinematic", ...)
            scene = json.loads(f.attrs["config"])["params"]
            known = bool(f.attrs["masses_known"])
            counts = ", ".join(f"type {t}: {c}" for t, c in
                               zip(*np.unique(types[0], return_counts=True)))
            about = [f"dt {f.dt:g} ({f.attrs['fps']:g} frames per time unit)",
                     f"particles per trajectory: {counts}",
                     "kinematic (inputs only, never predicted): "
                     + (", ".join(f"type {t}" for t in scene["kinematic_types"])
                        + f" ({int(kinematic[0].sum())} particles)"
                        if scene["kinematic_types"] else "none"),
                     "masses: " + ("recorded (they score the inverse model)" if known else
                                   "not given (ones; the mass posterior is reported, unscored)"),
                     "radii: " + (f"{np.min(radii):g} .. {np.max(radii):g} (the discs' contact "
                                  "metrics)" if (radii := f.read("radii", ...)).any() else
                                  "not given"),
                     f"graph: {scene['graph']}" + (f" (radius {scene['connectivity_radius']:g})"
                                                   if scene["graph"] == "radius" else ""),
                     f"walls: box {scene['box']:g}" if scene["box"] else "walls: none",
                     "periodic: " + (" x ".join(f"{p:g}" if p else "-" for p in f.meta.period)
                                     + " (minimum-image edges)" if f.meta.period else "no")]
        f.close()
    name = paths["train"].parent.name
    data_dir = paths["train"].parent.parent.parent
    where = "" if data_dir == Path("data") else f" paths.data_dir={data_dir}"
    return "\n".join([*lines, *about, f"done in {seconds:.1f} s; train with:",
                      f"  python -m bgn.train dataset=imported dataset.name={name}{where}"])


def main(cfg: Any) -> dict[str, Path]:
    """Entry point body: read ``cfg.path`` (layout ``cfg.format`` or detected), import it as
    ``cfg.name`` under ``cfg.paths.data_dir``."""
    from bgn.data.formats import read_trajectories

    validate_import(cfg)
    start = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", DataImportWarning)
        try:
            raw = read_trajectories(cfg.path, fmt=cfg.get("format"),
                                    split_seed=int(cfg.get("split_seed", 0)),
                                    allow_pickle=bool(cfg.get("allow_pickle", False)))
            raw = radii_from_types(raw, cfg.get("radii_by_type"))
        finally:  # one line each, before a refusal's own line
            for w in caught:
                if issubclass(w.category, DataImportWarning):
                    print(f"bgn: warning: {w.message}", file=sys.stderr)
                else:
                    warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    paths = import_dataset(raw, str(cfg.name), cfg.paths.data_dir, int(cfg.get("history", 5)),
                           bool(cfg.get("overwrite", False)), str(cfg.get("target")))
    print(describe(paths, time.perf_counter() - start))
    return paths

