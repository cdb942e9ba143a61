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


class DatasetFileError(RuntimeError):
    """A dataset file that cannot be used; the message names the file and the fix."""

    def __init__(self, path: str | Path, problem: str, hint: str | None = None) -> None:
        fix = (f"Delete it and regenerate it with `{hint}` (with the same dataset overrides)"
               if hint else "Delete it and regenerate it with `python -m bgn.data.generate`")
        super().__init__(f"dataset file {path}: {problem}. {fix}; nothing else is touched.")
        self.path = Path(path)


def write_dataset(path: Path, spec: DatasetSpec, meta: SceneMeta, arrays: dict[str, np.ndarray],
                  margin: float = 0.0, stats: dict[str, dict[str, np.ndarray]] | None = None,
                  ) -> None:
    """Write a complete file to a temporary name, then rename it into place (atomic)."""
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
                "bgn_version": __version__,
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


class DatasetFile:
    """A validated dataset file. Arrays are read on demand; the handle opens lazily.

    Safe to pickle into DataLoader workers: the h5py handle is never pickled, each process
    opens its own on first access.
    """

    def __init__(self, path: str | Path, spec: DatasetSpec | None = None,
                 check_values: bool = True) -> None:
        self.path = Path(path)
        self.hint = spec.regenerate_hint() if spec else None
        self._handle: h5py.File | None = None
        self._cache: dict[str, np.ndarray] = {}
        self.attrs = self._validate(check_values)
        self.meta = SceneMeta(**json.loads(self.attrs["meta"]))

    # -- validation ---------------------------------------------------------------------
    def _fail(self, problem: str) -> DatasetFileError:
        return DatasetFileError(self.path, problem, self.hint)

    def _validate(self, check_values: bool) -> dict[str, Any]:
        if not self.path.exists():
            raise self._fail("does not exist")
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
                if meta["target"] == "acceleration":
                    expected["accelerations"] = (s, t, n, d)
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
                    for name in (*expected, "contacts"):
                        if name in f:
                            self._check_finite(name, f[name][...])
        except DatasetFileError:
            raise
        except (OSError, KeyError, ValueError, RuntimeError) as err:
            # h5py reports truncation and corruption as assorted low-level errors
            raise self._fail(f"cannot be read as HDF5, it is truncated or corrupt ({err})"
                             ) from None
        return attrs

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
