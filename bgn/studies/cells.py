"""The cells of a study: one training run each, planned from a preset (per seed of its
``seeds``), trained through the real ``train`` config (``bgn.training.run.train``) and read back.
Shared by the grid study (``bgn.studies.grid``) and the Pareto study (``bgn.studies.pareto``),
which plan their cells differently (``plan_cells`` here is the grid's) and train and read them
alike.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from bgn.coerce import ConfigError
from bgn.training.checkpoints import read_record, write_atomic

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


@dataclass(frozen=True)
class Cell:
    """One training run of the study."""

    scene: str
    fps: float
    model: str
    ablation: str = "full"
    train_sims: int | None = None          # sample-efficiency cells only
    groups: tuple[str, ...] = field(default=("main",), compare=False)
    tag: str = ""                          # names the ``extra`` overrides (Pareto sizes,
                                           # the grid's ``variants``)
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
    seeds = [int(s) for s in (preset.get("seeds") or [0])]
    if len(set(seeds)) != len(seeds):
        raise ConfigError("preset.seeds", seeds, "each seed once")
    return seeds


def preset_variants(preset: DictConfig) -> list[tuple[str, tuple[str, ...]]]:
    """The main grid's variants (``preset.variants``: a name -> the train overrides it adds
    to each main cell, after the preset's own; the same scene and model with overrides A
    against B), as (``Cell.tag``, ``Cell.extra``); one unnamed variant without the key."""
    variants = preset.get("variants") or {}
    return [(str(name), tuple(str(o) for o in (overrides or [])))
            for name, overrides in variants.items()] or [("", ())]


def plan_cells(preset: DictConfig) -> list[Cell]:
    """Every cell of a preset, each once (an ablation=full cell is the main grid's BGN cell),
    the main grid's once per variant (``preset_variants``), per seed of ``preset.seeds`` (the
    first seed's cells first: an interrupted study has whole tables of the first seeds)."""
    cells: dict[str, Cell] = {}

    def add(cell: Cell, group: str) -> None:
        old = cells.get(cell.name)
        groups = (old.groups if old else ()) + (group,)
        cells[cell.name] = replace(cell, groups=tuple(dict.fromkeys(groups)))

    for scene in preset.scenes:
        for fps in preset.fps:
            for model in preset.models:
                for tag, extra in preset_variants(preset):
                    add(Cell(scene, float(fps), model, tag=tag, extra=extra), "main")
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


DEFAULT_STEPS = "default"  # a preset.max_steps entry: the scene's default step budget


def default_steps(scene: str) -> int | None:
    """The scene's default step budget, ``conf/budget/<scene>.yaml`` (what ``python -m
    bgn.train dataset=<scene>`` trains); None for a scene without one."""
    path = CONF_DIR / "budget" / f"{scene}.yaml"
    return int(OmegaConf.load(path).max_steps) if path.exists() else None


STEPS_SHAPE = (f"must be a mapping scene -> model -> optimiser steps or {DEFAULT_STEPS}, "
               "e.g. preset.max_steps.spring.bgn=1500 (one budget per scene and model: "
               "their steps differ)")


def preset_steps(preset: DictConfig, scene: str, model: str) -> tuple[int, bool]:
    """(``trainer.max_steps`` of the preset's cells of ``scene`` and ``model``, whether the
    preset names it). ``preset.max_steps`` maps scene -> model -> a number of optimiser steps
    or ``default`` (the scene's default budget, ``default_steps``, kept in one place); a pair
    it leaves out also trains the scene's default, named by ``unnamed_budgets`` (a budget in
    steps repeats on any machine, where ``max_time`` trains as many as the load allows; it
    stays a cap only). A table or scene entry that is not a mapping is one ``ConfigError``
    naming it."""
    key = f"preset.max_steps.{scene}.{model}"
    table = preset.get("max_steps")
    if table is not None and not isinstance(table, (DictConfig, dict)):
        raise ConfigError("preset.max_steps", table, STEPS_SHAPE)
    row = (table or {}).get(scene)
    if row is not None and not isinstance(row, (DictConfig, dict)):
        raise ConfigError(f"preset.max_steps.{scene}", row, STEPS_SHAPE)
    steps = (row or {}).get(model)
    if steps is None or steps == DEFAULT_STEPS:
        default = default_steps(scene)
        if default is None:
            raise ConfigError(key, steps, f"{scene} has no default step budget "
                              f"(conf/budget/{scene}.yaml): give its cells a number of "
                              "optimiser steps")
        return default, steps is not None
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ConfigError(key, steps, "must be a positive whole number of optimiser steps, "
                          f"or {DEFAULT_STEPS} (the scene's, conf/budget/{scene}.yaml)")
    return steps, True


def sets_steps(override: str) -> bool:
    """Whether a train override sets (or deletes) ``trainer.max_steps``."""
    return override.lstrip("+~").split("=", 1)[0] == "trainer.max_steps"


def step_budget(cell: Cell, preset: DictConfig) -> list[str]:
    """The cell's ``trainer.max_steps`` override (``preset_steps``): every cell gets one, so
    its ``cell.json`` records the steps it was given; none where the cell's own overrides set
    it (a Pareto cell's time schedule, a variant)."""
    if any(sets_steps(o) for o in cell.extra):
        return []
    return [f"++trainer.max_steps={preset_steps(preset, cell.scene, cell.model)[0]}"]


def preset_overrides(preset: DictConfig, key: str) -> list[str]:
    """The train overrides at ``preset.<key>`` (``overrides``, ``model_overrides.<model>``,
    ...; absent or null: none). One that sets ``trainer.max_steps`` is refused: it would
    silently beat the cell's budget from ``preset.max_steps``, which cell.json, the
    report and the note of unnamed budgets all state."""
    overrides = [str(o) for o in (OmegaConf.select(preset, key, default=None) or [])]
    for override in overrides:
        if sets_steps(override):
            raise ConfigError(f"preset.{key}", override, (
                "a step budget belongs in preset.max_steps (scene -> model -> steps, e.g. "
                "preset.max_steps.spring.bgn=1500), so each cell's record and the report "
                "state the steps it was given"))
    return overrides


def unnamed_budgets(preset: DictConfig) -> list[str]:
    """The scene/model pairs of the preset's cells that ``preset.max_steps`` does not name,
    each with the scene default it trains instead (``grid.run`` prints them before training)."""
    pairs = dict.fromkeys((c.scene, c.model) for c in plan_cells(preset))
    return [f"{scene}/{model}: {preset_steps(preset, scene, model)[0]} "
            f"(conf/budget/{scene}.yaml)" for scene, model in pairs
            if not preset_steps(preset, scene, model)[1]]


def cell_overrides(cell: Cell, cfg: DictConfig) -> list[str]:
    """The ``train`` overrides of one cell: the preset's common and per-scene ones, then the
    cell's own choices (later overrides win)."""
    preset = cfg.preset
    fps = int(cell.fps) if float(cell.fps).is_integer() else cell.fps
    out = [f"dataset={cell.scene}", f"fps={fps}", f"model={cell.model}",
           f"ablation={cell.ablation}",
           # null: the default job's cap (conf/trainer/default.yaml)
           *([f"trainer.max_time={preset.max_time}"] if preset.get("max_time") else []),
           *step_budget(cell, preset),
           *preset_overrides(preset, "overrides"),
           *preset_overrides(preset, f"model_overrides.{cell.model}"),
           *preset_overrides(preset, f"scene_overrides.{cell.scene}")]
    if cell.train_sims is not None:
        se = preset.sample_efficiency
        # n_sims is per split and must hold the largest train_sims; val/test use them all
        out += [f"dataset.n_sims={max(int(n) for n in se.train_sims)}",
                f"++dataset.train_sims={cell.train_sims}",
                *preset_overrides(preset, "sample_efficiency.overrides")]
    if cell.seeded or cell.seed != 0:  # seed 0 is train.yaml's: one-seed cells as before
        out.append(f"seed={cell.seed}")
    out += [*cell.extra,
            f"paths.data_dir={cfg.paths.data_dir}",
            f"paths.output_dir={Path(cfg.cells_dir) / cell.name}"]
    return out


def compose_train(overrides: list[str]) -> DictConfig:
    """Compose ``conf/train.yaml`` with overrides, inside or outside a Hydra app."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from bgn.training.config import register_configs

    register_configs()  # the model schemas the model yamls build on
    if GlobalHydra.instance().is_initialized():
        return compose(config_name="train", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def cut_by_cap(record: dict[str, Any]) -> bool:
    """Whether the wall-clock cap (``trainer.max_time``) cut a cell's run short of its step
    budget: its metrics.json ``budget.cut_by`` (the fit, the formula stage or the test ended
    before its work). A cell without a step budget (a Pareto cell: ``max_steps=-1``, its time
    schedule is its budget) is never cut: its clock ending the run is the plan."""
    budget = record.get("budget") or {}
    return bool(budget.get("cut_by")) and budget.get("max_steps") is not None


def shortfall(record: dict[str, Any]) -> str | None:
    """How a cell's training record (metrics.json) falls short of its step budget: what the
    cap cut and the steps trained, or the steps where it stopped before its budget on its own
    (early stopping on validation, ``max_epochs``: the same on any machine); None where it
    trained its budget whole (or has none, a Pareto cell's time schedule) and nothing was
    cut."""
    budget = record.get("budget") or {}
    steps, top = budget.get("steps"), budget.get("max_steps")
    trained = f"{steps} of {top} steps" if top else f"{steps} steps"
    if cut_by_cap(record):
        return f"cut by trainer.max_time: {', '.join(budget.get('cut') or ['its run'])}; " \
            f"trained {trained}"
    if top and steps is not None and steps < top:
        return f"stopped early (early stopping or trainer.max_epochs) at {trained}"
    return None


def with_earlier_attempts(record: dict[str, Any], earlier: dict[str, Any]) -> dict[str, Any]:
    """A continued cell's metrics.json record with the attempts the cap cut before it
    (``earlier``: their last record): ``budget.attempts`` lists each one's steps, wall time and
    what was cut, and ``metrics.wall_time_s`` is every attempt's together, so the report's
    ``train s`` is the cell's whole training."""
    before = (earlier.get("budget") or {}).get("attempts") or []
    own = earlier["metrics"].get("wall_time_s", 0.0) - sum(a["wall_time_s"] for a in before)
    attempts = [*before, {"steps": earlier["budget"].get("steps"), "wall_time_s": own,
                          "cut": earlier["budget"].get("cut") or []}]
    record["budget"]["attempts"] = attempts
    record["metrics"]["wall_time_s"] += sum(a["wall_time_s"] for a in attempts)
    return record


def train_cell(cell: Cell, cfg: DictConfig) -> tuple[dict[str, Any], bool]:
    """Train a cell unless its metrics.json exists; returns (the metrics record, trained?).
    A record the wall-clock cap cut (``cut_by_cap``) is not kept: the cell continues from its
    last.ckpt toward its step budget (the fit ends at once where it had trained them, and the
    formula stage and the test run again), so a resumed study holds the cells the same
    command trains on an idle machine; the cap of this attempt is the preset's as it is now
    (raise ``preset.max_time`` where it cuts again)."""
    from bgn.laws.stage import law_stage
    from bgn.training.run import train

    run_dir = Path(cfg.cells_dir) / cell.name
    metrics_path = run_dir / "metrics.json"
    record = read_record(metrics_path)  # None: missing, or damaged (named in a warning)
    if record is not None and not cut_by_cap(record):
        return record, False
    overrides = cell_overrides(cell, cfg)
    train_cfg = compose_train(overrides)
    last = run_dir / "checkpoints" / "last.ckpt"
    if last.exists():  # an interrupted (or cut) cell continues from its last checkpoint
        train_cfg.ckpt_path = str(last)
    if record is not None:
        print(f"  {cell.name}: {shortfall(record)}; "
              + ("continuing from its last checkpoint" if last.exists()
                 else "no last.ckpt: trained again"), flush=True)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_atomic(run_dir / "cell.json", json.dumps(
        {**asdict(cell), "name": cell.name, "overrides": overrides}, indent=2))
    write_atomic(run_dir / "train_config.yaml", OmegaConf.to_yaml(train_cfg, resolve=False))
    train(train_cfg, law_stage=law_stage)
    result = json.loads(metrics_path.read_text())
    if record is not None:
        result = with_earlier_attempts(result, record)
        write_atomic(metrics_path, json.dumps(result, indent=2, sort_keys=True))
    return result, True


def cell_datamodule(run_dir: Path, data_dir: str) -> Any:
    """The set-up datamodule of a trained cell's dataset (its ``train_config.yaml``)."""
    from bgn.data.datamodule import ParticleDataModule

    train_cfg = OmegaConf.load(run_dir / "train_config.yaml")
    datamodule = ParticleDataModule(train_cfg.dataset, train_cfg.fps, data_dir,
                                    show_progress=False)
    datamodule.setup()
    return datamodule


def set_threads(threads: int | None) -> None:
    """torch's intra-op threads of this process (None: torch's default)."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))


def map_in_processes(fn: Callable[..., Any], jobs: list[tuple[Any, ...]], workers: int,
                     threads: int | None) -> list[Any]:
    """``fn(*job)`` for every job, in order: in ``workers`` spawned processes with ``threads``
    torch threads each, or in this process where one worker (or one job) is enough."""
    if workers > 1 and len(jobs) > 1:
        with ProcessPoolExecutor(workers, mp_context=get_context("spawn"),
                                 initializer=set_threads, initargs=(threads,)) as pool:
            return list(pool.map(fn, *zip(*jobs)))
    return [fn(*job) for job in jobs]
