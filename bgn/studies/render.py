"""Animate a model's rollout against the truth: ``python -m bgn.render <checkpoint>``.

Reads the run's config beside the checkpoint (``<run>/.hydra/config.yaml``, or a study cell's
``train_config.yaml``) for the dataset, rolls the model out through the learned simulator
from a frame of a simulation of the chosen split, and writes a GIF (or an MP4 with ffmpeg)
of the true and predicted particles.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from omegaconf import OmegaConf

from bgn.training.checkpoints import run_config


def main(argv: list[str] | None = None) -> Path:
    parser = argparse.ArgumentParser(prog="python -m bgn.render", description=__doc__.split(
        "\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--config", type=Path, default=None,
                        help="the run's config (default: found beside the checkpoint)")
    parser.add_argument("--split", default="test", choices=["train", "val", "test"])
    parser.add_argument("--sim", type=int, default=0, help="simulation of the split")
    parser.add_argument("--start", type=int, default=None,
                        help="last true frame (default: 100, or the first possible)")
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--data-dir", default=None, help="default: the run's paths.data_dir")
    parser.add_argument("--out", type=Path, default=None,
                        help="a .gif or .mp4 (default: outputs/render/<run>_<split><sim>.gif)")
    parser.add_argument("--fps", type=int, default=20, help="frames per second of the file")
    args = parser.parse_args(argv)

    from bgn.data.datamodule import ParticleDataModule
    from bgn.figures import rollout_animation
    from bgn.rollout import REFERENCE_START, rollout
    from bgn.training.module import load_model

    if not args.checkpoint.exists():
        raise SystemExit(f"no checkpoint at {args.checkpoint}")
    cfg = OmegaConf.load(args.config or run_config(args.checkpoint))
    data_dir = args.data_dir or OmegaConf.select(cfg, "paths.data_dir", default="data")
    datamodule = ParticleDataModule(cfg.dataset, cfg.fps, data_dir)
    datamodule.prepare_data()
    datamodule.setup()
    dataset = datamodule.datasets[args.split]
    model = load_model(args.checkpoint).model
    start = args.start
    if start is None:
        start = min(REFERENCE_START, max(dataset.history + 1,
                                         dataset.file.n_frames - 1 - args.steps))
    result = rollout(model, dataset, args.sim, start, args.steps)
    run = args.checkpoint.resolve().parent.parent.name
    out = args.out or Path("outputs/render") / f"{run}_{args.split}{args.sim}.gif"
    path = rollout_animation(result, out, fps=args.fps)
    print(f"{len(result['predicted']) - 1} steps from frame {start} of {args.split} "
          f"simulation {args.sim}: {path}")
    return path
