"""Validation check of a pymunk_granular run: every simulation of a split rolled out 100 steps
from a start frame with ``bgn.load(run).rollout``; per type the Wasserstein-1 distance of the
speeds after 100 steps over the true mean speed, and the impacts' rate
(``bgn.metrics.collisions_per_frame``), as the engines block scores the test split.

    python docs/notes/granular/validation_speeds.py <run> [start=100] [split=val]
"""

from __future__ import annotations

import sys

import h5py
import numpy as np
from scipy.stats import wasserstein_distance

import bgn
from bgn.metrics import collisions_per_frame

STEPS = 100


def main(run: str, start: int = 100, split: str = "val") -> None:
    model = bgn.load(run)
    with h5py.File(f"data/imported/pymunk_granular/{split}.h5") as f:
        pos, radii, types = f["positions"][...], f["radii"][...], f["types"][...]
        dt = float(f.attrs["dt"])
    w = model.window_length
    pred_speed, true_speed, kinds, hits_pred, hits_true = [], [], [], 0, 0
    for s in range(pos.shape[0]):
        window = pos[s, start - w + 1:start + 1]
        rolled = np.asarray(model.rollout(window, STEPS, radii=radii[s], types=types[s]))
        pred = np.concatenate([window[-2:], rolled])
        true = pos[s, start - 1:start + STEPS + 1]
        v_pred = np.linalg.norm(np.diff(pred, axis=0), axis=-1) / dt
        v_true = np.linalg.norm(np.diff(true, axis=0), axis=-1) / dt
        error = float(np.linalg.norm(pred[-1] - true[-1], axis=-1).mean())
        print(f"simulation {s}: mean speed predicted / true after 1, 50, {STEPS} steps "
              + ", ".join(f"{v_pred[i].mean():.3f} / {v_true[i].mean():.3f}"
                          for i in (1, 50, -1)) + f"; position error {error:.3f}")
        pred_speed.append(v_pred[-1])
        true_speed.append(v_true[-1])
        kinds.append(types[s])
        hits_pred += int(collisions_per_frame(pred[1:], radii[s]).clip(0).sum())
        hits_true += int(collisions_per_frame(true[1:], radii[s]).sum())
    p, t, k = map(np.concatenate, (pred_speed, true_speed, kinds))
    for kind in np.unique(k):
        m = k == kind
        print(f"type {kind}: speed W1 / true mean speed "
              f"{wasserstein_distance(p[m], t[m]) / t[m].mean():.3f}")
    print(f"impacts predicted / true: {hits_pred} / {hits_true} = {hits_pred / hits_true:.3f}")


if __name__ == "__main__":
    args = sys.argv[1:]
    main(args[0], int(args[1]) if len(args) > 1 else 100, args[2] if len(args) > 2 else "val")
