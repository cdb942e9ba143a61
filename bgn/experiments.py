"""The study: ``python -m bgn.experiments preset=quick`` (presets: tiny | quick | standard |
full; the Pareto study's pareto_tiny | pareto_quick | pareto_full run through ``bgn.pareto``).

Trains every cell of a preset (scene x fps x model, BGN ablations, sample efficiency) by
composing the real ``train`` config and calling ``bgn.train.train``, evaluates each cell's
best checkpoint on the test split (``bgn.evaluate``), and writes the report (``bgn.report``:
Table 1, inverse, types, ablations, sample efficiency, report.md) under ``report_dir``.
Resumable: a cell whose ``metrics.json`` exists is not retrained (an interrupted cell
continues from its ``last.ckpt``), a cell whose ``eval.json`` is newer than its checkpoint is not
re-evaluated; the report is always rewritten from what is on disk. Those files are written
atomically (a temporary file, then a rename); a damaged one (an older bgn killed while writing
it, a hand edit) is named in a warning and its cell trained or evaluated again.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
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

    @property
    def name(self) -> str:
        fps = f"{self.fps:g}".replace(".", "p")
        sims = f"_sims{self.train_sims}" if self.train_sims is not None else ""
        tag = f"_{self.tag}" if self.tag else ""
        return f"{self.scene}_fps{fps}_{self.model}_{self.ablation}{sims}{tag}"


def plan_cells(preset: DictConfig) -> list[Cell]:
    """Every cell of a preset, each once (an ablation=full cell is the main grid's BGN cell)."""
    cells: dict[str, Cell] = {}

    def add(cell: Cell, group: str) -> None:
        old = cells.get(cell.name)
        groups = (old.groups if old else ()) + (group,)
        cells[cell.name] = Cell(cell.scene, cell.fps, cell.model, cell.ablation,
                                cell.train_sims, tuple(dict.fromkeys(groups)))

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
    return list(cells.values())


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


def evaluate_cell(cell: Cell, cfg: DictConfig) -> dict[str, Any]:
    """Test-split metrics of a cell's best checkpoint (cached in eval.json), and its KDE
    figure under the report's figures/ when the model has an inverse head."""
    from bgn.evaluate import evaluate_split, load_model, mass_figure

    run_dir = Path(cfg.cells_dir) / cell.name
    ckpt = best_checkpoint(run_dir)
    eval_path = run_dir / "eval.json"
    figure = Path(cfg.report_dir) / "figures" / f"mass_{cell.name}.png"
    if eval_path.exists() and eval_path.stat().st_mtime >= ckpt.stat().st_mtime:
        result = read_record(eval_path)  # None when damaged (named in a warning): redone
        if result is not None and (not result.get("figure") or figure.exists()) \
                and "rollout/rollout_cap" in result.get("metrics", {}):  # else: older metrics
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


# ----------------------------------------------------------------------------- command
def run(cfg: DictConfig) -> Path:
    """Train (what is missing), evaluate and report every cell of ``cfg.preset``."""
    cells = plan_cells(cfg.preset)
    start = time.perf_counter()
    results: dict[str, dict[str, Any]] = {}
    for i, cell in enumerate(cells, 1):
        print(f"[{i}/{len(cells)}] {cell.name}", flush=True)
        record, trained = train_cell(cell, cfg)
        print(f"  {'trained' if trained else 'already trained (metrics.json)'}", flush=True)
        results[cell.name] = {"train": record}
    for cell in cells:
        results[cell.name]["eval"] = evaluate_cell(cell, cfg)
    report = write_report(cfg.report_dir, cfg.preset.name, cfg.cells_dir, cells, results)
    print(f"report: {report} ({time.perf_counter() - start:.0f} s)")
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
    else:
        run(cfg)


if __name__ == "__main__":
    main()
