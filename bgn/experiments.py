"""The study: ``python -m bgn.experiments preset=quick`` (presets: tiny | quick | full).

Trains every cell of a preset (scene x fps x model, BGN ablations, sample efficiency) by
composing the real ``train`` config and calling ``bgn.train.train``, evaluates each cell's
best checkpoint on the test split (``bgn.evaluate``), and writes the report (Table 1, inverse,
types, ablations, sample efficiency, report.md) under ``report_dir``. Resumable: a cell whose
``metrics.json`` exists is not retrained, a cell whose ``eval.json`` is newer than its
checkpoint is not re-evaluated; the report is always rewritten from what is on disk.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
MODELS = ("bgn", "cranmer_gn", "gns")
ABLATIONS = ("full", "no_classifier", "no_contact", "no_inverse")

# The paper's Table 1 (the only values typed by hand). BGN per fps; the two baselines are
# single values per scene in its last two columns. The paper does not say which metric.
PAPER_BGN = {
    "collisions": {10: 0.003, 30: 0.003, 50: 0.003, 100: 0.006},
    "spring": {10: 0.0007, 30: 0.093, 50: 0.0009, 100: 0.08},
    "gravity_r2": {10: 1.023, 30: 1.363, 50: 1.306, 100: 0.804},
    "gravity_r1": {10: 0.129, 30: 0.561, 50: 0.588, 100: 0.836},
}
PAPER_CRANMER = {"collisions": 0.119, "spring": 0.047, "gravity_r2": 1.634, "gravity_r1": 0.077}
PAPER_SANCHEZ = {"collisions": 0.053, "spring": 0.734, "gravity_r2": 1.804, "gravity_r1": 1.340}
PAPER_LABEL = "paper (metric unstated)"


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

    @property
    def name(self) -> str:
        fps = f"{self.fps:g}".replace(".", "p")
        sims = f"_sims{self.train_sims}" if self.train_sims is not None else ""
        return f"{self.scene}_fps{fps}_{self.model}_{self.ablation}{sims}"


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
    out += [f"paths.data_dir={cfg.data_dir}",
            f"paths.output_dir={Path(cfg.cells_dir) / cell.name}"]
    return out


def compose_train(overrides: list[str]) -> DictConfig:
    """Compose ``conf/train.yaml`` with overrides, inside or outside a Hydra app."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose(config_name="train", overrides=overrides)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="train", overrides=overrides)


def train_cell(cell: Cell, cfg: DictConfig) -> tuple[dict[str, Any], bool]:
    """Train a cell unless its metrics.json exists; returns (the metrics record, trained?)."""
    from bgn.train import train

    run_dir = Path(cfg.cells_dir) / cell.name
    metrics_path = run_dir / "metrics.json"
    if metrics_path.exists():
        return json.loads(metrics_path.read_text()), False
    overrides = cell_overrides(cell, cfg)
    train_cfg = compose_train(overrides)
    last = run_dir / "checkpoints" / "last.ckpt"
    if last.exists():  # an interrupted cell continues from its last checkpoint
        train_cfg.ckpt_path = str(last)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "cell.json").write_text(json.dumps(
        {**asdict(cell), "name": cell.name, "overrides": overrides}, indent=2))
    OmegaConf.save(train_cfg, run_dir / "train_config.yaml", resolve=False)
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


def evaluate_cell(cell: Cell, cfg: DictConfig) -> dict[str, Any]:
    """Test-split metrics of a cell's best checkpoint (cached in eval.json), and its KDE
    figure under the report's figures/ when the model has an inverse head."""
    from bgn.data.datamodule import ParticleDataModule
    from bgn.evaluate import evaluate_model, load_model, mass_figure

    run_dir = Path(cfg.cells_dir) / cell.name
    ckpt = best_checkpoint(run_dir)
    eval_path = run_dir / "eval.json"
    figure = Path(cfg.report_dir) / "figures" / f"mass_{cell.name}.png"
    if eval_path.exists() and eval_path.stat().st_mtime >= ckpt.stat().st_mtime:
        result = json.loads(eval_path.read_text())
        if not result.get("figure") or figure.exists():
            return result
    train_cfg = OmegaConf.load(run_dir / "train_config.yaml")
    datamodule = ParticleDataModule(train_cfg.dataset, train_cfg.fps, cfg.data_dir,
                                    show_progress=False)
    datamodule.setup()
    e = cfg.preset.eval
    metrics, arrays = evaluate_model(load_model(ckpt), datamodule.datasets["test"],
                                     max_frames=e.max_frames, mass_frames=e.mass_frames,
                                     mass_samples=e.mass_samples, batch_size=e.batch_size)
    result = {"checkpoint": str(ckpt), "metrics": metrics, "figure": None}
    if arrays:
        result["figure"] = str(mass_figure(arrays, figure))
    eval_path.write_text(json.dumps(result, indent=2, sort_keys=True))
    return result


# ----------------------------------------------------------------------------- report
def fmt(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def write_table(report_dir: Path, stem: str, title: str, columns: list[str],
                rows: list[dict[str, Any]], notes: str = "", csv_too: bool = True) -> str:
    """``<stem>.md`` (a titled markdown table) and ``<stem>.csv`` with the same rows; returns
    the markdown (report.md embeds every table)."""
    lines = [f"# {title}", ""]
    if notes:
        lines += [notes, ""]
    lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    def cell(column: str, value: Any) -> str:  # figures show inline in markdown only
        return f"![{Path(value).stem}]({value})" if column == "figure" and value else fmt(value)

    lines += ["| " + " | ".join(cell(c, r.get(c)) for c in columns) + " |" for r in rows]
    if not rows:
        lines.append("\n(no cells of this kind in the preset)")
    text = "\n".join(lines) + "\n"
    (report_dir / f"{stem}.md").write_text(text)
    if csv_too:
        with open(report_dir / f"{stem}.csv", "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
    return text


# no-learning references in Table 1 (bgn.evaluate): metric suffix -> column
REFERENCES = {"last": "repeat-last NMSE", "linear": "linear-extrapolation NMSE"}


def _paper(scene: str, fps: float) -> float | None:
    return PAPER_BGN.get(scene, {}).get(int(fps)) if float(fps).is_integer() else None


def write_report(cfg: DictConfig, cells: list[Cell],
                 results: dict[str, dict[str, Any]]) -> Path:
    """Every report file from the cells' evaluations; returns report.md."""
    report_dir = Path(cfg.report_dir)
    (report_dir / "figures").mkdir(parents=True, exist_ok=True)

    def ev(cell: Cell) -> dict[str, Any]:
        return results[cell.name]["eval"]["metrics"]

    def test(cell: Cell) -> dict[str, Any]:
        return results[cell.name]["train"]["metrics"]

    main = [c for c in cells if "main" in c.groups]
    models = list(dict.fromkeys(c.model for c in main))
    tables: dict[str, str] = {}

    # Table 1: one row per scene x fps, MSE and NMSE per model, the paper's values beside
    rows = []
    for scene, fps in dict.fromkeys((c.scene, c.fps) for c in main):
        row: dict[str, Any] = {"scene": scene, "fps": fmt(fps)}
        for c in main:
            if (c.scene, c.fps) == (scene, fps):
                row[f"{c.model} MSE"], row[f"{c.model} NMSE"] = ev(c)["mse"], ev(c)["nmse"]
                for ref in REFERENCES:  # the same test frames for every model
                    row[REFERENCES[ref]] = ev(c).get(f"nmse_{ref}_extrapolation")
        row[f"BGN {PAPER_LABEL}"] = _paper(scene, fps)
        row[f"Cranmer et al. {PAPER_LABEL}"] = PAPER_CRANMER.get(scene)
        row[f"Sanchez-Gonzalez et al. {PAPER_LABEL}"] = PAPER_SANCHEZ.get(scene)
        rows.append(row)
    columns = ["scene", "fps", *[f"{m} {k}" for m in models for k in ("MSE", "NMSE")],
               *REFERENCES.values(), f"BGN {PAPER_LABEL}", f"Cranmer et al. {PAPER_LABEL}",
               f"Sanchez-Gonzalez et al. {PAPER_LABEL}"]
    tables["table1"] = write_table(
        report_dir, "table1", "Table 1: one-step error on the test split", columns, rows,
        "MSE of the forward target (next velocity for collisions, acceleration "
        "otherwise) in physical units; NMSE = MSE / training target variance. The "
        "paper's columns are its published Table 1 values (it does not say which "
        "metric); the baselines are single values per scene in the paper. The "
        "extrapolation columns learn nothing: they repeat the last observed target, or "
        "extrapolate the last two linearly, from the input window (the floor a learned "
        "model must beat; the models predict the change from the latter by default).")

    # inverse: BGN cells with a mass head
    inv_cols = ["scene", "fps", "welch_p", "wasserstein1", "modes_true", "modes_recovered",
                "relmass_r2", "coverage50", "coverage90", "mass_particles", "figure"]
    rows = []
    for c in main + [c for c in cells if "main" not in c.groups]:
        r = results[c.name]["eval"]
        if c.ablation == "full" and c.train_sims is None and r.get("figure"):
            figure = Path(r["figure"])
            rows.append({"scene": c.scene, "fps": fmt(c.fps), "model": c.model,
                         **ev(c), "figure": f"figures/{figure.name}"})
    tables["inverse"] = write_table(
        report_dir, "inverse", "Inverse model: sampled vs true masses", inv_cols, rows,
        "Log-masses (natural log) of every particle of a subset of test frames; "
        "Welch p: t-test of true vs sampled log-masses (unequal variances); W1: "
        "Wasserstein-1 distance of the log-masses; modes: KDE peaks of the true "
        "log-masses and how many have a sampled peak within 0.5; coverage: fraction "
        "of particles whose true log-mass lies in the central 50% / 90% interval of "
        "its samples (calibrated: 0.5 / 0.9); relmass R^2: relative log-mass head.")

    # types: collisions (scenes with a type head)
    rows = [{"scene": c.scene, "fps": fmt(c.fps), "model": c.model, **ev(c)}
            for c in cells if c.ablation == "full" and c.train_sims is None
            and "type_accuracy" in ev(c)]
    tables["types"] = write_table(
        report_dir, "types", "Particle-type classification (test split)",
        ["scene", "fps", "model", "type_accuracy", "type_auroc"], rows,
        "Accuracy and one-vs-rest AUROC of the type classifier (collisions).", csv_too=False)

    # ablations: per scene at the preset's ablation fps
    rows = []
    for c in cells:
        if "ablation" in c.groups:
            m = {**ev(c)}
            for k in ("contact_f1", "contact_auroc", "contact_r2"):
                m[k] = test(c).get(f"test/{k}")  # from the trainer's test of best.ckpt
            rows.append({"scene": c.scene, "fps": fmt(c.fps), "ablation": c.ablation, **m})
    tables["ablations"] = write_table(
        report_dir, "ablations", "Ablations of BGN",
        ["scene", "fps", "ablation", "nmse", "mse", "median_relative_error", "type_accuracy",
         "type_auroc", "contact_f1", "contact_auroc", "contact_r2", "relmass_r2",
         "wasserstein1", "coverage50", "coverage90"], rows,
        "Blank: the head is absent in that variant (or the scene has no such head). "
        "Contact metrics come from the training run's test of its best checkpoint.",
        csv_too=False)

    # sample efficiency
    rows = [{"scene": c.scene, "fps": fmt(c.fps), "model": c.model,
             "train_sims": c.train_sims, **ev(c)}
            for c in cells if "sample_efficiency" in c.groups]
    tables["sample_efficiency"] = write_table(
        report_dir, "sample_efficiency", "Sample efficiency",
        ["scene", "fps", "model", "train_sims", "nmse", "mse", "median_relative_error"], rows,
        "Test error against the number of training simulations (val and test use every "
        "simulation of their splits).")
    _sample_efficiency_plot(rows, report_dir / "sample_efficiency.png")

    total = sum(results[c.name]["train"]["metrics"].get("wall_time_s", 0.0) for c in cells)
    lines = [f"# Experiments report: preset `{cfg.preset.name}`", "",
             f"{len(cells)} cells trained under `{cfg.cells_dir}` "
             f"(total training wall time {total / 60:.1f} min). Every number comes from "
             "the checkpoints of these cells, evaluated on the test split, except the "
             "paper's published values (labelled).", "",
             "- [Table 1: one-step MSE and NMSE per scene, fps and model](table1.md) "
             "([csv](table1.csv))",
             "- [Inverse model: mass samples, coverage, modes, relative-mass R^2](inverse.md) "
             "([csv](inverse.csv)); KDE figures in [figures/](figures/)",
             "- [Particle types (collisions)](types.md)",
             "- [Ablations](ablations.md)",
             "- [Sample efficiency](sample_efficiency.md) ([csv](sample_efficiency.csv), "
             "[plot](sample_efficiency.png))", ""]
    for text in tables.values():  # every table inline too, one heading level down
        lines += ["#" + text.rstrip("\n"), ""]
    lines += ["![sample efficiency](sample_efficiency.png)", "",
              "## Cells", "", "| cell | groups | trained in (s) | test NMSE |", "|---|---|---|---|"]
    lines += [f"| {c.name} | {', '.join(c.groups)} | "
              f"{fmt(test(c).get('wall_time_s'))} | {fmt(ev(c)['nmse'])} |" for c in cells]
    path = report_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _sample_efficiency_plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib.pyplot as plt

    import bgn.figures  # noqa: F401  (selects the Agg backend)

    fig, ax = plt.subplots(figsize=(4.8, 3.4))
    for key in dict.fromkeys((r["scene"], r["fps"], r["model"]) for r in rows):
        pts = sorted((r["train_sims"], r["nmse"]) for r in rows
                     if (r["scene"], r["fps"], r["model"]) == key)
        ax.plot(*zip(*pts), "o-", label=f"{key[2]} ({key[0]}, fps {key[1]})")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("training simulations")
    ax.set_ylabel("test NMSE")
    if rows:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


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
    report = write_report(cfg, cells, results)
    print(f"report: {report} ({time.perf_counter() - start:.0f} s)")
    return report


@hydra.main(config_path="../conf", config_name="experiments", version_base="1.3")
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
