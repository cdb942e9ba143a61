"""The README's Python example on a run, timed: ``python examples/api/example.py <run folder>
<its test file .h5> [sim]``. Prints the rollout's error after 100 steps from frame 100, the
masses inferred from the first 200 frames beside the recorded ones, the learned law at r = 1,
and the wall time of each call (docs/results.md, "The Python API")."""

from __future__ import annotations

import sys
import time

import h5py
import numpy as np


def main(run: str, data: str, sim: int = 0) -> None:
    t0 = time.perf_counter()
    import bgn

    model = bgn.load(run)
    t1 = time.perf_counter()
    with h5py.File(data) as f:
        x, masses = f["positions"][sim], f["masses"][sim]
    k = model.window_length
    future = model.rollout(x[100 - k + 1:101], n_steps=100)
    t2 = time.perf_counter()
    posterior = model.infer(x[:200])
    t3 = time.perf_counter()
    law = model.law()
    print(model)
    print(f"error after 100 steps: {np.linalg.norm(future[-1] - x[200], axis=-1).mean():.3g}")
    print(f"masses ({posterior.describe()}): {np.round(posterior.median(), 4)}")
    print(f"recorded: {np.round(masses, 4)}; median relative error "
          f"{np.median(np.abs(posterior.median() / masses - 1)):.3g}")
    print(f"law f(1) = {float(law(1.0)):.4g} ({law.scale}); formula: {law.formula}")
    print(f"seconds: import + load {t1 - t0:.2f}, rollout of 100 steps {t2 - t1:.2f}, "
          f"infer {t3 - t2:.2f}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 0)
