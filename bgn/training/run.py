"""Train a model on a scene (the body of ``python -m bgn.train [dataset=spring] [fps=50] ...``,
whose command line is ``bgn/train/__main__.py``).

Generates the dataset on first use, trains with Lightning, evaluates the best checkpoint on
the test split and writes ``metrics.json`` in the run directory (sweeps gather these into a
summary table). The run's full config is saved by Hydra in ``<run>/.hydra/config.yaml``;
``python -m bgn.train --config-path <run>/.hydra --config-name config`` reproduces it.

Config: ``model`` (the model's options, typed by its dataclass: ``bgn.training.config``),
``optimizer`` and ``scheduler`` (Hydra partials, instantiated here and handed to
``PhysicsModule``), and ``dataset_model`` (a scene's own model defaults,
``conf/dataset_model/<scene>_<model>.yaml``).
Messages go through ``logging`` from the rank-zero process only (DDP runs one process per
device, each running this module).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from bgn.training.budget import Deadline, check
from bgn.training.checkpoints import (
    check_compatible,
    provenance,
    resolve_last,
    write_atomic,
)
from bgn.training.config import register_configs
from bgn.training.validate import validate_train

if TYPE_CHECKING:  # Lightning and the data and model modules load when they are used, so
    # that bad input is refused (bgn.training.validate) before the seconds their import takes
    from bgn.data.datamodule import ParticleDataModule
    from bgn.data.spec import DatasetSpec
    from bgn.training.module import PhysicsModule

register_configs()  # the schemas (bgn.training.config), before Hydra composes conf/train.yaml

# model.law=auto's stage (bgn.laws.stage.law_stage): (cfg, best checkpoint, datamodule, run
# directory, world size, deadline=the job's Deadline) -> its record, "choice" the law kept
# (the one that validates better; the network law where the cap stopped the comparison)
LawStage = Callable[..., dict[str, Any]]

log = logging.getLogger("bgn.train")  # not __main__ under python -m bgn.train

# The share of the job's time left when the fit starts that it keeps for what follows: the
# test, and with model.law=auto the formula stage. Only a cap: a default job ends on its
# step budget well before (docs/design.md#budgets).
RESERVE_SHARE = {"test": 0.1, "law": 0.25}

# Keys of the scheduler config that tell Lightning how to step it (its lr_scheduler config);
# the rest of the node is the scheduler's partial.
LIGHTNING_SCHEDULER_KEYS = ("monitor", "interval", "frequency", "strict", "name")


def info(message: str) -> None:
    """Log once per run, from the rank-zero process (not once per DDP process)."""
    from lightning.pytorch.utilities import rank_zero_only

    rank_zero_only(log.info)(message)


def plain_stats(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {g: {k: np.asarray(v).tolist() for k, v in entries.items()}
            for g, entries in stats.items()}


# simulations per training batch under mass_law=coupling: the batch's windows of one
# simulation are what its couplings are fitted to
COUPLING_SIMS_PER_BATCH = 2


def data_module(cfg: DictConfig, spec: DatasetSpec | None = None) -> ParticleDataModule:
    """The DataModule of a composed config (nothing generated or read yet). ``spec``: the
    one ``validate_train(cfg)`` returned, where the caller validated ``cfg`` already;
    without it, bad values fail here, before any data are generated."""
    from bgn.data.datamodule import ParticleDataModule

    if spec is None:
        spec = validate_train(cfg)
    # dataset.generate_workers: simulation processes when the data are generated here
    # (default one per core; 1 generates in this process)
    # a head that fits couplings per simulation over a batch's windows needs many windows of
    # each simulation in a batch (bgn.model.newton, mass_law=coupling)
    coupling = cfg.model.get("mass_law") == "coupling" and (
        cfg.model.get("dynamics", "newton") == "newton")
    return ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir,
                              generate_workers=cfg.dataset.get("generate_workers"), spec=spec,
                              sims_per_batch=COUPLING_SIMS_PER_BATCH if coupling else None)


def run_provenance(cfg: DictConfig, datamodule: ParticleDataModule) -> dict[str, Any]:
    """What this run's checkpoints record of it (``bgn.training.checkpoints.provenance``)."""
    spec = datamodule.spec
    train = datamodule.datasets.get("train")
    return provenance(spec.scene, spec.generating_config()["params"], spec.fps,
                      str(cfg.model.get("name", "bgn")), datamodule.history,
                      0.0 if train is None else train.margin)


def build(cfg: DictConfig, datamodule: ParticleDataModule | None = None,
          ) -> tuple[ParticleDataModule, PhysicsModule]:
    """DataModule (data generated if missing) and LightningModule from a composed config."""
    from bgn.rollout import rollout, rollout_error

    datamodule = datamodule or data_module(cfg)
    datamodule.prepare_data()
    datamodule.setup()
    rollout_fn = None
    if cfg.figures and cfg.rollout_steps > 0:
        rollout_fn = partial(rollout, dataset=datamodule.datasets["val"], sim=0,
                             n_steps=int(cfg.rollout_steps))
    error_fn = None
    if cfg.val_rollout_steps > 0:
        error_fn = partial(rollout_error, dataset=datamodule.datasets["val"],
                           n_sims=int(cfg.val_rollout_sims), n_steps=int(cfg.val_rollout_steps))
    module = build_module(cfg, dict(vars(datamodule.meta)), plain_stats(datamodule.stats()),
                          datamodule.history, rollout=rollout_fn, rollout_error=error_fn,
                          provenance=run_provenance(cfg, datamodule))
    return datamodule, module


def build_module(cfg: DictConfig, meta: dict[str, Any], stats: dict[str, Any], history: int,
                 rollout: Any = None, rollout_error: Any = None,
                 provenance: dict[str, Any] | None = None) -> PhysicsModule:
    """The LightningModule of a composed config: the model from ``cfg.model``, the optimiser
    and scheduler partials from ``cfg.optimizer`` and ``cfg.scheduler``."""
    from bgn.training.module import PhysicsModule

    model_config = OmegaConf.to_container(cfg.model, resolve=True)
    optimizer = scheduler = scheduler_config = None
    if cfg.get("optimizer") is not None:
        optimizer = instantiate(cfg.optimizer, _convert_="all")
    if cfg.get("scheduler") is not None:
        node = OmegaConf.to_container(cfg.scheduler, resolve=True)
        scheduler_config = {k: node.pop(k) for k in LIGHTNING_SCHEDULER_KEYS if k in node}
        scheduler = instantiate(node, _convert_="all")
    return PhysicsModule(model_config, meta, stats, history, optimizer=optimizer,
                         scheduler=scheduler, scheduler_config=scheduler_config,
                         figures=bool(cfg.figures), rollout=rollout,
                         rollout_error=rollout_error,
                         animation_every=int(cfg.animation_every),
                         provenance=provenance)


def resume_target(cfg: DictConfig) -> tuple[Path, list[str]]:
    """The run a resume command names: this config's run directory and the overrides of the
    command that started it (Hydra's; none outside a Hydra run)."""
    overrides: list[str] = []
    if HydraConfig.initialized():
        overrides = list(HydraConfig.get().overrides.task)
    return Path(cfg.paths.output_dir), overrides


def steps_per_epoch(cfg: DictConfig, datamodule: ParticleDataModule) -> int:
    """Optimiser steps in one epoch of the training split (one process)."""
    return max(1, math.ceil(len(datamodule.datasets["train"]) / int(cfg.dataset.batch_size)))


def check_step_budget(cfg: DictConfig, datamodule: ParticleDataModule) -> None:
    """Refuse a step budget that trains nothing; warn where it ends before the first
    validation (Lightning's ``val_check_interval`` / ``check_val_every_n_epoch``): the run
    is then validated once, at its end, so the learning-rate schedule and early stopping
    never act."""
    from bgn.coerce import ConfigError

    steps = cfg.trainer.get("max_steps")
    if steps is None or int(steps) < 0:
        return
    if int(steps) == 0:
        raise ConfigError("trainer.max_steps", 0, "trains nothing: set a number of optimiser "
                          "steps >= 1 (or -1: no step limit)")
    epoch = steps_per_epoch(cfg, datamodule)
    interval = cfg.trainer.get("val_check_interval")
    if isinstance(interval, int) and not isinstance(interval, bool) and interval > 1:
        first = interval
    else:
        every = int(cfg.trainer.get("check_val_every_n_epoch") or 1)
        first = math.ceil(float(interval or 1.0) * epoch) * every
    if int(steps) < first:
        log.warning("trainer.max_steps=%d ends the run before its first validation (at step "
                    "%d; an epoch is %d steps): it is validated once, at its end, so early "
                    "stopping and the learning-rate schedule never act", int(steps), first,
                    epoch)


def job_cap(cfg: DictConfig) -> float | None:
    """``trainer.max_time`` in seconds (None: no cap); a value Lightning cannot read is
    refused in one line."""
    from bgn.coerce import ConfigError, seconds

    value = cfg.trainer.get("max_time")
    try:
        cap = seconds(value)
    except (TypeError, ValueError):
        raise ConfigError("trainer.max_time", value, 'must be "DD:HH:MM:SS", timedelta fields '
                          "({minutes: 40}) or null (no cap)") from None
    if cap is not None and cap <= 0:
        raise ConfigError("trainer.max_time", value, "must be a positive time, or null")
    return cap


def set_threads(threads: Any) -> None:
    """torch's CPU threads for this job (``threads``; null: torch's default)."""
    from bgn.coerce import need_int

    n = need_int(threads, "threads", 1, optional=True,
                 why=": torch's CPU threads (null: one per core)")
    if n is not None:
        import torch

        torch.set_num_threads(n)


def fit_reserve(cfg: DictConfig, left: float | None) -> float:
    """Seconds of the job's time left at the fit's start kept for what follows it: the test
    and, with ``model.law=auto``, the formula stage (``RESERVE_SHARE``)."""
    if left is None:
        return 0.0
    share = RESERVE_SHARE["law"] if cfg.model.get("law") == "auto" else RESERVE_SHARE["test"]
    return share * left if cfg.test or cfg.model.get("law") == "auto" else 0.0


def train(cfg: DictConfig, spec: DatasetSpec | None = None,
          law_stage: LawStage | None = None, deadline: Deadline | None = None, *,
          run_dir: Path | None = None, overrides: list[str] | None = None,
          closing: bool = True) -> dict[str, float]:
    """Fit, test, and write metrics.json; returns the final metrics. ``spec``: as
    ``data_module``'s (``cfg`` validated already). ``law_stage``: with ``model.law=auto``,
    what reads the best checkpoint's law back as a formula and chooses between the two on
    validation, before the test and with ``test=false`` too (``bgn.laws.stage.law_stage``;
    handed in by the commands above this stage).

    ``deadline``: the whole job's wall-clock cap (docs/design.md#budgets; default
    ``trainer.max_time`` from now). The data are generated inside it; the fit stops at it
    less a reserve for the formula stage and the test (``fit_reserve``), the formula stage
    and the test check it; a run it cut says so (a warning, ``budget.cut_by`` in
    metrics.json). ``run_dir`` and ``overrides``: the run a signal's resume command names
    (default ``resume_target``; ``model.dynamics=auto`` passes its own run, not the
    candidate's folder). ``closing``: end with the closing summary (``summary``); auto's fits
    leave it to the job, whose summary states the whole job's time."""
    import lightning as L

    from bgn.coerce import ConfigError
    from bgn.training.budget import OutOfTime, clock_text, deferred, received, watch_signals
    from bgn.training.calibrate import calibrate_checkpoint, soft_contact_head
    from bgn.training.signals import FitDeadline, SignalCheckpoint, interrupted

    if cfg.model.get("dynamics") == "auto":  # candidates are composed from the overrides
        raise ValueError("model.dynamics=auto is a study of several trainings: run it with "
                         "python -m bgn.train, or bgn.studies.auto.run_auto(cfg, overrides)")
    # (a fast_dev_run writes no checkpoint: it has no law to read back)
    if cfg.model.get("law") == "auto" and law_stage is None \
            and not cfg.trainer.get("fast_dev_run"):
        raise ValueError("model.law=auto needs the formula stage: run python -m bgn.train, or "
                         "pass law_stage=bgn.laws.stage.law_stage")
    start = time.perf_counter()
    if deadline is None:
        deadline = Deadline.after(job_cap(cfg))
    watch_signals()  # idempotent: the command installed it already
    set_threads(cfg.get("threads"))
    default_dir, default_overrides = resume_target(cfg)
    run_dir = default_dir if run_dir is None else Path(run_dir)
    overrides = default_overrides if overrides is None else list(overrides)
    L.seed_everything(int(cfg.seed), workers=True)
    output_dir = Path(cfg.paths.output_dir)
    info(f"run directory: {output_dir}")
    datamodule = data_module(cfg, spec)
    checkpoint_dir = output_dir / "checkpoints"
    ckpt_path = resolve_last(cfg.get("ckpt_path"), checkpoint_dir)
    if cfg.get("ckpt_path") == "last":
        info(f"resuming from {ckpt_path}" if ckpt_path
             else f"ckpt_path=last: no last.ckpt in {checkpoint_dir} yet, starting afresh")
    if ckpt_path:  # before any data is generated: another scene or model is refused here
        check_compatible(ckpt_path, run_provenance(cfg, datamodule),
                         OmegaConf.to_container(cfg.model, resolve=True))
    stop = SignalCheckpoint(checkpoint_dir)
    phase = "data preparation"
    trainer: L.Trainer | None = None
    law_record: dict[str, Any] = {}
    law_match: dict[str, Any] | None = None
    calibration: dict[str, Any] | None = None
    tested_note = ""
    fit_deadline = FitDeadline(deadline, deadline)
    try:
        datamodule, module = build(cfg, datamodule)
        if deadline.passed():  # nothing could be learned: one line, the data are cached
            raise ConfigError("trainer.max_time", cfg.trainer.get("max_time"),
                              message=f"trainer.max_time={cfg.trainer.get('max_time')} was "
                              "spent before training began ("
                              f"{clock_text(time.perf_counter() - start)} preparing the data, "
                              "which are kept for the next run): raise trainer.max_time")
        check_step_budget(cfg, datamodule)
        coder = module.model.target_coder  # what target_prior=auto and dynamics_loss=auto chose
        info(f"dynamics target: prior={coder.prior_name}, loss={coder.loss_name}")
        # a group entry set to null (callbacks.early_stopping=null) switches that callback off
        callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c]
        fit_deadline = FitDeadline(deadline.less(fit_reserve(cfg, deadline.left())), deadline)
        loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c]
        trainer = instantiate(cfg.trainer, callbacks=[*callbacks, stop, fit_deadline],
                              logger=loggers)
        phase = "training"
        with deferred():  # SIGTERM: Lightning stops between batches, SignalCheckpoint saves
            trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
        check(None, "training")  # a SIGTERM Lightning did not act on (it raises, as a rule)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
        law_match = module.law_match  # force matching (law_init=match) of this fit
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback \
            and not trainer.interrupted else ""
        if best and Path(best).resolve().parent != checkpoint_dir.resolve():
            # restored with a checkpoint copied from another run (auto's formula candidate):
            # that run's best, not this one's; with no best of its own, the weights it has
            best = ""
        if best and cfg.model.get("contact_calibration") == "rollout" \
                and soft_contact_head(module.model) is not None:
            # the soft-contact head's dissipation, set on training rollouts (written into
            # the best checkpoint, which the test, the formula stage and bgn.load read)
            phase = "the contact calibration"
            if deadline.passed():
                log.warning("the contact calibration was not run: the job reached its "
                            "wall-clock cap (trainer.max_time)")
            else:
                calibration = calibrate_checkpoint(Path(best), datamodule.datasets["train"])
        tested, tested_ckpt = module, best or None
        # model.law=auto: the formula stage chooses on validation (train and val splits
        # only), so it runs with test=false too; the test below scores what it chose
        if cfg.model.get("law") == "auto" and best:
            phase = "the formula stage"
            law_record = law_stage(cfg, Path(best), datamodule, output_dir,
                                   trainer.world_size, deadline=deadline)
            if law_record.get("choice") == "formula":
                from bgn.training.module import load_model

                tested, tested_ckpt = load_model(law_record["path"]), None
        if not cfg.test and law_record:
            info(f"test=false: the {law_record.get('choice')} law is chosen, not tested")
        if cfg.test and not trainer.interrupted:
            phase = "the test"
            try:
                if deadline.passed():
                    raise OutOfTime("the test was not started: the job reached its "
                                    "wall-clock cap (trainer.max_time)")
                with deferred():  # Lightning checks SIGTERM between test batches
                    trainer.test(tested, datamodule=datamodule, ckpt_path=tested_ckpt,
                                 weights_only=True)
                metrics.update({k: float(v) for k, v in trainer.callback_metrics.items()})
                if cfg.test_rollouts and trainer.is_global_zero:  # the product, batched
                    from bgn.rollout import test_rollouts

                    check(deadline, "the test")
                    info("test rollouts: every test simulation, 100 steps, beside the "
                         "no-learning references")
                    metrics.update(test_rollouts(tested.model, datamodule.datasets["test"]))
            except OutOfTime as err:  # the run stays usable: its checkpoints are written
                tested_note = f"{err}; python -m bgn.evaluate {run_dir} tests it"
                log.warning(tested_note)  # (what the test finished before is kept)
        module = tested  # the run's model: the law the stage chose, tested or not
    except (SystemExit, KeyboardInterrupt) as exc:  # SIGTERMException is a SystemExit
        name = stop.signal or received() or \
            ("SIGINT" if isinstance(exc, KeyboardInterrupt) else None)
        if name is None:
            raise
        where = "" if trainer is None or phase != "training" else \
            f"at epoch {trainer.current_epoch}, step {trainer.global_step}"
        raise interrupted(name, run_dir, overrides, phase=phase, where=where,
                          saved=stop.saved, checkpoint_dir=checkpoint_dir,
                          log_it=trainer is None or trainer.is_global_zero) from None
    assert trainer is not None
    metrics["wall_time_s"] = time.perf_counter() - start
    budget = budget_record(cfg, trainer, fit_deadline, law_record, tested_note)
    if budget["cut_by"]:
        log.warning(cut_warning(budget, cfg))
    if not trainer.is_global_zero:  # DDP: one process writes the run's record
        return metrics
    record = {"metrics": metrics, "overrides": dict(o.split("=", 1) for o in overrides
                                                    if "=" in o),
              "dataset": cfg.dataset.scene, "fps": float(datamodule.spec.fps),
              "model": module.model.name, "budget": budget,
              "variant": module.model.describe()}  # label, given, physics written in
    if law_match:
        record["law_match"] = law_match
    if calibration:
        record["calibration"] = calibration
    if law_record:  # model.law=auto: which law was tested, and the validation behind it
        record["law"] = {k: law_record.get(k) for k in ("choice", "tuned", "validation",
                                                        "rollout_substeps", "path", "report",
                                                        "budget")}
    write_atomic(output_dir / "metrics.json", json.dumps(record, indent=2, sort_keys=True))
    if closing:
        info(summary(record, output_dir))
    return metrics


def budget_record(cfg: DictConfig, trainer: Any, fit: Any, law_record: dict[str, Any],
                  tested_note: str = "") -> dict[str, Any]:
    """metrics.json's ``budget``: the step budget, the steps trained, and what the wall-clock
    cap cut (``cut_by``: ``"max_time"`` where it ended the fit, the formula stage or the
    test before their work was done; null otherwise)."""
    from bgn.coerce import seconds
    from bgn.training.signals import timer_ran_out

    steps = cfg.trainer.get("max_steps")
    cut = fit.cut or timer_ran_out(trainer)
    parts = [p for p, hit in (("training", cut),
                              ("formula stage", (law_record.get("budget") or {}).get("cut_by")),
                              ("test", bool(tested_note))) if hit]
    return {"max_steps": None if steps is None or int(steps) < 0 else int(steps),
            "steps": int(trainer.global_step), "max_time_s": seconds(cfg.trainer.get("max_time")),
            "cut_by": "max_time" if parts else None, "cut": parts}


def cut_warning(budget: dict[str, Any], cfg: DictConfig) -> str:
    """The warning of a run the wall-clock cap cut short."""
    steps = f"{budget['steps']}" + (f" of its {budget['max_steps']} steps"
                                    if budget["max_steps"] else " steps")
    return (f"trainer.max_time={cfg.trainer.get('max_time')} cut this run short ("
            f"{', '.join(budget['cut'])}; trained {steps}): its model is not the one the same "
            "command trains on a faster or idler machine; raise trainer.max_time to let it "
            "finish")


def _g(value: Any) -> str:
    return "-" if value is None else f"{float(value):.3g}"


def law_verdict(law: dict[str, Any]) -> str:
    """What model.law=auto's formula stage decided (its record, ``finetune_formula``'s), as
    its log line and the closing summary say it: the law that validates better, or, where
    the job's wall-clock cap stopped the validation rollouts (``validation`` empty), the
    network law kept with nothing compared; where no formula fits the learned law (the law
    search's outcome), the network law kept for that reason."""
    if law.get("outcome") == "no formula fits":
        frames = (" nor fitted to the frames explains them as well as it"
                  if law.get("frames") else "")
        return (f"no formula fits the learned law within {law.get('tolerance')}{frames}: the "
                "network law kept")
    cut = "the validation rollouts" in ((law.get("budget") or {}).get("cut") or [])
    if cut or not law.get("validation"):
        return "the network law kept: the formula was not compared (trainer.max_time)"
    return f"the {law.get('choice')} law validates better and is the run's model"


def auto_job(auto: dict[str, Any], metrics: dict[str, Any]) -> str:
    """The parts of a ``model.dynamics=auto`` job that ran, as the closing summary names
    them: the candidates that trained (kept from an earlier attempt or not), the formula
    candidate where it was fitted and scored, the winner's continuation where it ran and its
    test where it was tested."""
    status = auto.get("status") or {}
    ran = [n for n, s in status.items() if not n.startswith("formula_")
           and (s == "trained" or s.startswith("not scored"))]
    parts = [f"{len(ran)} candidate{'s' * (len(ran) != 1)}" if ran
             else "no candidate trained"]
    if any(s == "trained" for n, s in status.items() if n.startswith("formula_")):
        parts.append("the formula candidate")
    if auto.get("continued"):
        tested = any(k.startswith("test/") for k in metrics)
        parts.append("the winner's continuation" + (" and its test" if tested else ""))
    kept = f"; {', '.join(auto['kept'])} kept from an earlier attempt" if auto.get("kept") \
        else ""
    return ", ".join(parts) + kept


def summary(record: dict[str, Any], output_dir: Path) -> str:
    """The closing lines of ``python -m bgn.train``: what was trained (and chosen), its
    steps and time, whether the cap cut it, the test rollouts beside the no-learning
    references, the one-step test NMSE, where the run and its reports are, and the next
    command. metrics.json holds every figure."""
    m, budget = record["metrics"], record["budget"]
    label = (record.get("variant") or {}).get("label") or record["model"]
    steps = f"{budget['steps']} steps" + (f" of {budget['max_steps']}"
                                          if budget.get("max_steps") else "")
    cut = f", CUT SHORT by trainer.max_time ({', '.join(budget['cut'])})" \
        if budget.get("cut_by") else ""
    auto = record.get("auto")  # model.dynamics=auto: wall_time_s is the whole job's
    job = "the whole job" if not auto else f"the whole job: {auto_job(auto, m)}"
    lines = [f"trained {label}: {steps} in {_clock(m.get('wall_time_s', 0.0))} ({job}){cut}"]
    if auto:
        why = "not by evidence: no candidate could be compared" if auto.get("fallback") \
            else "on validation rollouts"
        lines.append(f"model.dynamics=auto chose {auto['choice']} {why} (report: "
                     f"{auto['report']})")
    law = record.get("law")
    if law:
        lines.append(f"law: {law_verdict(law)} (report: {law.get('report')})")
    horizons = [h for h in (10, 50, 100) if f"test/rollout_error@{h}" in m]
    if horizons:
        h = horizons[-1]
        errors = ", ".join(f"{k} steps {_g(m[f'test/rollout_error@{k}'])}" for k in horizons)
        refs = ", ".join(f"{name} {_g(m[f'test/rollout_error@{h}_{name}'])}"
                         for name in ("last", "linear", "predictability")
                         if f"test/rollout_error@{h}_{name}" in m)
        lines.append(f"test rollouts, position error (mean, a failed rollout at the cap): "
                     f"{errors} (median after {h}: "
                     f"{_g(m.get(f'test/rollout_error_median@{h}'))}, failed "
                     f"{100 * m.get('test/rollout_failed_share', 0.0):.0f} %)"
                     + (f"; no learning after {h} steps: {refs}" if refs else ""))
    if "test/nmse" in m:
        lines.append(f"one-step test NMSE {_g(m['test/nmse'])}")
    elif not horizons:
        lines.append("not tested (test=false, or the cap reached first): python -m "
                     f"bgn.evaluate {output_dir} tests it")
    lines.append(f"run: {output_dir} (metrics.json, " + (
        f"auto/report.md, the model's checkpoints in auto/{auto['choice']}/)" if auto
        else "checkpoints/)"))
    lines.append(f"next: python -m bgn.evaluate {output_dir}   # the full report: "
                 "rollouts, references, inverse, figures")
    return "\n".join(lines)


def _clock(value: float) -> str:
    from bgn.training.budget import clock_text

    return clock_text(value)
