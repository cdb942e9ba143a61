"""The grid study (run by ``python -m bgn.experiments preset=first_look``:
``bgn.studies.dispatch``; presets tiny | first_look | standard | full | reproduce).

Trains every cell of a preset (scene x fps x model, BGN ablations, sample efficiency; each per
seed of the preset's ``seeds``: ``bgn.studies.cells``; ``workers=<n>``: n cells at once, each
in its own process), evaluates each cell's best checkpoint on the test split
(``bgn.eval.evaluate``), and writes the report (``bgn.studies.report``: Table 1, rollouts,
inverse, types, ablations, sample efficiency, report.md, provenance.json; several seeds: mean
and spread per row) under ``report_dir``, and with ``results_md=<file>`` the preset's generated
block of that file. A preset with ``stability`` or ``pareto`` then writes those tables from the
same cells (``bgn.studies.headline``: ``report_dir``/stability, /pareto; their own blocks).
Resumable: a cell whose ``metrics.json`` exists is not retrained (an interrupted cell
continues from its ``last.ckpt``), a cell whose ``eval.json`` is newer than its checkpoint is not
re-evaluated; the report is always rewritten from what is on disk. Those files are written
atomically (a temporary file, then a rename); a damaged one (an older bgn killed while writing
it, a hand edit) is named in a warning and its cell trained or evaluated again.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from bgn.studies.cells import (
    CONF_DIR,
    Cell,
    cell_datamodule,
    cell_overrides,
    compose_train,
    plan_cells,
    preset_seeds,
    train_cell,
)
from bgn.studies.headline import run_stages
from bgn.studies.report import write_report
from bgn.train.checkpoints import chosen_checkpoint, read_record, write_atomic


def cached_eval(cell: Cell, cfg: DictConfig) -> dict[str, Any] | None:
    """A cell's eval.json when it is newer than its best checkpoint, whole, of the current
    metrics and with its figure on disk; else None (``evaluate_cell`` evaluates it)."""
    run_dir = Path(cfg.cells_dir) / cell.name
    try:
        ckpt = chosen_checkpoint(run_dir)
    except FileNotFoundError:
        return None
    eval_path = run_dir / "eval.json"
    figure = Path(cfg.report_dir) / "figures" / f"mass_{cell.name}.png"
    if eval_path.exists() and eval_path.stat().st_mtime >= ckpt.stat().st_mtime:
        result = read_record(eval_path)  # None when damaged (named in a warning): redone
        if result is not None and (not result.get("figure") or figure.exists()) \
                and "rollout/rollout_cap" in result.get("metrics", {}):  # else: older metrics
            return result
    return None


def evaluate_cell(cell: Cell, cfg: DictConfig) -> dict[str, Any]:
    """Test-split metrics of a cell's chosen checkpoint (``chosen_checkpoint``; cached in
    eval.json), and its KDE figure under the report's figures/ when the model has an inverse
    head."""
    from bgn.eval.evaluate import evaluate_split, mass_figure
    from bgn.train.module import load_model

    run_dir = Path(cfg.cells_dir) / cell.name
    ckpt = chosen_checkpoint(run_dir)  # the formula where model.law=auto chose it
    eval_path = run_dir / "eval.json"
    figure = Path(cfg.report_dir) / "figures" / f"mass_{cell.name}.png"
    result = cached_eval(cell, cfg)
    if result is not None:
        if "model" not in result:  # an older record: what the model is, from its checkpoint
            result["model"] = load_model(ckpt).model.describe()
            write_atomic(eval_path, json.dumps(result, indent=2, sort_keys=True))
        return result
    datamodule = cell_datamodule(run_dir, cfg.data_dir)
    e = cfg.preset.eval
    module, test = load_model(ckpt), datamodule.datasets["test"]
    metrics, arrays = evaluate_split(  # the code of python -m bgn.evaluate
        module, test, datamodule.datasets["val"], max_frames=e.max_frames,
        mass_frames=e.mass_frames, mass_samples=e.mass_samples, batch_size=e.batch_size,
        rollout_steps=e.rollout_steps, rollout_starts=e.rollout_starts,
        rollout_sims=e.rollout_sims)
    # the report labels each row by what the model is given and has written in (bgn.studies.report)
    result = {"checkpoint": str(ckpt), "metrics": metrics, "figure": None,
              "model": module.model.describe()}
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


def set_threads(threads: int | None) -> None:
    """torch's intra-op threads of this process (None: torch's default)."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))


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
    from bgn.train.run import data_module

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
        done = (Path(cfg.cells_dir) / cell.name / "metrics.json").exists()
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
    from bgn.eval.evaluate import git_commit

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
                     failed: list[str], code: dict[str, Any]) -> dict[str, Any]:
    """What regenerates the report: the command, the preset and a hash of its composed
    config, the code's commit (and whether the tree had changes: ``code_state``), the
    machine, threads, workers, seeds and wall time."""
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
            "cpu_count": os.cpu_count(), "torch": torch.__version__, "device": device,
            "workers": workers, "threads_per_worker": threads or torch.get_num_threads(),
            "seeds": preset_seeds(cfg.preset), "wall_time_s": round(wall_s, 1),
            "failed_cells": failed, "preset_config": preset}


# ----------------------------------------------------------------------------- command
def run(cfg: DictConfig) -> Path:
    """Train (what is missing), evaluate and report every cell of ``cfg.preset``: ``workers``
    cells at a time, each with ``threads_per_worker`` torch threads. A failed cell is named
    and left out of the report; then ``CellsFailed`` is raised after the report is written."""
    import traceback

    cells = plan_cells(cfg.preset)
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
                                  code)
    report = write_report(cfg.report_dir, cfg.preset.name, cfg.cells_dir, cells, results,
                          provenance, cfg.get("results_md"))
    print(f"report: {report} ({time.perf_counter() - start:.0f} s)")
    # the stability and Pareto tables from the same cells (preset.stability / .pareto)
    failed += run_stages(cfg, cells, results, provenance, workers, threads)
    if cfg.preset.get("stability") is not None or cfg.preset.get("pareto") is not None:
        print(f"total wall time {time.perf_counter() - start:.0f} s")
    if failed:
        raise CellsFailed(report, failed)
    return report
