"""How alike the held-out charge data's splits are, as the charges' spreads see them
(docs/results.md, "Charges: masses and charges through the learned law"): one run's couplings
fitted per simulation on the train, validation and test splits (``examples/charges/score.py``'s
fit, 64 windows), the median |miss| / stated sd, |miss| and sd per split, then the spread
chosen on train (``spread_calibration``) and, beside it, a factor > 1 on the stated sd in place
of the floor (the same tails, the same rule), each split's coverage at 50 % / 90 %.

    python docs/notes/inverse/charge_splits.py outputs/charges_s0     # data/imported present
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from scipy.optimize import brentq
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "examples" / "charges"))
import score  # noqa: E402

from bgn.data.dataset import FrameDataset  # noqa: E402
from bgn.data.files import DatasetFile  # noqa: E402
from bgn.eval.law_posterior import TAILS, Spread, spread_calibration  # noqa: E402
from bgn.metrics import COVERAGE_LEVELS  # noqa: E402
from bgn.model.newton import pair_force_head_of  # noqa: E402
from bgn.training.checkpoints import resolve_run  # noqa: E402
from bgn.training.module import load_model  # noqa: E402

NAME, DATA = "charges4_heldout", Path("data/external/charges4_heldout")


def deviation(spread: Spread, miss: np.ndarray, sd: np.ndarray) -> float:
    held = spread.central(miss, sd)
    return max(abs(float(np.mean(held <= level)) - level) for level in COVERAGE_LEVELS)


def by_factor(miss: np.ndarray, sd: np.ndarray) -> Spread:
    """``spread_calibration``'s rule with a factor > 1 on the stated sd in place of a floor."""
    spreads = [Spread(brentq(lambda f, s=share, w=width: float(np.median(
        Spread(f, 0.0, s, w).central(miss, sd))) - 0.5, 1e-3, 1e6), 0.0, share, width)
        for share, width in TAILS]
    return min(spreads, key=lambda s: deviation(s, miss, sd))


def main(run: str) -> None:
    ckpt, _, config = resolve_run(run)
    cfg = OmegaConf.load(config)
    module = load_model(ckpt)
    head = pair_force_head_of(module.model)
    args = type("Args", (), {"data": DATA})()
    found = {}
    for split in ("train", "val", "test"):
        data = FrameDataset(DatasetFile(Path(cfg.paths.data_dir) / "imported" / NAME
                                        / f"{split}.h5"), history=module.model.history)
        _, masses, charges = score.split_truth(args, split)
        k, c, k_err, c_err, _ = score.learned_couplings(head, data, 64)
        for what, (miss, sd) in score.misses(k, c, k_err, c_err, masses, charges).items():
            ok = np.isfinite(miss) & np.isfinite(sd) & (sd > 0)
            found[split, what] = miss[ok], sd[ok]
            a = np.abs(miss[ok])
            print(f"{split} {what}: n {ok.sum()}, median |z| {np.median(a / sd[ok]):.3g}, "
                  f"median |miss| {np.median(a):.3g}, median sd {np.median(sd[ok]):.3g}, "
                  f"Spearman |miss| ~ sd {spearmanr(a, sd[ok]).correlation:.2f}")
    for what in ("log-mass", "charge"):
        for name, chosen in (("floor", spread_calibration(*found["train", what])),
                             ("factor", by_factor(*found["train", what]))):
            cells = [f"{split} " + " / ".join(
                f"{np.mean(chosen.covered(*found[split, what], level)):.3f}"
                for level in (0.5, 0.9)) for split in ("train", "val", "test")]
            print(f"{what}, {name} chosen on train ({chosen}): " + "; ".join(cells))


if __name__ == "__main__":
    main(sys.argv[1])
