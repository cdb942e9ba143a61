"""Few-body gravity from REBOUND (IAS15), written as plain arrays for bgn's importer.

    python examples/engines/rebound_nbody.py --out data/external/rebound_nbody

Writes ``nbody.npz`` (positions (S, T, N, D), velocities (S, T, N, D) from the engine, masses
(S, N), dt, split (S,)), ``energy.npz`` (the engine's energy, momentum and angular momentum per
frame, see engine_energy.py) and ``engine.json`` (engine, version, parameters, seed, command).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import rebound
from engine_energy import rebound_energy
from layouts import (
    assign_splits,
    engine_record,
    output_dir,
    write_energy,
    write_json,
    write_plain_npz,
)


def simulate(rng: np.random.Generator, args: argparse.Namespace) -> tuple[np.ndarray, ...]:
    """One trajectory: positions, velocities (T, N, 3) at equal spacing and masses (N,)."""
    n = args.bodies
    masses = np.exp(args.mass_log_std * rng.standard_normal(n))
    x = rng.standard_normal((n, 3))
    v = rng.standard_normal((n, 3))
    # centre-of-mass frame, then velocities scaled to the virial ratio K / |U| asked for, so
    # every system starts bound with the same balance of kinetic and potential energy
    x -= masses @ x / masses.sum()
    v -= masses @ v / masses.sum()
    iu = np.triu_indices(n, 1)
    r = np.linalg.norm(x[:, None] - x[None, :], axis=-1)[iu]
    potential = -args.G * np.sum((masses[:, None] * masses[None, :])[iu]
                                 / np.sqrt(r**2 + args.softening**2))
    kinetic = 0.5 * np.sum(masses * (v**2).sum(1))
    v *= np.sqrt(args.virial * abs(potential) / kinetic)

    sim = rebound.Simulation()
    sim.G, sim.softening, sim.integrator = args.G, args.softening, "ias15"
    for m, p, u in zip(masses, x, v):
        sim.add(m=float(m), x=p[0], y=p[1], z=p[2], vx=u[0], vy=u[1], vz=u[2])
    pos = np.empty((args.frames, n, 3))
    vel = np.empty((args.frames, n, 3))
    buf = np.empty((n, 6))
    for t in range(args.frames):
        # exact_finish_time: IAS15 lands on the frame time, so frames are equally spaced
        sim.integrate(t * args.frame_dt, exact_finish_time=1)
        sim.serialize_particle_data(xyzvxvyvz=buf)
        pos[t], vel[t] = buf[:, :3], buf[:, 3:]
    return pos, vel, masses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--sims", type=int, default=40)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--bodies", type=int, default=5)
    ap.add_argument("--frame-dt", type=float, default=0.01, help="time between frames")
    ap.add_argument("--G", type=float, default=1.0)
    ap.add_argument("--softening", type=float, default=0.1, help="Plummer length b")
    ap.add_argument("--mass-log-std", type=float, default=0.7, help="m = exp(std * z)")
    ap.add_argument("--virial", type=float, default=0.5, help="initial K / |U|")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()

    start = time.perf_counter()
    runs = [simulate(np.random.default_rng([args.seed, s]), args) for s in range(args.sims)]
    pos, vel, masses = (np.stack(a) for a in zip(*runs))
    energy = [rebound_energy(p, v, m, args.G, args.softening) for p, v, m in runs]
    split = assign_splits(args.sims, args.seed)
    seconds = time.perf_counter() - start
    params = {k: getattr(args, k) for k in
              ("sims", "frames", "bodies", "frame_dt", "G", "softening", "mass_log_std",
               "virial")}
    params.update(dim=3, integrator="ias15", softening_form="plummer")
    with output_dir(args.out, args.overwrite) as out:
        write_plain_npz(out / "nbody.npz", positions=pos, velocities=vel, masses=masses,
                        dt=args.frame_dt, split=split)
        write_energy(out, split, energy)
        write_json(out / "engine.json",
                   engine_record("rebound", rebound.__version__, params, args.seed, seconds))
    print(f"wrote {args.out}: {args.sims} x {args.frames} frames, {args.bodies} bodies, "
          f"{seconds:.1f} s")


if __name__ == "__main__":
    main()
