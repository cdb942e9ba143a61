"""The `reproduce` preset's baseline step budgets recalibrated from a finished run of it.

    python docs/notes/reproduce/calibrate_baselines.py outputs/reports/reproduce

Reads the run's `table1_per_seed.csv` (each cell's `train steps` and `train s`: its whole
training run, BGN's formula stage included) and conf/preset/reproduce.yaml, and prints per
scene and baseline the steps that would have made the baseline's mean `train s` equal to
BGN's on that machine and load: its steps x BGN's mean train s / its own. A cell's start-up
and test do not scale with its steps, so the figure slightly overshoots where the ratio is far
from 1; rerun the baseline cells with the new budgets and check Table 1's `train s` again.
The printed block pastes into the preset's `max_steps` (rounded to tens of steps).
"""
import csv
import statistics
import sys
from pathlib import Path

from omegaconf import OmegaConf

LABELS = {"gns_given": "GNS", "cranmer_gn_given": "Cranmer GN"}


def main(report: Path, preset: Path = Path("conf/preset/reproduce.yaml")) -> None:
    budgets = OmegaConf.to_container(OmegaConf.load(preset).max_steps)
    seconds: dict[tuple[str, str], list[float]] = {}
    for row in csv.DictReader(open(report / "table1_per_seed.csv")):
        model = "BGN" if row["model"].startswith("BGN") else row["model"].split(" +")[0]
        seconds.setdefault((row["scene"], model), []).append(float(row["train s"]))
    print("max_steps:  # recalibrated from", report)
    for scene, per_model in budgets.items():
        bgn = statistics.mean(seconds[(scene, "BGN")])
        new = {"bgn": per_model["bgn"]}
        for key, label in LABELS.items():
            own = statistics.mean(seconds[(scene, label)])
            new[key] = int(round(per_model[key] * bgn / own, -1))
            print(f"  # {scene} {key}: {per_model[key]} steps in {own:.0f} s against BGN's "
                  f"{bgn:.0f} s (ratio {own / bgn:.2f})")
        print(f"  {scene}: {{" + ", ".join(f"{k}: {v}" for k, v in new.items()) + "}")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
