"""The grid study's further headline tables, fed from its trained cells: the stability suite,
speed against error and the learned laws (``preset=reproduce``: its ``stability``, ``pareto``
and ``laws`` keys; ``bgn.studies.grid.run`` calls ``run_stages`` after its own report).

- **stability** (``preset.stability``): the hard cases of a stability preset
  (``conf/stability/preset/<preset>.yaml``, read through that config group) run by
  ``bgn.studies.stability`` with, per scene, the checkpoints of the grid's ``model`` cells at
  ``fps`` of every seed: each case simulated and checked once, every seed's model rolled out
  on it, the force scenes' references (frame oracle, predictability limit) once, the model
  rows as mean and spread over the seeds. No training of its own.
- **pareto** (``preset.pareto``): every main cell's rollout error after one simulated time
  unit (``pos_err_mean@fps``, a failed rollout at the cap) against its inference time per
  simulated time unit, both measured by the grid's own evaluation (``eval.json``:
  ``rollout/seconds_per_step``, the batched rollout of the test simulations), with the
  no-learning extrapolations and the exact simulator (timed here, ``simulator_repeats``) as
  references; the Pareto front per scene and its figure. No training, no rollout of its own.
  Training compute is the preset's step budget for every cell (``max_steps`` per scene and
  model, else the scene's default), so the front is against inference time only (the
  training-time front is ``bgn.studies.pareto``'s study); the table's notes state the
  budgets from the cells' records and name any cell that did not train its budget whole.
- **laws** (``preset.laws``): the pair law of every cell with a pair-force head read back and
  fitted as a formula, against the truth (``bgn.studies.laws_study``).

Each writes report.md, its tables (md, csv) and figures under ``<report_dir>/<stage>/`` with
the grid's provenance, and with ``results_md`` rewrites the block
``<!-- generated:<preset>_<stage>:begin/end -->`` of that file.
"""

from __future__ import annotations

import functools
import json
import math
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from bgn.coerce import ConfigError, need_int
from bgn.eval.columns import VARIANT_COLUMNS
from bgn.studies.cells import map_in_processes
from bgn.studies.laws_study import laws_stage, validate_laws
from bgn.studies.report import stage_provenance, write_stage
from bgn.tables import fmt, write_table

if TYPE_CHECKING:
    from bgn.studies.cells import Cell

STABILITY_KEYS = {"preset": "a stability preset (conf/stability/preset/<name>.yaml)",
                  "model": "the grid model whose cells are rolled out (one of preset.models)",
                  "fps": "the fps of those cells (one of preset.fps; null: the first)",
                  "seeds": "their seeds (a subset of preset.seeds; null: all)"}
PARETO_KEYS = {"simulator_repeats": "timed runs of the exact simulator per scene (median)"}
STAGES = ("stability", "pareto", "laws")  # laws: bgn.studies.laws_study


# ----------------------------------------------------------------------------- config
def stability_preset(name: str) -> DictConfig:
    """A stability preset composed through its config group (``conf/stability/preset/``, as
    ``python -m bgn.stability preset=<name>`` composes it: an alias's ``defaults`` too)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from bgn.studies.cells import CONF_DIR

    overrides = [f"stability/preset={name}"]
    try:
        if GlobalHydra.instance().is_initialized():  # inside the experiments app
            cfg = compose(config_name="stability/stability", overrides=overrides)
        else:
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                cfg = compose(config_name="stability/stability", overrides=overrides)
    except Exception as err:  # Hydra's: no such config, a bad yaml
        known = sorted(p.stem for p in (CONF_DIR / "stability" / "preset").glob("*.yaml"))
        raise ConfigError("preset.stability.preset", name,
                          f"not a stability preset (conf/stability/preset/; known: {known})"
                          ) from err
    return cfg.stability.preset


def _unknown(node: Any, known: dict[str, str], key: str) -> None:
    if not isinstance(node, DictConfig):
        raise ConfigError(key, node, "must be a mapping of " + ", ".join(known)
                          + " (or null: left out)")
    for k in node:
        if k not in known:
            raise ConfigError(f"{key}.{k}", node[k], "unknown key; known: "
                              + "; ".join(f"{n} ({what})" for n, what in known.items()))


def stability_fps(preset: DictConfig) -> float:
    st = preset.stability
    return float(st.get("fps") if st.get("fps") is not None else preset.fps[0])


def stability_seeds(preset: DictConfig) -> list[int]:
    from bgn.studies.cells import preset_seeds

    chosen = preset.stability.get("seeds")
    return preset_seeds(preset) if chosen is None else [int(s) for s in chosen]


def validate_stages(preset: DictConfig) -> None:
    """The ``stability``, ``pareto`` and ``laws`` keys of a grid preset (absent or null: a
    stage is left out): unknown keys and bad values raise one ``ConfigError`` naming the key."""
    from bgn.metrics import ROLLOUT_HORIZONS
    from bgn.studies.cells import preset_seeds

    st = preset.get("stability")
    if st is not None:
        _unknown(st, STABILITY_KEYS, "preset.stability")
        cases = stability_preset(str(st.get("preset"))).get("cases")
        if not cases:
            raise ConfigError("preset.stability.preset", st.get("preset"),
                              "the stability preset lists no cases")
        from bgn.studies.stability import load_case

        for case in cases:
            try:
                load_case(str(case))
            except ValueError as err:
                raise ConfigError("preset.stability.preset", st.get("preset"),
                                  message=f"preset.stability.preset={st.get('preset')}: {err}"
                                  ) from err
        if st.get("model") not in list(preset.models):
            raise ConfigError("preset.stability.model", st.get("model"),
                              f"must be one of preset.models {list(preset.models)}")
        fps = [float(f) for f in preset.fps]
        if st.get("fps") is not None and float(st.fps) not in fps:
            raise ConfigError("preset.stability.fps", st.fps,
                              f"must be one of preset.fps {list(preset.fps)} (or null)")
        seeds = st.get("seeds")
        if seeds is not None and (not seeds or not set(map(int, seeds))
                                  <= set(preset_seeds(preset))):
            raise ConfigError("preset.stability.seeds", list(seeds),
                              f"must be a subset of preset.seeds {preset_seeds(preset)} "
                              "(or null: all)")
    validate_laws(preset)
    pa = preset.get("pareto")
    if pa is not None:
        _unknown(pa, PARETO_KEYS, "preset.pareto")
        need_int(pa.get("simulator_repeats", 3), "preset.pareto.simulator_repeats", 1)
        steps = int(preset.eval.rollout_steps)
        for fps in preset.fps:
            h = steps_per_unit(float(fps))
            if h not in ROLLOUT_HORIZONS or h > steps:
                raise ConfigError(
                    "preset.pareto", None, message=(
                        f"preset.pareto: the error after one time unit at fps {fps} is "
                        f"pos_err_mean@{h}, which the evaluation reports only for horizons "
                        f"{list(ROLLOUT_HORIZONS)} up to preset.eval.rollout_steps={steps}"))


def steps_per_unit(fps: float) -> int:
    from bgn.studies.pareto import steps_per_unit as steps

    return steps(fps)


# ----------------------------------------------------------------------------- stability
def _stability_job(name: str, preset: dict[str, Any],
                   models: list[tuple[int, str, str]]) -> tuple[dict[str, Any],
                                                                list[dict[str, Any]]]:
    """One case: simulated and checked once, then every (seed, checkpoint, label) of its
    scene rolled out on it (the references with the first). Runs in a pool process."""
    from bgn.studies import stability as st

    cfg = OmegaConf.create(preset)
    case = st.load_case(name)
    try:
        case, scene, traj, row = st.simulate_case(case, cfg)
        rows = []
        for i, (seed, ckpt, label) in enumerate(models):
            model = _load(ckpt)  # model_checks rolls out a copy: one load per process
            for r in st.case_model_rows(case, scene, traj, row, model, label, cfg,
                                        references=i == 0):
                rows.append({"seed": seed, **r})
    except (ValueError, RuntimeError) as err:  # a broken case is reported, not fatal
        row = {"case": case.name, "scene": case.scene, "passed": False,
               "failed_checks": f"error: {err}", "energy_drift": float("nan")}
        rows = []
    return row, rows


@functools.lru_cache(maxsize=32)
def _load(ckpt: str) -> Any:
    from bgn.training.module import load_model

    return load_model(ckpt).model


def stability_models(cfg: DictConfig, cells: list[Cell], results: dict[str, Any],
                     ) -> dict[str, list[tuple[int, str, str]]]:
    """Per scene, (seed, checkpoint, label) of the grid's ``stability.model`` cells at
    ``stability.fps`` of the chosen seeds that trained and were evaluated."""
    from bgn.training.checkpoints import chosen_checkpoint

    preset, out = cfg.preset, {}
    seeds, fps = stability_seeds(preset), stability_fps(preset)
    for c in cells:
        if (c.model == preset.stability.model and c.fps == fps and c.seed in seeds
                and "main" in c.groups and c.name in results):
            ckpt = chosen_checkpoint(Path(cfg.cells_dir) / c.name)
            label = (results[c.name]["eval"].get("model") or {}).get("label", c.model)
            out.setdefault(c.scene, []).append((c.seed, str(ckpt), label))
    return out


def stability_stage(cfg: DictConfig, cells: list[Cell], results: dict[str, Any],
                    provenance: dict[str, Any], workers: int, threads: int | None) -> Path:
    """The stability suite on the grid's checkpoints (module doc); cases in ``workers``
    processes."""
    from bgn.studies import stability as st
    from bgn.studies.report import aggregate_rows, write_seeded_table

    t0 = time.perf_counter()
    spec = cfg.preset.stability
    sp = stability_preset(str(spec.preset))
    preset = OmegaConf.to_container(sp, resolve=True)
    cases = [st.load_case(str(n)) for n in sp.cases]
    models = stability_models(cfg, cells, results)
    jobs = [(c.name, preset, models.get(c.scene, [])) for c in cases]
    done = map_in_processes(_stability_job, jobs, workers, threads)
    for case, (row, _) in zip(cases, done):
        state = "ok" if row["passed"] else f"FAILED {row['failed_checks']}"
        print(f"  stability {case.name}: {state}", flush=True)
    sim_rows = [row for row, _ in done]
    model_rows = [r for _, rows in done for r in rows]
    for r in model_rows:  # numbers, so the mean over the seeds is the share that failed
        r["non_finite"] = float(not r.pop("finite"))
        r["left_scale"] = float(r["left_scale"])
    out = Path(cfg.report_dir) / "stability"
    out.mkdir(parents=True, exist_ok=True)
    n_failed = sum(not r["passed"] for r in sim_rows)
    sim_text = write_table(
        out, "simulator", st.SIM_COLUMNS, sim_rows,
        f"Stability: the simulator's checks on {len(cases)} hard cases "
        f"({n_failed} with a failed check)",
        "The exact trajectory of each case (`conf/stability/case/`), checked once: "
        "energy_drift max |E_t - E_0| / max(|E_0|, max kinetic energy); momentum_drift "
        "max |P_t - P_0| / sum |m v_0| (blank where walls exchange momentum); min_gap the "
        "smallest surface gap / mean radius (< 0: overlap); max_turns_per_frame and "
        "aliased_frames the fastest pair rotation per frame and the share of frames beyond "
        "what frames carry (n-body); transform_error of an offset or scaled case mapped back. "
        "Limits: " + ", ".join(f"{k} {v:g}" for k, v in st.LIMITS.items())
        + " (a case may set its own).")
    horizons = [f"error_{h}" for h in sp.horizons]
    columns = ["case", "scene", "model", "dtype", "steps", "non_finite", "left_scale",
               "aliased_frames", "one_step_rel_error", *horizons, "position_scale",
               "energy_error", "s_per_step"]
    given = {scene: sorted({s for s, _, _ in m}) for scene, m in models.items()}
    missing = sorted({c.scene for c in cases} - set(models))
    model_text = write_seeded_table(
        out, "model", columns, ["case", "scene", "model", "dtype"], model_rows,
        "Stability: model rollouts on the hard cases",
        f"The grid's `{spec.model}` cells at fps {fmt(stability_fps(cfg.preset))} (their "
        "chosen checkpoints; seeds per scene: "
        + (", ".join(f"{s} {v}" for s, v in given.items()) or "none")
        + (f"; no cell for: {', '.join(missing)}" if missing else "") + "), each rolled out "
        "once from the first full window (frame k+1) of each case's true trajectory, through "
        "the learned simulator. one_step_rel_error: RMS target error / RMS target over "
        "several starts; error_h: mean position error per particle after h steps; "
        "energy_error: |E_end - E_start| / |E_start| (finite-difference velocities); "
        "non_finite, left_scale: 1 where the rollout went non-finite or a particle left 10 "
        "scene scales (the evaluation's failure rule), so their mean is the share of seeds "
        "that failed. Force scenes also have the frame oracle (the true law and masses fed "
        "the same frames) and the predictability limit (the exact simulator 1e-6 off), "
        "which learn nothing (one row).",
        empty="(no model cells: the simulator's checks only)")
    st.figure(out / "stability.png", sim_rows,
              aggregate_rows(model_rows, ["case", "scene", "model", "dtype"]))
    (out / "results.json").write_text(json.dumps({"simulator": sim_rows, "model": model_rows},
                                                 indent=1, default=str))
    now = time.perf_counter()
    return write_stage(
        out, "stability", f"Stability suite on the `{cfg.preset.name}` cells",
        [f"Stability preset `{spec.preset}` (`conf/stability/preset/{spec.preset}.yaml`): "
         f"{len(cases)} cases, the model rows from the grid's trained cells."],
        [sim_text, model_text], ["stability.png"],
        stage_provenance(provenance, now - t0), cfg.get("results_md"))


# ----------------------------------------------------------------------------- pareto
PARETO_KEYS_ROW = ["scene", "fps", "model", *VARIANT_COLUMNS, "on front"]
PARETO_VALUES = ["rollout_error", "seconds_per_time_unit", "failed_share", "nmse",
                 "parameters", "cell_minutes"]
INFERENCE = "seconds_per_time_unit"


def pareto_points(cfg: DictConfig, cells: list[Cell], results: dict[str, Any],
                  ) -> list[dict[str, Any]]:
    """Per seed, every main cell's point and (from the first cell of each scene x fps) the
    no-learning extrapolations', from the grid's eval.json and metrics.json."""
    from bgn.studies.report import NOTHING, REFERENCES, evaluation, training, variant
    from bgn.training.checkpoints import chosen_checkpoint
    from bgn.training.module import load_model

    rows = []
    main = [c for c in cells if "main" in c.groups and c.name in results]
    for scene, fps in dict.fromkeys((c.scene, c.fps) for c in main):
        group = [c for c in main if (c.scene, c.fps) == (scene, fps)]
        h = steps_per_unit(fps)
        sources = [(variant(results, c), c, "rollout") for c in group]
        sources += [({"model": f"{ref} extrapolation", **NOTHING}, group[0], f"rollout_{ref}")
                    for ref in REFERENCES]
        for about, c, key in sources:
            m = evaluation(results, c)
            if m.get(f"{key}/pos_err_mean@{h}") is None:  # collisions: no linear extrapolation
                continue
            row = {"seed": c.seed, "scene": scene, "fps": fps, **about,
                   "rollout_error": m.get(f"{key}/pos_err_mean@{h}"),
                   INFERENCE: m.get(f"{key}/seconds_per_step", math.nan) * fps,
                   "failed_share": m.get(f"{key}/failed_share")}
            if key == "rollout":
                model = load_model(chosen_checkpoint(Path(cfg.cells_dir) / c.name)).model
                row.update(nmse=m.get("nmse"),
                           parameters=sum(p.numel() for p in model.parameters()),
                           cell_minutes=training(results, c).get("wall_time_s", math.nan) / 60)
            rows.append(row)
    return rows


def mark_fronts(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``on front`` of every per-seed row: whether its model's mean over the seeds is on the
    scene x fps Pareto front of mean error against mean inference time; returns the means."""
    from bgn.studies.pareto import pareto_front
    from bgn.studies.report import aggregate_rows

    keys = ["scene", "fps", "model"]
    means = aggregate_rows(rows, keys)
    on = set()
    for scene, fps in dict.fromkeys((m["scene"], m["fps"]) for m in means):
        pts = [m for m in means if (m["scene"], m["fps"]) == (scene, fps)
               and m["rollout_error"] is not None and math.isfinite(m[INFERENCE])]
        on |= {(scene, fps, p["model"]) for p in pareto_front(pts, INFERENCE)}
    for r in [*rows, *means]:
        r["on front"] = "yes" if (r["scene"], r["fps"], r["model"]) in on else "no"
    return means


def training_budget(cells: list[Cell], results: dict[str, Any]) -> str:
    """The sentence on what the cells trained, from their records (metrics.json's
    ``budget``): the step budget per scene and model, and every cell that fell short of it
    named (``bgn.studies.cells.shortfall``: cut by the wall-clock cap, or stopped early on
    its own); "every cell trained its step budget" only where that holds."""
    from bgn.studies.cells import cut_by_cap, shortfall
    from bgn.studies.report import cut_cells

    trained = [c for c in cells if c.name in results]
    steps: dict[str, dict[str, list[str]]] = {}
    for c in trained:
        top = (results[c.name]["train"].get("budget") or {}).get("max_steps")
        label = "not recorded" if top is None else str(top)
        shown = steps.setdefault(c.scene, {}).setdefault(c.model, [])
        if label not in shown:  # one value where every seed was given the same
            shown.append(label)
    budgets = "; ".join(f"{scene}: " + ", ".join(f"{m} {'/'.join(v)}" for m, v in models.items())
                        for scene, models in steps.items())
    given = (f"trainer.max_steps per scene and model, as each cell's metrics.json records it: "
             f"{budgets}; cell_minutes: the cell's whole run, where the preset sets the "
             "budgets to equal wall time")
    cut = cut_cells(trained, results)
    early = [f"{c.name} ({why})" for c in trained
             if not cut_by_cap(record := results[c.name]["train"]) and (why := shortfall(record))]
    if not cut and not early:
        return (f"Every cell trained its step budget ({given}), so training compute is not "
                "an axis here.")
    text = f"Each cell was given its step budget ({given}), but not every cell trained it:"
    if cut:
        text += (" the wall-clock cap (trainer.max_time) cut " + "; ".join(cut) + ", so "
                 "those rows depend on the machine's load (a rerun of the command continues "
                 "them)" + (";" if early else "."))
    if early:
        text += (" stopped before it by early stopping or trainer.max_epochs (the same on "
                 "any machine): " + "; ".join(early) + ".")
    return text


def pareto_stage(cfg: DictConfig, cells: list[Cell], results: dict[str, Any],
                 provenance: dict[str, Any]) -> Path:
    """Speed against error from the grid's cells (module doc)."""
    import torch

    from bgn.figures import pareto, save
    from bgn.studies.pareto import simulator_seconds, test_split
    from bgn.studies.report import write_seeded_table

    t0 = time.perf_counter()
    repeats = int(cfg.preset.pareto.get("simulator_repeats", 3))
    out = Path(cfg.report_dir) / "pareto"
    out.mkdir(parents=True, exist_ok=True)
    rows = pareto_points(cfg, cells, results)
    means = mark_fronts(rows)
    simulator = []
    for scene, fps in dict.fromkeys((r["scene"], r["fps"]) for r in rows):
        cell = next(c for c in cells if (c.scene, c.fps) == (scene, fps) and c.name in results)
        test = test_split(Path(cfg.cells_dir) / cell.name, cfg.paths.data_dir)
        simulator.append({"scene": scene, "fps": fps, "N": test.meta.n_particles,
                          INFERENCE: simulator_seconds(test, fps, repeats)})
    for r in [*rows, *simulator, *means]:
        r["fps"] = fmt(r["fps"])
    points = write_seeded_table(
        out, "points", [*PARETO_KEYS_ROW, *PARETO_VALUES], PARETO_KEYS_ROW, rows,
        "Speed against error (the grid's cells)",
        "rollout_error: mean position error per particle after one simulated time unit (fps "
        "steps), mean over all test rollouts of the grid's evaluation, a failed one at the "
        "cap (pos_err_mean@fps of the rollout table). seconds_per_time_unit: wall time of "
        "rolling one scene out for one simulated time unit, measured in that evaluation (the "
        "test simulations rolled out together, the time divided among them; "
        f"{provenance.get('threads_per_worker')} torch thread(s) per cell, "
        f"{provenance.get('workers')} cell(s) at once). on front: the model's mean over the "
        "seeds is on the scene's Pareto front of error against inference time (no model is "
        "both faster and more accurate). "
        f"{training_budget([c for c in cells if 'main' in c.groups], results)} "
        "The extrapolations learn nothing (one seed's cell); "
        "parameters: the trained model's.")
    sim_text = write_table(
        out, "simulator", ["scene", "fps", "N", INFERENCE], simulator,
        "The exact simulator (error zero)",
        f"Wall time per simulated time unit from the state before the first test "
        f"simulation's reference start, median of {repeats} runs ({torch.get_num_threads()} "
        "torch threads, after the cells).")
    figures = []
    for scene in dict.fromkeys(r["scene"] for r in means):
        pts = [m for m in means if m["scene"] == scene and m["rollout_error"] is not None]
        front = [p for p in pts if p["on front"] == "yes"]
        sim = {float(s["fps"]): s[INFERENCE] for s in simulator if s["scene"] == scene}
        save(pareto(pts, {INFERENCE: sorted(front, key=lambda p: p[INFERENCE])},
                    {INFERENCE: "inference s per simulated time unit"},
                    lambda p: f"{p['model']} fps{p['fps']}", sim,
                    f"{scene}: mean over seeds ({cfg.preset.name})"),
             out / f"pareto_{scene}.png")
        figures.append(f"pareto_{scene}.png")
    now = time.perf_counter()
    return write_stage(
        out, "pareto", f"Speed against error: the `{cfg.preset.name}` cells",
        ["Every point from the grid's own evaluation of its cells (no training or rollout of "
         "this stage); the figures show the means over the seeds."],
        [points, sim_text], figures, stage_provenance(provenance, now - t0),
        cfg.get("results_md"))


# ----------------------------------------------------------------------------- command
def run_stages(cfg: DictConfig, cells: list[Cell], results: dict[str, Any],
               provenance: dict[str, Any], workers: int, threads: int | None) -> list[str]:
    """The preset's stages after the grid's report; returns the names of those that failed
    (their traceback printed; the others still run)."""
    failed = []
    for stage in STAGES:
        if cfg.preset.get(stage) is None:
            continue
        print(f"[{stage}] from the grid's cells", flush=True)
        try:
            if stage == "stability":
                path = stability_stage(cfg, cells, results, provenance, workers, threads)
            elif stage == "laws":
                path = laws_stage(cfg, cells, results, provenance, workers, threads)
            else:
                path = pareto_stage(cfg, cells, results, provenance)
            print(f"  report: {path}", flush=True)
        except Exception:
            traceback.print_exc()
            print(f"  FAILED: stage {stage}", flush=True)
            failed.append(f"stage {stage}")
    return failed
