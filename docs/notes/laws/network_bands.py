"""The network's pair law against the truth per band of the training pairs' distances (issue
56, item 5: within 5 % wherever the data put at least 1 % of the pair distances), one row per
run, from the formula stage's own record of each run (``<run>/laws/law.json``: its ``bands``,
the network law in physical units against the scene's true law on 48 log-spaced distances
in each band of the distance quantiles, ``bgn.laws.compare``; near a zero crossing relative
to the law's change over 10 % of r). Writes bands.md, bands.csv and bands.png (the relative
error against r, one line per run, a panel per scene) in ``--out``.

    python docs/notes/laws/network_bands.py outputs/spring_s0 outputs/gravity_r2_s0 ... \\
        --label before --out outputs/reports/network_bands
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from bgn.figures import save
from bgn.laws.compare import relative_error
from bgn.tables import write_table

GOAL = 0.05           # the bar: within 5 % ...
COVERED = (0.01, 0.99)  # ... between these quantiles of the pair distances


def band_name(band: dict) -> str:
    q0, q1 = band["quantiles"]
    return f"{100 * q0:g}-{100 * q1:g} %"


def run_row(run: Path, label: str) -> tuple[dict, dict]:
    """A run's table row and its law curve (r, relative error) for the figure."""
    record = json.loads((run / "laws" / "law.json").read_text())
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml") if (run / ".hydra").exists() \
        else OmegaConf.load(run / "train_config.yaml")
    if len(record["pairs"]) != 1:
        raise SystemExit(f"{run}: {len(record['pairs'])} pairs of types; this table reads one")
    pair = record["pairs"][0]
    row = {"scene": record["scene"], "seed": int(cfg.seed), "trained with": label,
           "truth": record.get("truth_text") or "unknown"}
    inside = []
    for band in pair["bands"]:
        err = band.get("learned_vs_truth")
        if err is None:
            raise SystemExit(f"{run}: no truth to score against (imported data without a law)")
        row[band_name(band)] = f"{err['median']:.2g} / {err['max']:.2g}"
        q0, q1 = band["quantiles"]
        if q0 >= COVERED[0] - 1e-12 and q1 <= COVERED[1] + 1e-12:
            inside.append(err["max"])
    row["worst 1-99 %"] = max(inside)
    row["within 5 % over 1-99 %"] = "yes" if max(inside) <= GOAL else "no"
    with (run / "laws" / "law.csv").open() as f:
        rows = list(csv.DictReader(f))
    r = np.array([float(x["r"]) for x in rows])
    learned = np.array([float(x["learned"]) for x in rows])
    truth = np.array([float(x["truth"]) for x in rows])
    covered = [b["r"] for b in pair["bands"] if b["quantiles"][0] >= COVERED[0] - 1e-12
               and b["quantiles"][1] <= COVERED[1] + 1e-12]
    return row, {"r": r, "error": relative_error(learned, truth, r),
                 "lo": float(covered[0][0]), "hi": float(covered[-1][1])}


def figure(curves: dict[str, list[tuple[str, dict]]]):
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(curves), figsize=(4.2 * len(curves), 3.4), squeeze=False)
    for ax, (scene, runs) in zip(axes[0], sorted(curves.items())):
        for name, c in runs:
            ax.loglog(c["r"], np.maximum(c["error"], 1e-6), lw=1, label=name)
        ax.axvspan(runs[0][1]["lo"], runs[0][1]["hi"], color="0.9", zorder=0)
        ax.axhline(GOAL, color="k", ls="--", lw=0.8)
        ax.set(title=scene, xlabel="r", ylabel="|network - truth| / |truth|")
        ax.legend(fontsize=6)
    fig.tight_layout()
    return fig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--label", action="append", default=None,
                        help="what the runs were trained with (one, or one per run)")
    parser.add_argument("--out", type=Path, default=Path("outputs/reports/network_bands"))
    args = parser.parse_args()
    labels = args.label or ["-"]
    if len(labels) not in (1, len(args.runs)):
        parser.error(f"{len(labels)} labels for {len(args.runs)} runs: give one, or one per run")
    labels = labels * len(args.runs) if len(labels) == 1 else labels
    rows, curves = [], {}
    for run, label in zip(args.runs, labels):
        missing = run / "laws" / "law.json"
        if not missing.exists():
            parser.error(f"{missing} does not exist: the run has no formula stage record "
                         "(model.law=auto writes it; else python -m bgn.laws <run> finetune=false)")
        row, curve = run_row(run, label)
        rows.append(row)
        curves.setdefault(row["scene"], []).append((f"{label} s{row['seed']}", curve))
    bands = [k for k in rows[0] if k.endswith(" %") and k[0].isdigit()]
    columns = ["scene", "trained with", "seed", "truth", *bands, "worst 1-99 %",
               "within 5 % over 1-99 %"]
    args.out.mkdir(parents=True, exist_ok=True)
    for row in rows:
        row["worst 1-99 %"] = f"{row['worst 1-99 %']:.2g}" if math.isfinite(
            row["worst 1-99 %"]) else "nan"
    print(write_table(args.out, "bands", columns, rows,
                      "The network law against the truth per band of the pair distances",
                      "Each band: the median / largest relative error of the network law "
                      "(physical units) against the true law, over the band's distances."))
    save(figure(curves), args.out / "bands.png")
    print(f"\nwritten: {args.out}/bands.md, bands.csv, bands.png")


if __name__ == "__main__":
    main()
