"""Speed against error: ``python -m bgn.experiments preset=pareto_first_look`` (presets:
pareto_tiny | pareto_first_look | pareto_full, ``conf/preset/``; ``bgn.studies.grid`` hands a
preset with a ``schedule_s`` to ``run`` here).

Every cost is set against one error: the rollout error after one simulated time unit (the mean
position error per particle after ``fps`` steps, mean over all test rollouts from the reference
start frames, a failed one at the cap of ``bgn.metrics.rollout_metrics``).

- Training compute: one run per scene x fps x model (``bgn.studies.grid``' cells: resumable,
  trained by ``bgn.train``) with checkpoints on a time schedule (``TimeSchedule``); each
  checkpoint's one-step NMSE and rollout error.
- Inference cost: those checkpoints and BGN (and the baselines) at other sizes, trained for the
  schedule's last time: wall time per simulated time unit of a rollout of one scene (median of
  ``timing_repeats``, ``threads`` torch threads) against its rollout error.
- The exact simulator on the same scene and N (error zero) and, for collisions, at larger N at
  constant density beside a learned rollout of the same models (the graph scales with N).

The report (``report_dir``): per scene a log-log plot of error against training minutes and
against inference time with the Pareto fronts drawn and every point labelled, the fronts'
tables, the simulator's tables and report.md. Resumable: a cell with ``metrics.json`` is not
retrained, a cell whose ``pareto_eval.json`` is newer than its checkpoints is not re-evaluated,
the report is rewritten from disk.
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.callbacks import Callback
from omegaconf import DictConfig

from bgn.coerce import clock
from bgn.studies.cells import Cell, cell_datamodule, train_cell
from bgn.tables import fmt, write_table
from bgn.training.checkpoints import read_record, write_atomic

SCHEDULE = "schedule"    # the group of the cells with checkpoints on the time schedule
SIZES = "sizes"          # the group of the cells at other model sizes
REFERENCE = "last extrapolation (no learning)"   # beside the models at larger N


# ----------------------------------------------------------------------------- training
class TimeSchedule(Callback):
    """Saves ``t<seconds>s.ckpt`` in ``dirpath`` when the fit's wall time passes each of
    ``seconds`` and stops the fit after the last. The clock is kept in the checkpoints, so a
    resumed run continues it rather than starting again."""

    def __init__(self, dirpath: str, seconds: Sequence[float]) -> None:
        self.dirpath = Path(dirpath)
        self.seconds = sorted(float(s) for s in seconds)
        self.elapsed = 0.0          # wall time of earlier sittings (from the checkpoint)
        self._since: float | None = None

    def path(self, seconds: float) -> Path:
        return self.dirpath / f"t{seconds:g}s.ckpt"

    def now(self) -> float:
        return self.elapsed + (0.0 if self._since is None else time.perf_counter() - self._since)

    def on_train_start(self, trainer: Any, pl_module: Any) -> None:
        self._since = time.perf_counter()

    def on_train_batch_end(self, trainer: Any, *args: Any) -> None:
        now = self.now()
        for seconds in self.seconds:
            if seconds <= now and not self.path(seconds).exists():
                self.save(trainer, seconds)
        if now >= self.seconds[-1]:
            trainer.should_stop = True

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        # a fit ended by another limit (max_epochs) before the last mark: its final weights
        # under the next mark's name, with the time it really trained in the sidecar
        missing = [s for s in self.seconds if not self.path(s).exists()]
        if missing and not trainer.interrupted:
            self.save(trainer, missing[0])

    def save(self, trainer: Any, mark: float) -> None:
        trainer.save_checkpoint(self.path(mark))
        # the time actually trained: a long step may pass two marks at once
        write_atomic(self.path(mark).with_suffix(".json"),
                     json.dumps({"seconds": self.now(), "step": trainer.global_step}))

    def state_dict(self) -> dict[str, float]:
        return {"elapsed": self.now()}

    def load_state_dict(self, state_dict: dict[str, float]) -> None:
        self.elapsed = float(state_dict["elapsed"])


def schedule_overrides(cell_dir: Path, seconds: Sequence[float]) -> list[str]:
    """The train overrides of a cell with checkpoints at ``seconds`` of training: the
    ``TimeSchedule`` callback, a ``max_time`` it ends before, no test of best.ckpt (each
    scheduled checkpoint is evaluated here instead)."""
    last = max(float(s) for s in seconds)
    limit = int(2 * last + 60)  # a safety net only: the schedule stops the fit
    return ["+callbacks.time_schedule._target_=bgn.studies.pareto.TimeSchedule",
            f"+callbacks.time_schedule.dirpath={cell_dir / 'checkpoints'}",
            f"+callbacks.time_schedule.seconds=[{','.join(f'{s:g}' for s in seconds)}]",
            f"trainer.max_time={clock(limit)}",
            "trainer.max_steps=-1",  # the schedule's times end the cell, not a scene's steps
            "test=false"]


def size_grid(axes: DictConfig) -> list[tuple[str, list[str]]]:
    """(tag, overrides) of every point of a model's size grid: ``axes`` maps an axis name to
    ``{keys: [config keys set together], values: [...]}``."""
    names = list(axes)
    out = []
    for values in itertools.product(*(axes[n]["values"] for n in names)):
        tag = "_".join(f"{n}{v}" for n, v in zip(names, values))
        out.append((tag, [f"{key}={v}" for n, v in zip(names, values) for key in axes[n]["keys"]]))
    return out


def plan_cells(cfg: DictConfig) -> list[Cell]:
    """The schedule cells (scene x fps x model, checkpoints at ``schedule_s``) and the size
    cells (per model, its size grid at ``sizes.fps``, trained for the schedule's last time)."""
    preset, cells_dir = cfg.preset, Path(cfg.cells_dir)
    cells = []
    for scene, fps, model in itertools.product(preset.scenes, preset.fps, preset.models):
        cell = Cell(scene, float(fps), model, groups=(SCHEDULE,))
        cells.append(replace(cell, extra=tuple(schedule_overrides(cells_dir / cell.name,
                                                                  preset.schedule_s))))
    sizes = preset.get("sizes") or {}
    for scene, fps in itertools.product(sizes.get("scenes", []), sizes.get("fps", [])):
        for model, axes in (sizes.get("grid") or {}).items():
            for tag, overrides in size_grid(axes):
                cell = Cell(scene, float(fps), model, groups=(SIZES,), tag=tag)
                cells.append(replace(cell, extra=(*overrides, *schedule_overrides(
                    cells_dir / cell.name, [max(preset.schedule_s)]))))
    return cells


# ----------------------------------------------------------------------------- measuring
def steps_per_unit(fps: float) -> int:
    """Frames in one simulated time unit."""
    return max(1, round(fps))


def timed(fn: Callable[[], Any], repeats: int, warm_up: bool = True) -> tuple[Any, float]:
    """The first call's result and the median wall time of ``repeats`` calls; with
    ``warm_up`` the first call is not timed (torch's first call pays for its set-up)."""
    times, result = [], None
    for i in range(repeats + warm_up):
        start = time.perf_counter()
        out = fn()
        if i == 0:
            result = out
        if i >= warm_up:
            times.append(time.perf_counter() - start)
    return result, statistics.median(times)


def learned_rollout(model: Any, window: np.ndarray, masses: np.ndarray, radii: np.ndarray,
                    types: np.ndarray, dt: float, margin: float, n_steps: int,
                    ) -> Callable[[], np.ndarray]:
    """A call that rolls ``model`` out of one true ``window`` (k+2, N, D) for ``n_steps`` and
    returns the last predicted frame (N, D)."""
    from bgn.simulator import LearnedSimulator, Particles

    sim = LearnedSimulator(model, dt, margin)
    parts = Particles(*(torch.as_tensor(a)[None] for a in (masses, radii, types)),
                      torch.zeros(1, dtype=torch.long))
    start = window.shape[0] - 1

    @torch.no_grad()
    def run() -> np.ndarray:
        return sim.rollout(torch.as_tensor(window)[None], parts, n_steps, start
                           ).positions[0, -1].numpy()

    return run


def evaluate_checkpoint(ckpt: Path, test: Any, fps: float, e: DictConfig) -> dict[str, Any]:
    """One checkpoint: one-step NMSE (forward metrics without the inverse), rollout error
    after one time unit, wall time per simulated time unit of a rollout of one scene."""
    from bgn.data.frames import evenly_spaced
    from bgn.eval.evaluate import evaluate_model
    from bgn.metrics import rollout_metrics
    from bgn.rollout import rollout_many, rollout_starts
    from bgn.training.module import load_model

    module = load_model(ckpt)
    forward, _ = evaluate_model(module, test, max_frames=e.max_frames, batch_size=e.batch_size,
                                inverse=False)
    n = steps_per_unit(fps)
    sims = evenly_spaced(test.file.n_sims, e.rollout_sims)
    starts = rollout_starts(test, n, e.rollout_starts)
    t = rollout_many(module.model, test, sims, starts, n)
    rollout = rollout_metrics(t.predicted, t.true, t.masses, test.dt, test.scene.energy,
                              t.first_non_finite, test.meta.box, horizons=(n,))
    k, sim, start = test.history, sims[0], starts[0]
    window = test.file.read("positions", (sim, slice(start - k - 1, start + 1)))
    run = learned_rollout(module.model, window, test.file.read("masses", sim),
                          test.file.read("radii", sim), test.file.read("types", sim), test.dt,
                          test.margin, n)
    seconds = timed(run, e.timing_repeats)[1] / (n * test.dt)
    return {"nmse": forward["nmse"], "rollout_error": rollout[f"pos_err_mean@{n}"],
            "failed_share": rollout["failed_share"], "seconds_per_time_unit": seconds,
            "parameters": sum(p.numel() for p in module.model.parameters())}


def checkpoints(run_dir: Path) -> list[tuple[Path, float]]:
    """A cell's scheduled checkpoints and the training seconds each holds."""
    out = []
    for ckpt in sorted((run_dir / "checkpoints").glob("t*s.ckpt")):
        side = read_record(ckpt.with_suffix(".json"))
        out.append((ckpt, float(side["seconds"]) if side else float(ckpt.stem[1:-1])))
    return sorted(out, key=lambda c: c[1])


@functools.cache
def test_split(run_dir: Path, data_dir: str) -> Any:
    """The test split of a cell's dataset, read once per run of the study."""
    return cell_datamodule(run_dir, data_dir).datasets["test"]


def evaluate_cell(cell: Cell, cfg: DictConfig) -> list[dict[str, Any]]:
    """Every scheduled checkpoint of a cell (cached in ``pareto_eval.json``)."""
    run_dir = Path(cfg.cells_dir) / cell.name
    ckpts = checkpoints(run_dir)
    if not ckpts:
        raise FileNotFoundError(f"no scheduled checkpoint in {run_dir / 'checkpoints'}")
    path = run_dir / "pareto_eval.json"
    newest = max(c.stat().st_mtime for c, _ in ckpts)
    if path.exists() and path.stat().st_mtime >= newest:
        cached = read_record(path)
        if cached is not None:
            return cached["points"]
    test = test_split(run_dir, cfg.paths.data_dir)
    points = [{"scene": cell.scene, "fps": cell.fps, "model": cell.model,
               "size": cell.tag or "default", "minutes": seconds / 60, "group": cell.groups[0],
               **evaluate_checkpoint(ckpt, test, cell.fps, cfg.preset.eval)}
              for ckpt, seconds in ckpts]
    write_atomic(path, json.dumps({"points": points}, indent=2))
    return points


def simulator_seconds(test: Any, fps: float, repeats: int) -> float:
    """The exact simulator's wall time per simulated time unit, from the state one frame
    before the reference start of the first test simulation, writing ``fps`` frames."""
    from bgn.rollout import rollout_starts
    from bgn.sim.scene import State

    n = steps_per_unit(fps)
    frame = (0, rollout_starts(test, n)[0] - 1)
    state = State(test.file.read("positions", frame), test.file.read("velocities", frame),
                  test.file.read("masses", 0), test.file.read("radii", 0),
                  test.file.read("types", 0))
    times = np.arange(n + 1) * test.dt
    # a numpy simulator has no first-call set-up: every run timed
    return timed(lambda: test.scene.simulate_from(state, times), repeats,
                 warm_up=False)[1] / (n * test.dt)


def scaled_collisions(cells: list[Cell], cfg: DictConfig, n_particles: int,
                      ) -> list[dict[str, Any]]:
    """Collisions at ``n_particles`` discs at the dataset's density (the box grows): the exact
    simulator's time per time unit, and the final checkpoint of each of ``cells`` (one scene
    and fps) rolled out of the same true window: its time and its error after one time unit
    against the exact simulator."""
    from bgn.model.references import Extrapolation
    from bgn.training.module import load_model

    sc = cfg.preset.simulator
    cell = cells[0]
    test = test_split(Path(cfg.cells_dir) / cell.name, cfg.paths.data_dir)
    base = test.scene
    scene = replace(base, n_particles=n_particles,
                    box=base.box * (n_particles / base.n_particles) ** (1 / base.dim))
    state = scene.draw_state(np.random.default_rng(0))
    n, k = steps_per_unit(cell.fps), test.history
    repeats = sc.repeats if n_particles <= sc.repeat_below else 1   # big N: one run
    # the true window and the unit after it in one run, which is also the timed one
    times = np.arange(k + 2 + n) * test.dt
    truth, exact = timed(lambda: scene.simulate_from(state, times).positions, repeats,
                         warm_up=False)
    rows = [{"N": n_particles, "box": scene.box, "model": "exact simulator",
             "seconds_per_time_unit": exact / (times[-1] - times[0]), "rollout_error": 0.0}]
    predictors = {c.model: load_model(checkpoints(Path(cfg.cells_dir) / c.name)[-1][0]).model
                  for c in cells}
    # the scale of the errors: every disc on its last velocity, no collision at all
    predictors[REFERENCE] = Extrapolation(scene.meta, k, "last")
    for name, model in predictors.items():
        run = learned_rollout(model, truth[:k + 2], state.masses, state.radii, state.types,
                              test.dt, test.margin, n)
        last, seconds = timed(run, repeats)   # the warm-up run gives the error
        error = float(np.linalg.norm(last - truth[-1], axis=-1).mean())
        rows.append({"N": n_particles, "box": scene.box, "model": name,
                     "seconds_per_time_unit": seconds / (n * test.dt),
                     "rollout_error": error if np.isfinite(error) else math.inf})
    return rows


# ----------------------------------------------------------------------------- the front
def pareto_front(points: Sequence[dict[str, Any]], cost: str,
                 error: str = "rollout_error") -> list[dict[str, Any]]:
    """The points no other point beats on both ``cost`` and ``error`` (lower is better), by
    increasing cost."""
    front: list[dict[str, Any]] = []
    for p in sorted(points, key=lambda p: (p[cost], p[error])):
        if math.isfinite(p[error]) and (not front or p[error] < front[-1][error]):
            front.append(p)
    return front


def label(p: dict[str, Any]) -> str:
    """model, size, fps, training minutes of a point."""
    size = "" if p["size"] == "default" else f" {p['size']}"
    return f"{p['model']}{size} fps{fmt(p['fps'])} {p['minutes']:.2g}min"


def goal_check(points: Sequence[dict[str, Any]], cost: str, similar: float = 2.0) -> str:
    """Whether some BGN point is on the front, and every baseline point that is both cheaper
    and more accurate than the best BGN point within a factor ``similar`` of its cost."""
    front = pareto_front(points, cost)
    bgn = [p for p in points if p["model"] == "bgn" and math.isfinite(p["rollout_error"])]
    lines = [f"BGN on the front: {'yes' if any(p['model'] == 'bgn' for p in front) else 'no'}"]
    beaten = []
    for b in points:
        if b["model"] == "bgn" or not math.isfinite(b["rollout_error"]):
            continue
        near = [p for p in bgn if b[cost] / similar <= p[cost] <= b[cost] * similar]
        if near:
            best = min(near, key=lambda p: p["rollout_error"])
            if b[cost] < best[cost] and b["rollout_error"] < best["rollout_error"]:
                beaten.append(f"{label(b)} beats {label(best)}")
    lines.append("baselines both faster and more accurate than the best BGN of similar cost "
                 f"(within {similar:g}x): " + ("; ".join(beaten) if beaten else "none"))
    return ". ".join(lines) + "."


# ----------------------------------------------------------------------------- the report
POINT_COLUMNS = ["scene", "fps", "model", "size", "minutes", "parameters", "nmse",
                 "rollout_error", "failed_share", "seconds_per_time_unit"]
COSTS = {"minutes": "training minutes", "seconds_per_time_unit": "inference s per time unit"}


def write_report(cfg: DictConfig, points: list[dict[str, Any]],
                 simulator: list[dict[str, Any]], scaling: list[dict[str, Any]],
                 wall_s: float) -> Path:
    """The plots, the tables and report.md under ``cfg.report_dir``."""
    from bgn.figures import pareto, save
    from bgn.provenance import machine

    out = Path(cfg.report_dir)
    out.mkdir(parents=True, exist_ok=True)
    sc = cfg.preset.simulator
    where = (f"{machine(torch=torch.__version__)}; {torch.get_num_threads()} torch threads; "
             f"rollout times: medians of {cfg.preset.eval.timing_repeats} after a warm-up; "
             f"the exact simulator's: of {sc.repeats} (one run above {sc.repeat_below} "
             "particles)")
    lines = [f"# Pareto study: preset `{cfg.preset.name}`", "",
             f"Machine: {where}. Study wall time {wall_s / 60:.1f} min (training, evaluation "
             "and timing of what was not on disk yet).", "",
             "Error: mean position error per particle after one simulated time unit (fps "
             "steps), mean over all the test rollouts (a failed one at 10 scene scales). "
             "Costs: training wall time of the checkpoint, and the wall time of rolling one "
             "scene out for one time unit.", "",
             "- [every point](points.md) ([csv](points.csv))",
             "- [the exact simulator](simulator.md) ([csv](simulator.csv))"]
    write_table(out, "points", POINT_COLUMNS, points, "Every checkpoint")
    write_table(out, "simulator", ["scene", "fps", "N", "seconds_per_time_unit"], simulator,
                "The exact simulator", "Its error is zero.")
    if scaling:
        lines.append("- [collisions at larger N](scaling.md) ([csv](scaling.csv))")
        lines += ["", "#" + scaling_text(out, scaling, cfg)]
    for scene in dict.fromkeys(p["scene"] for p in points):
        pts = [p for p in points if p["scene"] == scene]
        sim = {r["fps"]: r["seconds_per_time_unit"] for r in simulator if r["scene"] == scene}
        fronts = {cost: pareto_front(pts, cost) for cost in COSTS}
        save(pareto(pts, fronts, COSTS, label, sim, f"{scene}: {where}"),
             out / f"pareto_{scene}.png")
        lines += ["", f"## {scene}", "", f"![{scene}](pareto_{scene}.png)", ""]
        for cost, name in COSTS.items():
            table = write_table(out, f"front_{scene}_{cost}", POINT_COLUMNS, fronts[cost])
            lines += [f"Front against {name}: {goal_check(pts, cost)}", "", table]
        times = ", ".join(f"fps {fmt(f)}: {fmt(s)} s" for f, s in sim.items())
        lines += [f"Exact simulator, per simulated time unit: {times}."]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def scaling_text(out: Path, rows: list[dict[str, Any]], cfg: DictConfig) -> str:
    """The collisions-at-larger-N table and at which N a learned rollout gets cheaper."""
    table = write_table(out, "scaling", ["N", "box", "model", "seconds_per_time_unit",
                                         "rollout_error"], rows,
                        f"Collisions at larger N (fps {fmt(cfg.preset.simulator.collisions_fps)})",
                        "Constant density (the box grows with sqrt N); every learned model "
                        "rolled out of the same true window as the exact simulator, error "
                        "after one time unit against it; the last-velocity extrapolation "
                        "(no learning, no collision) gives the errors their scale.")
    verdicts = []
    for model in dict.fromkeys(r["model"] for r in rows
                               if r["model"] not in ("exact simulator", REFERENCE)):
        cheaper = [r for r in rows if r["model"] == model and r["seconds_per_time_unit"]
                   < next(e["seconds_per_time_unit"] for e in rows
                          if e["N"] == r["N"] and e["model"] == "exact simulator")]
        verdicts.append(f"{model}: cheaper than the exact simulator from N = {cheaper[0]['N']} "
                        f"(error {fmt(cheaper[0]['rollout_error'])})" if cheaper else
                        f"{model}: not cheaper at any measured N")
    return table + "\n" + "; ".join(verdicts) + ".\n"


# ----------------------------------------------------------------------------- command
def run(cfg: DictConfig) -> Path:
    """Train what is missing, evaluate every checkpoint, time the simulator, report."""
    torch.set_num_threads(int(cfg.preset.threads))
    start = time.perf_counter()
    cells = plan_cells(cfg)
    for i, cell in enumerate(cells, 1):
        print(f"[{i}/{len(cells)}] {cell.name}", flush=True)
        train_cell(cell, cfg)
    points = [p for cell in cells for p in evaluate_cell(cell, cfg)]
    sc = cfg.preset.simulator
    simulator = []
    for cell in cells:
        if SCHEDULE in cell.groups and cell.model == cfg.preset.models[0]:
            test = test_split(Path(cfg.cells_dir) / cell.name, cfg.paths.data_dir)
            simulator.append({"scene": cell.scene, "fps": cell.fps,
                              "N": test.meta.n_particles,
                              "seconds_per_time_unit": simulator_seconds(test, cell.fps,
                                                                         sc.repeats)})
    scaling = []
    at_scale = [c for c in cells if SCHEDULE in c.groups and c.scene == "collisions"
                and c.fps == float(sc.collisions_fps)]
    for n in sc.collisions_n if at_scale else []:
        scaling += scaled_collisions(at_scale, cfg, int(n))
    report = write_report(cfg, points, simulator, scaling, time.perf_counter() - start)
    print(f"report: {report} ({time.perf_counter() - start:.0f} s)")
    return report
