"""Per simulation, how far the impact posterior's discs sit from their recorded masses
together (their common shift) and apart (the spread about it), against the posterior's own
standard deviation: where ratios are pinned by impacts, what is left is one shift per
simulation, which the types' mass laws place.

    python docs/notes/inverse/impact_shifts.py <run> [--frames 400] [--noise 1e-4]

Reads the run's chosen checkpoint and its test and validation splits (the frames
``python -m bgn.evaluate <run> mass_frames=400`` scores); prints one row per simulation and
the share of simulations whose shift lies within the central 50 % / 90 % of its posterior.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from scipy.stats import norm

from bgn.data.datamodule import ParticleDataModule
from bgn.data.frames import evenly_spaced
from bgn.eval.evaluate import load_checked
from bgn.eval.impact_posterior import impact_posterior, simulation_impacts
from bgn.eval.mass_baselines import MassPrior
from bgn.training.checkpoints import resolve_run


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--noise", type=float, default=1e-4, help="one impact's log-ratio std")
    args = ap.parse_args(argv)
    ckpt, _, config = resolve_run(str(args.run))
    cfg = OmegaConf.load(config)
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir)
    module = load_checked(ckpt, cfg, dm).eval()
    dm.prepare_data()
    dm.setup()
    print("| split | simulation | discs in an impact | shift | posterior std | z | "
          "spread about the shift |")
    print("|---|---|---|---|---|---|---|")
    for split in ("val", "test"):
        ds = dm.datasets[split]
        prior = MassPrior.of_scene(ds.scene)
        z_all = []
        for sim in simulation_impacts(module.model.force_head, ds,
                                      evenly_spaced(len(ds), args.frames)):
            mean, std = impact_posterior(sim, prior, args.noise)
            seen = np.isin(np.arange(len(sim.types)), sim.pairs)
            err = mean[seen] - sim.true_log[seen]
            z = err.mean() / std[seen].mean()
            z_all.append(z)
            print(f"| {split} | {sim.sim} | {seen.mean():.2f} | {err.mean():+.4f} | "
                  f"{std[seen].mean():.4f} | {z:+.2f} | {err.std():.1e} |")
        z_all = np.abs(np.asarray(z_all))
        print(f"\n{split}: shifts within the central 50 % / 90 %: "
              f"{np.mean(z_all < norm.ppf(0.75)):.2f} / {np.mean(z_all < norm.ppf(0.95)):.2f} "
              f"of {len(z_all)} simulations\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
