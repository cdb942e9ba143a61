"""The table of run.sh: every model on one dataset, scored by score.py, mean ± std over seeds.

    python examples/fluids/summary.py outputs/fluids sph_tgv

reads ``<out>/<name>_reference/score.json``, ``<out>/<name>_bgn_s<seed>/`` (score.json,
job_time.json) and ``<out>/<name>_{gns,segnn}_s<seed>/`` (score.json, peer.json) and writes
``<out>/<name>_summary.md`` and ``.csv``.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

METRICS = ("mse5", "mse10", "mse20", "mse", "sinkhorn", "e_kin_mse", "failed")
GIVEN_BGN = "positions of the last 6 frames, particle types (no wall distance, no external force)"


def cell(values: list[float]) -> str:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    if len(v) == 0:
        return "-"
    if len(v) == 1:
        return f"{v[0]:.4g}"
    return f"{v.mean():.4g} ± {v.std(ddof=1):.2g} ({v.min():.4g}–{v.max():.4g})"


def rows(out: Path, name: str) -> list[dict]:
    found = []
    ref = out / f"{name}_reference" / "score.json"
    if ref.is_file():
        s = json.loads(ref.read_text())
        found.append({"model": "constant velocity (no learning)", "given": "the last two of "
                      "the six frames", "seeds": 1, "steps": "-", "wall s": "-",
                      **{m: cell([s[m]]) for m in METRICS}})
    for model, label in (("bgn", "bgn (the job run.sh ran)"),
                         ("gns", "LagrangeBench GNS"), ("segnn", "LagrangeBench SEGNN")):
        runs = sorted(out.glob(f"{name}_{model}_s*"))
        scores, steps, wall, given = [], [], [], GIVEN_BGN
        for run in runs:
            if not (run / "score.json").is_file():
                continue
            scores.append(json.loads((run / "score.json").read_text()))
            if model == "bgn":
                wall.append(json.loads((run / "job_time.json").read_text())["seconds"])
                steps.append(json.loads((run / "metrics.json").read_text())["budget"]["steps"])
            else:
                peer = json.loads((run / "peer.json").read_text())
                wall.append(peer["train_s"])
                steps.append(peer["steps"])
                given = peer["given"]
        if scores:
            found.append({"model": label, "given": given, "seeds": len(scores),
                          "steps": cell(steps), "wall s": cell(wall),
                          **{m: cell([s[m] for s in scores]) for m in METRICS}})
    return found


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path)
    p.add_argument("name")
    a = p.parse_args(argv)
    table = rows(a.out, a.name)
    if not table:
        p.error(f"{a.out}: no scored runs of {a.name}; run examples/fluids/run.sh first")
    head = list(table[0])
    with open(a.out / f"{a.name}_summary.csv", "w", newline="") as f:
        w = csv.DictWriter(f, head)
        w.writeheader()
        w.writerows(table)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(str(r[h]) for h in head) + " |" for r in table]
    text = (f"{a.name}: test rollouts from the first six frames to the end, LagrangeBench's "
            "metrics (score.py; MSE of positions over the first 5/10/20 predicted frames and "
            "all of them, Sinkhorn and kinetic-energy MSE every 10th frame; means over the "
            "rollouts that did not fail), mean ± std (min–max) over seeds; wall s: the whole "
            "training job (bgn: start-up to test; the peer: its training call, compilation "
            "included)\n\n" + "\n".join(lines) + "\n")
    (a.out / f"{a.name}_summary.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
