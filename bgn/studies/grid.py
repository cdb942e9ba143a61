"""The grid study (run by ``python -m bgn.experiments preset=first_look``:
``bgn.studies.dispatch``; presets tiny | first_look | standard | full | reproduce | recheck).

Trains every cell of a preset (scene x fps x model (x ``variants``: named sets of train
overrides), BGN ablations, sample efficiency; each per seed of the preset's ``seeds``:
``bgn.studies.cells``; ``workers=<n>``: n cells at once, each in its own process), evaluates
each cell's best checkpoint on the split ``eval.split`` names (test by default; val to re-check
a default, the mass flow then recalibrated on train: ``bgn.eval.evaluate``), and writes the
report (``bgn.studies.report``: Table 1, rollouts,
inverse, types, ablations, sample efficiency, report.md, provenance.json; several seeds: mean
and spread per row) under ``report_dir``, and with ``results_md=<file>`` the preset's generated
block of that file. A preset with ``stability`` or ``pareto`` then writes those tables from the
same cells (``bgn.studies.headline``: ``report_dir``/stability, /pareto; their own blocks).
Resumable: a cell whose ``metrics.json`` exists is not retrained (an interrupted cell
continues from its ``last.ckpt``, and so does one the wall-clock cap cut, ``budget.cut_by``,
toward its step budget: ``bgn.studies.cells.train_cell``), a cell whose ``eval.json`` is newer
than its checkpoint is not re-evaluated; the report is always rewritten from what is on disk
and names every cell the cap cut. Those files are written
atomically (a temporary file, then a rename); a damaged one (an older bgn killed while writing
it, a hand edit) is named in a warning and its cell trained or evaluated again.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from bgn.coerce import ConfigError
from bgn.provenance import git_commit, library_versions, processor
from bgn.studies.cells import (
    CONF_DIR,
    Cell,
    cell_datamodule,
    cell_overrides,
    compose_train,
    cut_by_cap,
    plan_cells,
    preset_seeds,
    set_threads,
    train_cell,
    unnamed_budgets,
)
from bgn.studies.headline import STAGES, run_stages
from bgn.studies.report import CALIBRATION_SPLIT, cut_cells, write_report
from bgn.training.checkpoints import chosen_checkpoint, read_record, write_atomic


def eval_split(preset: DictConfig) -> str:
    """The split a grid preset scores (``eval.split``; test where the key is absent)."""
    return str((preset.get("eval") or {}).get("split", "test"))


def validate_grid(preset: DictConfig) -> None:
    """The grid's own keys ``eval.split`` and ``variants``, checked before any cell trains
    (``bgn.studies.dispatch.validate_cells``): a bad value is one ``ConfigError`` naming it."""
    split = eval_split(preset)
    if split not in CALIBRATION_SPLIT:
        raise ConfigError("preset.eval.split", split,
                          f"choose one of {list(CALIBRATION_SPLIT)} (the split every table "
                          "scores; val to re-check a default)")
    stages = [k for k in STAGES if preset.get(k) is not None]
    if split != "test" and stages:
        raise ConfigError("preset.eval.split", split, (
            f"the {' and '.join(stages)} stage(s) write headline test tables; set "
            + " and ".join(f"preset.{k}=null" for k in stages) + " for a validation study"))
    variants = preset.get("variants")
    if variants is None:
        return
    if not isinstance(variants, DictConfig) or not variants:
        raise ConfigError("preset.variants", variants, "must be a mapping of a variant's "
                          "name to its list of train overrides (or null)")
    for name, overrides in variants.items():
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", str(name)):
            raise ConfigError(f"preset.variants.{name}", name, "a variant's name becomes "
                              "part of its cells' names: letters, digits, _ . -")
        if overrides is not None and (not isinstance(overrides, ListConfig) or not all(
                isinstance(o, str) for o in overrides)):
            raise ConfigError(f"preset.variants.{name}", overrides,
                              "must be a list of train overrides (key=value strings)")
    if stages:
        raise ConfigError("preset.variants", list(variants), (
            f"the {' and '.join(stages)} stage(s) read one cell per scene, model and seed; "
            "set " + " and ".join(f"preset.{k}=null" for k in stages) + " with variants"))


def check_variant_cells(cfg: DictConfig) -> None:
    """A variant's cells already under ``cells_dir`` were trained with its overrides: a
    trained cell is not retrained (resumable), so a variant renamed to other overrides would
    otherwise report the old cells under the new overrides. Refused before any cell trains."""
    for cell in plan_cells(cfg.preset):
        record = Path(cfg.cells_dir) / cell.name / "cell.json"
        if not cell.tag or not record.exists():
            continue
        trained = tuple((read_record(record) or {}).get("extra") or ())
        if trained != cell.extra:
            raise ConfigError(f"preset.variants.{cell.tag}", list(cell.extra), (
                f"cell {cell.name} under {cfg.cells_dir} was trained with "
                f"{list(trained) or 'no overrides'}: give this variant another name, or "
                "use another cells_dir"))


def eval_files(cell: Cell, cfg: DictConfig) -> tuple[Path, Path]:
    """A cell's evaluation record and mass figure for the preset's split: eval.json and
    figures/mass_<cell>.png for test, eval_<split>.json and mass_<cell>_<split>.png
    otherwise (a re-check on validation keeps the test evaluation, and reads as another)."""
    split = eval_split(cfg.preset)
    suffix = "" if split == "test" else f"_{split}"
    return (Path(cfg.cells_dir) / cell.name / f"eval{suffix}.json",
            Path(cfg.report_dir) / "figures" / f"mass_{cell.name}{suffix}.png")


def cached_eval(cell: Cell, cfg: DictConfig) -> dict[str, Any] | None:
    """A cell's evaluation record of the preset's split (``eval_files``) when it is newer
    than its best checkpoint, whole, of the current metrics and split and with its figure on
    disk; else None (``evaluate_cell`` evaluates it)."""
    run_dir = Path(cfg.cells_dir) / cell.name
    try:
        ckpt = chosen_checkpoint(run_dir)
    except FileNotFoundError:
        return None
    eval_path, figure = eval_files(cell, cfg)
    if eval_path.exists() and eval_path.stat().st_mtime >= ckpt.stat().st_mtime:
        result = read_record(eval_path)  # None when damaged (named in a warning): redone
        if result is not None and (not result.get("figure") or figure.exists()) \
                and result.get("split", "test") == eval_split(cfg.preset) \
                and "rollout/rollout_cap" in result.get("metrics", {}):  # else: older metrics
            return result
    return None


def trained_steps(run_dir: Path) -> int | None:
    """The optimiser steps a cell trained, so the report shows each cell's budget: its
    training record's (``metrics.json``, ``budget.steps``: the trainer's count at the end),
    else its last checkpoint's (the best one where there is no last; None where neither
    records it). The record first: a run that reaches its step budget inside an epoch ends
    after its last checkpoint was written (at the end of the epoch before)."""
    from bgn.training.checkpoints import read, read_record

    steps = ((read_record(run_dir / "metrics.json") or {}).get("budget") or {}).get("steps")
    if isinstance(steps, int):
        return steps
    for name in ("last.ckpt", "best.ckpt"):
        path = run_dir / "checkpoints" / name
        if path.is_file():
            step = read(path).get("global_step")
            return None if step is None else int(step)
    return None


def evaluate_cell(cell: Cell, cfg: DictConfig) -> dict[str, Any]:
    """Metrics of a cell's chosen checkpoint (``chosen_checkpoint``) on the preset's split
    (``eval.split``: test, or val with the mass flow recalibrated on train, as
    ``python -m bgn.evaluate <run> split=val calibration_split=train``; cached in
    ``eval_files``), and its KDE figure under the report's figures/ when the model has an
    inverse head."""
    from bgn.eval.evaluate import evaluate_split, mass_figure
    from bgn.training.module import load_model

    run_dir = Path(cfg.cells_dir) / cell.name
    ckpt = chosen_checkpoint(run_dir)  # the formula where model.law=auto chose it
    eval_path, figure = eval_files(cell, cfg)
    split = eval_split(cfg.preset)
    calibration = CALIBRATION_SPLIT[split]  # never the scored split
    result = cached_eval(cell, cfg)
    if result is not None:
        # an older record: what the model is (trained with, given), from its checkpoint
        if "supervision" not in (result.get("model") or {}) or "train_steps" not in result:
            result["model"] = load_model(ckpt).model.describe()
            result["train_steps"] = trained_steps(run_dir)
            write_atomic(eval_path, json.dumps(result, indent=2, sort_keys=True))
        return result
    datamodule = cell_datamodule(run_dir, cfg.paths.data_dir)
    e = cfg.preset.eval
    module, scored = load_model(ckpt), datamodule.datasets[split]
    metrics, arrays = evaluate_split(  # the code of python -m bgn.evaluate
        module, scored, datamodule.datasets[calibration], max_frames=e.max_frames,
        mass_frames=e.mass_frames, mass_samples=e.mass_samples, batch_size=e.batch_size,
        rollout_steps=e.rollout_steps, rollout_starts=e.rollout_starts,
        rollout_sims=e.rollout_sims)
    # the report labels each row by what the model is given and has written in (bgn.studies.report)
    result = {"checkpoint": str(ckpt), "metrics": metrics, "figure": None,
              "model": module.model.describe(), "train_steps": trained_steps(run_dir),
              "split": split,
              "calibration_split": calibration}
    if arrays:
        result["figure"] = str(mass_figure(arrays, figure))
    write_atomic(eval_path, json.dumps(result, indent=2, sort_keys=True))
    return result


# ----------------------------------------------------------------------------- workers
_ARGV: list[str] = []  # the command line as typed (set under ``__main__``), for provenance
_WORKER = ("import sys; from bgn.studies.grid import worker_main; "
           "sys.exit(worker_main(sys.argv[1]))")


class CellsFailed(RuntimeError):
    """Some cells failed (named); the others were trained, evaluated and reported."""

    def __init__(self, report: Path, failed: list[str]) -> None:
        self.report, self.failed = report, failed
        super().__init__(f"{len(failed)} cell(s) failed: {', '.join(failed)} (their "
                         f"worker.log or the output above says why); report of the others: "
                         f"{report}")


def cell_from_record(record: dict[str, Any]) -> Cell:
    """A Cell from ``asdict(cell)`` (its JSON form: tuples as lists)."""
    return Cell(**{**record, "groups": tuple(record["groups"]),
                   "extra": tuple(record["extra"])})


def worker_main(job_path: str) -> int:
    """One cell in its own process (``run`` with workers > 1): trained unless its
    metrics.json exists, then evaluated (eval.json, cached); an error exits non-zero with its
    traceback in the cell's worker.log."""
    job = json.loads(Path(job_path).read_text())
    set_threads(job.get("threads"))
    cfg, cell = OmegaConf.create(job["cfg"]), cell_from_record(job["cell"])
    train_cell(cell, cfg)
    evaluate_cell(cell, cfg)
    return 0


def cell_process(cell: Cell, cfg: DictConfig, threads: int | None) -> tuple[bool, Path]:
    """Train and evaluate a cell in a fresh Python process (``worker_main``) with ``threads``
    torch threads (OMP_NUM_THREADS too, so the OpenMP pool is that size from the start);
    returns (succeeded, its log)."""
    run_dir = Path(cfg.cells_dir) / cell.name
    run_dir.mkdir(parents=True, exist_ok=True)
    job = run_dir / "job.json"
    write_atomic(job, json.dumps({"cell": asdict(cell), "threads": threads,
                                  "cfg": OmegaConf.to_container(cfg, resolve=True)}, indent=2))
    env = dict(os.environ)
    if threads:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    log = run_dir / "worker.log"
    with open(log, "a") as fh:
        code = subprocess.run([sys.executable, "-c", _WORKER, str(job)], stdout=fh,
                              stderr=subprocess.STDOUT, env=env).returncode
    return code == 0, log


def prepare_datasets(cells: list[Cell], cfg: DictConfig) -> None:
    """Generate every dataset the cells read, once each, before parallel cells start (each
    with every core; the cells would otherwise wait on one another's file locks)."""
    from bgn.training.run import data_module

    seen: set[Path] = set()
    for cell in cells:
        datamodule = data_module(compose_train(cell_overrides(cell, cfg)))
        path = datamodule.spec.with_split("train").path(datamodule.data_dir)
        if path not in seen:
            seen.add(path)
            datamodule.prepare_data()


def train_all(cells: list[Cell], cfg: DictConfig, workers: int,
              threads: int | None) -> list[str]:
    """Train every cell (what is missing): in this process one after the other, or in
    ``workers`` parallel processes (each also evaluates its cell); returns the failed cells'
    names (the others continue)."""
    import threading
    import traceback

    failed: list[str] = []
    lock = threading.Lock()
    if workers <= 1:
        set_threads(threads)
        for i, cell in enumerate(cells, 1):
            print(f"[{i}/{len(cells)}] {cell.name}", flush=True)
            try:
                _, trained = train_cell(cell, cfg)
            except Exception:  # named, the others go on; an interruption stops the study
                traceback.print_exc()
                print(f"  FAILED: {cell.name}", flush=True)
                failed.append(cell.name)
                continue
            print(f"  {'trained' if trained else 'already trained (metrics.json)'}", flush=True)
        return failed

    prepare_datasets(cells, cfg)

    def one(i: int, cell: Cell) -> None:
        # a record the cap cut is not done: its process continues it (train_cell)
        record = read_record(Path(cfg.cells_dir) / cell.name / "metrics.json")
        done = record is not None and not cut_by_cap(record)
        # a cell trained and evaluated before needs no process (a resumed study)
        ok, log = (True, None) if done and cached_eval(cell, cfg) is not None \
            else cell_process(cell, cfg, threads)
        state = ("already trained (metrics.json)" if done else "trained") if ok \
            else f"FAILED (log: {log})"
        with lock:
            print(f"[{i}/{len(cells)}] {cell.name}\n  {state}", flush=True)
            if not ok:
                failed.append(cell.name)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        for future in [pool.submit(one, i, c) for i, c in enumerate(cells, 1)]:
            future.result()
    return [c.name for c in cells if c.name in failed]  # in the study's order


def code_state() -> dict[str, Any]:
    """The git commit of the code and whether its tracked files had uncommitted changes
    (None: unknown), taken when the study starts (the code that trains)."""
    if os.environ.get("BGN_GIT_COMMIT"):  # a copy of the code: its git state is not known
        return {"git_commit": git_commit(), "git_dirty": None}
    try:
        status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                cwd=CONF_DIR.parent, capture_output=True, text=True,
                                timeout=10)
        dirty: bool | None = bool(status.stdout.strip()) if status.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        dirty = None
    return {"git_commit": git_commit(), "git_dirty": dirty}


def study_provenance(cfg: DictConfig, workers: int, threads: int | None, wall_s: float,
                     failed: list[str], code: dict[str, Any],
                     cut: list[str] | None = None) -> dict[str, Any]:
    """What regenerates the report: the command, the preset and a hash of its composed
    config, the code's commit (and whether the tree had changes: ``code_state``), the
    machine, threads, workers, seeds and wall time, the failed cells and those the wall-clock
    cap cut (``cut``: ``bgn.studies.report.cut_cells``)."""
    import hashlib
    import platform

    import torch

    if _ARGV:
        command = " ".join(["python -m bgn.experiments", *map(shlex.quote, _ARGV[1:])])
    else:  # run() called from Python: the command that composes the same preset
        command = f"python -m bgn.experiments preset={cfg.preset.name}"
    preset = OmegaConf.to_container(cfg.preset, resolve=True)
    device = (f"cuda ({torch.cuda.get_device_name(0)})" if torch.cuda.is_available()
              else "cpu")
    return {"command": command, "preset": str(cfg.preset.name),
            "config_hash": hashlib.sha256(json.dumps(preset, sort_keys=True).encode())
            .hexdigest()[:12],
            **code,
            "machine": f"{platform.platform()}, {platform.processor() or platform.machine()}",
            "processor": processor(), "cpu_count": os.cpu_count(),
            "torch": torch.__version__, "libraries": library_versions(), "device": device,
            "workers": workers, "threads_per_worker": threads or torch.get_num_threads(),
            "seeds": preset_seeds(cfg.preset), "eval_split": eval_split(cfg.preset),
            "calibration_split": CALIBRATION_SPLIT[eval_split(cfg.preset)],
            "wall_time_s": round(wall_s, 1),
            "failed_cells": failed, "cut_cells": cut or [], "preset_config": preset}


# ----------------------------------------------------------------------------- command
def run(cfg: DictConfig) -> Path:
    """Train (what is missing), evaluate and report every cell of ``cfg.preset``: ``workers``
    cells at a time, each with ``threads_per_worker`` torch threads. A failed cell is named
    and left out of the report; then ``CellsFailed`` is raised after the report is written."""
    import traceback

    cells = plan_cells(cfg.preset)
    unnamed = unnamed_budgets(cfg.preset)
    if unnamed:  # recorded too in each cell's cell.json (its ++trainer.max_steps)
        print("preset.max_steps does not name these cells' step budgets; they train their "
              f"scene's default: {'; '.join(unnamed)}", flush=True)
    start, code = time.perf_counter(), code_state()
    workers = max(1, int(cfg.get("workers") or 1))
    threads = cfg.get("threads_per_worker")
    threads = int(threads) if threads else (1 if workers > 1 else None)
    failed = train_all(cells, cfg, workers, threads)
    results: dict[str, dict[str, Any]] = {}
    for cell in cells:
        if cell.name in failed:
            continue
        try:  # cached in eval.json where a worker evaluated the cell
            record = read_record(Path(cfg.cells_dir) / cell.name / "metrics.json")
            if record is None:
                raise FileNotFoundError(f"{cell.name}: no readable metrics.json")
            results[cell.name] = {"train": record, "eval": evaluate_cell(cell, cfg)}
        except Exception:
            traceback.print_exc()
            print(f"  FAILED (evaluation): {cell.name}", flush=True)
            failed.append(cell.name)
    provenance = study_provenance(cfg, workers, threads, time.perf_counter() - start, failed,
                                  code, cut_cells(cells, results))
    report = write_report(cfg.report_dir, cfg.preset.name, cfg.cells_dir, cells, results,
                          provenance, cfg.get("results_md"), split=eval_split(cfg.preset))
    print(f"report: {report} ({time.perf_counter() - start:.0f} s)")
    # the stability and Pareto tables from the same cells (preset.stability / .pareto)
    failed += run_stages(cfg, cells, results, provenance, workers, threads)
    if any(cfg.preset.get(k) is not None for k in STAGES):
        print(f"total wall time {time.perf_counter() - start:.0f} s")
    if failed:
        raise CellsFailed(report, failed)
    return report
