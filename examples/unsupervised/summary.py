"""The table of examples/unsupervised/run.sh: per run trained without recorded masses
(``ablation=unsupervised``), the masses read per simulation through its learned law (the law
posterior, its scale placed by the scene's mass law) or, with an impulse head, through the
impacts its contact head sees (the impact posterior, each type's mass law as prior), against
the recorded ones, beside the physical estimator that knows the true law on the same windows,
and the forward figures.

    python examples/unsupervised/summary.py outputs/unsupervised/spring_s0 ... [--eval DIR]

``--eval``: the evaluation folder inside each run (default ``eval400``, run.sh's). Any run
evaluated so reads the same way, one trained with recorded masses too (its "trained with"
column names them; the per-simulation posteriors are then placed and spread on the validation
split's masses).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

# the per-simulation posteriors, as the run's metrics prefix them: the first one present
POSTERIORS = {"law_posterior": "learned law", "impact_posterior": "contact head's impacts"}
COLUMNS = [  # (header, key in <run>/eval400/metrics.json: "~" the run's posterior prefix)
    ("trained with", None),
    ("through", None),
    ("relative-mass R^2", "~/relmass_r2_estimate"),
    ("per-simulation mass error", "~/sim_mass_rel_err"),
    ("physical estimator, per simulation", "~/physical_sim_mass_rel_err"),
    ("physical estimator, relative-mass R^2", "~/physical_relmass_r2_estimate"),
    ("scale", "~/scale"),
    ("information over the prior (nats)", "~/info_gain"),
    ("over the type", "~/info_gain_over_type"),
    ("shift std", "~/shift_std"),
    ("coverage 50 / 90", None),
    ("largest coverage deviation", "~/coverage_max_dev"),
    ("tail (share x width)", None),
    ("share of the prior", "~/contamination"),
    ("NMSE", "nmse"),
    ("mean error @100", "rollout/pos_err_mean@100"),
]


def cell(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return "-" if value is None else str(value)


def row(run: Path, folder: str) -> list[str]:
    record = json.loads((run / folder / "metrics.json").read_text())
    m, model = record["metrics"], record["provenance"].get("model", {})
    prefix = next((p for p in POSTERIORS if f"{p}/sim_mass_rel_err" in m), None)
    out = [run.name]
    for header, key in COLUMNS:
        if header == "trained with":
            sup = model.get("supervision", {})
            out.append("; ".join(f"{q} ({', '.join(t)})" for q, t in sup.items()) or "-")
        elif header == "through":
            out.append(POSTERIORS.get(prefix, "-"))
        elif header.startswith("coverage"):
            out.append(f"{cell(m.get(f'{prefix}/coverage50'))} / "
                       f"{cell(m.get(f'{prefix}/coverage90'))}")
        elif header.startswith("tail"):  # the law posterior's likelihood's heavy tail
            share = m.get(f"{prefix}/tail_share")
            out.append("-" if share is None else
                       "none" if share == 0 else f"{share:g} x {m[f'{prefix}/tail_width']:g}")
        else:
            out.append(cell(m.get(key.replace("~", str(prefix)))))
    return out


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--eval", default="eval400", help="the evaluation folder in each run")
    args = ap.parse_args(argv)
    missing = [str(r) for r in args.runs if not (r / args.eval / "metrics.json").is_file()]
    if missing:
        ap.error(f"no {args.eval}/metrics.json in {', '.join(missing)}: run "
                 "examples/unsupervised/run.sh first (or name the folder with --eval)")
    print("| run | " + " | ".join(h for h, _ in COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    for run in args.runs:
        print("| " + " | ".join(row(run, args.eval)) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
