"""Rollouts as VTK time series that ParaView (or any VTK reader) opens: one PolyData file
(``.vtp``, binary, appended) per frame, its particles as vertices with per-particle fields, and
a ``.pvd`` collection that orders the frames in simulated time. Written with pyevtk's
``VtkFile`` and ``VtkGroup``, not by hand.

Positions of 2-D scenes get z = 0 (VTK's points are 3-D); vectors likewise.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _vector(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, D) -> three contiguous float64 columns, zero-padded to 3-D."""
    a = np.asarray(a, dtype=np.float64)
    cols = [np.ascontiguousarray(a[:, i]) if i < a.shape[1] else np.zeros(len(a))
            for i in range(3)]
    return cols[0], cols[1], cols[2]


def write_frame(path: Path, positions: np.ndarray,
                fields: dict[str, np.ndarray]) -> Path:
    """One frame: ``positions`` (N, D) as vertices and ``fields``, each (N,) (a scalar) or
    (N, D) (a vector), as point data. ``path`` without its suffix; returns the ``.vtp``."""
    from pyevtk.vtk import VtkFile, VtkPolyData

    n = len(positions)
    data: dict[str, np.ndarray | tuple[np.ndarray, ...]] = {}
    for name, value in fields.items():
        value = np.asarray(value)
        if value.shape[0] != n or value.ndim not in (1, 2):
            raise ValueError(f"field {name!r}: give (N,) or (N, D) values for {n} particles; "
                             f"got shape {value.shape}")
        data[name] = _vector(value) if value.ndim == 2 else np.ascontiguousarray(
            value, dtype=np.int32 if value.dtype.kind in "iub" else np.float64)
    points = _vector(positions)
    connectivity = np.arange(n, dtype=np.int32)  # each vertex one point
    offsets = np.arange(1, n + 1, dtype=np.int32)
    w = VtkFile(str(path), VtkPolyData)
    w.openGrid()
    w.openPiece(npoints=n, nverts=n)
    w.openElement("Points")
    w.addData("points", points)
    w.closeElement("Points")
    w.openElement("Verts")
    w.addData("connectivity", connectivity)
    w.addData("offsets", offsets)
    w.closeElement("Verts")
    if data:
        scalars = next((k for k, v in data.items() if isinstance(v, np.ndarray)), None)
        vectors = next((k for k, v in data.items() if isinstance(v, tuple)), None)
        w.openData("Point", scalars=scalars, vectors=vectors)
        for name, value in data.items():
            w.addData(name, value)
        w.closeData("Point")
    w.closePiece()
    w.closeGrid()
    w.appendData(points)
    w.appendData(connectivity).appendData(offsets)
    for value in data.values():
        w.appendData(value)
    w.save()
    return Path(w.getFileName())


def write_series(folder: str | Path, name: str, positions: np.ndarray, dt: float,
                 fields: dict[str, np.ndarray] | None = None, start_time: float = 0.0,
                 ) -> Path:
    """A trajectory as a time series: ``positions`` (T, N, D); ``fields`` per particle, each
    (N,) or (N, D) (the same every frame) or (T, N) or (T, N, D) (per frame); frame t at time
    ``start_time + t * dt``. Writes ``<folder>/<name>/<name>_<t>.vtp`` and
    ``<folder>/<name>.pvd``; returns the ``.pvd``."""
    from pyevtk.vtk import VtkGroup

    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 3 or len(positions) < 1:
        raise ValueError(f"positions: give (frames, N, D); got shape {positions.shape}")
    t_count, n = positions.shape[:2]
    per_frame: dict[str, np.ndarray] = {}
    for key, value in (fields or {}).items():
        value = np.asarray(value)
        if value.shape[:2] == (t_count, n) and value.ndim >= 2 and (
                value.ndim == 3 or value.shape != (n, positions.shape[2])):
            per_frame[key] = value
        else:
            per_frame[key] = np.broadcast_to(value, (t_count, *value.shape))
    folder = Path(folder)
    (folder / name).mkdir(parents=True, exist_ok=True)
    group = VtkGroup(str(folder / name))
    width = len(str(t_count - 1))
    for t in range(t_count):
        vtp = write_frame(folder / name / f"{name}_{t:0{width}d}", positions[t],
                          {k: v[t] for k, v in per_frame.items()})
        group.addFile(str(vtp), sim_time=start_time + t * dt)  # written relative
    group.save()
    return folder / f"{name}.pvd"
