"""HDF5 dataset files: layout, atomic writing, validation on open, lazy reading.

Layout (schema version ``SCHEMA_VERSION``), S simulations, T frames, N particles, D dims:

- root attributes: ``schema_version``, ``scene``, ``fps``, ``dt``, ``seed``, ``split``,
  ``n_sims``, ``n_frames``, ``n_particles``, ``dim``, ``config`` (the full generating config
  as JSON), ``meta`` (the scene's metadata record as JSON), ``margin`` (contact margin of
  radius graphs, 0 for full graphs), ``bgn_version``.
- ``positions``, ``velocities`` (S, T, N, D) float64: true instantaneous states.
- ``accelerations`` (S, T, N, D) float64: force scenes only.
- ``masses``, ``radii`` (S, N) float64; ``types`` (S, N) int64.
- ``contacts`` (M, 4) int64 rows ``(sim, frame, i, j)``, i < j: contact scenes only.
- imported data (``bgn.data.importing``): no ``accelerations`` (the law is unknown), a
  ``kinematic`` (S, N) bool array, and the attributes ``source``, ``source_metadata`` (JSON)
  and ``masses_known``.
- group ``stats`` (train split only): normalisation statistics, see ``bgn.data.stats``.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from bgn import __version__
from bgn.data.spec import DatasetSpec
from bgn.sim import SceneMeta

SCHEMA_VERSION = 3  # 2: statistics of velocity increments; 3: of target differences
STATE_ARRAYS = ("positions", "velocities")
PARTICLE_ARRAYS = ("masses", "radii", "types")


# The statistics groups of a train file (bgn.data.stats.compute_stats) and their columns:
# "dim" (one per spatial dimension) or 1.
STATS_GROUPS = {"velocity": "dim", "velocity_increment": "dim", "target": "dim",
                "target_diff1": "dim", "target_diff2": "dim", "log_mass": 1,
                "rel_position": "dim", "rel_velocity": "dim", "rel_log_mass": 1, "contact": 1}
STATS_ENTRIES = ("mean", "std", "median", "robust_scale", "min", "max", "count")
# Groups recomputed from the arrays on open (cheap): stored values must match them
RECOMPUTED_STATS = ("velocity", "target", "log_mass")


class DatasetFileError(RuntimeError):
    """A dataset file that cannot be used; the message names the file and the fix."""

    def __init__(self, path: str | Path, problem: str, hint: str | None = None,
                 missing: bool = False) -> None:
        command = hint or "python -m bgn.train.generate"
        fix = (f"Make it with `{command}`" if missing
               else f"Delete it and regenerate it with `{command}`; nothing else is touched")
        super().__init__(f"dataset file {path}: {problem}. {fix}.")
        self.path = Path(path)


def write_dataset(path: Path, spec: DatasetSpec, meta: SceneMeta, arrays: dict[str, np.ndarray],
                  margin: float = 0.0, stats: dict[str, dict[str, np.ndarray]] | None = None,
                  attrs: dict[str, Any] | None = None) -> None:
    """Write a complete file to a temporary name, then rename it into place (atomic).
    ``attrs``: further root attributes (imported data: their source)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs.update({
                "schema_version": SCHEMA_VERSION, "scene": spec.scene, "fps": spec.fps,
                "dt": spec.dt, "seed": spec.seed, "split": spec.split, "n_sims": spec.n_sims,
                "n_frames": spec.n_frames, "n_particles": meta.n_particles, "dim": meta.dim,
                "config": json.dumps(spec.generating_config(), sort_keys=True),
                "meta": json.dumps(asdict(meta)), "margin": float(margin),
                "bgn_version": __version__, **(attrs or {}),
            })
            for name, value in arrays.items():
                value = np.asarray(value)
                chunks = None
                if value.ndim == 4:  # one simulation, a run of frames per chunk
                    chunks = (1, min(value.shape[1], 128), *value.shape[2:])
                f.create_dataset(name, data=value, chunks=chunks,
                                 compression="gzip" if value.size > 1024 else None,
                                 shuffle=value.size > 1024)
            for group, entries in (stats or {}).items():
                g = f.create_group(f"stats/{group}")
                for key, value in entries.items():
                    g.create_dataset(key, data=np.asarray(value, dtype=np.float64))
            f.flush()
        with open(tmp, "rb") as fh:  # the bytes are on disk before the name points at them
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def _within(value: np.ndarray, low: np.ndarray, high: np.ndarray) -> bool:
    """``low <= value <= high`` up to round-off (a mean of equal values may differ in the last
    bit)."""
    slack = 1e-12 * np.maximum(np.abs(low), np.abs(high))
    return bool(((value >= low - slack) & (value <= high + slack)).all())


class DatasetFile:
    """A validated dataset file. Arrays are read on demand; the handle opens lazily.

    Safe to pickle into DataLoader workers: the h5py handle is never pickled, each process
    opens its own on first access.
    """

    def __init__(self, path: str | Path, spec: DatasetSpec | None = None,
                 check_values: bool = True) -> None:
        self.path = Path(path)
        self.spec = spec
        self.hint = spec.regenerate_hint(self.path.parent) if spec else self._own_hint()
        self._handle: h5py.File | None = None
        self._cache: dict[str, np.ndarray] = {}
        self.attrs = self._validate(check_values)
        self.meta = SceneMeta(**json.loads(self.attrs["meta"]))
        if spec is not None:
            self._compare(spec)

    def _own_hint(self) -> str | None:
        """The regenerate command of the file's own generating config (None if unreadable);
        of a file in an imported dataset's folder (``<data>/imported/<name>/``), the import."""
        imported = (f"python -m bgn.data.import <your trajectories> name={self.path.parent.name}"
                    if self.path.parent.parent.name == "imported" else None)
        if not self.path.exists():
            return imported
        try:
            with h5py.File(self.path, "r") as f:
                config = json.loads(f.attrs["config"])
                spec = DatasetSpec(config["scene"], int(config["n_sims"]),
                                   int(config["n_frames"]), int(config["seed"]),
                                   float(f.attrs["fps"]), str(f.attrs["split"]),
                                   config["params"])
            return spec.regenerate_hint(self.path.parent)
        except Exception:  # noqa: BLE001 (a corrupt file: the generic hint)
            return imported

    def _compare(self, spec: DatasetSpec) -> None:
        """The file's attributes against the config it is opened for: a file renamed or
        copied under another config's name is refused."""
        asked = {"scene": spec.scene, "split": spec.split, "n_sims": spec.n_sims,
                 "n_frames": spec.n_frames, "seed": spec.seed}
        differ = [f"{k}={self.attrs.get(k)!r} (the config asks for {v!r})"
                  for k, v in asked.items() if self.attrs.get(k) != v]
        if not np.isclose(float(self.attrs["fps"]), spec.fps, rtol=1e-12, atol=0.0):
            differ.append(f"fps={self.attrs['fps']:g} (the config asks for {spec.fps:g})")
        if not differ and json.loads(self.attrs["config"]) != json.loads(
                json.dumps(spec.generating_config(), sort_keys=True)):
            differ.append("its generating parameters (attribute 'config') differ from the "
                          "config's")
        if differ:
            raise self._fail("was not written for this config: it holds " + "; ".join(differ))

    # -- validation ---------------------------------------------------------------------
    def _fail(self, problem: str) -> DatasetFileError:
        return DatasetFileError(self.path, problem, self.hint)

    def _validate(self, check_values: bool) -> dict[str, Any]:
        if not self.path.exists():
            raise DatasetFileError(self.path, "does not exist", self.hint, missing=True)
        try:
            with h5py.File(self.path, "r") as f:
                attrs = {k: (v.item() if isinstance(v, np.generic) else v)
                         for k, v in f.attrs.items()}
                version = attrs.get("schema_version")
                if version != SCHEMA_VERSION:
                    raise self._fail(f"has schema version {version}, this bgn reads version "
                                     f"{SCHEMA_VERSION}")
                missing = [k for k in ("scene", "fps", "dt", "n_sims", "n_frames",
                                       "n_particles", "dim", "meta", "config") if k not in attrs]
                if missing:
                    raise self._fail(f"lacks the attributes {missing}")
                s, t, n, d = (int(attrs[k]) for k in ("n_sims", "n_frames", "n_particles",
                                                      "dim"))
                meta = json.loads(attrs["meta"])
                expected = {name: (s, t, n, d) for name in STATE_ARRAYS}
                expected.update({name: (s, n) for name in PARTICLE_ARRAYS})
                if meta["target"] == "acceleration" and meta["interaction"] != "unknown":
                    expected["accelerations"] = (s, t, n, d)  # the true law's (imported: none)
                if "kinematic" in f:  # imported: particles the source moves
                    expected["kinematic"] = (s, n)
                for name, shape in expected.items():
                    if name not in f:
                        raise self._fail(f"lacks the array {name!r}")
                    if f[name].shape != shape:
                        raise self._fail(f"array {name!r} has shape {f[name].shape}, "
                                         f"expected {shape}")
                if meta["interaction"] == "contact":
                    if "contacts" not in f or f["contacts"].ndim != 2 or \
                            f["contacts"].shape[1] != 4:
                        raise self._fail("lacks a (M, 4) 'contacts' array")
                if check_values:
                    arrays = {name: f[name][...] for name in (*expected, "contacts")
                              if name in f}
                    for name, value in arrays.items():
                        self._check_finite(name, value)
                    self._check_particles(arrays, meta)
                    if "stats" in f:
                        self._check_stats(f["stats"], arrays, float(attrs["dt"]), d, meta)
        except DatasetFileError:
            raise
        except (OSError, KeyError, ValueError, RuntimeError) as err:
            # h5py reports truncation and corruption as assorted low-level errors
            raise self._fail(f"cannot be read as HDF5, it is truncated or corrupt ({err})"
                             ) from None
        return attrs

    def _check_particles(self, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        """Masses positive, radii non-negative, types among the scene's."""
        if not (arrays["masses"] > 0).all():
            bad = int((~(arrays["masses"] > 0)).sum())
            raise self._fail(f"array 'masses' holds {bad} masses that are not positive")
        if not (arrays["radii"] >= 0).all():
            raise self._fail("array 'radii' holds negative radii")
        types = arrays["types"]
        if types.size and (types.min() < 0 or types.max() >= int(meta["n_types"])):
            raise self._fail(f"array 'types' holds types outside 0..{int(meta['n_types']) - 1}")

    def _check_stats(self, group: h5py.Group, arrays: dict[str, np.ndarray], dt: float,
                     dim: int, meta: dict[str, Any]) -> None:
        """Normalisation statistics: every group and entry present with the arrays' number of
        columns, finite, scales >= 0, min <= mean, median <= max, and the groups that are
        cheap to recompute (``RECOMPUTED_STATS``) equal to what the arrays give."""
        from bgn.data.stats import summarize  # the one definition of the statistics
        from bgn.data.targets import backward_velocities, targets

        for name, columns in STATS_GROUPS.items():
            width = dim if columns == "dim" else columns
            if name not in group:
                raise self._fail(f"lacks the statistics group 'stats/{name}'")
            for key in STATS_ENTRIES:
                if key not in group[name]:
                    raise self._fail(f"lacks the statistics 'stats/{name}/{key}'")
                value = group[name][key][...]
                shape = () if key == "count" else (width,)
                where = f"statistics 'stats/{name}/{key}'"
                if value.shape != shape:
                    raise self._fail(f"{where} have shape {value.shape}, expected {shape}")
                if not np.isfinite(value).all():
                    raise self._fail(f"{where} hold non-finite values (NaN or inf)")
                if key in ("std", "robust_scale") and (value < 0).any():
                    raise self._fail(f"{where} hold negative scales")
            s = {key: group[name][key][...] for key in STATS_ENTRIES}
            if s["count"] > 0 and not ((s["min"] <= s["max"]).all()
                                       and _within(s["mean"], s["min"], s["max"])
                                       and _within(s["median"], s["min"], s["max"])):
                raise self._fail(f"statistics 'stats/{name}' are inconsistent (a mean or median "
                                 "outside [min, max])")
        x = np.moveaxis(arrays["positions"], 1, 0)
        fresh = {"velocity": lambda: backward_velocities(x, dt).reshape(-1, dim),
                 "target": lambda: targets(x, dt, meta["target"]).reshape(-1, dim),
                 "log_mass": lambda: np.log(arrays["masses"]).reshape(-1, 1)}
        for name in RECOMPUTED_STATS:
            expected = summarize(fresh[name]())
            for key, value in expected.items():
                stored = group[name][key][...]
                scale = float(np.max(np.abs(value))) if np.size(value) else 0.0
                if not np.allclose(stored, value, rtol=1e-9, atol=1e-12 * scale):
                    raise self._fail(f"statistics 'stats/{name}/{key}' do not match the arrays "
                                     f"(stored {np.round(stored, 6).tolist()}, the arrays give "
                                     f"{np.round(value, 6).tolist()})")

    def _check_finite(self, name: str, value: np.ndarray) -> None:
        if value.dtype.kind == "f" and not np.isfinite(value).all():
            bad = int((~np.isfinite(value)).sum())
            raise self._fail(f"array {name!r} holds {bad} non-finite values (NaN or inf)")

    # -- reading ------------------------------------------------------------------------
    @property
    def handle(self) -> h5py.File:
        if self._handle is None:
            self._handle = h5py.File(self.path, "r")
        return self._handle

    def read(self, name: str, index: Any = ()) -> np.ndarray:
        """Read ``name[index]``; whole arrays are cached (``load_all`` fills the cache)."""
        if name in self._cache:
            return self._cache[name][index]
        try:
            return self.handle[name][index]
        except (OSError, KeyError) as err:
            raise self._fail(f"reading {name!r} failed ({err})") from None

    @property
    def loaded(self) -> bool:
        """Whether ``load_all`` has put the arrays in memory."""
        return bool(self._cache)

    def load_all(self) -> None:
        """Read every array into memory once (small and medium datasets)."""
        for name in self.handle:
            if isinstance(self.handle[name], h5py.Dataset):
                self._cache[name] = self.read(name, ...)
        self.close()

    def stats(self) -> dict[str, dict[str, np.ndarray]]:
        if "stats" not in self.handle:
            raise self._fail("has no normalisation statistics (only train files carry them)")
        return {g: {k: v[...] for k, v in self.handle["stats"][g].items()}
                for g in self.handle["stats"]}

    @property
    def n_sims(self) -> int:
        return int(self.attrs["n_sims"])

    @property
    def n_frames(self) -> int:
        return int(self.attrs["n_frames"])

    @property
    def dt(self) -> float:
        return float(self.attrs["dt"])

    @property
    def margin(self) -> float:
        return float(self.attrs.get("margin", 0.0))

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_handle"] = None  # never pickle an h5py handle
        return state
