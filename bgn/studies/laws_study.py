"""The grid study's laws stage (``preset.laws``; ``preset=reproduce``): the learned pair law
of every grid cell with a pair-force head read back as a formula and fine-tuned on the
training frames, then scored against the scene's true law at every training distance.

Per cell of ``laws.model`` (``laws.seeds`` of its seeds), from its network checkpoint
(``best_checkpoint``: the stage starts from the network law even where the cell's own
``model.law=auto`` stage chose a formula, so every scene is treated alike):
``bgn.laws.stage.formula_stage`` with ``finetune=true`` (``python -m bgn.laws <ckpt>
finetune=true``), its fitting at most ``laws.max_seconds``, on the training and validation
splits only; its report, law.png and formula checkpoint in ``<report_dir>/laws/<cell>/``.
The table (``against_truth``): the law read back from the network (the law search) and the
formula fitted to the frames (or "no formula fits", the network law kept), the largest
relative error of each against the truth over the training pairs' distances, whether the
fitted form is the truth's and its constants' distance from the truth's, and the network law
against the formula on the validation rollouts (the choice a ``model.law=auto`` run makes).
Cells without a pair-force head (the impulse head, the decoder, the baselines) are listed as
left out. Cells run in ``workers`` processes.
"""

from __future__ import annotations

import json
import math
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from bgn.coerce import ConfigError
from bgn.eval.columns import VARIANT_COLUMNS
from bgn.studies.cells import map_in_processes, preset_seeds
from bgn.studies.report import stage_provenance, variant, write_stage
from bgn.tables import write_table

if TYPE_CHECKING:
    from bgn.studies.cells import Cell

LAWS_KEYS = {"model": "the grid model whose cells' laws are read (one of preset.models)",
             "seeds": "their seeds (a subset of preset.seeds; null: all)",
             "max_seconds": "each cell's fitting of the forms at most this (null: no limit)"}
KEYS = ["scene", "model", *VARIANT_COLUMNS, "truth"]  # one row per scene
TEXT = ["read back from the network", "fitted to the frames"]
VALUES = ["form is the truth's", "constants vs truth", "network vs truth",
          "network vs truth 1-99%", "fitted vs truth", "fitted vs truth 1-99%",
          "formula chosen", "network val error", "formula val error", "network failed",
          "formula failed", "stage s"]


def validate_laws(preset: DictConfig) -> None:
    """``preset.laws`` (absent or null: the stage is left out): one ``ConfigError`` naming a
    bad key."""
    spec = preset.get("laws")
    if spec is None:
        return
    if not isinstance(spec, DictConfig):
        raise ConfigError("preset.laws", spec, "must be a mapping of " + ", ".join(LAWS_KEYS)
                          + " (or null)")
    for key in spec:
        if key not in LAWS_KEYS:
            raise ConfigError(f"preset.laws.{key}", spec[key],
                              "unknown key; known: " + ", ".join(LAWS_KEYS))
    if spec.get("model") not in list(preset.models):
        raise ConfigError("preset.laws.model", spec.get("model"),
                          f"must be one of preset.models {list(preset.models)}")
    seeds = spec.get("seeds")
    if seeds is not None and (not seeds or not set(map(int, seeds))
                              <= set(preset_seeds(preset))):
        raise ConfigError("preset.laws.seeds", list(seeds),
                          f"must be a subset of preset.seeds {preset_seeds(preset)} (or null)")
    limit = spec.get("max_seconds")
    if limit is not None and not (isinstance(limit, (int, float)) and limit > 0):
        raise ConfigError("preset.laws.max_seconds", limit, "must be a positive number of "
                          "seconds (or null: no limit)")


def _law_job(cell_dir: str, data_dir: str, out_dir: str,
             max_seconds: float | None) -> dict[str, Any]:
    """One cell's formula stage (in a pool process): its record and wall time, or
    ``{"left_out": reason}`` where the cell's model has no pair-force head."""
    from bgn.laws.sample import pair_force_head
    from bgn.laws.stage import formula_stage
    from bgn.studies.cells import cell_datamodule
    from bgn.training.checkpoints import best_checkpoint
    from bgn.training.module import load_model

    t0 = time.perf_counter()
    best = best_checkpoint(Path(cell_dir))
    try:
        pair_force_head(load_model(best))
    except ValueError as err:
        return {"left_out": str(err).split(", so")[0]}
    datamodule = cell_datamodule(Path(cell_dir), data_dir)
    cfg = OmegaConf.load(Path(cell_dir) / "train_config.yaml")
    try:
        record = formula_stage(best, datamodule.datasets["train"], datamodule.datasets["val"],
                               cfg, Path(out_dir),
                               max_seconds=None if max_seconds is None else float(max_seconds))
    except Exception as err:  # one cell's failure is named in the table, not the stage's end
        traceback.print_exc()
        return {"failed": f"{type(err).__name__}: {err}"}
    return {"record": record, "seconds": time.perf_counter() - t0}


def law_row(record: dict[str, Any]) -> dict[str, Any]:
    """A table row's values from a formula stage's record (``against_truth`` and the
    validation rollouts the choice reads, ``bgn.laws.finetune.law_choice``: the failed rollouts
    and the mean error after the stage's horizon, a failed one at the cap)."""
    from bgn.laws.finetune import failed_rollouts
    from bgn.laws.report import spec_text

    truth = record.get("against_truth") or {}
    v = record.get("validation") or {}  # empty: no formula fits, or the rollouts were cut
    n = v["network"]["horizon"] if "network" in v else None

    def mean(law: str) -> float:  # JSON keys are strings in a record read back
        errors = v.get(law, {}).get("errors", {})
        return float(errors.get(n, errors.get(str(n), math.nan)))

    def failed(law: str) -> float:
        return float(failed_rollouts(v[law])) if law in v else math.nan

    def got(key: str) -> float:
        return float(truth.get(key, math.nan))

    read_back = json.loads(Path(record["report"]).with_name("law.json").read_text())
    return {"truth": record.get("truth") or "unknown",
            "read back from the network": "; ".join(p["formula"] for p in read_back["pairs"]),
            "fitted to the frames": (spec_text(record["tuned"])
                                     if record.get("outcome") != "no formula fits"
                                     else "no formula fits"),
            "form is the truth's": got("tuned_form_is_truth"),
            "constants vs truth": got("tuned_constants_vs_truth"),
            "network vs truth": got("network_max"),
            "network vs truth 1-99%": got("network_max_1_99"),
            "fitted vs truth": got("tuned_max"), "fitted vs truth 1-99%": got("tuned_max_1_99"),
            "formula chosen": float(record["choice"] == "formula"),
            "network val error": mean("network"), "formula val error": mean("formula"),
            "network failed": failed("network"), "formula failed": failed("formula"),
            "horizon": n}


def _g(value: float) -> str:
    return "nan" if not math.isfinite(value) else f"{value:.2g}"


def findings(rows: list[dict[str, Any]], horizon: str) -> list[str]:
    """The laws table's findings in prose, from its per-seed rows (written beside the table,
    so the prose is always of the run the table is): per scene, how many seeds' fitted
    formula has the truth's form, the worst of its constants and of its error against the
    truth, the network law's error, and which law the validation rollouts chose."""
    if not rows:
        return []
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    of = {scene: [r for r in rows if r["scene"] == scene] for scene in scenes}

    def worst(scene: str, key: str) -> float:
        values = [float(r[key]) for r in of[scene] if r.get(key) is not None]
        return max(values) if values else math.nan

    def each(text: Any) -> str:
        return ", ".join(f"{text(scene)} ({scene})" for scene in scenes)

    truth_form = sum(int(r["form is the truth's"] == 1.0) for r in rows)
    chosen = sum(int(r["formula chosen"] == 1.0) for r in rows)
    mean = {law: {scene: sum(float(r[f"{law} val error"]) for r in of[scene]) / len(of[scene])
                  for scene in scenes} for law in ("network", "formula")}
    failed = {law: sum(int(r[f"{law} failed"]) for r in rows
                       if math.isfinite(float(r[f"{law} failed"])))
              for law in ("network", "formula")}
    none_fits = sum(int(r.get("fitted to the frames") == "no formula fits") for r in rows)
    per_scene = ", ".join(f"{scene} {sum(int(r[TRUTH_FORM] == 1.0) for r in of[scene])} of "
                          f"{len(of[scene])}" for scene in scenes)
    return [
        f"- **The fitted formula has the truth's form in {truth_form} of {len(rows)} cells** "
        f"({per_scene}); its constants within "
        + each(lambda s: f"{_g(100 * worst(s, 'constants vs truth'))} %")
        + " of the truth's (the worst seed). At every training distance its largest relative "
        "error is " + each(lambda s: _g(worst(s, "fitted vs truth")))
        + "; between the 1st and 99th percentiles "
        + each(lambda s: _g(worst(s, "fitted vs truth 1-99%"))) + ".",
        "- The network law's largest relative error against the truth is "
        + each(lambda s: _g(worst(s, "network vs truth"))) + " ("
        + each(lambda s: _g(worst(s, "network vs truth 1-99%")))
        + " between the percentiles; the worst seed).",
        f"- The formula was chosen over the network law in {chosen} of {len(rows)} cells "
        f"(the fewer failed validation rollouts, then the lower mean error after {horizon} "
        "steps, a failed rollout at the cap; mean over the seeds, formula against network: "
        + each(lambda s: f"{_g(mean['formula'][s])} against {_g(mean['network'][s])}")
        + f"; failed rollouts, all cells: formula {failed['formula']}, network "
        f"{failed['network']}).",
        *([f"- No formula fit the learned law (within the search's tolerance) in {none_fits} "
           f"of {len(rows)} cells: nothing was fine-tuned there and the network law was kept."]
          if none_fits else []),
        ]


TRUTH_FORM = "form is the truth's"


def laws_stage(cfg: DictConfig, cells: list[Cell], results: dict[str, Any],
               provenance: dict[str, Any], workers: int, threads: int | None) -> Path:
    """The laws of the grid's cells (module doc); cells in ``workers`` processes."""
    from bgn.studies.report import write_seeded_table

    t0 = time.perf_counter()
    spec = cfg.preset.laws
    seeds = set(map(int, spec.seeds)) if spec.get("seeds") else set(preset_seeds(cfg.preset))
    chosen = [c for c in cells if c.model == spec.model and "main" in c.groups
              and c.seed in seeds and c.name in results]
    out = Path(cfg.report_dir) / "laws"
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(str(Path(cfg.cells_dir) / c.name), str(cfg.paths.data_dir), str(out / c.name),
             spec.get("max_seconds")) for c in chosen]
    done = map_in_processes(_law_job, jobs, workers, threads)
    rows, left_out, failed, figures, horizons = [], {}, {}, [], set()
    for cell, job in zip(chosen, done):
        if "left_out" in job:
            left_out.setdefault(cell.scene, job["left_out"])
            continue
        if "failed" in job:
            failed[cell.name] = job["failed"]
            print(f"  laws {cell.name}: FAILED {job['failed']}", flush=True)
            continue
        row = {"seed": cell.seed, "scene": cell.scene, **variant(results, cell),
               **law_row(job["record"]), "stage s": job["seconds"]}
        if (horizon := row.pop("horizon")) is not None:  # none where nothing was rolled out
            horizons.add(horizon)
        print(f"  laws {cell.name}: {row['fitted to the frames']} ({row['truth']})",
              flush=True)
        rows.append(row)
        if all(f"{cell.scene}_fps" not in f for f in figures):  # one figure per scene
            figures.append(f"{cell.name}/law.png")
    h = ", ".join(str(k) for k in sorted(horizons)) or "?"
    limit = spec.get("max_seconds")
    skipped = ("" if not left_out else " Left out (no law to read): "
               + "; ".join(f"{s}: {r}" for s, r in left_out.items()) + ".")
    skipped += ("" if not failed else " FAILED (not in the tables): "
                + "; ".join(f"{c}: {r}" for c, r in failed.items()) + ".")
    formulas = write_table(
        out, "formulas", ["scene", "seed", "truth", *TEXT], rows,
        "Learned laws read back as formulas (every seed)",
        "Each cell's network law read back as a formula over the training pairs' distances "
        "(`read back from the network`), and the formula fitted to the training frames as "
        "the model's law (`fitted to the frames`: the law search's front members tuned on the "
        "frames, the lowest loss kept, then polished; `no formula fits` where the search "
        "chose no member within its tolerance, the network law kept; "
        "`python -m bgn.laws <cell>/checkpoints/best.ckpt finetune=true`, "
        + ("no time limit" if limit is None else f"its fitting at most {limit:g} s")
        + "). Training and validation splits only." + skipped,
        empty="(no cell with a pair-force head)")
    table = write_seeded_table(
        out, "laws", [*KEYS, *VALUES], KEYS, rows,
        "Learned laws against the truth",
        "`form is the truth's`: the fitted formula is the truth's form up to constants "
        "(bgn.laws.search.same_form; the share of seeds); `constants vs truth`: the largest "
        "relative difference of its constants from the truth's in its own family (the family "
        "fitted to the truth); `... vs truth`: "
        "the largest relative error against the true law over the training pairs' distances "
        "(all of them, and between their 1st and 99th percentiles; near a zero crossing "
        "relative to the law's change over 10 % of r). `formula chosen`: the share of seeds "
        "whose formula validated better than the network law (the fewer failed validation "
        "rollouts, then the lower mean error, the formula where its mean is within one "
        "standard error of the network law's: bgn.laws.finetune.law_choice); the two validation "
        f"errors: the mean position error after {h} steps over the validation rollouts, a "
        "failed one at the cap; `... failed`: how many of those rollouts failed.",
        empty="(no cell with a pair-force head)")
    now = time.perf_counter()
    path = write_stage(
        out, "laws", f"Learned laws of the `{cfg.preset.name}` cells",
        [f"The grid's `{spec.model}` cells of seeds {', '.join(map(str, sorted(seeds)))} "
         "(their network checkpoints), read back and fitted by the formula stage, one cell "
         f"per process ({workers} at once). What the tables below show, written from them:",
         "", *findings(rows, h)],
        [formulas, table], figures, stage_provenance(provenance, now - t0), cfg.get("results_md"))
    if failed:  # the tables of the others are written; the command still fails
        raise RuntimeError(f"laws stage: {len(failed)} cell(s) failed ({', '.join(failed)}); "
                           f"their tracebacks are above, the others' tables in {path}")
    return path
