"""Score rollouts with LagrangeBench's own metrics, the same code for every model.

Runs in the peer environment (setup_peer.sh). A rollouts file holds ``predicted`` and
``truth``, (n, T, N, D) positions of the test trajectories from their first frame (the first
six are given, the rest predicted), as peer.py writes them and as bgn's rollouts are exported
(examples/fluids/bgn_rollouts.py). Metrics (LagrangeBench's MetricsComputer): the mean squared
position error over the first 5, 10 and 20 predicted frames and over all of them, the Sinkhorn
divergence between predicted and true particle clouds and the mean squared error of the
kinetic energy, both every 10th frame; plus, ours, whether a rollout failed (a non-finite
position, or a particle more than a connectivity radius outside a closed box).

    .venv-peer/bin/python examples/fluids/score.py data/external/sph_tgv \
        outputs/fluids/sph_tgv_gns_s0/rollouts.npz --json outputs/fluids/sph_tgv_gns_s0/score.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax_sph.jax_md import space
from lagrangebench.evaluate.metrics import MetricsComputer

jax.config.update("jax_enable_x64", True)

INPUT_FRAMES = 6
STRIDE = 10
HORIZONS = (5, 10, 20)


def score(data: Path, rollouts: Path) -> dict:
    meta = json.loads((data / "metadata.json").read_text())
    bounds = np.asarray(meta["bounds"], dtype=float)
    periodic = np.asarray(meta["periodic_boundary_conditions"], dtype=bool)
    box = bounds[:, 1] - bounds[:, 0]
    displacement, _ = space.periodic(side=jnp.asarray(box)) if periodic.any() else space.free()
    computer = MetricsComputer(["mse", "sinkhorn", "e_kin"], dist_fn=displacement,
                               metadata=meta, input_seq_length=INPUT_FRAMES, stride=STRIDE,
                               loss_ranges=list(HORIZONS))
    with np.load(rollouts) as f:
        predicted, truth = f["predicted"], f["truth"]
    if predicted.shape != truth.shape:
        raise SystemExit(f"{rollouts}: predicted {predicted.shape} and truth {truth.shape} differ")
    per = []
    for pred, true in zip(predicted, truth):
        pred, true = pred[INPUT_FRAMES:], true[INPUT_FRAMES:]
        finite = np.isfinite(pred).all()
        outside = False
        if not periodic.any():
            margin = meta["default_connectivity_radius"]
            outside = bool(((pred < bounds[:, 0] - margin) | (pred > bounds[:, 1] + margin)).any())
        row = {"failed": bool((not finite) or outside)}
        if finite:
            m = computer(jnp.asarray(pred), jnp.asarray(true))
            row.update({f"mse{h}": float(m[f"mse{h}"].mean()) for h in HORIZONS},
                       mse=float(m["mse"].mean()), sinkhorn=float(m["sinkhorn"].mean()),
                       e_kin_mse=float(m["e_kin"]["mse"]))
        per.append(row)
    keys = [f"mse{h}" for h in HORIZONS] + ["mse", "sinkhorn", "e_kin_mse"]
    ok = [r for r in per if not r["failed"]]
    summary = {k: (float(np.mean([r[k] for r in ok])) if ok else None) for k in keys}
    summary.update(failed=sum(r["failed"] for r in per), rollouts=len(per),
                   frames=int(predicted.shape[1] - INPUT_FRAMES), stride=STRIDE,
                   per_rollout=per)
    return summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, help="the dataset folder (its metadata.json)")
    p.add_argument("rollouts", type=Path, help="a rollouts .npz (predicted, truth)")
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    s = score(a.data, a.rollouts)
    if a.json:
        a.json.write_text(json.dumps(s, indent=1))
    print(json.dumps({k: v for k, v in s.items() if k != "per_rollout"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
