"""Test rollouts of trained runs on the charge data, one row per simulation, beside the
no-learning references and the true law (issue "Laws found, not looked up", item 3).

    python examples/charges/rollouts.py <run> [<run> ...] --out outputs/charges/rollouts
    python examples/charges/rollouts.py <run> ... --data data/external/charges4_heldout \
        --imported charges4_heldout --out outputs/charges/rollouts_heldout

Every run (a training run's folder; ``python -m bgn.train dataset=imported
dataset.name=charges4 ...``) rolled out on its test split from frame 100 for 100 steps, as the
training command's test does (``bgn.rollout.rollout_many``: a model whose held fit reads the
frames before the start is given them), beside: the last and the linear extrapolation of the
window (``bgn.model.references``), and the TRUE law ``1 / (r + softening)^2`` (like charges
repel; the softening from ``make.json``) written into the coupling head, its couplings fitted
to the frames before the start as the learned model's are: what the frame rate allows a model
that knows the law. The error after each horizon: the mean position error per particle
(``bgn.metrics.capped_errors``, a failed rollout at the cap). Writes ``rollouts.md`` and
``rollouts.csv`` (every run, reference and simulation) under ``--out``: the mean and median over
the test simulations, and after 50 steps and after ``--steps`` the median error, the mean
error over the best reference's mean, each simulation's error over the best reference's (the
better of the two extrapolations, per simulation) and the share of simulations within 1/10 of
it (issue "Laws found, not looked up": the charge goal). With
``--imported NAME`` every run is rolled out on that imported dataset's test split instead of its
own (simulations of the same law none of the runs saw; ``--data`` its ``make.py`` folder).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from bgn.data.dataset import FrameDataset
from bgn.data.files import DatasetFile
from bgn.metrics import capped_errors, rollout_failures
from bgn.model import build_model
from bgn.model.references import REFERENCES, Extrapolation
from bgn.rollout import rollout_many, rollout_starts
from bgn.training.checkpoints import resolve_run
from bgn.training.module import load_model

HORIZONS = (10, 50, 100)


def errors(model, dataset: FrameDataset, steps: int) -> np.ndarray:
    """(S, len(HORIZONS)) each test simulation's error after each horizon."""
    sims = list(range(len(dataset.sims)))
    rolled = rollout_many(model, dataset, sims, rollout_starts(dataset, steps), steps)
    failed = rollout_failures(rolled.predicted, rolled.true, None, rolled.first_non_finite)
    err = capped_errors(rolled.predicted, rolled.true, None, failed)[0]
    return err[:, list(HORIZONS)]


def true_law(dataset: FrameDataset, train: FrameDataset, softening: float):
    spec = json.dumps([{"types": [0, 0], "terms": [
        {"kind": "shifted", "power": -2.0, "a": 1.0, "c": softening}]}])
    return build_model({"name": "newton", "mass_law": "coupling", "law": "formula",
                        "law_formula": spec}, dataset.meta, train.file.stats(), dataset.history)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--data", type=Path, default=Path("data/external/charges4"),
                    help="the folder make.py wrote (its make.json: the softening)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--imported", help="score on this imported dataset's test split "
                    "(default: each run's own)")
    args = ap.parse_args(argv)

    softening = json.loads((args.data / "make.json").read_text())["params"]["softening"]
    rows: list[dict] = []
    data: dict[str, FrameDataset] = {}
    for run in args.runs:
        ckpt, _, config = resolve_run(str(run))
        cfg = OmegaConf.load(config)
        module = load_model(ckpt)
        folder = Path(cfg.paths.data_dir) / "imported" / (args.imported or cfg.dataset.name)
        test = FrameDataset(DatasetFile(folder / "test.h5"), history=module.model.history)
        data.setdefault("test", test)
        data.setdefault("train", FrameDataset(DatasetFile(folder / "train.h5"),
                                              history=module.model.history))
        rows += [{"predictor": str(run), "model": module.model.label, "sim": s,
                  **{f"@{h}": float(e) for h, e in zip(HORIZONS, row)}}
                 for s, row in enumerate(errors(module.model, test, args.steps))]
    test, train = data["test"], data["train"]
    others = {f"{p} extrapolation": Extrapolation(test.meta, test.history, p) for p in REFERENCES}
    others["true law, couplings fitted"] = true_law(test, train, softening)
    for name, model in others.items():
        rows += [{"predictor": name, "model": name, "sim": s,
                  **{f"@{h}": float(e) for h, e in zip(HORIZONS, row)}}
                 for s, row in enumerate(errors(model, test, args.steps))]
    goal_at = list(dict.fromkeys(h for h in (50, args.steps) if h in HORIZONS))
    best = {h: np.minimum(*[np.array([r[f"@{h}"] for r in rows if r["predictor"] == n])
                            for n in (f"{p} extrapolation" for p in REFERENCES)])
            for h in goal_at}
    for h in goal_at:
        for r in rows:
            r[f"over best reference @{h}"] = r[f"@{h}"] / best[h][r["sim"]]
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "rollouts.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    lines = [f"| predictor | model | mean @{args.steps} | median @{args.steps} | "
             + " | ".join(f"@{h}: median error, mean over the best reference's mean, median per "
                          "simulation over the best reference, within 1/10" for h in goal_at)
             + " |", "|---|---|---|---|" + "---|" * len(goal_at)]
    for name in dict.fromkeys(r["predictor"] for r in rows):
        own = [r for r in rows if r["predictor"] == name]
        last = np.array([r[f"@{args.steps}"] for r in own])
        cells = []
        for h in goal_at:
            err = np.array([r[f"@{h}"] for r in own])
            ratio = np.array([r[f"over best reference @{h}"] for r in own])
            cells.append(f"{np.median(err):.3g}, {err.mean() / best[h].mean():.3g}, "
                         f"{np.median(ratio):.3g}, {int((ratio <= 0.1).sum())} of {len(ratio)}")
        lines.append(f"| {name} | {own[0]['model']} | {last.mean():.4g} | {np.median(last):.4g} "
                     f"| {' | '.join(cells)} |")
    text = (f"# Test rollouts on {test.file.path.parent.name}\n\nFrom frame 100, "
            f"{args.steps} steps, {len(test.sims)} test simulations; mean position error per "
            "particle, a failed rollout at the cap.\n\n" + "\n".join(lines) + "\n")
    (args.out / "rollouts.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
