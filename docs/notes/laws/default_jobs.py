"""The default jobs' law and rollouts, one row per run, against issue 56's goals for them
(spring <= 0.0005 and gravity_r1 <= 0.015 mean position error after 100 test steps;
gravity_r2 median <= 0.015; no failed rollout): from each run's ``metrics.json`` (written by
``python -m bgn.train``) and ``laws/formula.json`` (the formula stage's record). Per run: the
law kept and the formula tuned, its form and constants against the scene's law, the
validation scores the choice was made on (mean / typical error after 50 steps, failed, how
many rollouts), the test rollouts. Then per scene the mean ± standard deviation over the runs
given. Writes default_jobs.md and default_jobs.csv in ``--out``.

    python docs/notes/laws/default_jobs.py outputs/gravity_r2_s0 ... \\
        --out outputs/reports/default_jobs
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from bgn.tables import write_table

# issue 56: (test metric, goal) per scene
GOALS = {"spring": ("test/rollout_error@100", 0.0005),
         "gravity_r1": ("test/rollout_error@100", 0.015),
         "gravity_r2": ("test/rollout_error_median@100", 0.015)}


def law_text(tuned: list[dict] | None) -> str:
    if not tuned:
        return "-"
    import sympy

    from bgn.model.formula_law import parse_expression

    out = []
    for t in tuned:
        expr = parse_expression(t["expr"], t["constants"])
        values = {sympy.Symbol(k, real=True): v for k, v in t["constants"].items()}
        out.append(sympy.sstr(sympy.N(sympy.simplify(expr.subs(values)), 5)))
    return "; ".join(out)


def scores(v: dict | None) -> str:
    if not v:
        return "-"
    h = str(v["horizon"])
    return (f"{v['errors'][h]:.3g} / {v['typical'][h]:.3g}, {v['failed']} of "
            f"{v.get('rollouts', '?')} failed")


def run_row(run: Path) -> dict:
    m = json.loads((run / "metrics.json").read_text())
    record = json.loads((run / "laws" / "formula.json").read_text()) \
        if (run / "laws" / "formula.json").is_file() else {}
    scene, seed = m["dataset"], OmegaConf.load(run / ".hydra" / "config.yaml").seed
    x, truth = m["metrics"], record.get("against_truth", {})
    val = record.get("validation", {})
    key, goal = GOALS.get(scene, (None, None))
    failed = x.get("test/rollout_failed_share", float("nan"))
    met = (key is not None and x.get(key, np.inf) <= goal and failed == 0)
    return {"scene": scene, "seed": seed, "law kept": record.get("choice", "network"),
            "formula tuned": law_text(record.get("tuned")),
            "truth's form": {1.0: "yes", 0.0: "no"}.get(truth.get("tuned_form_is_truth"), "-"),
            "constants vs truth": (f"{truth['tuned_constants_vs_truth']:.2g}"
                                   if truth.get("tuned_form_is_truth") == 1.0 else "-"),
            "validation network: mean / typical @50, failed": scores(val.get("network")),
            "validation formula": scores(val.get("formula")),
            "formula's substeps": record.get("rollout_substeps", "-"),
            # law_choice's paired standard error of the two means (records since e81fd73)
            "standard error": (f"{record['choice_standard_error']:.2g}"
                               if record.get("choice_standard_error") is not None else "-"),
            "test @10": x.get("test/rollout_error@10"), "test @50": x.get("test/rollout_error@50"),
            "test @100": x.get("test/rollout_error@100"),
            "test median @100": x.get("test/rollout_error_median@100"),
            "failed": failed, "one-step NMSE": x.get("test/nmse"),
            "goal": f"{key.split('/')[1].replace('rollout_error', 'error')} <= {goal}"
            if key else "-", "met": "yes" if met else "no"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=Path("outputs/reports/default_jobs"))
    args = parser.parse_args()
    rows = [run_row(r) for r in args.runs]
    numeric = ["test @10", "test @50", "test @100", "test median @100", "failed",
               "one-step NMSE"]
    summary = []
    for scene in sorted({r["scene"] for r in rows}):
        group = [r for r in rows if r["scene"] == scene]
        s = {"scene": scene, "runs": len(group),
             "formula kept": sum(r["law kept"] == "formula" for r in group),
             "truth's form": sum(r["truth's form"] == "yes" for r in group),
             "goal met": sum(r["met"] == "yes" for r in group)}
        for k in numeric:
            v = np.array([r[k] for r in group], float)
            s[k] = (f"{v.mean():.3g} ± {v.std(ddof=1):.2g} ({v.min():.3g}-{v.max():.3g})"
                    if len(v) > 1 else f"{v[0]:.3g}")
        summary.append(s)
    for r in rows:
        for k in numeric:
            r[k] = f"{r[k]:.3g}"
    args.out.mkdir(parents=True, exist_ok=True)
    print(write_table(args.out, "default_jobs", list(rows[0]), rows,
                      "The default jobs' law and test rollouts, per run",
                      "validation: the formula stage's scores (mean / typical position error "
                      "after 50 steps, a failed rollout at the cap); the formula's substeps: "
                      "the integrator it was rolled out with; standard error: of the "
                      "difference of the two validation means, paired over the simulations "
                      "(bgn.laws.finetune.paired_standard_error); test: every test "
                      "simulation from frame 100, mean (median) position error, a failed "
                      "rollout at the cap."))
    print(write_table(args.out, "default_jobs_summary", list(summary[0]), summary,
                      "Per scene: mean ± standard deviation (min-max) over the runs"))
    print(f"\nwritten: {args.out}/default_jobs.md, default_jobs_summary.md (and .csv)")


if __name__ == "__main__":
    main()
