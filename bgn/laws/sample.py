"""A pair-force head's law sampled (the first step of reading it back).

``sample_law``: ``f`` on a log-spaced grid over the distances of the training split's pairs
(per pair of types where the law reads types), through the head's own ``pair_terms``; r in
the data's units. The law's scale is physical where the head was trained with the recorded
masses (BGN's ``law`` loss); where the window's mass fit absorbs it (``model=newton``, BGN
without the law loss) only the shape is learned, and ``calibrate_scale`` puts it in physical
units by least squares against the recorded masses of training frames (said in the report).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from bgn.laws.options import DEFAULTS


def pair_force_head(module_or_model: Any) -> tuple[Any, Any]:
    """(model, its ``PairForceHead``) of a LightningModule or model; a model without one is
    refused in one line."""
    from bgn.model.newton import pair_force_head_of

    model = getattr(module_or_model, "model", module_or_model)
    head = pair_force_head_of(model)
    if head is None:
        name = getattr(model, "name", type(model).__name__)
        scene = getattr(getattr(model, "meta", None), "name", "?")
        raise ValueError(f"the {name} model of {scene} has no pair-force head, so it has no "
                         "law to read: train model=newton, or model=bgn model.dynamics=newton, "
                         "on a pairwise-force scene")
    return model, head


def sample_law(head: Any, r: np.ndarray, dim: int, types: tuple[int, int] = (0, 0),
               ) -> np.ndarray:
    """The head's law ``f(r)`` at physical distances ``r`` between a particle of type
    ``types[0]`` (the source) and one of ``types[1]`` (``PairForceHead.law_at``: through the
    head's own ``pair_terms``, so whatever inputs the law reads, they are read so)."""
    return head.law_at(r, dim, types)


def pair_distances(dataset: Any) -> dict[tuple[int, int], np.ndarray]:
    """The distances of every pair of particles at the frames of ``dataset``'s simulations
    (a ``FrameDataset``; frames thinned evenly beyond ``DEFAULTS.max_distances``), per pair of types
    (sorted; all (0, 0) where the scene has one type). On a radius graph only the pairs within
    its reach: beyond it a pair has no edge, and the law no force to learn."""
    from bgn.data.edges import minimum_image

    file, sims = dataset.file, list(dataset.sims)
    n = dataset.meta.n_particles
    reach = np.inf
    if dataset.meta.graph == "radius":
        reach = float(dataset.margin) + 2 * float(np.max(file.read("radii", ...), initial=0.0))
    i, j = np.triu_indices(n, k=1)
    stride = max(1, math.ceil(len(sims) * file.n_frames * len(i) / DEFAULTS.max_distances))
    found: dict[tuple[int, int], list[np.ndarray]] = {}
    for s in sims:
        x = np.asarray(file.read("positions", (s, slice(None, None, stride))), np.float64)
        r = np.sqrt((minimum_image(x[:, i] - x[:, j], dataset.meta.period) ** 2).sum(-1))
        types = (np.asarray(file.read("types", s)) if dataset.meta.n_types > 1
                 else np.zeros(n, dtype=np.int64))
        lo, hi = np.minimum(types[i], types[j]), np.maximum(types[i], types[j])
        for a, b in sorted(set(zip(lo.tolist(), hi.tolist()))):
            found.setdefault((a, b), []).append(r[:, (lo == a) & (hi == b)].ravel())
    # coincident particles (r = 0) have no direction, and no place on a log-r grid
    kept = {k: d[(d > 0) & (d <= reach)] for k, v in found.items() if (d := np.concatenate(v)).size}
    return {k: d for k, d in kept.items() if d.size}


@torch.no_grad()
def calibrate_scale(head: Any, dataset: Any, frames: int = DEFAULTS.calibration_frames,
                    ) -> tuple[float, float]:
    """(k, relative error): the factor that puts the law in physical units, by least squares
    of the head's prediction with the recorded masses against the training targets (relative,
    as ``newton.law_loss``), and the mean relative squared error of ``k`` times the prediction
    (how well the recorded masses and the law explain the targets). A head that fits couplings
    (``mass_law=coupling``) has no recorded ones: its own fit (couplings of unit rms per
    simulation, ``bgn.model.coupling.normalise``) stands in for them, so ``k`` is that gauge's
    (near 1)."""
    from bgn.data.frames import evenly_spaced
    from bgn.graph import collate
    from bgn.model.target_coder import relative_floor

    idx = evenly_spaced(len(dataset), frames)
    pred, target = [], []
    for start in range(0, len(idx), 64):
        g = collate([dataset[k] for k in idx[start:start + 64]])
        pred.append(head(g, known_masses=head.mass_law != "coupling")[0].double())
        target.append(g.target.double())
    p, t = torch.cat(pred), torch.cat(target)
    size = (t * t).sum(-1)
    w = 1 / (size + relative_floor(size))
    k = float((w * (p * t).sum(-1)).sum() / (w * (p * p).sum(-1)).sum().clamp_min(1e-300))
    error = float((w * ((k * p - t) ** 2).sum(-1)).mean())
    return k, error


