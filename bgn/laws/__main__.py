"""``python -m bgn.laws <run folder or checkpoint> [finetune=true] [key=value ...]``: the
learned pair law as a formula (``bgn.laws``); ``--help`` lists the keys (``conf/laws.yaml``),
which set ``LawOptions``' fields of the same names.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bgn.laws.options import COMMAND_KEYS, DEFAULTS, LawOptions, from_keys
from bgn.laws.sample import pair_force_head
from bgn.laws.stage import formula_stage
from bgn.training.validate import cli


def checked_options(cfg: Any) -> tuple[Path, Path, LawOptions]:
    """``python -m bgn.laws``'s keys (``conf/laws.yaml``) checked before any data or model is
    read: (the checkpoint, its run's config, the law options its keys set). The checkpoint is
    the one ``python -m bgn.evaluate`` scores (``bgn.training.checkpoints.resolve_run``: a run
    folder's chosen one)."""
    from bgn.training.checkpoints import resolve_run
    from bgn.training.validate import ConfigError, need_float, need_int

    if not cfg.get("ckpt"):
        raise ConfigError("ckpt", None, "give a run folder or checkpoint: python -m bgn.laws "
                          "outputs/train/runs/<run> [finetune=true]")
    if not isinstance(cfg.finetune, bool):
        raise ConfigError("finetune", cfg.finetune, "true or false")
    need_int(cfg.max_terms, "max_terms", 1, 3)  # the search's sums: pairs and triples
    need_float(cfg.tolerance, "tolerance", 0.0, strict_low=False)
    for key, high in (("finetune_steps", None), ("finetune_substeps", 64),
                      ("finetune_batch_size", None), ("finetune_horizon", None),
                      ("finetune_val_sims", None), ("finetune_val_rollouts", None)):
        need_int(cfg[key], key, 1, high, optional=True)
    ckpt, _, config = resolve_run(str(cfg.ckpt), cfg.get("run_config"))
    return ckpt, Path(config), from_keys({k: cfg[k] for k in COMMAND_KEYS})


def run(checkpoint: Path, config: Path, options: LawOptions = DEFAULTS, finetune: bool = False,
        data_dir: str | None = None, out_dir: str | None = None) -> Path:
    """Read the law of ``checkpoint`` over its training split (its run's ``config``; the
    data in ``data_dir``, else the run's) and write the report in ``out_dir`` (else
    ``<run>/laws``); with ``finetune`` also the fitted formula as the law, fine-tuned
    (``formula_stage``): ``formula.ckpt``, ``formula.json`` and a section of report.md in the
    same folder."""
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.training.module import load_model

    pair_force_head(load_model(checkpoint))  # refused before any data are read
    cfg = OmegaConf.load(config)
    data_dir = data_dir or OmegaConf.select(cfg, "paths.data_dir", default="data")
    datamodule = ParticleDataModule(cfg.dataset, cfg.fps, data_dir, show_progress=False)
    datamodule.prepare_data()
    datamodule.setup()
    out = Path(out_dir or checkpoint.resolve().parent.parent / "laws")
    record = formula_stage(checkpoint, datamodule.datasets["train"],
                           datamodule.datasets["val"], cfg, out, finetune=finetune,
                           options=options)
    return Path(record["report"])


@cli("laws", positional="ckpt")  # bad input: one line, exit 2 (bgn.training.validate)
def main(cfg: Any) -> Path:
    """``python -m bgn.laws <run folder or checkpoint> [finetune=true] ...``; a model without
    a pair-force head or an unusable checkpoint: one line, exit code 2."""
    from bgn.data.files import DatasetFileError
    from bgn.training.checkpoints import CheckpointError
    from bgn.training.validate import CONFIG_EXIT, DATA_EXIT, fail, full_error

    checkpoint, config, options = checked_options(cfg)
    try:
        path = run(checkpoint, config, options, finetune=cfg.finetune,
                   data_dir=cfg.paths.data_dir or None, out_dir=cfg.out_dir or None)
    except DatasetFileError as err:
        if full_error():
            raise
        fail(err, DATA_EXIT)
    except (CheckpointError, ValueError, FileNotFoundError) as err:
        if full_error():
            raise
        fail(err, CONFIG_EXIT)
    print(f"law: {path}")
    return path


if __name__ == "__main__":
    main()
