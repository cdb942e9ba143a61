"""The `reproduce` preset's baseline step budgets recalibrated from finished runs of it.

    python docs/notes/reproduce/calibrate_baselines.py outputs/reports/reproduce
    python docs/notes/reproduce/calibrate_baselines.py <older report> <newer report>

Reads each run's `table1_per_seed.csv` (each cell's `train steps` and `train s`: its whole
training run, BGN's formula stage included) and conf/preset/reproduce.yaml, and prints per
scene and baseline the steps that would make the baseline's mean `train s` equal to BGN's mean
in the newest run. With one run: its steps x BGN's mean train s / its own (a ratio: a cell's
start-up and test do not scale with its steps, so a large cut undershoots and a large increase
overshoots). With two runs at different budgets of the same baseline: the line through the two
(steps, mean train s) points, solved for BGN's train s, which the fixed cost does not bias.
The printed block pastes into the preset's `max_steps` (rounded to tens of steps).
"""
import csv
import statistics
import sys
from pathlib import Path

from omegaconf import OmegaConf

LABELS = {"gns_given": "GNS", "cranmer_gn_given": "Cranmer GN"}


def cells(report: Path) -> dict[tuple[str, str], tuple[float, float]]:
    """(scene, model) -> (mean train steps, mean train s) of a run's Table 1 per seed."""
    rows: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for row in csv.DictReader(open(report / "table1_per_seed.csv")):
        model = "BGN" if row["model"].startswith("BGN") else row["model"].split(" +")[0]
        rows.setdefault((row["scene"], model), []).append(
            (float(row["train steps"]), float(row["train s"])))
    return {key: (statistics.mean(s for s, _ in v), statistics.mean(t for _, t in v))
            for key, v in rows.items()}


def main(reports: list[Path], preset: Path = Path("conf/preset/reproduce.yaml")) -> None:
    budgets = OmegaConf.to_container(OmegaConf.load(preset).max_steps)
    runs = [cells(r) for r in reports]
    newest = runs[-1]
    print("max_steps:  # recalibrated from", ", ".join(str(r) for r in reports))
    for scene, per_model in budgets.items():
        bgn = newest[(scene, "BGN")][1]
        new = {"bgn": per_model["bgn"]}
        for key, label in LABELS.items():
            steps, own = newest[(scene, label)]
            points = {run[(scene, label)] for run in runs if (scene, label) in run}
            if len(points) >= 2 and len({s for s, _ in points}) >= 2:
                (s1, t1), (s2, t2) = sorted(points)[:1] + sorted(points)[-1:]
                per_step = (t2 - t1) / (s2 - s1)
                fixed = t1 - per_step * s1
                target = (bgn - fixed) / per_step
                how = f"line: {fixed:.0f} s + {per_step * 1000:.1f} s per 1000 steps"
            else:
                target = steps * bgn / own
                how = "ratio"
            new[key] = int(round(target, -1))
            print(f"  # {scene} {key}: {steps:.0f} steps in {own:.0f} s against BGN's "
                  f"{bgn:.0f} s (ratio {own / bgn:.2f}; {how})")
        print(f"  {scene}: {{" + ", ".join(f"{k}: {v}" for k, v in new.items()) + "}")


if __name__ == "__main__":
    main([Path(p) for p in sys.argv[1:]])
