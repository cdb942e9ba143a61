"""The masses and charges a trained model infers through the law IT learned, scored against the
hidden truth (issue "The inverse half", item 3): beside ``identify.py``'s fits with the true law.

    python examples/charges/score.py <run> data/external/charges4 --out outputs/charges/score
    python examples/charges/score.py <run> data/external/charges4_heldout \
        --imported charges4_heldout --out outputs/charges/score_heldout

For each simulation of a split of imported data (``data/imported/<name>/<split>.h5``; by
default the run's own data and its test split): its model's pair-force head
(``mass_law=coupling``; a run of ``model.dynamics=auto`` whose winner is another head has
nothing to score) fits ``a_i = k_i sum_j c_j f(s_ij) u_ij`` with its own learned ``f`` to
``--windows`` windows spread over the simulation, pooled
(``bgn.eval.law_posterior.pooled_system``, the accelerations its law misses screened out as
the law posterior does). Scored as ``identify.py`` scores (``identify.scores``: log-masses
``log(c / k)`` centred per simulation, charge signs up to the global sign, charge R^2), against
``_hidden/truth.npz``, which the model never read. ``--imported``: more simulations of the
same law made by ``make.py`` with another ``--seed`` and imported under that name, none of
them seen in training.

The posterior: each particle's centred log-mass and charge (unit rms per simulation, the
global sign aligned with the truth's, the one gauge the frames leave) about the fit, their
spreads the fit's standard errors (``coupling_errors``, the delta method for ``log(c / k)``)
times a factor or with a floor added, with a heavy tail, all chosen on the ``--calibration``
split of the same data (``bgn.eval.law_posterior.spread_calibration``: half its particles
within the central 50 % interval, the tail that brings its coverage nearest every level;
never the split scored). Scored: the coverage of the central 50 % and 90 % intervals on the
scored split, with its 5-95 % range
over the simulations resampled (a few dozen simulations pin a coverage only to about
±0.05-0.1: a simulation's particles share one fit). Writes ``score.md`` and
``score.csv`` under ``--out``: the row of the learned law, and beside it ``identify.py``'s fit
with the true law on the same windows' frames (no errors: no coverage).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from bgn.data.dataset import FrameDataset
from bgn.data.files import DatasetFile
from bgn.data.frames import evenly_spaced
from bgn.eval.law_posterior import Spread, pooled_system, screened, spread_calibration
from bgn.model.newton import FIT_EPS, pair_force_head_of
from bgn.training.checkpoints import resolve_run
from bgn.training.module import load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from identify import aligned_charges, fit, scores, system  # noqa: E402


def learned_couplings(head: torch.nn.Module, dataset: FrameDataset, windows: int,
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[list[int]]]:
    """k and c (S, N) of every simulation of ``dataset`` through the head's learned law, their
    standard errors (S, N) each, and the frames each fit read."""
    ks, cs, k_errs, c_errs, frames = [], [], [], [], []
    per = dataset.frames_per_sim
    for s in range(len(dataset.sims)):
        index = [s * per + i for i in evenly_spaced(per, windows)]
        graphs = [dataset[i] for i in index]
        with torch.no_grad():
            g, past, seen, start = pooled_system(head, graphs)
            couplings, errors = head.fit_observed(g, *screened(head, g, past, seen, start),
                                                  with_error=True)
        k, c = couplings[:, 0].double().numpy(), couplings[:, 1].double().numpy()
        # the learned law's sign is free (f -> -f, c -> -c): turned so that most masses c / k
        # are positive, as bgn.eval.law_posterior does
        turn = np.sign(np.median(c / np.where(k == 0, FIT_EPS, k))) or 1.0
        if not (k.any() or c.any()):  # the fit failed whole (no coupling at all): not fitted
            turn = np.nan
        ks.append(k)
        cs.append(c * turn)
        k_errs.append(errors[:, 0].double().numpy())
        c_errs.append(errors[:, 1].double().numpy())
        frames.append([dataset.locate(i)[1] for i in index])
    return np.stack(ks), np.stack(cs), np.stack(k_errs), np.stack(c_errs), frames


def misses(k: np.ndarray, c: np.ndarray, k_err: np.ndarray, c_err: np.ndarray,
           masses: np.ndarray, charges: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per particle (flattened over simulations), the fit's miss and standard deviation of the
    centred log-mass and of the charge (unit rms per simulation, the global sign aligned with
    the truth's); NaN where a simulation has a mass that is not positive (not identified)."""
    with np.errstate(invalid="ignore", divide="ignore"):  # k = 0: no mass, NaN below
        log_m = np.log(c / k)
        mass_sd = np.hypot(k_err / np.abs(k), c_err / np.abs(c))
    log_m = np.where(np.isfinite(log_m).all(1, keepdims=True), log_m, np.nan)
    true_m = np.log(masses)
    mass_miss = (log_m - log_m.mean(1, keepdims=True)) - (true_m - true_m.mean(1, keepdims=True))
    aligned, q = aligned_charges(c, charges)
    return {"log-mass": (mass_miss.ravel(), mass_sd.ravel()),
            "charge": ((aligned - q).ravel(), c_err.ravel())}


def coverage(miss: np.ndarray, sd: np.ndarray, spread: Spread, level: float, sims: int,
             rng: np.random.Generator, resamples: int = 2000) -> tuple[float, float, float]:
    """The share of the particles (identified ones) whose truth lies in the central ``level``
    interval of their calibrated likelihood about the fit, and the 5-95 % range of that share
    over the ``sims`` simulations resampled with replacement (a simulation's particles share
    its fit, so they are resampled together: the spread a coverage over so few simulations
    carries)."""
    ok = (np.isfinite(miss) & np.isfinite(sd)).reshape(sims, -1)
    held = np.zeros(ok.shape)
    held[ok] = spread.covered(miss.reshape(sims, -1)[ok], sd.reshape(sims, -1)[ok], level)
    pick = rng.integers(0, sims, (resamples, sims))
    shares = held[pick].sum((1, 2)) / np.maximum(ok[pick].sum((1, 2)), 1)
    low, high = np.quantile(shares, [0.05, 0.95])
    return float(held.sum() / ok.sum()), float(low), float(high)


def split_truth(args: argparse.Namespace, split: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of ``split`` in the data's hidden truth, their masses and charges."""
    truth = np.load(args.data / "_hidden" / "truth.npz")
    rows = np.flatnonzero(truth["split"] == split)
    return rows, truth["masses"][rows], truth["charges"][rows]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a training run's folder")
    ap.add_argument("data", type=Path, help="the folder make.py wrote (its _hidden/truth.npz)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--imported", help="the data's name under data/imported (default: the "
                    "run's own data)")
    ap.add_argument("--split", default="test", help="the split scored")
    ap.add_argument("--calibration", default="val", help="the split the spreads are chosen on")
    ap.add_argument("--windows", type=int, default=64, help="windows per simulation")
    ap.add_argument("--charge-floor", type=float, default=0.2)
    args = ap.parse_args(argv)

    ckpt, _, config = resolve_run(str(args.run))
    run_cfg = OmegaConf.load(config)
    module = load_model(ckpt)
    head = pair_force_head_of(module.model)
    if head is None or head.mass_law != "coupling":
        raise SystemExit(f"{args.run}: its model has no pair-force head with mass_law=coupling "
                         f"({module.model.label}): nothing to score")
    name = args.imported or run_cfg.dataset.name

    def fitted(split: str) -> tuple:
        path = Path(run_cfg.paths.data_dir) / "imported" / name / f"{split}.h5"
        if not path.is_file():
            raise SystemExit(f"{path}: no such file; import the data first (python -m "
                             f"bgn.data.import {args.data}/charges.npz name={name})")
        data = FrameDataset(DatasetFile(path), history=module.model.history)
        return (*split_truth(args, split), *learned_couplings(head, data, args.windows))

    rows, masses, charges, k, c, k_err, c_err, frames = fitted(args.split)
    learned = scores(k, c, masses, charges, args.charge_floor)
    _, cal_masses, cal_charges, *cal_fit, _ = fitted(args.calibration)
    chosen = {}
    for what, (miss, sd) in misses(*cal_fit, cal_masses, cal_charges).items():
        ok = np.isfinite(miss) & np.isfinite(sd)
        chosen[what] = spread_calibration(miss[ok], sd[ok])
    rng = np.random.default_rng(0)
    for what, (miss, sd) in misses(k, c, k_err, c_err, masses, charges).items():
        spread = chosen[what]
        learned[f"{what} coverage 50 / 90 (5-95 % over simulations)"] = " / ".join(
            "{:.3f} ({:.2f}-{:.2f})".format(*coverage(miss, sd, spread, level, len(rows), rng))
            for level in (0.5, 0.9))
        learned[f"{what} sd factor, floor, tail"] = (
            f"{spread.factor:.3g}, {spread.floor:.3g}, "
            f"{spread.tail_share:.3g} x {spread.tail_width:.3g}")
    raw = np.load(args.data / "charges.npz")
    positions, dt = raw["positions"][rows], float(raw["dt"])
    softening = json.loads((args.data / "make.json").read_text())["params"]["softening"]
    # the true law on the same frames (identify.py's fit): each window's frames t-k+1 .. t-1
    k_true, c_true = fit([system(positions[s], dt, np.unique(np.concatenate(
        [np.arange(t - module.model.history + 1, t) for t in windows])), softening)
        for s, windows in enumerate(frames)])
    true_row = {**scores(k_true, c_true, masses, charges, args.charge_floor),
                **{key: "-" for key in learned if "coverage" in key or "factor" in key}}
    table = [{"law": f"learned ({module.model.label})", **learned},
             {"law": "true (identify.py's fit)", **true_row}]
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "score.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
    lines = ["| " + " | ".join(table[0]) + " |", "|" + "---|" * len(table[0])]
    lines += ["| " + " | ".join(f"{row[key]:.4g}" if isinstance(row[key], float)
                                else str(row[key]) for key in table[0]) + " |" for row in table]
    text = (f"# Masses and charges through the learned law\n\nRun `{args.run}`, data `{name}`, "
            f"split {args.split} ({len(rows)} simulations, {args.windows} windows each), the "
            f"spreads chosen on its {args.calibration} split; charge signs scored where |q| >= "
            f"{args.charge_floor} x the simulation's rms charge.\n\n" + "\n".join(lines) + "\n")
    (args.out / "score.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
