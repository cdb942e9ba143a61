"""The trial behind model.contact_calibration=rollout (docs/results.md, "Granular media"): a
trained soft-contact run's damping scaled by one factor, chosen by golden section on the mean
speed of 100-step rollouts from frame 100 of four training simulations, then the fitted and
the calibrated model both scored on the validation split (speed W1 per type over the true mean
speed after 100 steps, the impacts' rate), as validation_speeds.py does.

    python docs/notes/granular/calibration_trial.py <run> [train sims, default 0,8,16,24]
"""

from __future__ import annotations

import math
import sys

import h5py
import numpy as np
import torch
from scipy.stats import wasserstein_distance

import bgn
from bgn.metrics import collisions_per_frame
from bgn.training.calibrate import speed_misfit

STEPS, START = 100, 100


def read(split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    with h5py.File(f"data/imported/pymunk_granular/{split}.h5") as f:
        return f["positions"][...], f["radii"][...], f["types"][...], float(f.attrs["dt"])


def rollouts(model: bgn.Model, split: str, sims: list[int]) -> list[tuple]:
    pos, radii, types, dt = read(split)
    w, out = model.window_length, []
    for s in sims:
        window = pos[s, START - w + 1:START + 1]
        rolled = np.asarray(model.rollout(window, STEPS, radii=radii[s], types=types[s]))
        out.append((np.concatenate([window[-2:], rolled]), pos[s, START - 1:START + STEPS + 1],
                    radii[s], types[s], dt))
    return out


def misfit(outs: list[tuple]) -> float:
    return speed_misfit(np.stack([o[0] for o in outs]), np.stack([o[1] for o in outs]))


def scores(outs: list[tuple]) -> tuple[list[float], float]:
    ps, ts, ks, hits_pred, hits_true = [], [], [], 0, 0
    for pred, true, radii, types, dt in outs:
        ps.append(np.linalg.norm(pred[-1] - pred[-2], axis=-1) / dt)
        ts.append(np.linalg.norm(true[-1] - true[-2], axis=-1) / dt)
        ks.append(types)
        hits_pred += int(collisions_per_frame(pred[1:], radii).clip(0).sum())
        hits_true += int(collisions_per_frame(true[1:], radii).sum())
    p, t, k = map(np.concatenate, (ps, ts, ks))
    w1 = [wasserstein_distance(p[k == c], t[k == c]) / t[k == c].mean() for c in np.unique(k)]
    return w1, hits_pred / hits_true


def main(run: str, train_sims: list[int]) -> None:
    model = bgn.load(run)
    head = model.model.force_head
    zeta0 = (float(head.pair.zeta().detach()), float(head.wall.zeta().detach()))

    def set_scale(s: float) -> None:
        with torch.no_grad():
            head.pair.set_zeta(s * zeta0[0])
            head.wall.set_zeta(s * zeta0[1])

    def f(log_s: float) -> float:
        set_scale(math.exp(log_s))
        v = misfit(rollouts(model, "train", train_sims))
        print(f"  scale {math.exp(log_s):.3f} (pair zeta {zeta0[0] * math.exp(log_s):.4f}): "
              f"train speed misfit {v:.4f}", flush=True)
        return v

    a, b = math.log(0.5), math.log(30.0)
    g = (math.sqrt(5) - 1) / 2
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(6):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    best = math.exp(c if fc < fd else d)
    print(f"fitted damping ratios {zeta0}; best scale {best:.3f}")
    for s in (1.0, best):
        set_scale(s)
        outs = rollouts(model, "val", list(range(4)))
        w1, ratio = scores(outs)
        print(f"scale {s:.3f}: validation speed misfit {misfit(outs):.4f}, speed W1 / mean "
              f"per type {np.round(w1, 3)}, impacts ratio {ratio:.3f}", flush=True)


if __name__ == "__main__":
    sims = [int(x) for x in sys.argv[2].split(",")] if len(sys.argv) > 2 else [0, 8, 16, 24]
    main(sys.argv[1], sims)
