"""How the formula stage's law choice depends on its validation rollouts (issue 56: a choice
that hangs on one diverging rollout). For each run with a formula stage (``<run>/laws/
formula.ckpt``), the network law (the run's own checkpoint) and the formula law are rolled out
on the validation split from the stage's start frame (frame 100: the 10 rollouts the stage
scores today) and from ``--starts - 1`` more start frames per simulation, spread evenly
(``bgn.rollout.rollout_starts``); each rollout's capped error (``bgn.metrics.
failure_capped_errors``, a failed rollout at the cap) after 10, 50 and 100 steps. Then the
law each rule keeps, on the stage's rollouts and on all of them: ``mean`` (the stage's rule,
``bgn.laws.finetune.law_choice``: fewest failed, then the mean error), ``median``,
``typical`` (the geometric mean) and ``paired`` (the law better on more rollouts), each after
fewest failed. Validation only: nothing here reads the test split. Writes choice.md,
choice.csv and rollouts.csv (every rollout's errors) in ``--out``.

    python docs/notes/laws/choice_rule.py outputs/s22/gravity_r2_s0 ... --starts 10 \\
        --out outputs/reports/choice_rule

``--stage``: instead, both laws scored exactly as the formula stage scores them today
(``bgn.laws.finetune.validation_errors`` at the stage's defaults: at least 100 rollouts), and
the law kept by the lower mean alone (the rule before the one-standard-error rule) and by
``law_choice`` (the formula wherever its mean is within one standard error of the network
law's), beside the choice the run's stage recorded: writes stage.md and stage.csv.

    python docs/notes/laws/choice_rule.py outputs/s26/gravity_r2_s0 ... --stage \\
        --out outputs/reports/choice_stage
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import torch

from bgn.laws.options import DEFAULTS
from bgn.tables import write_table

CHOICE_HORIZON = DEFAULTS.finetune_horizon  # the stage's
FLOOR = DEFAULTS.typical_floor               # ... and its floor of the geometric mean
HORIZONS = (10, CHOICE_HORIZON, 100)


def rollout_errors(checkpoint: Path, val, starts: list[int], n_steps: int) -> tuple[np.ndarray,
                                                                                    np.ndarray]:
    """(R, T) capped errors and (R,) failure steps of ``checkpoint``'s rollouts, rows ordered
    start by start, the simulations within."""
    from bgn.metrics import failure_capped_errors
    from bgn.rollout import rollout_many
    from bgn.training.module import load_model

    model = load_model(checkpoint).model.eval()
    with torch.no_grad():
        t = rollout_many(model, val, list(range(val.file.n_sims)), starts, n_steps, chunk=4096)
    return failure_capped_errors(t.predicted, t.true, t.first_non_finite, val.meta.box)


def summaries(errors: np.ndarray, failed: np.ndarray) -> dict[str, float]:
    e = errors[:, CHOICE_HORIZON - 1]
    return {"failed": int(np.sum(failed >= 0)), "mean": float(e.mean()),
            "median": float(np.median(e)),
            "typical": float(np.exp(np.log(e + FLOOR).mean()))}


def choose(net: tuple[np.ndarray, np.ndarray], formula: tuple[np.ndarray, np.ndarray],
           rule: str) -> str:
    """The law ``rule`` keeps: fewest failed first, the network law on a tie."""
    a, b = summaries(*net), summaries(*formula)
    if a["failed"] != b["failed"]:
        return "network" if a["failed"] < b["failed"] else "formula"
    if rule == "paired":
        wins = np.sum(formula[0][:, CHOICE_HORIZON - 1] < net[0][:, CHOICE_HORIZON - 1])
        return "formula" if wins > len(net[0]) / 2 else "network"
    return "formula" if b[rule] < a[rule] else "network"


def stage_row(run: Path, network: Path, formula: Path, val) -> dict:
    """One run's row of ``--stage``: both laws through ``validation_errors`` as the stage
    rolls them out (the formula with the substeps its checkpoint holds)."""
    from bgn.laws.finetune import law_choice, mean_error, paired_standard_error, validation_errors
    from bgn.training.module import load_model

    scores = {}
    for law, ckpt in (("network", network), ("formula", formula)):
        with torch.no_grad():
            scores[law] = validation_errors(load_model(ckpt).model, val, val.history)
    h = scores["network"]["horizon"]
    margin = mean_error(scores["formula"], h) - mean_error(scores["network"], h)
    se = paired_standard_error(scores["network"], scores["formula"], h)
    recorded = json.loads((run / "laws" / "formula.json").read_text()).get("choice")
    by_mean = min(scores, key=lambda k: (scores[k]["failed"], mean_error(scores[k], h),
                                         k != "network"))
    return {"run": str(run), "rollouts": scores["network"]["rollouts"],
            **{f"{law}: failed, mean / typical @{h}":
               f"{s['failed']}, {mean_error(s, h):.3g} / {s['typical'][h]:.3g}"
               for law, s in scores.items()},
            "formula - network": f"{margin:.3g}",
            "standard error": f"{se:.3g}" if se is not None else "-",
            "lower mean": by_mean, "one standard error": law_choice(scores, h),
            "the stage recorded": recorded}


def main() -> None:
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.rollout import REFERENCE_START, rollout_starts
    from bgn.training.checkpoints import best_checkpoint

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--starts", type=int, default=10, help="start frames per simulation")
    parser.add_argument("--out", type=Path, default=Path("outputs/reports/choice_rule"))
    parser.add_argument("--stage", action="store_true",
                        help="score both laws as the formula stage does; the two rules")
    args = parser.parse_args()
    rows, per_rollout, stage_rows = [], [], []
    for run in args.runs:
        formula = run / "laws" / "formula.ckpt"
        if not formula.is_file():
            parser.error(f"{formula} does not exist: the run has no formula law to compare")
        network = Path(json.loads((run / "laws" / "formula.json").read_text()).get(
            "checkpoint") or best_checkpoint(run))
        cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
        dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, show_progress=False)
        dm.prepare_data()
        dm.setup()
        val = dm.datasets["val"]
        if args.stage:
            stage_rows.append(stage_row(run, network, formula, val))
            print(stage_rows[-1], flush=True)
            continue
        n_steps = min(max(HORIZONS), val.file.n_frames - val.history - 2)
        spread = rollout_starts(val, n_steps, per_sim=args.starts)
        starts = [REFERENCE_START] + [s for s in spread if s != REFERENCE_START]
        starts = starts[:args.starts]
        laws = {"network": rollout_errors(network, val, starts, n_steps),
                "formula": rollout_errors(formula, val, starts, n_steps)}
        n = val.file.n_sims
        stage = {k: (e[:n], f[:n]) for k, (e, f) in laws.items()}  # start frame 100 only
        row = {"run": run.name, "scene": cfg.dataset.scene, "seed": int(cfg.seed),
               "rollouts (stage / all)": f"{n} / {len(laws['network'][0])}"}
        for which, sets in (("stage", stage), ("all", laws)):
            for law, (e, f) in sets.items():
                s = summaries(e, f)
                row[f"{law} {which}: failed, mean / median / typical @50"] = (
                    f"{s['failed']}, {s['mean']:.3g} / {s['median']:.3g} / {s['typical']:.3g}")
            for rule in ("mean", "median", "typical", "paired"):
                row[f"{rule} ({which})"] = choose(sets["network"], sets["formula"], rule)
        rows.append(row)
        for law, (e, f) in laws.items():
            for i in range(len(e)):
                per_rollout.append({"run": run.name, "law": law, "start": starts[i // n],
                                    "sim": i % n, "failed_step": int(f[i]),
                                    **{f"error@{h}": float(e[i, h - 1]) for h in HORIZONS
                                       if h <= n_steps}})
        print(row, flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.stage:
        print(write_table(args.out, "stage", list(stage_rows[0]), stage_rows,
                          "The formula stage's law choice: the lower mean against the "
                          "one-standard-error rule",
                          "Validation split only, rolled out as the stage does "
                          "(bgn.laws.finetune.validation_errors). standard error: of the "
                          "difference of the two means, the rollouts averaged per simulation "
                          "first (bgn.laws.finetune.paired_standard_error)."))
        return
    print(write_table(args.out, "choice", list(rows[0]), rows,
                      "The formula stage's law choice under four rules, on the stage's "
                      "validation rollouts and on more start frames",
                      "Validation split only. stage: the 10 rollouts from frame 100 the stage "
                      "scores; all: every start frame. Each rule after fewest failed; paired: "
                      "the law with the lower error on more rollouts."))
    with (args.out / "rollouts.csv").open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(per_rollout[0]))
        w.writeheader()
        w.writerows(per_rollout)
    print(f"\nwritten: {args.out}/choice.md, choice.csv, rollouts.csv")


if __name__ == "__main__":
    main()
