"""The pair law bgn learned on an engine's data, against the engine's own force.

    python examples/engines/engine_law.py data/external/ase_morse_gas <run>/laws
    python examples/engines/engine_law.py data/external/rebound_nbody <run>/laws

Reads the engine's parameters (``engine.json`` of the dataset folder) and a ``python -m bgn.laws``
output folder (``law.csv``: the learned law and the formula read back on the training
distances; ``formula.json``, where ``finetune=true`` wrote one: the formula fitted to the
frames). The engine's force is computed by the engine itself, on a two-body system at each
distance (ASE's MorsePotential, smooth cutoff included; REBOUND's softened gravity, by one
leapfrog kick from rest as ``examples/heldout_laws/make.py`` scans it), not from a
transcription of its documentation. Prints, and writes beside the law as ``engine_law.md``
and ``engine_law.png``, the relative errors in bands of the training distances (by their
quantiles) and the figure.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

BANDS = ((0.0, 0.01), (0.01, 0.1), (0.1, 0.5), (0.5, 0.9), (0.9, 0.99), (0.99, 1.0))


def ase_morse_force(r: np.ndarray, morse: dict) -> np.ndarray:
    """f(r) between two unit-mass atoms, bgn's convention (> 0 repulsive), by ASE itself."""
    from ase import Atoms
    from engine_energy import morse_calculator

    out = np.empty(len(r))
    # a cell far larger than the cutoff (matscipy's neighbour list needs one), no periodicity
    atoms = Atoms(numbers=[18, 18], positions=[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
                  cell=[50.0, 50.0, 50.0], pbc=False)
    atoms.calc = morse_calculator(morse)
    for k, d in enumerate(r):
        atoms.set_positions([[0.0, 0.0, 0.0], [float(d), 0.0, 0.0]])
        out[k] = atoms.get_forces()[1, 0]  # on atom 1 along +x, away from atom 0
    return out


def engine_force(dataset: Path, r: np.ndarray) -> tuple[np.ndarray, str]:
    """The engine's pair force at ``r`` and a line naming it (engines with a pair law)."""
    record = json.loads((dataset / "engine.json").read_text())
    if record.get("engine") == "ase" and "morse" in record.get("params", {}):
        morse = record["params"]["morse"]
        text = (f"ASE {record.get('version')} MorsePotential: V = eps (exp(-2 rho0 (r/r0 - 1)) - "
                f"2 exp(-rho0 (r/r0 - 1))) times a smooth cutoff from rcut1 r0 to rcut2 r0; "
                + ", ".join(f"{k} = {v:.6g}" for k, v in morse.items()))
        return ase_morse_force(r, morse), text
    if record.get("engine") == "rebound":
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "heldout_laws"))
        from make import rebound_scan

        p = record["params"]
        text = (f"REBOUND {record.get('version')} gravity with Plummer softening: f = -G r / "
                f"(r^2 + b^2)^1.5, G = {p['G']:g}, b = {p['softening']:g}")
        return rebound_scan({"constants": {"G": p["G"], "b": p["softening"]}}, r), text
    raise SystemExit(f"{dataset}: engine {record.get('engine')!r} has no pair law this script "
                     "knows (ASE's Morse gas, REBOUND's softened gravity)")


def read_law_folder(laws: Path) -> dict[str, np.ndarray]:
    with open(laws / "law.csv") as f:
        rows = [row for row in csv.DictReader(f)]
    cols = {k: np.array([float(row[k]) for row in rows]) for k in ("r", "learned", "formula")}
    density = np.asarray(json.loads((laws / "law.json").read_text())["pairs"][0]["density"])
    cols["density"] = density
    if (laws / "formula.json").is_file():
        from bgn.laws.report import spec_values

        record = json.loads((laws / "formula.json").read_text())
        cols["fitted"] = spec_values(json.dumps(record["tuned"]), (0, 0), cols["r"])
        cols["fitted_text"] = record["tuned"]
    return cols


def bands_table(r: np.ndarray, density: np.ndarray, truth: np.ndarray,
                laws: dict[str, np.ndarray], relative: bool = True) -> list[str]:
    """Median / max error of each law against the engine in quantile bands of the training
    distances (``density``: the data's density of log r on the grid ``r``): relative to the
    engine's force (``relative``), else to its RMS size over the training distances."""
    weight = density * np.gradient(np.log(r))
    cdf = np.cumsum(weight) / weight.sum()
    scale = np.sqrt(np.average(truth**2, weights=weight))  # floor near the zero crossing
    lines = ["| data quantiles | r | " + " | ".join(f"{k} vs engine" for k in laws) + " |",
             "|---|---|" + "---|" * len(laws)]
    for lo, hi in BANDS:
        inside = (cdf >= lo) & (cdf <= hi) if hi < 1 else cdf >= lo
        if not inside.any():
            continue
        cells = []
        for values in laws.values():
            size = np.maximum(np.abs(truth[inside]), 0.01 * scale) if relative else scale
            rel = np.abs(values[inside] - truth[inside]) / size
            cells.append(f"{np.median(rel):.3g} / {rel.max():.3g}")
        lines.append(f"| {lo:g}-{hi:g} | {r[inside][0]:.3g}-{r[inside][-1]:.3g} | "
                     + " | ".join(cells) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path, help="the engine's dataset folder (engine.json)")
    ap.add_argument("laws", type=Path, help="a python -m bgn.laws output folder")
    args = ap.parse_args()
    law = read_law_folder(args.laws)
    truth, text = engine_force(args.dataset, law["r"])
    compared = {"learned": law["learned"], "read back": law["formula"]}
    if "fitted" in law:
        compared["fitted to the frames"] = law["fitted"]
    lines = [f"# {args.laws}: the learned pair law against the engine's", "", f"Engine: {text}.",
             "", "Relative errors |a - b| / |b| (|b| floored at 1 % of the engine's RMS force "
             "over the training distances), median / max, in quantile bands of the training "
             "pair distances:", "", *bands_table(law["r"], law["density"], truth, compared),
             "", "The same errors against the engine's RMS force over the training distances "
             "(where the force is near zero, beyond the cutoff's start, a relative error says "
             "little):", "",
             *bands_table(law["r"], law["density"], truth, compared, relative=False)]
    if "fitted" in law:
        lines += ["", f"Formula fitted to the frames (bgn.model.formula_law spec): "
                      f"`{json.dumps(law['fitted_text'])}`"]
    report = "\n".join(lines) + "\n"
    print(report)
    (args.laws / "engine_law.md").write_text(report)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, err) = plt.subplots(2, 1, figsize=(6.5, 7), sharex=True)
    ax.plot(law["r"], truth, "k:", lw=2, label="engine")
    floor = 0.01 * np.sqrt(np.mean(truth**2))
    for name, values in compared.items():
        ax.plot(law["r"], values, label=name)
        err.semilogy(law["r"], np.abs(values - truth) / np.maximum(np.abs(truth), floor),
                     label=name)
    ax.set(ylabel="f(r) between unit masses (> 0 repulsive)")
    ax.set_ylim(1.3 * truth.min(), 1.1 * truth.max())
    ax.legend()
    err.set(xlabel="r (training pair distances)",
            ylabel="relative error vs engine (floor: 1 % of its RMS)")
    err.legend()
    fig.tight_layout()
    fig.savefig(args.laws / "engine_law.png", dpi=120)


if __name__ == "__main__":
    main()
