"""A chaotic 2D Morse fluid in a periodic box from ASE (MorsePotential calculator,
VelocityVerlet), written in LagrangeBench's HDF5 layout for bgn's importer.

    python examples/engines/ase_morse_gas.py --out data/external/ase_morse_gas

Writes {train,valid,test}.h5 (groups "00000".. with wrapped ``position`` (T, N, 2) and
``particle_type`` (N,) zeros), metadata.json (LagrangeBench keys: dt of the integrator,
write_every, bounds, periodic_boundary_conditions, default_connectivity_radius = the potential's
outer cutoff, statistics of the training split), energy.npz (the engine's total, potential and
kinetic energy and momentum per written frame) and engine.json.

Units are ASE's: energy eV, length Angstrom, mass amu, so with epsilon = 1 eV and mass 1 amu
the time unit sqrt(amu A^2 / eV) is 1 A sqrt(m / epsilon). The defaults put the well where
Lennard-Jones with sigma = 1 has it (r0 = 2^(1/6)); ASE's own defaults are chosen "similar to
Lennard-Jones". matscipy's neighbour list, where installed, replaces ASE's (the calculator's
``neighbor_list`` hook; same pairs, several times faster).
"""

from __future__ import annotations

import argparse
import time

import ase
import numpy as np
from ase import Atoms
from ase.md.verlet import VelocityVerlet
from engine_energy import fast_neighbour_list, morse_calculator
from layouts import (
    assign_splits,
    engine_record,
    output_dir,
    write_energy,
    write_json,
    write_lagrangebench,
)

CELL_Z = 10.0  # the non-periodic third cell edge; atoms stay at z = 0 (no force along z)


def simulate(rng: np.random.Generator, args: argparse.Namespace, morse: dict, box: float
             ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """One trajectory: wrapped positions (T, N, 2) and the engine's energies per frame."""
    n = args.atoms
    side = int(np.ceil(np.sqrt(n)))
    grid = (np.arange(side) + 0.5) * box / side
    sites = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    # a jittered square lattice: no overlapping atoms; the burn-in melts its memory
    xy = sites[rng.permutation(len(sites))[:n]] + rng.uniform(-0.1, 0.1, (n, 2)) * box / side
    atoms = Atoms(numbers=[18] * n, positions=np.c_[xy, np.zeros(n)],
                  cell=[box, box, CELL_Z], pbc=[True, True, False], masses=np.full(n, args.mass))
    v = rng.standard_normal((n, 2))
    v -= v.mean(0)  # no net momentum: the box does not drift
    # kinetic energy N kT (2 degrees of freedom per atom), T in units of epsilon / k_B
    v *= np.sqrt(n * args.temperature / (0.5 * args.mass * (v**2).sum()))
    atoms.set_velocities(np.c_[v, np.zeros(n)])
    atoms.calc = morse_calculator(morse)
    md = VelocityVerlet(atoms, timestep=args.md_dt)
    md.run(args.burn_in)

    pos = np.empty((args.frames, n, 2))
    en = {k: np.empty(args.frames) for k in ("energy", "potential", "kinetic")}
    en["momentum"] = np.empty((args.frames, 3))
    for t in range(args.frames):
        if t:
            md.run(args.write_every)
        pos[t] = atoms.get_positions(wrap=True)[:, :2]  # LagrangeBench stores wrapped positions
        en["potential"][t] = atoms.get_potential_energy()
        en["kinetic"][t] = atoms.get_kinetic_energy()
        en["energy"][t] = en["potential"][t] + en["kinetic"][t]
        en["momentum"][t] = atoms.get_momenta().sum(0)
    return pos, en


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--sims", type=int, default=30)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--atoms", type=int, default=64)
    ap.add_argument("--density", type=float, default=0.4, help="atoms per A^2")
    ap.add_argument("--temperature", type=float, default=1.0, help="initial kT / epsilon")
    ap.add_argument("--md-dt", type=float, default=0.01, help="VelocityVerlet time step")
    ap.add_argument("--write-every", type=int, default=2, help="MD steps between frames")
    ap.add_argument("--burn-in", type=int, default=200, help="MD steps before frame 0")
    ap.add_argument("--epsilon", type=float, default=1.0, help="well depth, eV")
    ap.add_argument("--r0", type=float, default=2 ** (1 / 6), help="well position, A")
    ap.add_argument("--rho0", type=float, default=6.0, help="stiffness (ASE's default)")
    ap.add_argument("--rcut1", type=float, default=1.9, help="smooth cutoff starts, x r0")
    ap.add_argument("--rcut2", type=float, default=2.7, help="smooth cutoff ends, x r0")
    ap.add_argument("--mass", type=float, default=1.0, help="amu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()

    morse = {"epsilon": args.epsilon, "r0": args.r0, "rho0": args.rho0, "rcut1": args.rcut1,
             "rcut2": args.rcut2}
    cutoff = args.rcut2 * args.r0
    box = float(np.sqrt(args.atoms / args.density))
    if box < 2 * cutoff:
        raise SystemExit(f"box {box:.2f} < 2 x cutoff {cutoff:.2f}: "
                         "lower --density or raise --atoms")
    start = time.perf_counter()
    runs = [simulate(np.random.default_rng([args.seed, s]), args, morse, box)
            for s in range(args.sims)]
    split = assign_splits(args.sims, args.seed)
    seconds = time.perf_counter() - start
    metadata = {
        "case": "MORSE2D", "solver": f"ase {ase.__version__} VelocityVerlet, MorsePotential",
        "dim": 2, "dx": box / np.ceil(np.sqrt(args.atoms)), "dt": args.md_dt,
        "write_every": args.write_every,
        "t_end": args.md_dt * args.write_every * (args.frames - 1),
        "bounds": [[0.0, box], [0.0, box]], "periodic_boundary_conditions": [True, True],
        "default_connectivity_radius": cutoff, "num_particles_max": args.atoms,
    }
    params = {k: getattr(args, k) for k in
              ("sims", "frames", "atoms", "density", "temperature", "md_dt", "write_every",
               "burn_in", "mass")}
    params.update(morse=morse, box=[box, box], cell_z=CELL_Z, dim=2,
                  neighbour_list="matscipy" if fast_neighbour_list() else "ase")
    with output_dir(args.out, args.overwrite) as out:
        write_lagrangebench(out, [p for p, _ in runs],
                            [np.zeros(args.atoms, dtype=np.int64)] * args.sims, split, metadata)
        write_energy(out, split, [e for _, e in runs])
        write_json(out / "engine.json",
                   engine_record("ase", ase.__version__, params, args.seed, seconds))
    print(f"wrote {args.out}: {args.sims} x {args.frames} frames, {args.atoms} atoms, "
          f"{seconds:.1f} s")


if __name__ == "__main__":
    main()
