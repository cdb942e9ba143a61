"""Generate (or find in the cache) the HDF5 files of a dataset.

``ensure_splits`` writes the train, val and test files under a data directory (the command
``python -m bgn.train.generate dataset=collisions fps=10``, ``bgn/train/generate.py``, and the
DataModule call it). Simulations run in parallel processes; each one draws from its own
seed sequence ``(seed, split, index)``, so the arrays are bit-identical whatever the number of
workers, and the simulations of a larger ``n_sims`` extend those of a smaller one.
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import warnings
from concurrent.futures import ProcessPoolExecutor
from contextlib import nullcontext
from glob import escape as glob_escape
from multiprocessing import get_context
from pathlib import Path

import h5py
import numpy as np
from filelock import FileLock
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from bgn.data.edges import contact_margin
from bgn.data.files import DatasetFile, write_dataset
from bgn.data.spec import IMPORTED, SPLITS, DatasetSpec
from bgn.data.stats import compute_stats
from bgn.sim import Trajectory
from bgn.sim.nbody import NYQUIST_TURN, pair_turns

SPLIT_IDS = {name: i for i, name in enumerate(SPLITS)}
# share of a force scene's frames beyond the frame rate's Nyquist limit above which generation
# warns; the default gravity_r2 training split stays below it at fps 10 and 50
# (docs/notes/2026-11-26-results-history.md, "Frames that alias")
ALIASED_WARN = 0.05


def simulate_one(spec: DatasetSpec, index: int) -> Trajectory:
    """Simulation ``index`` of a split: a pure function of the spec and the index."""
    rng = np.random.default_rng(np.random.SeedSequence([spec.seed, SPLIT_IDS[spec.split], index]))
    # j / fps (not j * dt): the times of different frame rates then agree exactly.
    times = np.arange(spec.n_frames) / spec.fps
    return spec.build_scene().simulate(rng, times)


PR_SET_PDEATHSIG = 1  # linux/prctl.h


def end_with_parent(parent: int) -> None:
    """Initializer of a generation worker: the worker ends when its parent does.

    On Linux the kernel sends SIGKILL to the worker when the parent dies (PR_SET_PDEATHSIG),
    even by kill -9, which no Python-level handler sees; without this the workers of a
    killed generation keep simulating, re-parented. A parent already gone: exit at once.
    """
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
        except (OSError, AttributeError):  # no prctl: the pool's own checks remain
            pass
    if os.getppid() != parent:  # died before prctl took effect
        os._exit(1)


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove the temporary files (``<name>.tmp<pid>``) that a killed writer of ``path``
    left. Call with the file's lock held: no live writer of it exists then."""
    stale = sorted(path.parent.glob(f"{glob_escape(path.name)}.tmp*"))
    for tmp in stale:
        tmp.unlink(missing_ok=True)
    return stale


def _simulate_indexed(args: tuple[DatasetSpec, int]) -> tuple[int, Trajectory]:
    return args[1], simulate_one(*args)


def simulate_split(spec: DatasetSpec, workers: int = 1,
                   progress: Progress | None = None) -> list[Trajectory]:
    """All simulations of one split, in index order."""
    results: list[Trajectory | None] = [None] * spec.n_sims
    task = progress.add_task(f"{spec.scene} fps={spec.fps:g} {spec.split}",
                             total=spec.n_sims) if progress else None
    jobs = [(spec, i) for i in range(spec.n_sims)]
    if workers <= 1:
        finished = map(_simulate_indexed, jobs)
        pool = None
    else:
        # spawn: safe even when torch (and its thread pools) is already imported
        pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"),
                                   initializer=end_with_parent, initargs=(os.getpid(),))
        finished = pool.map(_simulate_indexed, jobs)
    try:
        for index, trajectory in finished:
            results[index] = trajectory
            if progress is not None and task is not None:
                progress.advance(task)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    return results  # type: ignore[return-value]


def stack(trajectories: list[Trajectory]) -> dict[str, np.ndarray]:
    """Trajectories -> the file's arrays (leading simulation axis; contacts as a table)."""
    arrays = {name: np.stack([getattr(t, name) for t in trajectories])
              for name in ("positions", "velocities", "masses", "radii")}
    arrays["types"] = np.stack([t.types for t in trajectories]).astype(np.int64)
    if trajectories[0].accelerations is not None:
        arrays["accelerations"] = np.stack([t.accelerations for t in trajectories])
    if trajectories[0].contacts is not None:
        rows = [np.column_stack([np.full(len(t.contacts), s), t.contacts])
                for s, t in enumerate(trajectories)]
        arrays["contacts"] = np.concatenate(rows).astype(np.int64).reshape(-1, 4)
    return arrays


def contact_gaps(arrays: dict[str, np.ndarray]) -> np.ndarray:
    """(M,) the gap between the surfaces of the two discs of every recorded contact, at the
    frame it is recorded in (the contact comes before the next frame)."""
    c, x, r = arrays["contacts"], arrays["positions"], arrays["radii"]
    return (np.linalg.norm(x[c[:, 0], c[:, 1], c[:, 2]] - x[c[:, 0], c[:, 1], c[:, 3]], axis=-1)
            - r[c[:, 0], c[:, 2]] - r[c[:, 0], c[:, 3]])


def radius_margin(arrays: dict[str, np.ndarray], dt: float) -> float:
    """Margin of the radius graph that makes every contact before the next frame a candidate.

    Relative speed times dt (with a safety factor) from the fastest disc of the split, widened
    if a recorded contact would still fall outside (a chain of collisions within one frame).
    Computed on the train split only: val and test take the train split's margin
    (``generate_file``), so no test contact or speed shapes a test input.
    """
    speed = np.linalg.norm(arrays["velocities"], axis=-1).max()
    margin = contact_margin(2.0 * speed, dt)
    if len(arrays["contacts"]):
        margin = max(margin, contact_margin(float(contact_gaps(arrays).max()) / dt, dt))
    return float(margin)


def aliased_share(arrays: dict[str, np.ndarray], dt: float) -> float:
    """Share of the frames (over every simulation) in which some pair turns more than
    ``NYQUIST_TURN`` revolution per frame (``bgn.sim.nbody.pair_turns``): motion the frames
    cannot carry, which no model fed them can follow."""
    x, v = arrays["positions"], arrays["velocities"]
    return float(np.mean([np.mean(pair_turns(x[s], v[s], dt) > NYQUIST_TURN)
                          for s in range(len(x))]))


def generate_file(spec: DatasetSpec, path: Path, workers: int = 1,
                  progress: Progress | None = None, margin: float | None = None) -> None:
    """Simulate a split and write its file. On a radius-graph scene the train split sets the
    graph's margin (``radius_margin``); val and test take ``margin``, the train split's: a
    recorded contact of theirs outside it is counted and warned about, never widened for."""
    scene = spec.build_scene()
    arrays = stack(simulate_split(spec, workers, progress))
    if scene.meta.interaction == "pairwise" and spec.split == "train":  # force scenes
        share = aliased_share(arrays, spec.dt)
        if share > ALIASED_WARN:
            warnings.warn(
                f"{spec.scene} at fps {spec.fps:g}: in {100 * share:.0f} % of the frames a pair "
                f"turns more than {NYQUIST_TURN:g} revolution per frame (close encounters "
                "faster than the frame rate); frames cannot carry that motion and no model fed "
                "them can follow it. A higher fps resolves it.", stacklevel=2)
    if scene.meta.graph != "radius":
        margin = 0.0
    elif spec.split == "train":
        margin = radius_margin(arrays, spec.dt)
    elif margin is None:
        raise ValueError(f"the {spec.split} split of {spec.scene} takes the train split's "
                         "radius-graph margin: pass margin= (ensure_dataset reads it from the "
                         "train file)")
    else:
        warn_uncovered(spec, arrays, margin)
    stats = compute_stats(scene, arrays, spec.dt, margin) if spec.split == "train" else None
    write_dataset(path, spec, scene.meta, arrays, margin=margin, stats=stats)


def warn_uncovered(spec: DatasetSpec, arrays: dict[str, np.ndarray], margin: float) -> int:
    """Warn when recorded contacts of a val or test split are no candidate edges of the
    radius graph with the train split's ``margin``; returns how many."""
    gaps = contact_gaps(arrays)
    missed = int(np.sum(gaps > margin))
    if missed:
        warnings.warn(
            f"{spec.scene} at fps {spec.fps:g}, {spec.split} split: {missed} of {len(gaps)} "
            f"recorded contacts lie outside the train split's radius-graph margin "
            f"{margin:.4g} (no candidate edge); the margin is not widened from "
            f"{spec.split} data", stacklevel=2)
    return missed


def train_margin(spec: DatasetSpec, data_dir: str | Path, workers: int | None = None,
                 progress: Progress | None = None) -> float | None:
    """The radius-graph margin a val or test file must carry: the train file's (generated
    first if missing); None for a train split or a scene without a radius graph."""
    if spec.split == "train" or spec.build_scene().meta.graph != "radius":
        return None
    path = ensure_dataset(spec.with_split("train"), data_dir, workers, progress)
    with h5py.File(path, "r") as f:
        return float(f.attrs["margin"])


def _other_margin(path: Path, margin: float | None) -> bool:
    """Whether the file at ``path`` was written with a margin other than ``margin`` (a val or
    test file of the old rule, which took its own split's): stale, to be regenerated. A file
    that cannot be read is left to validation, which names the problem."""
    if margin is None or not path.exists():
        return False
    try:
        with h5py.File(path, "r") as f:
            return float(f.attrs["margin"]) != margin
    except (OSError, KeyError):
        return False


def ensure_dataset(spec: DatasetSpec, data_dir: str | Path, workers: int | None = None,
                   progress: Progress | None = None) -> Path:
    """Path of the valid file for ``spec``, generating it first if it is not cached.

    A lock next to the file lets concurrent processes share the work: the first generates,
    the others wait and then read the same file. An existing bad file raises
    ``DatasetFileError`` and is left untouched. A val or test file of a radius-graph scene
    takes the train file's margin (the train file comes first); one written with another
    margin (the old rule: its own split's) is regenerated.
    """
    path = spec.path(data_dir)
    if spec.scene == IMPORTED:  # never generated: written by bgn.data.importing
        DatasetFile(path, spec).close()
        return path
    margin = train_margin(spec, data_dir, workers, progress)
    if not path.exists() or _other_margin(path, margin):
        path.parent.mkdir(parents=True, exist_ok=True)
        with FileLock(path.with_name(f".{path.name}.lock")):  # hidden; never removed (safe)
            if not path.exists() or _other_margin(path, margin):  # replaced atomically
                remove_stale_temporaries(path)  # a killed writer's partial file
                workers = default_workers(spec.n_sims) if workers is None else workers
                generate_file(spec, path, workers, progress, margin)
    DatasetFile(path, spec).close()  # validate (cheap at our sizes) before anyone trains on it
    return path


def default_workers(n_sims: int) -> int:
    return max(1, min(n_sims, len(os.sched_getaffinity(0))))


def progress_bar() -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn())


def ensure_splits(spec: DatasetSpec, data_dir: str | Path, workers: int | None = None,
                  show_progress: bool = True) -> dict[str, Path]:
    """Generate or find the train, val and test files of a dataset."""
    progress = progress_bar() if show_progress else None
    with progress or nullcontext():
        return {split: ensure_dataset(spec.with_split(split), data_dir, workers, progress)
                for split in SPLITS}


if __name__ == "__main__":  # python -m bgn.data.generate, the older name of the command
    import runpy

    runpy.run_module("bgn.train.generate", run_name="__main__", alter_sys=True)
