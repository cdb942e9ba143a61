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
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

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

# model.law=auto's stage (bgn.eval.laws.law_stage): (cfg, best checkpoint, datamodule, run
# directory, world size) -> its record, "choice" the law that validates better
LawStage = Callable[[DictConfig, Path, "ParticleDataModule", Path, int], dict[str, Any]]

log = logging.getLogger("bgn.train")  # not __main__ under python -m bgn.train

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


def data_module(cfg: DictConfig, spec: DatasetSpec | None = None) -> ParticleDataModule:
    """The DataModule of a composed config (nothing generated or read yet). ``spec``: the
    one ``validate_train(cfg)`` returned, where the caller validated ``cfg`` already;
    without it, bad values fail here, before any data are generated."""
    from bgn.data.datamodule import ParticleDataModule

    if spec is None:
        spec = validate_train(cfg)
    # dataset.generate_workers: simulation processes when the data are generated here
    # (default one per core; 1 generates in this process)
    return ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir,
                              generate_workers=cfg.dataset.get("generate_workers"), spec=spec)


def run_provenance(cfg: DictConfig, datamodule: ParticleDataModule) -> dict[str, Any]:
    """What this run's checkpoints record of it (``bgn.training.checkpoints.provenance``)."""
    spec = datamodule.spec
    return provenance(spec.scene, spec.generating_config()["params"], spec.fps,
                      str(cfg.model.get("name", "bgn")), datamodule.history)


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


def train(cfg: DictConfig, spec: DatasetSpec | None = None,
          law_stage: LawStage | None = None) -> dict[str, float]:
    """Fit, test, and write metrics.json; returns the final metrics. ``spec``: as
    ``data_module``'s (``cfg`` validated already). ``law_stage``: with ``model.law=auto``,
    what reads the best checkpoint's law back as a formula and chooses between the two on
    validation, before the test and with ``test=false`` too (``bgn.eval.laws.law_stage``;
    handed in by the commands above this stage)."""
    import lightning as L

    from bgn.training.signals import SignalCheckpoint, interrupted

    if cfg.model.get("dynamics") == "auto":  # candidates are composed from the overrides
        raise ValueError("model.dynamics=auto is a study of several trainings: run it with "
                         "python -m bgn.train, or bgn.studies.auto.run_auto(cfg, overrides)")
    # (a fast_dev_run writes no checkpoint: it has no law to read back)
    if cfg.model.get("law") == "auto" and law_stage is None \
            and not cfg.trainer.get("fast_dev_run"):
        raise ValueError("model.law=auto needs the formula stage: run python -m bgn.train, or "
                         "pass law_stage=bgn.eval.laws.law_stage")
    start = time.perf_counter()
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
    datamodule, module = build(cfg, datamodule)
    coder = module.model.target_coder  # what target_prior=auto and dynamics_loss=auto chose
    info(f"dynamics target: prior={coder.prior_name}, loss={coder.loss_name}")
    # a group entry set to null (callbacks.early_stopping=null) switches that callback off
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c]
    stop = SignalCheckpoint(checkpoint_dir)
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=[*callbacks, stop], logger=loggers)
    law_record: dict[str, Any] = {}
    law_match: dict[str, Any] | None = None
    try:
        trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
        metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
        law_match = module.law_match  # force matching (law_init=match) of this fit
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback \
            and not trainer.interrupted else ""
        tested, tested_ckpt = module, best or None
        # model.law=auto: the formula stage chooses on validation (train and val splits
        # only), so it runs with test=false too; the test below scores what it chose
        if cfg.model.get("law") == "auto" and best:
            law_record = law_stage(cfg, Path(best), datamodule, output_dir,
                                   trainer.world_size)
            if law_record.get("choice") == "formula":
                from bgn.training.module import load_model

                tested, tested_ckpt = load_model(law_record["path"]), None
        if not cfg.test and law_record:
            info(f"test=false: the {law_record.get('choice')} law is chosen, not tested")
        if cfg.test and not trainer.interrupted:
            trainer.test(tested, datamodule=datamodule, ckpt_path=tested_ckpt,
                         weights_only=True)
            metrics.update({k: float(v) for k, v in trainer.callback_metrics.items()})
            if cfg.test_rollouts and trainer.is_global_zero:  # the product: rollouts, batched
                from bgn.rollout import test_rollouts

                metrics.update(test_rollouts(tested.model, datamodule.datasets["test"]))
        module = tested  # the run's model: the law the stage chose, tested or not
    except (SystemExit, KeyboardInterrupt):  # SIGTERMException is a SystemExit
        if stop.signal is None:
            raise
        raise interrupted(stop, trainer, output_dir) from None
    metrics["wall_time_s"] = time.perf_counter() - start
    if not trainer.is_global_zero:  # DDP: one process writes the run's record
        return metrics
    overrides = {}
    if HydraConfig.initialized():
        overrides = dict(o.split("=", 1) for o in HydraConfig.get().overrides.task if "=" in o)
    record = {"metrics": metrics, "overrides": overrides,
              "dataset": cfg.dataset.scene, "fps": float(datamodule.spec.fps),
              "model": module.model.name,
              "variant": module.model.describe()}  # label, given, physics written in
    if law_match:
        record["law_match"] = law_match
    if law_record:  # model.law=auto: which law was tested, and the validation behind it
        record["law"] = {k: law_record.get(k) for k in ("choice", "tuned", "validation",
                                                        "rollout_substeps", "path", "report")}
    write_atomic(output_dir / "metrics.json", json.dumps(record, indent=2, sort_keys=True))
    info("final metrics:\n" + json.dumps({k: round(v, 6) for k, v in sorted(metrics.items())
                                          if k.startswith(("test/", "val/nmse"))}, indent=1))
    return metrics
