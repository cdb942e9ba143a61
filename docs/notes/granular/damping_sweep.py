"""How the speed W1 of the validation rollouts moves with the pair damping ratio, beside the
training misfits the calibration could minimise (docs/results.md, "Granular media"): a trained
soft-contact run's damping set to its calibrated value and to 7 ratios log-spaced over
0.02-0.3 (walls in proportion); for each, the mean-speed misfit of the calibration
(``bgn.training.calibrate.speed_misfit``) and the same misfit per disc type (mean over types)
on 100-step rollouts from frame 100 of training simulations 0, 8, 16, 24, then the speed W1 per
type over the true mean speed and the impacts' rate on the 4 validation simulations.

    python docs/notes/granular/damping_sweep.py <run>     # from the root, data/imported present
"""

from __future__ import annotations

import sys

import calibration_trial as trial
import numpy as np
import torch

import bgn


def per_type_misfit(outs: list[tuple]) -> float:
    """The calibration's misfit, the squared log gap of the mean speed, per disc type."""
    gaps = []
    for pred, true, _, types, _ in outs:
        for kind in np.unique(types):
            p = np.linalg.norm(np.diff(pred[:, types == kind], axis=0), axis=-1).mean(-1)
            t = np.linalg.norm(np.diff(true[:, types == kind], axis=0), axis=-1).mean(-1)
            gaps.append(np.mean((np.log(p + 1e-12) - np.log(t + 1e-12)) ** 2))
    return float(np.mean(gaps))


def main(run: str) -> None:
    model = bgn.load(run)
    head = model.model.force_head
    pair = float(head.pair.zeta().detach())
    ratio = float(head.wall.zeta().detach()) / pair
    print(f"calibrated pair damping ratio {pair:.4f}")
    for zeta in [pair, *np.geomspace(0.02, 0.3, 7)]:
        with torch.no_grad():
            head.pair.set_zeta(zeta)
            head.wall.set_zeta(zeta * ratio)
        train = trial.rollouts(model, "train", [0, 8, 16, 24])
        val = trial.rollouts(model, "val", list(range(4)))
        w1, impacts = trial.scores(val)
        print(f"ratio {zeta:.4f}: training misfit {trial.misfit(train):.4f}, per type "
              f"{per_type_misfit(train):.4f} | validation speed W1 / mean per type "
              f"{np.round(w1, 3)}, impacts {impacts:.3f}", flush=True)


if __name__ == "__main__":
    main(sys.argv[1])
