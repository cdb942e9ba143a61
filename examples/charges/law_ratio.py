"""The pair law a coupling head learned on the charge data, against the truth, per distance.

    python examples/charges/law_ratio.py <run> [<run> ...] --data data/imported/charges4

For each run (a run folder or checkpoint, ``bgn.load``): the learned law ``f(r)`` over the
truth's ``1 / (r + 0.01)^2`` (make.py's law) at fixed distances, each row divided by its median
between r = 0.2 and 0.6 (the law's scale and sign are the couplings' gauge, free); and the
training split's pair-distance quantiles, so that a ratio can be read against how many pairs
the data hold there. Prints a markdown table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

R = np.array([0.02, 0.03, 0.05, 0.1, 0.14, 0.2, 0.3, 0.6, 1.0, 3.0, 10.0, 30.0])
SOFTENING = 0.01  # make.py's law: 1 / (r + SOFTENING)^2
QUANTILES = (0.001, 0.005, 0.01, 0.05, 0.5, 0.99)


def distances(data: Path) -> np.ndarray:
    """Every pair distance of the training split's frames."""
    with h5py.File(data / "train.h5") as f:
        x = np.asarray(f["positions"])
    i, j = np.triu_indices(x.shape[2], k=1)
    return np.linalg.norm(x[:, :, i] - x[:, :, j], axis=-1).ravel()


def over_the_data(law: np.ndarray, d: np.ndarray) -> tuple[float, float, float]:
    """(share within 5 %, median, 90th percentile of |ratio - 1|) of ``law`` (at ``d``) over
    the truth, scaled by the ratio's median."""
    ratio = law / (1 / (d + SOFTENING) ** 2)
    ratio = ratio / np.median(ratio)
    miss = np.abs(ratio - 1)
    return float(np.mean(miss <= 0.05)), float(np.median(miss)), float(np.quantile(miss, 0.9))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    parser.add_argument("--data", type=Path, default=Path("data/imported/charges4"))
    args = parser.parse_args()
    import bgn

    truth = 1 / (R + SOFTENING) ** 2
    d = distances(args.data)
    lo, hi = np.quantile(d, [0.01, 0.99])
    inside = np.sort(d[(d >= lo) & (d <= hi)])
    inside = inside[np.linspace(0, len(inside) - 1, 20_000).astype(int)]  # evenly in rank
    print("| run | substeps | " + " | ".join(f"r={r:g}" for r in R) + " |")
    print("|---|---|" + "---|" * len(R))
    rows = []
    for run in args.runs:
        model = bgn.load(run)
        law = model.law()
        ratio = law(R) / truth
        ratio = ratio / np.median(ratio[(R >= 0.2) & (R <= 0.6)])
        substeps = getattr(model.model.force_head, "substeps", 1)
        print(f"| {Path(run).name} | {substeps} | " + " | ".join(f"{v:.3f}" for v in ratio)
              + " |")
        rows.append((Path(run).name, *over_the_data(law(inside), inside)))
    q = np.quantile(d, QUANTILES)
    print("\ntraining pair distances at the quantiles "
          + ", ".join(f"{p:g}: {v:.3g}" for p, v in zip(QUANTILES, q)))
    print(f"\nover the training pairs from r = {lo:.3g} to {hi:.3g} (1st to 99th percentile):\n")
    print("| run | pairs within 5 % | median abs error | 90th percentile |")
    print("|---|---|---|---|")
    for name, share, median, p90 in rows:
        print(f"| {name} | {share:.3f} | {median:.3f} | {p90:.3f} |")


if __name__ == "__main__":
    main()
