"""Which loss pulls on a pair-force head's overall scale: the gradient of each loss term of a
BGN run along a common factor ``s`` of its law (``f -> s f``, at ``s = 1``), over random
training batches, with its standard error. The window's mass fit absorbs the factor, so only
the law loss (the head with the recorded masses) should see it (docs/design.md, "The law's
scale"; docs/results.md, "The law's scale as a parameter of its own").

    python docs/notes/laws/scale_gradient.py \
        outputs/engines_relfit/rebound_nbody_s0/auto/newton_source
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from bgn.data.datamodule import ParticleDataModule
from bgn.graph import collate
from bgn.laws.sample import pair_force_head
from bgn.training.module import load_model


class Scaled(torch.nn.Module):
    """A law times a scalar that carries the gradient."""

    def __init__(self, law: torch.nn.Module, factor: torch.Tensor) -> None:
        super().__init__()
        self.law, self.factor = law, factor

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.law(x) * self.factor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a run folder with train_config.yaml and checkpoints/")
    ap.add_argument("--checkpoint", default="best.ckpt")
    ap.add_argument("--batches", type=int, default=30)
    ap.add_argument("--batch-size", type=int, default=32)
    args = ap.parse_args()
    module = load_model(args.run / "checkpoints" / args.checkpoint)
    model, head = pair_force_head(module)
    cfg = OmegaConf.load(args.run / "train_config.yaml")
    data = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, show_progress=False)
    data.prepare_data()
    data.setup()
    train = data.datasets["train"]
    factor = torch.ones((), requires_grad=True)
    head.force_law = Scaled(head.force_law, factor)
    model.eval()
    rng = np.random.default_rng(0)
    grads: dict[str, list[float]] = {}
    for _ in range(args.batches):
        idx = rng.choice(len(train), args.batch_size, replace=False)
        g = collate([train[int(k)] for k in idx])
        terms = model.loss_terms(g, model(g))
        for name, value in terms.items():
            grad, = torch.autograd.grad(value, factor, retain_graph=True, allow_unused=True)
            grads.setdefault(name, []).append(0.0 if grad is None else float(grad))
    print(f"d(loss)/d(factor of the law) at 1, {args.batches} training batches of "
          f"{args.batch_size}: mean (standard error)")
    for name, values in grads.items():
        v = np.asarray(values)
        print(f"  {name:12s} {v.mean():+.3g} ({v.std(ddof=1) / np.sqrt(len(v)):.2g})")


if __name__ == "__main__":
    main()
