"""The masses of REBOUND's bodies read off the frames through REBOUND's own law: the physical
estimator that knows the true law, on the frames ``python -m bgn.evaluate`` scores.

    python examples/engines/engine_masses.py data/external/rebound_nbody <run> \
        [--eval <run>/eval/test] [--frames 32] [--law-frames 0]

Imported data carry no force law bgn knows, so the evaluation's physical estimator has
nothing to read there (``physical/identified`` 0). This script gives it the engine's law from
the dataset's ``engine.json`` (G, the Plummer softening b: ``a_i = sum_j G m_j d_ij / (|d_ij|^2 +
b^2)^(3/2)``) and runs bgn's own gravity estimator (``bgn.eval.mass_baselines.gravity_log_mass``:
least squares of the masses at the source over every interior frame of the windows) per test
simulation on the windows of the evaluated frames (``mass_frames`` evenly spaced, and
``law_frames`` more per simulation, as the law posterior reads them). With ``--eval``, the
run's evaluation (its ``metrics.json``) is printed beside it: the law posterior's error over
this estimator's, the ratio issue 57 asks to be at most 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


class PlummerLaw:
    """The pair-force magnitude of Plummer-softened gravity at unit masses, in the form
    ``gravity_log_mass`` reads a scene's: ``f(r) = G r / (r^2 + b^2)^(3/2)``."""

    def __init__(self, g: float, softening: float) -> None:
        self.g, self.b = float(g), float(softening)

    def pair_force_magnitude(self, x: np.ndarray, masses: np.ndarray, snd: np.ndarray,
                             rcv: np.ndarray) -> np.ndarray:
        r = np.linalg.norm(x[..., snd, :] - x[..., rcv, :], axis=-1)
        return self.g * masses[snd] * r / (r ** 2 + self.b ** 2) ** 1.5


def main(argv: list[str]) -> int:
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.data.frames import evenly_spaced
    from bgn.eval.impact_posterior import position_window
    from bgn.eval.law_posterior import simulation_frames
    from bgn.eval.mass_baselines import gravity_log_mass
    from bgn.metrics import relative_mass_error
    from bgn.training.checkpoints import resolve_run

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="the engine's dataset folder (engine.json)")
    ap.add_argument("run", type=Path, help="a run trained on its import")
    ap.add_argument("--eval", type=Path, help="the run's evaluation folder (metrics.json)")
    ap.add_argument("--frames", type=int, default=32, help="bgn.evaluate's mass_frames")
    ap.add_argument("--law-frames", type=int, default=0, help="bgn.evaluate's law_frames")
    args = ap.parse_args(argv)
    engine = json.loads((args.data / "engine.json").read_text())
    params = engine.get("params", {})
    if engine.get("engine") != "rebound" or params.get("softening_form") != "plummer":
        ap.error(f"{args.data}/engine.json is not REBOUND with Plummer softening: this "
                 "estimator knows that law only")
    law = PlummerLaw(params["G"], params["softening"])
    _, _, config = resolve_run(str(args.run))
    cfg = OmegaConf.load(config)
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir)
    dm.setup()
    test = dm.datasets["test"]
    indices = evenly_spaced(len(test), args.frames)
    estimate, truth = [], []
    print("| simulation | windows | median abs relative mass error |")
    print("|---|---|---|")
    for sim, frames in simulation_frames(test, indices, args.law_frames).items():
        windows = np.stack([position_window(test, i) for i in frames])
        log_mass = gravity_log_mass(law, windows, test.dt)
        true_log = np.log(test.file.read("masses", sim))
        estimate.append(log_mass)
        truth.append(true_log)
        print(f"| {sim} | {len(frames)} | {relative_mass_error(log_mass, true_log):.3g} |")
    error = relative_mass_error(np.concatenate(estimate), np.concatenate(truth))
    print(f"\nthe engine's law, per simulation: {error:.3g}")
    if args.eval is not None:
        metrics = json.loads((args.eval / "metrics.json").read_text())["metrics"]
        learned = metrics.get("law_posterior/sim_mass_rel_err")
        if learned is None:
            print(f"{args.eval}: no law posterior (no pair-force head)")
        else:
            print(f"the learned law (law posterior), per simulation: {learned:.3g}, "
                  f"{learned / error:.2f} times the engine's law's")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
