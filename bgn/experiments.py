"""The study: ``python -m bgn.experiments preset=quick`` (presets: tiny | quick | standard |
full | reproduce; the Pareto study's pareto_tiny | pareto_quick | pareto_full run through
``bgn.pareto``).

Trains every cell of a preset (scene x fps x model, BGN ablations, sample efficiency; each
per seed of the preset's ``seeds``) by composing the real ``train`` config and calling
``bgn.train.train`` (``workers=<n>``: n cells at once, each in its own process), evaluates each
cell's best checkpoint on the test split (``bgn.evaluate``), and writes the report
(``bgn.report``: Table 1, rollouts, inverse, types, ablations, sample efficiency, report.md,
provenance.json; several seeds: mean and spread per row) under ``report_dir``, and with
``results_md=<file>`` the preset's generated block of that file.
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
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from bgn.checkpoints import read_record, write_atomic
from bgn.report import write_report
from bgn.validate import cli

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


# ----------------------------------------------------------------------------- cells
@dataclass(frozen=True)
class Cell:
    """One training run of the study."""

    scene: str
    fps: float
    model: str
    ablation: str = "full"
    train_sims: int | None = None          # sample-efficiency cells only
    groups: tuple[str, ...] = field(default=("main",), compare=False)
    tag: str = ""                          # names the ``extra`` overrides (bgn.pareto's sizes)
    extra: tuple[str, ...] = ()            # train overrides of this cell alone, applied last
    seed: int = 0                          # the training seed (train override seed=<s>)
    seeded: bool = False                   # one of several seeds: the name ends in _s<seed>

    @property
    def name(self) -> str:
        fps = f"{self.fps:g}".replace(".", "p")
        sims = f"_sims{self.train_sims}" if self.train_sims is not None else ""
        tag = f"_{self.tag}" if self.tag else ""
        seed = f"_s{self.seed}" if self.seeded else ""
        return f"{self.scene}_fps{fps}_{self.model}_{self.ablation}{sims}{tag}{seed}"


def preset_seeds(preset: DictConfig) -> list[int]:
    """The preset's training seeds (``seeds``, default [0]), each once."""
    from bgn.validate import ConfigError

    seeds = [int(s) for s in (preset.get("seeds") or [0])]
    if len(set(seeds)) != len(seeds):
        raise ConfigError("preset.seeds", seeds, "each seed once")
    return seeds


def plan_cells(preset: DictConfig) -> list[Cell]:
    """Every cell of a preset, each once (an ablation=full cell is the main grid's BGN cell),
    per seed of ``preset.seeds`` (the first seed's cells first: an interrupted study has whole
    tables of the first seeds)."""
    cells: dict[str, Cell] = {}

    def add(cell: Cell, group: str) -> None:
        old = cells.get(cell.name)
        groups = (old.groups if old else ()) + (group,)
        cells[cell.name] = replace(cell, groups=tuple(dict.fromkeys(groups)))

    for scene in preset.scenes:
        for fps in preset.fps:
            for model in preset.models:
                add(Cell(scene, float(fps), model), "main")
    ab = preset.get("ablations") or {}
    for scene in ab.get("scenes", []) or []:
        for ablation in ["full", *ab.get("variants", [])]:
            add(Cell(scene, float(ab.fps), "bgn", ablation), "ablation")
    se = preset.get("sample_efficiency") or {}
    for scene in se.get("scenes", []) or []:
        for model in se.get("models", preset.models):
            for n in se.train_sims:
                add(Cell(scene, float(se.fps), model, "full", int(n)), "sample_efficiency")
    seeds = preset_seeds(preset)
    return [replace(c, seed=s, seeded=len(seeds) > 1) for s in seeds for c in cells.values()]


def cell_overrides(cell: Cell, cfg: DictConfig) -> list[str]:
    """The ``train`` overrides of one cell: the preset's common and per-scene ones, then the
    cell's own choices (later overrides win)."""
    preset = cfg.preset
    fps = int(cell.fps) if float(cell.fps).is_integer() else cell.fps
    out = [f"dataset={cell.scene}", f"fps={fps}", f"model={cell.model}",
           f"ablation={cell.ablation}", f"trainer.max_time={preset.max_time}",
           *preset.get("overrides", []),
           *(preset.get("model_overrides", {}) or {}).get(cell.model, []),
           *(preset.get("scene_overrides", {}) or {}).get(cell.scene, [])]
    if cell.train_sims is not None:
        se = preset.sample_efficiency
        # n_sims is per split and must hold the largest train_sims; val/test use them all
        out += [f"dataset.n_sims={max(int(n) for n in se.train_sims)}",
                f"++dataset.train_sims={cell.train_sims}", *se.get("overrides", [])]
    if cell.seeded or cell.seed != 0:  # seed 0 is train.yaml's: one-seed cells as before
        out.append(f"seed={cell.seed}")
    out += [*cell.extra,
            f"paths.data_dir={cfg.data_dir}",
            f"paths.output_dir={Path(cfg.cells_dir) / cell.name}"]
    return out


def compose_train(overrides: list[str]) -> DictConfig:
    """Compose ``conf/train.yaml`` with overrides, inside or outside a Hydra app."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from bgn.config import register_configs

    register_configs()  # the model schemas the model yamls build on
    if GlobalHydra.instance().is_initialized():
        return compose(config_name="train", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def train_cell(cell: Cell, cfg: DictConfig) -> tuple[dict[str, Any], bool]:
    """Train a cell unless its metrics.json exists; returns (the metrics record, trained?)."""
    from bgn.train import train

    run_dir = Path(cfg.cells_dir) / cell.name
    metrics_path = run_dir / "metrics.json"
    record = read_record(metrics_path)  # None: missing, or damaged (named in a warning)
    if record is not None:
        return record, False
    overrides = cell_overrides(cell, cfg)
    train_cfg = compose_train(overrides)
    last = run_dir / "checkpoints" / "last.ckpt"
    if last.exists():  # an interrupted cell continues from its last checkpoint
        train_cfg.ckpt_path = str(last)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(run_dir / "cell.json", json.dumps(
        {**asdict(cell), "name": cell.name, "overrides": overrides}, indent=2))
    write_atomic(run_dir / "train_config.yaml", OmegaConf.to_yaml(train_cfg, resolve=False))
    train(train_cfg)
    return json.loads(metrics_path.read_text()), True


def best_checkpoint(run_dir: Path) -> Path:
    """best.ckpt (or the newest best-vN.ckpt after a resume), else last.ckpt."""
    ckpts = run_dir / "checkpoints"
    best = sorted(ckpts.glob("best*.ckpt"), key=lambda p: p.stat().st_mtime)
    if best:
        return best[-1]
    if (ckpts / "last.ckpt").exists():
        return ckpts / "last.ckpt"
    raise FileNotFoundError(f"no checkpoint in {ckpts}")


def cell_datamodule(run_dir: Path, data_dir: str) -> Any:
    """The set-up datamodule of a trained cell's dataset (its ``train_config.yaml``)."""
    from bgn.data.datamodule import ParticleDataModule

    train_cfg = OmegaConf.load(run_dir / "train_config.yaml")
    datamodule = ParticleDataModule(train_cfg.dataset, train_cfg.fps, data_dir,
                                    show_progress=False)
    datamodule.setup()
    return datamodule


def cached_eval(cell: Cell, cfg: DictConfig) -> dict[str, Any] | None:
    """A cell's eval.json when it is newer than its best checkpoint, whole, of the current
    metrics and with its figure on disk; else None (``evaluate_cell`` evaluates it)."""
    run_dir = Path(cfg.cells_dir) / cell.name
    try:
        ckpt = best_checkpoint(run_dir)
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
    """Test-split metrics of a cell's best checkpoint (cached in eval.json), and its KDE
    figure under the report's figures/ when the model has an inverse head."""
    from bgn.evaluate import evaluate_split, load_model, mass_figure

    run_dir = Path(cfg.cells_dir) / cell.name
    ckpt = best_checkpoint(run_dir)
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
    # the report labels each row by what the model is given and has written in (bgn.report)
    result = {"checkpoint": str(ckpt), "metrics": metrics, "figure": None,
              "model": module.model.describe()}
    if arrays:
        result["figure"] = str(mass_figure(arrays, figure))
    write_atomic(eval_path, json.dumps(result, indent=2, sort_keys=True))
    return result


# ----------------------------------------------------------------------------- workers
_ARGV: list[str] = []  # the command line as typed (set under ``__main__``), for provenance
_WORKER = ("import sys; from bgn.experiments import worker_main; "
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
    from bgn.train import data_module

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
    from bgn.evaluate import git_commit

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
    if failed:
        raise CellsFailed(report, failed)
    return report


def is_pareto(cfg: DictConfig) -> bool:
    """A Pareto-study preset (``conf/preset/pareto_*.yaml``: checkpoints on a time schedule)
    is run by ``bgn.pareto``."""
    return "schedule_s" in cfg.preset


def validate_cells(cfg: DictConfig) -> None:
    """The train config of every cell, checked before the first cell trains
    (``bgn.validate.validate_train``): a bad preset fails at once, naming the cell."""
    from bgn.pareto import plan_cells as pareto_cells
    from bgn.validate import ConfigError, validate_train

    for cell in pareto_cells(cfg) if is_pareto(cfg) else plan_cells(cfg.preset):
        try:
            validate_train(compose_train(cell_overrides(cell, cfg)))
        except ConfigError as err:
            raise ConfigError(err.key, message=f"cell {cell.name}: {err}") from err


@cli("experiments", validate_cells)  # Hydra app; bad input: one line, exit 2
def main(cfg: DictConfig) -> None:
    """``python -m bgn.experiments preset=...``: see the module docstring."""
    if is_pareto(cfg):
        from bgn import pareto

        pareto.run(cfg)
        return
    try:
        run(cfg)
    except CellsFailed as err:  # the report of the others is written; the command fails
        raise SystemExit(f"bgn.experiments: {err}") from None


if __name__ == "__main__":
    _ARGV[:] = sys.argv
    main()
