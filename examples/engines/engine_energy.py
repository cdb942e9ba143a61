"""The engines' own energy (and momenta) for arbitrary positions and velocities, e.g. a learned
model's rollout, so its drift is measured by the engine that made the data.

    python examples/engines/engine_energy.py data/external/rebound_nbody \
        --positions rollout.npz --split test

``rollout.npz`` holds ``positions`` (S, T, N, D) (or ``predicted``, as ``python -m bgn.evaluate``'s
``rollouts.npz`` does) and, optionally, ``velocities``; without them
velocities are finite differences of the positions (``frame_velocities``: five-point stencil,
minimum image where periodic), so compare a rollout with the truth passed through the same
differences (``--positions`` omitted: the dataset's own split). Prints the relative energy change
from frame 2 (the first with the five-point stencil) after 10 / 50 / 100 frames per
trajectory. Datasets made by pymunk_granular.py have no conserved energy and are refused.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from layouts import FILE_STEMS, minimum_image

AFTER = (10, 50, 100)  # frames after the first with the five-point stencil
CONSERVATIVE = ("rebound", "ase")  # the engines whose data keep an energy (pymunk dissipates)


def _pad3(x: np.ndarray) -> np.ndarray:
    """(..., N, D<=3) -> (..., N, 3) with zeros: both engines work in 3D."""
    pad = [(0, 0)] * (x.ndim - 1) + [(0, 3 - x.shape[-1])]
    return np.pad(np.asarray(x, dtype=np.float64), pad)


def rebound_energy(positions: np.ndarray, velocities: np.ndarray, masses: np.ndarray,
                   G: float = 1.0, softening: float = 0.0) -> dict[str, np.ndarray]:
    """Total energy, momentum (3,) and angular momentum (3,) per frame of one trajectory
    (positions, velocities (T, N, D), masses (N,)), from REBOUND Simulations built frame by frame.

    REBOUND's ``Simulation.energy()`` uses the unsoftened potential -G m_i m_j / r while its
    gravity uses Plummer softening, 1 / (r^2 + b^2)^(3/2); the difference is added so that the
    energy is the one the engine's equations of motion conserve."""
    import rebound

    x, v = _pad3(positions), _pad3(velocities)
    iu = np.triu_indices(len(masses), 1)
    mm = (masses[:, None] * masses[None, :])[iu]
    out = {"energy": np.empty(len(x)), "momentum": np.empty((len(x), 3)),
           "angular_momentum": np.empty((len(x), 3))}
    for t in range(len(x)):
        sim = rebound.Simulation()
        sim.G, sim.softening = G, softening
        for m, p, u in zip(masses, x[t], v[t]):
            sim.add(m=float(m), x=p[0], y=p[1], z=p[2], vx=u[0], vy=u[1], vz=u[2])
        r = np.linalg.norm(x[t][:, None] - x[t][None, :], axis=-1)[iu]
        correction = G * np.sum(mm * (1.0 / r - 1.0 / np.sqrt(r**2 + softening**2)))
        out["energy"][t] = sim.energy() + correction
        com = sim.com()
        out["momentum"][t] = com.m * np.array([com.vx, com.vy, com.vz])
        out["angular_momentum"][t] = sim.angular_momentum()
    return out


def fast_neighbour_list():
    """matscipy's neighbour list where installed (the same pairs as ASE's, several times
    faster), else None: ASE's own."""
    try:
        from matscipy.neighbours import neighbour_list
    except ImportError:
        return None
    return neighbour_list


def morse_calculator(morse: dict):
    """ASE's MorsePotential with the given keywords (epsilon, r0, rho0, rcut1, rcut2)."""
    from ase.calculators.morse import MorsePotential

    nl = fast_neighbour_list()
    return MorsePotential(**morse, **({"neighbor_list": nl} if nl is not None else {}))


def ase_morse_energy(positions: np.ndarray, velocities: np.ndarray, masses: np.ndarray,
                     cell: np.ndarray, pbc: np.ndarray, morse: dict) -> dict[str, np.ndarray]:
    """Total energy (ASE MorsePotential plus kinetic) and momentum per frame of one trajectory;
    ``cell`` (3,) edge lengths, ``pbc`` (3,) bools, ``morse`` the calculator's keywords."""
    from ase import Atoms

    x, v = _pad3(positions), _pad3(velocities)
    atoms = Atoms(numbers=[18] * x.shape[1], positions=x[0], cell=cell, pbc=pbc,
                  masses=np.asarray(masses, dtype=np.float64))
    atoms.calc = morse_calculator(morse)
    out = {"energy": np.empty(len(x)), "momentum": np.empty((len(x), 3))}
    for t in range(len(x)):
        atoms.set_positions(x[t])
        atoms.set_velocities(v[t])
        out["energy"][t] = atoms.get_potential_energy() + atoms.get_kinetic_energy()
        out["momentum"][t] = atoms.get_momenta().sum(0)
    return out


def frame_velocities(positions: np.ndarray, dt: float, box: np.ndarray | None = None
                     ) -> np.ndarray:
    """Velocities (T, N, D) from positions: the five-point stencil inside (error ~ dt^4, so a
    collision spread over a few frames still gives the kinetic energy to a small fraction),
    central differences next to the ends and one-sided at the ends, all on positions unwrapped by
    the minimum image where ``box`` (D,) is periodic (np.inf for open dimensions)."""
    d = minimum_image(np.diff(positions.astype(np.float64), axis=0), box)
    x = np.concatenate([np.zeros_like(d[:1]), np.cumsum(d, axis=0)])  # unwrapped, from frame 0
    v = np.empty(x.shape)
    v[0], v[-1] = d[0] / dt, d[-1] / dt
    v[1:-1] = (x[2:] - x[:-2]) / (2 * dt)
    v[2:-2] = (-x[4:] + 8 * x[3:-1] - 8 * x[1:-3] + x[:-4]) / (12 * dt)
    return v


def dataset_energy(data_dir: Path, positions: np.ndarray, velocities: np.ndarray | None,
                   split: str) -> list[dict[str, np.ndarray]]:
    """Energy series for trajectories (S, T, N, D) of ``split`` of the dataset in ``data_dir``,
    with the engine and parameters its engine.json records."""
    rec = json.loads((data_dir / "engine.json").read_text())
    p = rec["params"]
    if rec["engine"] == "rebound":
        with np.load(data_dir / "nbody.npz") as f:
            masses, dt = f["masses"][f["split"] == split], float(f["dt"])
        if velocities is None:
            velocities = np.stack([frame_velocities(x, dt) for x in positions])
        return [rebound_energy(x, v, m, p["G"], p["softening"])
                for x, v, m in zip(positions, velocities, masses)]
    if rec["engine"] == "ase":
        meta = json.loads((data_dir / "metadata.json").read_text())
        dt = meta["dt"] * meta["write_every"]
        box = np.asarray(p["box"], dtype=np.float64)
        if velocities is None:
            velocities = np.stack([frame_velocities(x, dt, box) for x in positions])
        cell = np.r_[box, np.ones(3 - len(box)) * p["cell_z"]][:3]
        pbc = np.r_[np.ones(len(box), bool), np.zeros(3 - len(box), bool)]
        masses = np.full(positions.shape[2], p["mass"])
        return [ase_morse_energy(x, v, masses, cell, pbc, p["morse"])
                for x, v in zip(positions, velocities)]
    raise SystemExit(f"{data_dir}/engine.json: engine {rec['engine']!r} conserves no energy "
                     "(dissipative); nothing to measure")


def _split_positions(data_dir: Path, split: str) -> np.ndarray:
    """The dataset's own trajectories of one split, (S, T, N, D)."""
    if (data_dir / "nbody.npz").exists():
        with np.load(data_dir / "nbody.npz") as f:
            return f["positions"][f["split"] == split]
    import h5py

    with h5py.File(data_dir / f"{FILE_STEMS[split]}.h5", "r") as f:
        return np.stack([f[k]["position"][()] for k in sorted(f)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", type=Path)
    ap.add_argument("--positions", type=Path, help="npz with positions (S,T,N,D) [velocities]")
    ap.add_argument("--split", default="test", choices=["train", "val", "test"])
    ap.add_argument("--key", help="the array of --positions to read (default: positions, else "
                    "predicted; 'true' gives the recorded frames of the same rollouts)")
    ap.add_argument("--conserved", action="store_true",
                    help="only answer whether the engine conserves an energy (exit 0 if so, "
                    "1 if not; regenerate.sh asks before it rolls out for this measurement)")
    ap.add_argument("--json", type=Path, metavar="FILE",
                    help="also write the changes there (examples/engines/summary.py's "
                    "energy table reads <run>/energy_<key>.json)")
    args = ap.parse_args()
    engine = json.loads((args.data_dir / "engine.json").read_text())["engine"]
    if args.conserved:
        raise SystemExit(0 if engine in CONSERVATIVE else 1)
    if engine not in CONSERVATIVE:
        raise SystemExit(f"{args.data_dir}/engine.json: engine {engine!r} conserves no energy "
                         "(dissipative); nothing to measure")
    velocities = None
    if args.positions is None:
        positions = _split_positions(args.data_dir, args.split)
    else:
        with np.load(args.positions) as f:  # bgn.eval.evaluate's rollouts.npz: "predicted"
            key = args.key or ("positions" if "positions" in f else "predicted")
            positions = f[key]
            velocities = f["velocities"] if "velocities" in f else None
    changes = []
    for s, e in enumerate(dataset_energy(args.data_dir, positions, velocities, args.split)):
        energy = e["energy"]
        rel = [float(abs(energy[2 + k] - energy[2]) / abs(energy[2]))
               for k in AFTER if 2 + k < len(energy) - 2]
        changes.append(rel)
        print(f"trajectory {s}: relative energy change after 10/50/100 frames "
              + " ".join(f"{r:.2e}" for r in rel))
    if args.json is not None:
        args.json.write_text(json.dumps({
            "engine": engine, "split": args.split, "positions": str(args.positions),
            "key": args.key, "after": list(AFTER), "relative_change": changes}, indent=1))


if __name__ == "__main__":
    main()
