"""Normalisation statistics, computed once on the training split (float64) and stored in it.

Targets of the force scenes are heavy-tailed (docs/design.md#frames-and-targets): next to mean and
standard deviation we keep the median and a robust scale (1.4826 x median absolute deviation),
so the model can choose a normalisation that a few extreme frames do not dominate.
"""

from __future__ import annotations

import numpy as np

from bgn.data.edges import minimum_image, pair_codes, scene_edges
from bgn.data.frames import evenly_spaced
from bgn.data.targets import backward_velocities, targets
from bgn.sim import Scene

MAX_EDGE_FRAMES = 100  # frames per simulation used for edge statistics (evenly spaced)


def summarize(values: np.ndarray) -> dict[str, np.ndarray]:
    """Per-column statistics of (M, C) values in float64; variances are never negative."""
    x = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
    if len(x) == 0:
        zeros = np.zeros(x.shape[1])
        return {"mean": zeros, "std": zeros, "median": zeros, "robust_scale": zeros,
                "min": zeros, "max": zeros, "count": np.array(0.0)}
    median = np.median(x, axis=0)
    return {
        "mean": x.mean(axis=0),
        "std": x.std(axis=0),  # two-pass in numpy: never negative
        "median": median,
        "robust_scale": 1.4826 * np.median(np.abs(x - median), axis=0),
        "min": x.min(axis=0),
        "max": x.max(axis=0),
        "count": np.array(float(len(x))),
    }


def compute_stats(scene: Scene, arrays: dict[str, np.ndarray], dt: float,
                  margin: float) -> dict[str, dict[str, np.ndarray]]:
    """Statistics of inputs, targets, edge features and masses of one (training) split. The
    ``contact`` group is the contact fraction (contact scenes), the true pair force magnitude
    (force scenes) or zeros (imported data: the law is unknown)."""
    meta = scene.meta
    positions = arrays["positions"]  # (S, T, N, D)
    d = meta.dim
    velocity = backward_velocities(np.moveaxis(positions, 1, 0), dt)  # (T-1, S, N, D)
    target = targets(np.moveaxis(positions, 1, 0), dt, meta.target)
    log_mass = np.log(arrays["masses"])
    stats = {
        "velocity": summarize(velocity.reshape(-1, d)),
        # v[t] - v[t-1]: the scale of the increments inside an input window
        "velocity_increment": summarize(np.diff(velocity, axis=0).reshape(-1, d)),
        "target": summarize(target.reshape(-1, d)),
        # what is left of the target after the last observed value (diff1) or after a linear
        # extrapolation of the last two (diff2): the scales of the residual targets that a
        # model with model.target_prior=last|linear predicts (bgn.model.target_coder)
        "target_diff1": summarize(np.diff(target, n=1, axis=0).reshape(-1, d)),
        "target_diff2": summarize(np.diff(target, n=2, axis=0).reshape(-1, d)),
        "log_mass": summarize(log_mass.reshape(-1, 1)),
    }

    rel_pos, rel_vel, rel_logm, contact = [], [], [], []
    n_sims, n_frames = positions.shape[:2]
    frames = [1 + i for i in evenly_spaced(n_frames - 2, MAX_EDGE_FRAMES)]  # 1 .. T-2
    n = meta.n_particles
    if meta.interaction == "contact":
        c = arrays["contacts"]  # rows (sim, frame, i, j)
    for s in range(n_sims):
        for t in frames:
            x = positions[s, t]
            snd, rcv = scene_edges(meta.graph, x, arrays["radii"][s], margin, meta.period)
            rel_pos.append(minimum_image(x[rcv] - x[snd], meta.period))
            rel_vel.append((x[rcv] - positions[s, t - 1][rcv])
                           - (x[snd] - positions[s, t - 1][snd]))
            rel_logm.append(log_mass[s, rcv] - log_mass[s, snd])
            if meta.interaction == "contact":
                here = c[(c[:, 0] == s) & (c[:, 1] == t)]
                contact.append(np.isin(pair_codes(snd, rcv, n),
                                       pair_codes(here[:, 2], here[:, 3], n)).astype(float))
            elif meta.interaction == "unknown":  # imported data: no law, no force target
                contact.append(np.zeros(len(snd)))
            else:
                contact.append(scene.pair_force_magnitude(x, arrays["masses"][s], snd, rcv))
    stats["rel_position"] = summarize(np.concatenate(rel_pos))
    stats["rel_velocity"] = summarize(np.concatenate(rel_vel) / dt)
    stats["rel_log_mass"] = summarize(np.concatenate(rel_logm)[:, None])
    stats["contact"] = summarize(np.concatenate(contact)[:, None])
    return stats
