"""``python -m bgn.train [dataset=spring] [fps=50] [model=bgn] ...``: train a model on a scene.

Generates the dataset on first use, trains with Lightning, evaluates the best checkpoint on
the test split and writes ``metrics.json`` in the run directory (``bgn.training.run``). The run's
full config is saved by Hydra in ``<run>/.hydra/config.yaml``; ``python -m bgn.train
--config-path <run>/.hydra --config-name config`` reproduces it. ``model.dynamics=auto`` is a
study of several trainings (``bgn.studies.auto``), started from here.
"""

from __future__ import annotations

from omegaconf import DictConfig

from bgn.training.budget import Deadline, watch_signals
from bgn.training.checkpoints import CheckpointError
from bgn.training.run import job_cap, train
from bgn.training.validate import cli, validate_train


@cli("train")  # Hydra app; bad input: one line, exit 2 (bgn.training.validate)
def main(cfg: DictConfig) -> float:
    # the job's wall-clock cap counts from here: data generation, training, the formula stage
    # and the test inside it (docs/design.md#budgets); SIGTERM acted on anywhere within seconds
    deadline = Deadline.after(job_cap(cfg))
    watch_signals()
    spec = validate_train(cfg)  # once per run: the DatasetSpec is handed on to the DataModule
    try:
        if cfg.model.get("dynamics") == "auto":  # the structure chosen by evidence
            from bgn.studies.auto import run_auto

            metrics = run_auto(cfg, deadline=deadline)
        else:
            from bgn.laws.stage import law_stage  # model.law=auto's formula stage

            metrics = train(cfg, spec, law_stage=law_stage, deadline=deadline)
    except CheckpointError as err:  # one line, no traceback
        raise SystemExit(f"bgn.train: {err}") from None
    return metrics.get("val/nmse", float("nan"))  # the objective a sweeper would minimise


if __name__ == "__main__":
    main()
