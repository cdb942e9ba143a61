"""Train a model on a scene: ``python -m bgn.train [dataset=spring] [fps=50] [model=bgn] ...``.

Generates the dataset on first use, trains with Lightning, evaluates the best checkpoint on
the test split and writes ``metrics.json`` in the run directory (sweeps gather these into a
summary table). The run's full config is saved by Hydra in ``<run>/.hydra/config.yaml``;
``python -m bgn.train --config-path <run>/.hydra --config-name config`` reproduces it.
"""

from __future__ import annotations

import json
import time
from functools import partial
from pathlib import Path
from typing import Any

import hydra
import lightning as L
import numpy as np
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from bgn.data.datamodule import ParticleDataModule
from bgn.module import PhysicsModule
from bgn.rollout import rollout


def plain_stats(stats: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, Any]]:
    return {g: {k: np.asarray(v).tolist() for k, v in entries.items()}
            for g, entries in stats.items()}


def build(cfg: DictConfig) -> tuple[ParticleDataModule, PhysicsModule]:
    """DataModule (data generated if missing) and LightningModule from a composed config."""
    if not cfg.fps or float(cfg.fps) <= 0:
        raise ValueError(f"fps={cfg.fps} must be a positive number of frames per time unit")
    # dataset.generate_workers: simulation processes when the data are generated here
    # (default one per core; 1 generates in this process)
    datamodule = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir,
                                    generate_workers=cfg.dataset.get("generate_workers"))
    datamodule.prepare_data()
    datamodule.setup()
    model_config = OmegaConf.to_container(cfg.model, resolve=True)
    lr = model_config.pop("lr", 1e-3)
    weight_decay = model_config.pop("weight_decay", 0.0)
    rollout_fn = None
    if cfg.get("figures", True) and cfg.get("rollout_steps", 0) > 0:
        rollout_fn = partial(rollout, dataset=datamodule.datasets["val"], sim=0,
                             n_steps=int(cfg.rollout_steps))
    module = PhysicsModule(model_config, dict(vars(datamodule.meta)),
                           plain_stats(datamodule.stats()), datamodule.history, lr=lr,
                           weight_decay=weight_decay, figures=bool(cfg.get("figures", True)),
                           rollout=rollout_fn)
    return datamodule, module


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit, test, and write metrics.json; returns the final metrics."""
    start = time.perf_counter()
    L.seed_everything(int(cfg.seed), workers=True)
    output_dir = Path(cfg.paths.output_dir)
    print(f"run directory: {output_dir}")
    datamodule, module = build(cfg)
    coder = module.model.target_coder  # what target_prior=auto and dynamics_loss=auto chose
    print(f"dynamics target: prior={coder.prior_name}, loss={coder.loss_name}")
    # a group entry set to null (callbacks.early_stopping=null) switches that callback off
    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c]
    loggers = [instantiate(c) for c in (cfg.get("logger") or {}).values() if c]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=loggers)
    resume = {"ckpt_path": cfg.ckpt_path} if cfg.get("ckpt_path") else {}
    trainer.fit(module, datamodule=datamodule, **resume)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    if cfg.get("test", True) and not trainer.interrupted:
        best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback \
            else ""
        trainer.test(module, datamodule=datamodule, ckpt_path=best or None)
        metrics.update({k: float(v) for k, v in trainer.callback_metrics.items()})
    metrics["wall_time_s"] = time.perf_counter() - start
    if not trainer.is_global_zero:  # DDP: one process writes the run's record
        return metrics
    overrides = {}
    if HydraConfig.initialized():
        overrides = dict(o.split("=", 1) for o in HydraConfig.get().overrides.task if "=" in o)
    record = {"metrics": metrics, "overrides": overrides,
              "dataset": cfg.dataset.scene, "fps": float(cfg.fps),
              "model": module.model.label}
    output_dir.mkdir(parents=True, exist_ok=True)
    (output_dir / "metrics.json").write_text(json.dumps(record, indent=2, sort_keys=True))
    print(json.dumps({k: round(v, 6) for k, v in sorted(metrics.items())
                      if k.startswith(("test/", "val/nmse"))}, indent=1))
    return metrics


@hydra.main(config_path="../conf", config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float:
    metrics = train(cfg)
    return metrics.get("val/nmse", float("nan"))  # the objective a sweeper would minimise


if __name__ == "__main__":
    main()
