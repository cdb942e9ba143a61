"""The no-learning reference of a LagrangeBench-layout test split, in the form score.py reads:
every particle keeps the velocity of the last two of the six given frames (walls, which do not
move, stay), so that a learned model's score has a floor beside it.

    python examples/fluids/reference_rollouts.py data/external/sph_tgv \
        --out outputs/fluids/sph_tgv_reference/rollouts.npz
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import h5py
import numpy as np

INPUT_FRAMES = 6


def constant_velocity(positions: np.ndarray, period: np.ndarray | None = None) -> np.ndarray:
    """(T, N, D) -> the same frames with every frame after the sixth extrapolated from the
    fifth and sixth (their difference by the minimum image where ``period`` gives the box)."""
    x = positions.astype(np.float64)
    step = x[INPUT_FRAMES - 1] - x[INPUT_FRAMES - 2]
    if period is not None:                    # 0: not periodic along that axis
        wrap = period > 0
        step[..., wrap] -= period[wrap] * np.round(step[..., wrap] / period[wrap])
    k = np.arange(1, len(x) - INPUT_FRAMES + 1)[:, None, None]
    return np.concatenate([x[:INPUT_FRAMES], x[INPUT_FRAMES - 1] + k * step])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path, help="the LagrangeBench-layout dataset folder")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--split", default="test")
    a = p.parse_args(argv)
    if not (a.data / f"{a.split}.h5").is_file():
        p.error(f"{a.data}: no {a.split}.h5; give a LagrangeBench-layout dataset folder")
    period = None
    if (a.data / "metadata.json").is_file():
        meta = json.loads((a.data / "metadata.json").read_text())
        if any(meta.get("periodic_boundary_conditions", [])):
            bounds = np.asarray(meta["bounds"], dtype=float)
            period = np.where(meta["periodic_boundary_conditions"], bounds[:, 1] - bounds[:, 0],
                              0.0)
    with h5py.File(a.data / f"{a.split}.h5", "r") as f:
        truth = [f[k]["position"][()] for k in sorted(f)]
    predicted = np.stack([constant_velocity(t, period) for t in truth]).astype(np.float32)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, predicted=predicted, truth=np.stack(truth).astype(np.float32),
                        start=INPUT_FRAMES - 1)
    print(f"{a.out}: {len(truth)} rollouts of constant velocity")
    return 0


if __name__ == "__main__":
    sys.exit(main())
