"""The study's report: one function per table (Table 1, inverse, types, ablations, sample
efficiency) and report.md, from the cells' training records and their evaluations on the
split the preset scores (``preset.eval.split``: test, or val to re-check a default; every
title, report.md's heading and provenance.json name it, and a validation study's
``results_md`` block is ``<preset>_val``, never the test block ``<preset>``).

Every number in the report comes from the cells' checkpoints except the paper's published
Table 1 values below, the only ones typed by hand. ``results`` maps a cell's name to
``{"train": metrics.json record, "eval": eval.json record}`` (``bgn.studies.grid``).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bgn.eval.columns import (
    GIVEN,
    INVERSE_COLUMNS,
    INVERSE_REFERENCES,
    NO_LEARNING,
    PHYSICS,
    ROLLOUT_COLUMNS,
    TRAINED_WITH,
    VARIANT_COLUMNS,
    inverse_reference_variant,
    supervision_text,
)
from bgn.provenance import write_block
from bgn.studies.cells import cut_by_cap, shortfall
from bgn.tables import fmt, write_csv, write_table

if TYPE_CHECKING:
    from bgn.studies.cells import Cell

Results = dict[str, dict[str, Any]]

# The paper's Table 1. BGN per fps; the two baselines are single values per scene in its last
# two columns. The paper does not say which metric.
PAPER_BGN = {
    "collisions": {10: 0.003, 30: 0.003, 50: 0.003, 100: 0.006},
    "spring": {10: 0.0007, 30: 0.093, 50: 0.0009, 100: 0.08},
    "gravity_r2": {10: 1.023, 30: 1.363, 50: 1.306, 100: 0.804},
    "gravity_r1": {10: 0.129, 30: 0.561, 50: 0.588, 100: 0.836},
}
PAPER_CRANMER = {"collisions": 0.119, "spring": 0.047, "gravity_r2": 1.634, "gravity_r1": 0.077}
PAPER_SANCHEZ = {"collisions": 0.053, "spring": 0.734, "gravity_r2": 1.804, "gravity_r1": 1.340}
PAPER_LABEL = "paper (metric unstated)"
PAPER_COLUMNS = {"BGN": PAPER_BGN, "Cranmer et al.": PAPER_CRANMER,
                 "Sanchez-Gonzalez et al.": PAPER_SANCHEZ}

# no-learning references in Table 1 (bgn.eval.evaluate): metric suffix -> column
REFERENCES = {"last": "repeat-last NMSE", "linear": "linear-extrapolation NMSE"}
EMPTY = "(no cells of this kind in the preset)"

# the splits a study scores (preset.eval.split), each with the split the mass flow is
# recalibrated on first: never the scored one (python -m bgn.evaluate refuses that too)
CALIBRATION_SPLIT = {"test": "val", "val": "train"}
SPLIT_NAMES = {"test": "test", "val": "validation", "train": "training"}
VAL_NOTE = ("Validation split: a re-check of defaults, not test results. The mass flow is "
            "recalibrated on the training split, whose masses it was trained on: compare "
            "relmass_r2 and info_gain across rows, not coverage.")
OVERRIDES = "overrides"  # the preset variant of a cell (preset.variants), where it has one


def variant_overrides(cell: Cell) -> str:
    """A cell's preset variant (``preset.variants``: its name and the train overrides it
    adds), blank where the preset has none."""
    return f"{cell.tag}: {' '.join(cell.extra) or 'none'}" if cell.tag else ""


def override_columns(cells: list[Cell]) -> list[str]:
    """The overrides column where some cell has a preset variant (none otherwise: the tables
    of a preset without variants are as before)."""
    return [OVERRIDES] if any(c.tag for c in cells) else []


def split_notes(split: str, notes: str) -> str:
    """A table's notes, led by what a validation table is (``VAL_NOTE``)."""
    return f"{VAL_NOTE} {notes}" if split == "val" else notes


# ----------------------------------------------------------------------------- seeds
SEED = "seed"          # the training seed of a per-seed row (bgn.studies.cells.Cell.seed)
SEEDS = "seeds"        # how many seeds an aggregated row holds
MODEL_ID = "model_id"  # a per-seed row's model config (cell model and variant): what groups it
MODEL_TEXT = ("model", *VARIANT_COLUMNS)  # what describes it, seed by seed
STATS = ("std", "min", "max", "n")  # the spread columns beside each mean in the CSV
SEEDS_NOTE = ("Seeds: each row is the mean over its `seeds` training seeds, ± the sample "
              "standard deviation, with (min–max) after it; never the best seed. A value "
              "absent in some seeds is averaged over those that have it (n in the CSV); nan: a "
              "seed's value is NaN (min–max over the others). "
              "Per-seed values: {stem}_per_seed.csv.")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _group_key(row: dict[str, Any], keys: list[str]) -> tuple[Any, ...]:
    """What makes rows one aggregated row: ``keys``, where a row has a ``MODEL_ID`` (the
    cell's model config) that in place of the texts describing the model, which may differ
    across seeds (a formula law fitted per run)."""
    if MODEL_ID not in row:
        return tuple(row.get(k) for k in keys)
    return (*(row.get(k) for k in keys if k not in MODEL_TEXT), row[MODEL_ID])


def merged_text(values: list[Any]) -> Any:
    """One cell for a text column whose seeds differ: the common start, then each seed's
    rest (``a, formula x`` and ``a, formula y``: ``a, formula (per seed: x; y)``: no ``|``,
    which would split a markdown table's cell). The start ends at a space outside
    parentheses, so no seed's formula is cut inside a bracket."""
    distinct = list(dict.fromkeys(values))
    if len(distinct) < 2 or not all(isinstance(v, str) for v in distinct):
        return distinct[0] if distinct else None
    head = os.path.commonprefix(distinct)
    cut = head.rfind(" ")
    while cut > 0 and head[:cut].count("(") != head[:cut].count(")"):
        cut = head.rfind(" ", 0, cut)
    head = head[:max(cut, 0) + 1] if head else ""
    return f"{head}(per seed: {'; '.join(v[len(head):] for v in values)})"


def aggregate_rows(rows: list[dict[str, Any]], keys: list[str]) -> list[dict[str, Any]]:
    """One row per distinct ``keys`` (``_group_key``; in order of first appearance) from
    per-seed rows: each numeric column becomes its mean over the seeds that have a value, with
    ``<col>_std`` (sample standard deviation; 0 with one value), ``<col>_min``, ``<col>_max``
    and ``<col>_n``; a non-numeric column keeps its first seed's value (a key column whose
    seeds differ: ``merged_text``); ``seeds`` counts the rows. A non-finite value is kept (a
    NaN makes the mean NaN; min and max are over the other seeds): a diverged seed is not
    hidden."""
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(_group_key(row, keys), []).append(row)
    out = []
    for members in groups.values():
        row: dict[str, Any] = {k: merged_text([m.get(k) for m in members]) for k in keys}
        row[SEEDS] = len(members)
        columns = dict.fromkeys(c for r in members for c in r
                                if c not in keys and c not in (SEED, MODEL_ID))
        for column in columns:
            values = [r[column] for r in members if r.get(column) is not None]
            if values and all(_is_number(v) for v in values):
                values = [float(v) for v in values]
                mean = sum(values) / len(values)
                var = (sum((v - mean) ** 2 for v in values) / (len(values) - 1)
                       if len(values) > 1 else 0.0)
                numbers = [v for v in values if not math.isnan(v)] or [math.nan]
                row.update({column: mean, f"{column}_std": math.sqrt(var),
                            f"{column}_min": min(numbers), f"{column}_max": max(numbers),
                            f"{column}_n": len(values)})
            else:
                row[column] = values[0] if values else None
        out.append(row)
    return out


def spread(row: dict[str, Any], column: str) -> str:
    """A table cell of an aggregated row: ``mean ± std (min–max)``, the plain value where
    the seeds agree (or one seed has it)."""
    if f"{column}_std" not in row:
        return fmt(row.get(column))
    def show(value: float) -> str:  # a NaN mean says so (fmt leaves NaN blank)
        return "nan" if math.isnan(value) else fmt(value)

    mean, std = row[column], row[f"{column}_std"]
    low, high = row[f"{column}_min"], row[f"{column}_max"]
    if row[f"{column}_n"] < 2 or (low == high and not math.isnan(mean)):
        return show(mean)
    # an infinite seed has no finite std: the range alone then shows it
    middle = f" ± {show(std)}" if math.isfinite(std) else ""
    return f"{show(mean)}{middle} ({show(low)}–{show(high)})"


def write_seeded_table(report_dir: Path, stem: str, columns: list[str], keys: list[str],
                       rows: list[dict[str, Any]], title: str, notes: str, empty: str = EMPTY,
                       csv_too: bool = True, images: tuple[str, ...] = ()) -> str:
    """``write_table`` of per-seed ``rows`` (each with a ``seed``): with one seed exactly
    as before; with several, one row per ``keys`` (``aggregate_rows``) showing mean ± std
    (min–max) and the number of seeds, ``<stem>.csv`` with the mean, std, min, max and n of
    every value column, and ``<stem>_per_seed.csv`` with every seed's row."""
    if len({r.get(SEED) for r in rows}) <= 1:
        return write_table(report_dir, stem, columns, rows, title, notes, empty=empty,
                           csv_too=csv_too, images=images)
    aggregated = aggregate_rows(rows, keys)
    values = [c for c in columns if c not in keys]
    first = next((i for i, c in enumerate(columns) if c not in keys), len(columns))
    shown = [{**r, **{c: spread(r, c) for c in values}} for r in aggregated]
    text = write_table(report_dir, stem, [*columns[:first], SEEDS, *columns[first:]], shown,
                       title, f"{notes} {SEEDS_NOTE.format(stem=stem)}".strip(), empty=empty,
                       csv_too=False, images=images)
    write_csv(report_dir / f"{stem}.csv",
              [*[c for c in columns if c in keys], SEEDS,
               *[f"{c}_{s}" if s else c for c in values for s in ("", *STATS)]], aggregated)
    write_csv(report_dir / f"{stem}_per_seed.csv", [SEED, *columns], rows)
    return text


def paper_value(source: str, scene: str, fps: float) -> float | None:
    """The paper's Table 1 value of ``source`` (a key of ``PAPER_COLUMNS``) for a scene and
    fps; the baselines have one value per scene, BGN one per integer fps."""
    if source != "BGN":
        return PAPER_COLUMNS[source].get(scene)
    return PAPER_BGN.get(scene, {}).get(int(fps)) if float(fps).is_integer() else None


def evaluation(results: Results, cell: Cell) -> dict[str, Any]:
    """The test-split metrics of a cell (``bgn.eval.evaluate``)."""
    return results[cell.name]["eval"]["metrics"]


def training(results: Results, cell: Cell) -> dict[str, Any]:
    """The metrics the training run recorded (its own test of best.ckpt, wall time)."""
    return results[cell.name]["train"]["metrics"]


def _main(cells: list[Cell]) -> list[Cell]:
    return [c for c in cells if "main" in c.groups]


def describe_columns(info: dict[str, Any]) -> dict[str, str]:
    """``VARIANT_COLUMNS`` of a ``PhysicsModel.describe`` record (a model that trained)."""
    return {TRAINED_WITH: supervision_text(info),
            GIVEN: ", ".join(info.get("given", [])) or ("-" if info else ""),
            PHYSICS: info.get("physics", "")}


def variant(results: Results, cell: Cell) -> dict[str, str]:
    """What a cell's model is (``PhysicsModel.describe``, recorded by ``bgn.studies.grid``):
    its label, what its training loss reads beyond the frames, what it is given at inference
    beyond the position window and the physics written into it; the cell's model name alone
    where an older record lacks it."""
    info = results[cell.name]["eval"].get("model") or {}
    return {MODEL_ID: f"{cell.model}/{cell.tag}", "model": info.get("label", cell.model),
            **describe_columns(info)}


# a reference that learns nothing and reads nothing but the window (the extrapolations)
NOTHING = {TRAINED_WITH: NO_LEARNING, GIVEN: "-", PHYSICS: "none"}
VARIANT_NOTE = ("trained with: what the model's training loss reads beyond the frames, each "
                "recorded quantity with the loss terms that read it (mass_nll: the mass "
                "flow; relmass: the relative masses; law: the pair law with the recorded "
                "masses; impulse_mass: the impulse head's masses; contact: the contact head; "
                "type: the type classifier; a term weighted 0 reads nothing; - the frames "
                "alone), from its config and loss weights; given at inference: what it reads "
                "beyond the position window when it predicts (radii, types, masses; - "
                "nothing); physics written in: the structure its dynamics has by "
                "construction (none: a learned map).")
# the paper's BGN is its decoder, its baselines read neither radii nor types: its value
# stands beside a row of the same family given nothing and with no physics written in
PAPER_SOURCE = {"bgn": "BGN", "cranmer_gn": "Cranmer et al.", "gns": "Sanchez-Gonzalez et al."}


# what each cell trained: its optimiser steps and its whole run's wall time
BUDGET_COLUMNS = ["train steps", "train s"]
BUDGET_NOTE = ("train steps: the optimiser steps the cell trained (its training record; "
               "an older record without one: its last checkpoint's); "
               "train s: the wall time of its whole training run (the fit, BGN's formula "
               "stage where it has one, the test; a cell the wall-clock cap cut and a rerun "
               "continued: every attempt's together), on the machine and load of the "
               "provenance above: the two show what \"trained for the same wall time\" "
               "held. A cell the cap cut is named in the provenance (cells cut by the "
               "wall-clock cap).")


def cut_cells(cells: list[Cell], results: Results) -> list[str]:
    """Every cell whose training record says the wall-clock cap (``trainer.max_time``) cut
    it, with what was cut and the steps it trained (``bgn.studies.cells.shortfall``): its
    rows depend on the machine's load, so the report and provenance.json name it."""
    return [f"{c.name} ({shortfall(results[c.name]['train'])})" for c in cells
            if c.name in results and cut_by_cap(results[c.name]["train"])]


def budget_columns(results: Results, cell: Cell) -> dict[str, Any]:
    """``BUDGET_COLUMNS`` of a cell: its steps and its training run's wall time (metrics.json).
    The steps are the training record's (``budget.steps``): the last checkpoint is written at
    a validation and lags the budget's end by up to a validation interval, so its step
    (``bgn.studies.grid`` records it beside the evaluation) is only the fallback of a record
    without one."""
    steps = (results[cell.name]["train"].get("budget") or {}).get("steps")
    return {"train steps": steps if steps is not None
            else results[cell.name]["eval"].get("train_steps"),
            "train s": training(results, cell).get("wall_time_s")}


def contact_scene(scene: str) -> bool:
    """Whether a built-in scene's interaction is contact (collisions); False for a scene the
    simulators do not know (imported data)."""
    from bgn.sim import make_scene

    try:
        return make_scene(scene).meta.interaction == "contact"
    except ValueError:
        return False


def table1(report_dir: Path, cells: list[Cell], results: Results, split: str = "test") -> str:
    """Table 1: one row per scene x fps x model (x preset variant) of the main grid (its
    variant, what it is given, the physics written in), MSE and NMSE on ``split``, the
    no-learning references of the same frames and the paper's value for the paper's
    variant."""
    main, rows = _main(cells), []
    extra = override_columns(main)
    for scene, fps in dict.fromkeys((c.scene, c.fps) for c in main):
        for c in [c for c in main if (c.scene, c.fps) == (scene, fps)]:
            m, about = evaluation(results, c), variant(results, c)
            source = PAPER_SOURCE.get((results[c.name]["eval"].get("model") or {}).get(
                "name", c.model))  # the registry name: model=bgn_decoder is a "bgn"
            paper = (paper_value(source, scene, fps) if source and about[GIVEN] == "-"
                     and about[PHYSICS] == "none" else None)
            rows.append({SEED: c.seed, "scene": scene, "fps": fmt(fps), **about,
                         OVERRIDES: variant_overrides(c), **budget_columns(results, c),
                         "MSE": m["mse"],
                         "NMSE": m["nmse"], "frames": m.get("n_frames"),
                         # the same frames for every model of a scene x fps
                         **{column: m.get(f"nmse_{ref}_extrapolation")
                            for ref, column in REFERENCES.items()}, PAPER_LABEL: paper})
    columns = ["scene", "fps", "model", *extra, *VARIANT_COLUMNS, *BUDGET_COLUMNS, "MSE",
               "NMSE", "frames", *REFERENCES.values(), PAPER_LABEL]
    return write_seeded_table(
        report_dir, "table1", columns, ["scene", "fps", "model", *extra, *VARIANT_COLUMNS,
                                        PAPER_LABEL], rows,
        f"Table 1: one-step error on the {SPLIT_NAMES[split]} split",
        split_notes(split, "MSE of the forward target (next velocity for collisions, acceleration "
        "otherwise) in physical units; NMSE = MSE / training target variance; frames: how "
        "many frames, evenly spread over the split, they average (preset.eval.max_frames; "
        "the targets are heavy-tailed, so the figure depends on it). model: the "
        "variant (BGN with the paper's decoder or a structured head; a baseline with the "
        f"node inputs it is given); {VARIANT_NOTE} {BUDGET_NOTE} The paper column is the "
        "published Table 1 value (it does not say which metric) of the paper's variant "
        "only: its BGN is the decoder, its baselines read neither radii nor types (single "
        "values per scene). The extrapolation columns learn nothing: they repeat the last "
        "observed target, or extrapolate the last two linearly, from the input window "
        "(the floor a learned model must beat; the models predict the change from the "
        "latter by default)." + (" overrides: the preset variant (its name and the train "
                                 "overrides it adds)." if extra else "")),
        empty=EMPTY)



def inverse_table(report_dir: Path, cells: list[Cell], results: Results,
                  split: str = "test") -> str:
    """Inverse model: every full-model cell with a mass head (main grid first), its sample,
    calibration and information metrics and figure on ``split``, with the prior-only sampler,
    the type-only sampler (where each type has its own mass law) and the force-law estimator
    on the same particles below it; each row says what it is given and the physics written
    in."""
    main = _main(cells)
    extra = override_columns(main)
    keys = ["scene", "fps", "model", *extra, *VARIANT_COLUMNS]
    columns = [*keys, *INVERSE_COLUMNS, "mass_calibration_scale50",
               "mass_calibration_scale90", "mass_particles", "figure"]
    rows = []
    for c in main + [c for c in cells if "main" not in c.groups]:
        figure = results[c.name]["eval"].get("figure")
        if c.ablation == "full" and c.train_sims is None and figure:
            m = evaluation(results, c)
            rows.append({SEED: c.seed, "scene": c.scene, "fps": fmt(c.fps),
                         **variant(results, c), OVERRIDES: variant_overrides(c), **m,
                         "figure": f"figures/{Path(figure).name}"})
            for key, label in INVERSE_REFERENCES.items():
                values = {k: m.get(f"{key}/{k}") for k in INVERSE_COLUMNS}
                if any(v is not None for v in values.values()):
                    rows.append({SEED: c.seed, "scene": c.scene, "fps": fmt(c.fps),
                                 "model": label,
                                 **inverse_reference_variant(key, contact_scene(c.scene)),
                                 OVERRIDES: variant_overrides(c), **values})
    return write_seeded_table(
        report_dir, "inverse", columns, keys, rows,
        f"Inverse model: sampled vs true masses ({SPLIT_NAMES[split]} split)",
        split_notes(split, f"Log-masses (natural log) of every particle of a subset of "
        f"{SPLIT_NAMES[split]} frames, the flow recalibrated first on as many "
        f"{SPLIT_NAMES[CALIBRATION_SPLIT[split]]} frames (a monotone map of its base radius; "
        "mass_calibration_scale50/90: the map's scale at those levels, > 1 where the trained "
        "flow was overconfident). Calibration (docs/design.md#inverse-metrics): coverage50/90, "
        "the fraction "
        "of particles whose true log-mass lies in the central 50% / 90% interval of its "
        "posterior (read from the truth's randomised rank among the samples; calibrated: "
        "0.5 / 0.9), and coverage_max_dev, the largest |coverage - level| over the levels "
        "0.05 ... 0.95 (the curve is in the figure); sbc_p, chi-square p of the uniformity "
        "of simulation-based-calibration ranks; tarp_atc, TARP's area between its coverage "
        "curve and the diagonal above 0.5 (< 0: overconfident); the two tests count each "
        "distinct particle once. info_gain: mean log posterior density of the true log-mass "
        "minus the prior's (nats; 0 = learned nothing); info_gain_over_type, where each type "
        "has its own mass law (collisions): minus the type-only sampler's density instead, "
        "what the posterior tells beyond the type (below 0: less than the type alone). "
        "relmass_r2: the relative-mass head "
        "(Eq. 9-10); relmass_r2_estimate: of the posterior means' differences on the same "
        "edges; mass_rel_err: median |m_hat / m - 1| of one frame's posterior mean; "
        "sim_mass_rel_err: of each particle's per-frame posteriors pooled (their Gaussian "
        "product) over the evaluated frames of its simulation; on collisions, the momentum "
        "exchanged at the impacts the contact head sees in those frames, solved jointly per "
        "simulation, each group of discs linked by impacts placed by its members' pooled "
        "posteriors (sim_mass_rel_err_flow: the pooled posteriors alone). Welch p, W1 (log-masses) "
        "and modes (KDE peaks of the true log-masses, how many have a sampled peak within "
        "0.5) compare pooled samples, which a sampler of the prior also passes. References "
        "on the same particles: the prior-only sampler (draws from the scene's mass law: "
        "calibrated, zero information); on collisions the type-only sampler (draws from each "
        "disc's own type's mass law: calibrated, all that the type, which the radius shows, "
        "tells); and the physical estimator (the known force law on the window's finite "
        "differences; collisions: momentum exchange at impacts, which one window rarely "
        "holds, each group of discs linked by impacts placed by its members' types' mass "
        "laws; its per-simulation value pools the windows of a simulation). Where the frames "
        "say nothing of a particle the estimator falls back to its type's mean log-mass "
        "(the law's mean with one type): identified and sim_identified are the shares it "
        f"estimated, per frame and per simulation, the rest fell back. {VARIANT_NOTE}"),
        images=("figure",))


def types_table(report_dir: Path, cells: list[Cell], results: Results,
                split: str = "test") -> str:
    """Particle types: accuracy and AUROC on ``split`` of every full-model cell with a type
    head (its variant, what it is given, the physics written in)."""
    rows = [{SEED: c.seed, "scene": c.scene, "fps": fmt(c.fps), **variant(results, c),
             OVERRIDES: variant_overrides(c), **evaluation(results, c)}
            for c in cells if c.ablation == "full" and c.train_sims is None
            and "type_accuracy" in evaluation(results, c)]
    keys = ["scene", "fps", "model", *override_columns(cells), *VARIANT_COLUMNS]
    return write_seeded_table(
        report_dir, "types", [*keys, "type_accuracy", "type_auroc"], keys, rows,
        f"Particle-type classification ({SPLIT_NAMES[split]} split)",
        split_notes(split, "Accuracy and one-vs-rest AUROC of the type classifier "
                    f"(collisions). {VARIANT_NOTE}"),
        csv_too=False)


def ablations_table(report_dir: Path, cells: list[Cell], results: Results,
                    split: str = "test") -> str:
    """Ablations of BGN per scene: the forward error and every head's metric on ``split``;
    contact metrics from the training run's test of its best checkpoint."""
    rows = []
    for c in cells:
        if "ablation" in c.groups:
            m = {**evaluation(results, c)}
            for k in ("contact_f1", "contact_auroc", "contact_r2"):  # the test split's
                m[k] = training(results, c).get(f"test/{k}") if split == "test" else None
            rows.append({SEED: c.seed, "scene": c.scene, "fps": fmt(c.fps),
                         "ablation": c.ablation, **m})
    return write_seeded_table(
        report_dir, "ablations",
        ["scene", "fps", "ablation", "nmse", "mse", "median_relative_error", "type_accuracy",
         "type_auroc", "contact_f1", "contact_auroc", "contact_r2", "relmass_r2",
         "wasserstein1", "coverage50", "coverage90"], ["scene", "fps", "ablation"], rows,
        f"Ablations of BGN ({SPLIT_NAMES[split]} split)",
        split_notes(split, "Blank: the head is absent in that variant (or the scene has no "
                    "such head). " + ("Contact metrics come from the training run's test of "
                                      "its best checkpoint." if split == "test" else
                                      "Contact metrics are left out: they come from the "
                                      "training run's test, on the test split.")),
        csv_too=False)


def sample_efficiency_table(report_dir: Path, cells: list[Cell], results: Results,
                            split: str = "test") -> str:
    """Sample efficiency: the error on ``split`` against the number of training simulations,
    as a table and as a log-log plot (``sample_efficiency.png``)."""
    from bgn.figures import sample_efficiency, save

    rows = [{SEED: c.seed, "scene": c.scene, "fps": fmt(c.fps), "model": c.model,
             "train_sims": c.train_sims, **evaluation(results, c)}
            for c in cells if "sample_efficiency" in c.groups]
    keys = ["scene", "fps", "model", "train_sims"]
    save(sample_efficiency(aggregate_rows(rows, keys), split),  # the mean over seeds
         report_dir / "sample_efficiency.png")
    return write_seeded_table(
        report_dir, "sample_efficiency",
        [*keys, "nmse", "mse", "median_relative_error"], keys, rows,
        f"Sample efficiency ({SPLIT_NAMES[split]} split)",
        split_notes(split, f"{SPLIT_NAMES[split].capitalize()} error against the number of "
                    "training simulations (val and test use every simulation of their "
                    "splits)."))



def rollout_table(report_dir: Path, cells: list[Cell], results: Results,
                  split: str = "test") -> str:
    """Rollouts beside Table 1: per scene x fps (x preset variant: its overrides may change
    the data), every model of the main grid and the no-learning references rolled out from
    the same frames of ``split``."""
    rows, extra = [], override_columns(_main(cells))
    for scene, fps, tag in dict.fromkeys((c.scene, c.fps, c.tag) for c in _main(cells)):
        group = [c for c in _main(cells) if (c.scene, c.fps, c.tag) == (scene, fps, tag)]
        sources = [(variant(results, c), c, "rollout") for c in group]
        # the references learn nothing: one seed's cell holds them (the same test frames)
        sources += [({"model": f"{ref} extrapolation", **NOTHING}, group[0],
                     f"rollout_{ref}") for ref in REFERENCES]
        sources.append(({"model": "predictability limit (simulator, 1e-6 off)", **NOTHING,
                         PHYSICS: "the exact simulator"}, group[0], "predictability"))
        for about, c, key in sources:
            values = {k: evaluation(results, c).get(f"{key}/{k}") for k in ROLLOUT_COLUMNS}
            if any(v is not None for v in values.values()):
                rows.append({SEED: c.seed, "scene": scene, "fps": fmt(fps), **about,
                             OVERRIDES: variant_overrides(c), **values})
    keys = ["scene", "fps", "model", *extra, *VARIANT_COLUMNS]
    return write_seeded_table(
        report_dir, "rollouts", [*keys, *ROLLOUT_COLUMNS], keys, rows,
        f"Rollouts on the {SPLIT_NAMES[split]} split",
        split_notes(split, "Each model (its variant, what it was trained with and is given "
        "and the physics written in: as Table 1) fed its own frames from the same start "
        f"frames of every {SPLIT_NAMES[split]} simulation "
        "(frame 100 when the file is long enough), through the learned simulator. Every "
        "rollout counts, a failed one at the cap (rollout_cap: 10 scene scales, the mean "
        "over the rollouts). pos_err_mean@h: mean over all rollouts of the mean position "
        "error per particle after h steps (@all: mean over the whole rollout); "
        "pos_err_median: their median, which alone would hide up to half the rollouts "
        "failing; pos_mse_mean: mean squared position error per coordinate over all "
        "rollouts (a failed one at cap^2 / D). energy_err: median "
        "|E_t - E_0| / |E_0| at the end, with velocities as backward differences; "
        "energy_err_truth: the same for the true frames (the finite-difference floor). "
        "momentum_err where momentum is conserved (no walls). Disc gas: speed_w1_type<k>, "
        "the Wasserstein-1 distance of type k's speeds at the last step from the truth's, "
        "over the true mean speed, pooled over all rollouts (a failed rollout's discs at 10 x "
        "that speed); collision_rate_ratio, predicted over true impacts between frames (one "
        "detector for both; a failed rollout's impacts stop at its failure). A rollout "
        "fails on a non-finite value or a particle more than 10 scene scales astray. The "
        "extrapolation rows learn nothing (repeat the last observed target, or "
        "extrapolate the last two). The predictability row is the exact simulator "
        "started with every position 1e-6 off: chaos alone; a rollout error above it is "
        "the model's."))


TABLES = {"table1": table1, "rollouts": rollout_table, "inverse": inverse_table,
          "types": types_table,
          "ablations": ablations_table, "sample_efficiency": sample_efficiency_table}


# provenance.json's fields shown in report.md's header, in this order
PROVENANCE_FIELDS = {
    "command": "command", "preset": "preset", "config_hash": "composed preset config (sha256)",
    "git_commit": "git commit", "git_dirty": "uncommitted changes in the tree",
    "machine": "machine", "processor": "processor", "cpu_count": "CPUs", "torch": "torch",
    "libraries": "libraries", "device": "device",
    "workers": "workers (parallel cells)", "threads_per_worker": "torch threads per cell",
    "seeds": "training seeds", "eval_split": "split scored (every table)",
    "calibration_split": "mass flow recalibrated on",
    "wall_time_s": "wall time of this command (s)",
    "stage_wall_time_s": "then this table's stage, from the trained cells (s)",
    "failed_cells": "failed cells (not in the tables)",
    "cut_cells": "cells cut by the wall-clock cap (trainer.max_time; in the tables, their rows "
                 "depend on the load; a rerun continues them)"}


def provenance_lines(provenance: dict[str, Any]) -> list[str]:
    """The provenance as a markdown list (report.md's header, the results_md block)."""
    def value(key: str) -> str:
        v = provenance.get(key)
        if key == "command":
            return f"`{v}`"
        if v is None:  # git state of a copy without history, say
            return "unknown"
        return (", ".join(map(str, v)) or "none") if isinstance(v, list) else fmt(v)

    return [f"- {label}: {value(key)}" for key, label in PROVENANCE_FIELDS.items()
            if key in provenance]


def regenerate_line(provenance: dict[str, Any] | None) -> list[str]:
    """The line under each table naming the command that writes it."""
    if not provenance:
        return []
    return [f"Regenerated by `{provenance['command']}` (commit "
            f"{str(provenance.get('git_commit'))[:10]}, config hash "
            f"{provenance.get('config_hash')}, seeds {fmt(provenance.get('seeds'))}).", ""]


def cut_paragraph(cut: list[str]) -> list[str]:
    """report.md's lines naming the cells the wall-clock cap cut (none: no lines)."""
    if not cut:
        return []
    return [f"**{len(cut)} cell(s) cut by the wall-clock cap** (`trainer.max_time`, their "
            "metrics.json `budget.cut_by`) before their step budget, formula stage or test "
            "ended: " + "; ".join(cut) + ". Their rows are not what the same command trains "
            "on an idler machine; running the command again continues each from its "
            "last.ckpt (raise `preset.max_time` where the cap cuts it again).", ""]


def report_md(report_dir: Path, preset: str, cells_dir: str | Path, cells: list[Cell],
              results: Results, tables: dict[str, str],
              provenance: dict[str, Any] | None = None, split: str = "test") -> Path:
    """report.md: the provenance, links to every file, every table inline (one heading level
    down, each with the command that regenerates it), the plot, and one line per cell
    (training time, NMSE on ``split``)."""
    cells = [c for c in cells if c.name in results]  # a failed cell has no record
    total = sum(training(results, c).get("wall_time_s", 0.0) for c in cells)
    name = SPLIT_NAMES[split]
    lines = [f"# Experiments report: preset `{preset}`, scored on the {name} split", ""]
    if split != "test":
        lines += [VAL_NOTE, ""]
    if provenance:
        lines += ["## Provenance", "", *provenance_lines(provenance),
                  "", "(also in [provenance.json](provenance.json))", ""]
    lines += [f"{len(cells)} cells trained under `{cells_dir}` "
             f"(total training wall time {total / 60:.1f} min). Every number comes from "
             f"the checkpoints of these cells, evaluated on the {name} split, except the "
             "paper's published values (labelled).", "",
             *cut_paragraph(cut_cells(cells, results)),
             "- [Table 1: one-step MSE and NMSE per scene, fps and model](table1.md) "
             "([csv](table1.csv))",
             "- [Rollouts: trajectory error, energy, failures, beside the no-learning "
             "references](rollouts.md) ([csv](rollouts.csv))",
             "- [Inverse model: mass samples, coverage, modes, relative-mass R^2](inverse.md) "
             "([csv](inverse.csv)); KDE figures in [figures/](figures/)",
             "- [Particle types (collisions)](types.md)",
             "- [Ablations](ablations.md)",
             "- [Sample efficiency](sample_efficiency.md) ([csv](sample_efficiency.csv), "
             "[plot](sample_efficiency.png))", ""]
    for text in tables.values():
        lines += ["#" + text.rstrip("\n"), "", *regenerate_line(provenance)]
    lines += ["![sample efficiency](sample_efficiency.png)", "",
              "## Cells", "",
              f"| cell | groups | train steps | trained in (s) | {split} NMSE |",
              "|---|---|---|---|---|"]
    lines += [f"| {c.name} | {', '.join(c.groups)} | "
              f"{fmt(results[c.name]['eval'].get('train_steps'))} | "
              f"{fmt(training(results, c).get('wall_time_s'))} | "
              f"{fmt(evaluation(results, c)['nmse'])} |" for c in cells]
    path = report_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def write_report(report_dir: str | Path, preset: str, cells_dir: str | Path,
                 cells: list[Cell], results: Results,
                 provenance: dict[str, Any] | None = None,
                 results_md: str | Path | None = None, split: str = "test") -> Path:
    """Every report file under ``report_dir`` (with ``provenance``: provenance.json too, and
    its header in report.md), each table titled with ``split`` (the split the cells were
    scored on); with ``results_md``, that file's generated block of this preset and split
    rewritten (``bgn.provenance.write_block``, ``block_name``). Cells without a record
    (failed) are left out. Returns report.md."""
    report_dir = Path(report_dir)
    (report_dir / "figures").mkdir(parents=True, exist_ok=True)
    cells = [c for c in cells if c.name in results]
    tables = {name: table(report_dir, cells, results, split=split)
              for name, table in TABLES.items()}
    if provenance:
        (report_dir / "provenance.json").write_text(
            json.dumps(provenance, indent=2, sort_keys=True) + "\n")
    report = report_md(report_dir, preset, cells_dir, cells, results, tables, provenance,
                       split)
    if results_md:
        write_results_block(Path(results_md), block_name(preset, split), report_dir, tables,
                            provenance)
    return report


# ----------------------------------------------------------------------------- results_md
def block_name(preset: str, split: str = "test") -> str:
    """The generated block of a study in a results file: ``<preset>`` for the test split (the
    headline tables), ``<preset>_<split>`` otherwise, so that a validation study never
    overwrites (or reads as) a block of test results."""
    return preset if split == "test" else f"{preset}_{split}"


def write_results_block(path: Path, preset: str, report_dir: Path, tables: dict[str, str],
                        provenance: dict[str, Any] | None) -> None:
    """Write the report's tables and provenance into ``path``'s generated block of
    ``preset`` (docs/results.md: its headline tables are written by the command); headings
    two levels down, figure links made relative to ``path``."""
    rel = Path(os.path.relpath(report_dir.resolve(), path.resolve().parent)).as_posix()
    body = ["_Written by the command below; do not edit by hand._", ""]
    if provenance:
        body += [*provenance_lines(provenance), ""]
    for text in tables.values():
        if EMPTY in text:  # a kind of cell the preset has none of
            continue
        text = text.replace("](figures/", f"]({rel}/figures/")
        body += ["###" + text.rstrip("\n"), "", *regenerate_line(provenance)]
    write_block(path, preset, "\n".join(body))


# ----------------------------------------------------------------------------- provenance
def stage_provenance(provenance: dict[str, Any], seconds: float) -> dict[str, Any]:
    """The grid's provenance (its wall time: the cells') with this stage's wall time."""
    return {**provenance, "stage_wall_time_s": round(seconds, 1)}


def write_stage(out: Path, name: str, title: str, intro: list[str], tables: list[str],
                figures: list[str], provenance: dict[str, Any], results_md: Any) -> Path:
    """report.md and provenance.json of a stage under ``out``; with ``results_md``, its
    block ``<preset>_<name>`` rewritten (figure links made relative to that file)."""
    (out / "provenance.json").write_text(json.dumps(provenance, indent=2, sort_keys=True)
                                         + "\n")
    def body(level: str, rel: str) -> list[str]:
        lines = []
        for text in tables:
            lines += [level + text.rstrip("\n"), "", *regenerate_line(provenance)]
        lines += [f"![{Path(f).stem}]({rel}{f})" for f in figures]
        return lines

    lines = [f"# {title}", "", "## Provenance", "", *provenance_lines(provenance), "",
             *intro, "", *body("#", "")]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    if results_md:
        results = Path(results_md)
        rel = Path(os.path.relpath(out.resolve(), results.resolve().parent)).as_posix() + "/"
        block = ["_Written by the command below; do not edit by hand._", "",
                 *provenance_lines(provenance), "", *intro, "", *body("###", rel)]
        write_block(results, f"{provenance['preset']}_{name}", "\n".join(block))
    return path
