"""How many Newton steps the shooting needs (``bgn.model.newton.SHOOTING_ITERATIONS``), measured
on a split's frames with the scene's true law and masses.

The pair-force head with ``model.substeps > 1`` predicts a frame's finite-difference
acceleration by shooting (``newton.shoot``): the velocity at frame t is corrected by Newton
steps until the integration back over one frame meets x[t-1]. Fed the true law and the
recorded masses, the prediction should reproduce the recorded target to the integrator's
accuracy; how close it gets after each number of steps says how many are enough. Per number of
iterations and substeps: the relative error ``|a_pred - a_true| / |a_true|`` over every
particle of ``frames`` frames spread evenly over the split's simulations (median, 90th and
99th percentiles) and the NMSE (mean squared error over the targets' variance)::

    python -m bgn.benchmarks.shooting [scene=gravity_r2] [fps=50] [split=val] [frames=1024]
        [iterations=[1,2,3,4,8,16,24]] [substeps=[16,64]] [paths.data_dir=data]
        [report_dir=outputs/benchmarks]      # --help: every key (conf/benchmarks/shooting.yaml)

Writes ``shooting.md`` and ``shooting.csv`` under ``report_dir``; the data are generated into
``paths.data_dir`` where missing. Choose on the validation split (the default): the fewest
iterations whose percentiles are within ``tolerance`` of the most iterations' is printed.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from bgn.benchmarks._report import (
    command,
    compose_train,
    console,
    need_ints,
    need_strings,
    options,
    print_table,
)
from bgn.provenance import machine
from bgn.tables import markdown_table, write_csv

COLUMNS = ["substeps", "iterations", "median", "p90", "p99", "nmse", "seconds"]


def split_data(scene: str, fps: float, split: str, data_dir: str,
               overrides: list[str]) -> Any:
    """The ``split`` of ``dataset=<scene>`` at ``fps`` (generated where missing): a
    ``FrameDataset``, its file and scene."""
    from bgn.data.datamodule import ParticleDataModule

    cfg = compose_train([f"dataset={scene}", f"fps={fps}", *overrides])
    datamodule = ParticleDataModule(cfg.dataset, cfg.fps, data_dir, show_progress=False)
    datamodule.prepare_data()
    datamodule.setup()
    return datamodule.datasets[split]


def frames(file: Any, count: int) -> list[tuple[int, np.ndarray]]:
    """(simulation, frame indices t) of ``count`` frames spread evenly over the simulations,
    each with x[t-1] and x[t+1] in the file."""
    from bgn.data.frames import evenly_spaced

    per_sim = max(1, math.ceil(count / file.n_sims))
    inner = np.arange(1, file.n_frames - 1)
    return [(s, inner[evenly_spaced(len(inner), per_sim)]) for s in range(file.n_sims)]


def shoot_frames(scene: Any, masses: np.ndarray, prev: np.ndarray, now: np.ndarray,
                 dt: float, substeps: int, iterations: int) -> np.ndarray:
    """The shooting's finite-difference acceleration (B, N, D) at frames ``now`` (B, N, D)
    with the scene's true law and ``masses`` (N,), from the velocity ``(now - prev) / dt``."""
    from bgn.model.newton import shoot

    b, n, d = now.shape

    def accel(pos: torch.Tensor) -> torch.Tensor:
        return torch.as_tensor(scene.accelerations(pos.numpy().reshape(b, n, d), masses)
                               .reshape(b * n, d))

    return shoot(accel, torch.as_tensor(now.reshape(b * n, d)),
                 torch.as_tensor(((now - prev) / dt).reshape(b * n, d)),
                 torch.full((b * n, 1), dt, dtype=torch.float64), substeps,
                 iterations).numpy().reshape(b, n, d)


def errors(data: Any, chosen: list[tuple[int, np.ndarray]], substeps: int,
           iterations: int) -> tuple[np.ndarray, float]:
    """(relative errors per particle, NMSE) of the shooting's prediction with the scene's
    true law and masses against the recorded targets."""
    file, dt = data.file, float(data.file.dt)
    rel, sq, targets = [], [], []
    for s, t in chosen:
        x = file.read("positions", s)  # (T, N, D)
        masses = np.asarray(file.read("masses", s), dtype=np.float64)
        target = (x[t + 1] - 2 * x[t] + x[t - 1]) / dt**2
        diff = shoot_frames(data.scene, masses, x[t - 1], x[t], dt, substeps,
                            iterations) - target
        rel.append((np.linalg.norm(diff, axis=-1)
                    / np.maximum(np.linalg.norm(target, axis=-1), 1e-300)).ravel())
        sq.append((diff**2).reshape(-1, diff.shape[-1]))
        targets.append(target.reshape(-1, target.shape[-1]))
    every = np.concatenate(targets)
    return np.concatenate(rel), float(np.concatenate(sq).mean() / max(every.var(0).mean(),
                                                                        1e-300))


def fewest(rows: list[dict[str, Any]], tolerance: float) -> dict[int, int]:
    """Per substeps, the fewest iterations whose median, 90th and 99th percentiles are within
    ``tolerance`` (relative) of those of the most iterations measured."""
    out = {}
    for k in sorted({r["substeps"] for r in rows}):
        group = sorted((r for r in rows if r["substeps"] == k), key=lambda r: r["iterations"])
        best = group[-1]
        out[k] = next(r["iterations"] for r in group if all(
            abs(r[q] - best[q]) <= tolerance * abs(best[q]) for q in ("median", "p90", "p99")))
    return out


SPLITS = ("train", "val", "test")


def check(cfg: Any) -> None:
    """Everything ``python -m bgn.benchmarks.shooting`` is given, before data are read or
    generated (the dataset's own keys: ``python -m bgn.train``'s checks)."""
    from bgn.coerce import ConfigError, need_float, need_int
    from bgn.training.validate import CONF_DIR, one_line, validate_dataset

    scenes = sorted(p.stem for p in (CONF_DIR / "dataset").glob("*.yaml"))
    if cfg.scene not in scenes:
        raise ConfigError("scene", cfg.scene, f"one of {scenes} (conf/dataset/)")
    if cfg.split not in SPLITS:
        raise ConfigError("split", cfg.split, f"one of {list(SPLITS)}")
    need_int(cfg.frames, "frames", 1)
    need_ints(cfg.iterations, "iterations", 1, why=" (Newton steps)")
    need_ints(cfg.substeps, "substeps", 2, why=" (one substep does not shoot)")
    need_float(cfg.tolerance, "tolerance", 0)
    if not cfg.paths.data_dir:
        raise ConfigError("paths.data_dir", cfg.paths.data_dir, "a folder (default: data)")
    overrides = need_strings(cfg.overrides, "overrides")
    try:
        train = compose_train([f"dataset={cfg.scene}", f"fps={cfg.fps}", *overrides])
    except Exception as err:  # noqa: BLE001 (Hydra's refusal of an override, on one line)
        raise ConfigError("overrides", message=f"overrides={overrides}: {one_line(err)}"
                          ) from err
    validate_dataset(train.dataset, train.fps, cfg.paths.data_dir)


@command("shooting", check)  # key=value; bad input: one line, exit 2
def main(cfg: Any) -> int:
    """Measure each (substeps, iterations) and write the report under ``report_dir``."""
    args = options(cfg)
    data = split_data(args.scene, args.fps, args.split, args.paths["data_dir"],
                      args.overrides)
    chosen = frames(data.file, args.frames)
    rows = []
    for k in args.substeps:
        for it in sorted(args.iterations):
            start = time.perf_counter()
            rel, nmse = errors(data, chosen, k, it)
            rows.append({"substeps": k, "iterations": it, "median": float(np.median(rel)),
                         "p90": float(np.quantile(rel, 0.9)),
                         "p99": float(np.quantile(rel, 0.99)), "nmse": nmse,
                         "seconds": time.perf_counter() - start})
    enough = fewest(rows, args.tolerance)
    n = sum(len(t) for _, t in chosen)
    title = (f"Shooting iterations: {args.scene} at fps {args.fps:g}, {args.split} split, "
             f"{n} frames, the true law and masses")
    notes = (f"Relative error |a_pred - a_true| / |a_true| per particle (median, p90, p99) and "
             "NMSE of the shooting's finite-difference acceleration against the recorded "
             "target; seconds: the wall time of each row. Fewest iterations within "
             f"{args.tolerance:g} of the most measured: "
             + ", ".join(f"{k} substeps: {v}" for k, v in enough.items()) + ". "
             + machine(torch=torch.__version__) + ".")
    args.report_dir.mkdir(parents=True, exist_ok=True)
    write_csv(args.report_dir / "shooting.csv", COLUMNS, rows)
    (args.report_dir / "shooting.md").write_text(
        f"# {title}\n\n{notes}\n\n" + markdown_table(COLUMNS, rows))
    out = console()
    print_table(out, title, COLUMNS, [[f"{r[c]:.3g}" if isinstance(r[c], float) else str(r[c])
                                       for c in COLUMNS] for r in rows])
    out.print(notes)
    return 0


if __name__ == "__main__":
    main()
