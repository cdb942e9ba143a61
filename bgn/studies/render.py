"""Animate a model's rollout against the truth: ``python -m bgn.render <run folder or
checkpoint> [split=test] [sim=0] [steps=200] ...`` (``--help`` lists the keys,
``conf/render.yaml``).

The model is the one ``python -m bgn.evaluate`` scores (``bgn.training.checkpoints.resolve_run``: a
run folder's chosen checkpoint, or a checkpoint file), with the run's config
(``<run>/.hydra/config.yaml``, or a study cell's ``train_config.yaml``) for the dataset; it is
rolled out through the learned simulator from a frame of a simulation of the chosen split,
and a GIF (or an MP4 with ffmpeg) of the true and predicted particles is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from bgn.training.validate import ConfigError, cli, need_int

SPLITS = ("train", "val", "test")


def validate_render(cfg: Any) -> tuple[Path, Path, Path]:
    """Everything ``python -m bgn.render`` is given, before any data or model is read;
    returns ``resolve_run``'s (checkpoint, run folder, run config)."""
    from bgn.training.checkpoints import resolve_run

    if not cfg.get("ckpt"):
        raise ConfigError("ckpt", None, "give a run folder or checkpoint: python -m bgn.render "
                          "outputs/train/runs/<run> [split=test] [sim=0]")
    if cfg.split not in SPLITS:
        raise ConfigError("split", cfg.split, f"choose one of {list(SPLITS)}")
    need_int(cfg.sim, "sim", 0, why=" (a simulation of the split)")
    need_int(cfg.start, "start", 1, optional=True, why=" (null: frame 100, or the first possible)")
    need_int(cfg.steps, "steps", 1)
    need_int(cfg.fps, "fps", 1, why=" (frames per second of the file)")
    if cfg.out is not None and Path(str(cfg.out)).suffix not in (".gif", ".mp4"):
        raise ConfigError("out", cfg.out, "a .gif or .mp4 file")
    return resolve_run(str(cfg.ckpt), cfg.get("run_config"))


def _run_name(given: str, ckpt: Path) -> str:
    """The default file's stem: the run folder's name (a checkpoint's: its run's)."""
    path = Path(given).expanduser()
    if path.is_dir():
        return path.resolve().name
    return ckpt.resolve().parent.parent.name


@cli("render", validate_render, positional="ckpt")  # bad input: one line, exit 2
def main(cfg: Any) -> Path:
    """Roll the model out and write the animation; returns its path."""
    from bgn.data.datamodule import ParticleDataModule
    from bgn.figures import rollout_animation
    from bgn.rollout import REFERENCE_START, rollout
    from bgn.training.checkpoints import resolve_run
    from bgn.training.module import load_model

    ckpt, _, config = resolve_run(str(cfg.ckpt), cfg.get("run_config"))
    run_cfg = OmegaConf.load(config)
    data_dir = cfg.paths.data_dir or OmegaConf.select(run_cfg, "paths.data_dir", default="data")
    model = load_model(ckpt).model  # an unusable checkpoint fails before any data are made
    datamodule = ParticleDataModule(run_cfg.dataset, run_cfg.fps, data_dir)
    datamodule.prepare_data()
    datamodule.setup()
    dataset = datamodule.datasets[cfg.split]
    n_sims = dataset.file.n_sims
    if cfg.sim >= n_sims:
        raise ConfigError("sim", cfg.sim, f"the {cfg.split} split has {n_sims} simulations "
                          f"(0..{n_sims - 1})")
    start = cfg.start
    if start is None:
        start = min(REFERENCE_START, max(dataset.history + 1,
                                         dataset.file.n_frames - 1 - cfg.steps))
    result = rollout(model, dataset, int(cfg.sim), int(start), int(cfg.steps))
    out = Path(cfg.out) if cfg.out else \
        Path("outputs/render") / f"{_run_name(str(cfg.ckpt), ckpt)}_{cfg.split}{cfg.sim}.gif"
    path = rollout_animation(result, out, fps=int(cfg.fps))
    print(f"{len(result['predicted']) - 1} steps from frame {start} of {cfg.split} "
          f"simulation {cfg.sim}: {path}")
    return path
