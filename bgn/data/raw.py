"""Trajectories brought from outside bgn, before they become bgn's dataset files.

Every importable layout (``bgn.data.formats``) and the in-memory API (``bgn.data.from_arrays``)
reduce to one ``RawTrajectories``: per split, positions (S, T, N, D) and what else the source
carries, plus the frame spacing, the box and where the data came from. ``bgn.data.importing``
checks it and writes the three HDF5 files.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

IMPORT_SPLITS = ("train", "val", "test")


class DataImportError(ValueError):
    """Trajectories that cannot be imported; the message names the file, trajectory and frame
    and says what to do. Raised before anything is written."""


class DataImportWarning(UserWarning):
    """Something of the source that the import ignores or doubts (a key no reader uses, a
    misspelt one); the import goes on."""


@dataclass
class SplitArrays:
    """One split: S trajectories of T frames, N particles, D dimensions (float64).

    ``masses``, ``radii`` (S, N) float64 and ``types`` (S, N) int64 are None where the source
    does not carry them; ``velocities`` (S, T, N, D) likewise. ``names`` are the source's
    trajectory keys (for error messages)."""

    positions: np.ndarray
    masses: np.ndarray | None = None
    radii: np.ndarray | None = None
    types: np.ndarray | None = None
    velocities: np.ndarray | None = None
    names: list[str] = field(default_factory=list)


@dataclass
class RawTrajectories:
    """What an import reads: the splits (``IMPORT_SPLITS`` keys), the frame spacing ``dt``,
    the box ``bounds`` (D, 2) lower/upper or None, which dimensions are ``periodic`` (D,) bools,
    the particle types that are kinematic (moved by the source, never predicted or scored), the
    connectivity radius the source suggests (None: a complete graph), and the provenance
    (``source``: format, files and their sha256; ``metadata``: the source's own metadata)."""

    splits: dict[str, SplitArrays]
    dt: float
    bounds: np.ndarray | None = None
    periodic: np.ndarray | None = None
    kinematic_types: tuple[int, ...] = ()
    connectivity_radius: float | None = None
    source: dict[str, Any] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
