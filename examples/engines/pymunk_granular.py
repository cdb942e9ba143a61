"""Dissipative granular discs under gravity in a walled box from pymunk (Chipmunk2D), written in
the GNS / learning_to_simulate npz layout for bgn's importer.

    python examples/engines/pymunk_granular.py --out data/external/pymunk_granular

The physics fits none of bgn's structured heads on purpose: contacts lose energy (restitution
below 1) and carry Coulomb friction, a tangential force that also spins the discs (rotation is
not in the files), and the space damps every velocity (a velocity-dependent drag). Writes
{train,valid,test}.npz (``simulation_trajectory_<j>``: positions (T, N, 2) float32,
particle_type (N,): 0 small discs, 1 large discs), metadata.json (bounds, dt between frames,
connectivity radius, dim, sequence_length, statistics of the training split), energy.npz (the
engine's kinetic energy per frame, translation and rotation, and the gravitational potential
energy; not conserved) and engine.json. Units are the box's: the box is [0, 1]^2, time in
seconds of the engine's clock.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pymunk
from layouts import assign_splits, engine_record, output_dir, write_energy, write_gns, write_json

BOX = 1.0


def place_discs(rng: np.random.Generator, radii: np.ndarray, low: float) -> np.ndarray:
    """Non-overlapping centres inside the box at heights above ``low`` (rejection sampling,
    largest discs first)."""
    pos = np.full((len(radii), 2), np.inf)
    for i in np.argsort(-radii, kind="stable"):
        for _ in range(10_000):
            p = rng.uniform([radii[i], max(radii[i], low)], [BOX - radii[i], BOX - radii[i]])
            gap = np.linalg.norm(pos - p, axis=1) - radii - radii[i]
            if np.all(gap > 1e-3 * BOX):
                pos[i] = p
                break
        else:
            raise SystemExit("the discs do not fit: lower --discs or --fill-from")
    return pos


def simulate(rng: np.random.Generator, args: argparse.Namespace
             ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """One trajectory: positions (T, N, 2), particle types (N,) and energies per frame."""
    n = args.discs
    types = np.arange(n) % 2  # half small (0), half large (1)
    radii = np.where(types == 0, args.radius_small, args.radius_large)
    masses = args.density * np.pi * radii**2

    space = pymunk.Space()
    space.gravity = (0.0, -args.gravity)
    space.damping = args.damping
    space.iterations = args.iterations
    space.collision_slop = args.slop * args.radius_small  # the default 0.1 is a tenth of the box
    corners = [(0.0, 0.0), (BOX, 0.0), (BOX, BOX), (0.0, BOX)]
    for a, b in zip(corners, corners[1:] + corners[:1]):
        wall = pymunk.Segment(space.static_body, a, b, 0.0)
        wall.elasticity, wall.friction = args.wall_elasticity, args.wall_friction
        space.add(wall)

    pos0 = place_discs(rng, radii, args.fill_from * BOX)
    vel0 = args.velocity_std * rng.standard_normal((n, 2))
    bodies = []
    for m, r, p, v in zip(masses, radii, pos0, vel0):
        body = pymunk.Body(float(m), pymunk.moment_for_circle(float(m), 0.0, float(r)))
        body.position, body.velocity = tuple(p), tuple(v)
        shape = pymunk.Circle(body, float(r))
        shape.elasticity, shape.friction = args.elasticity, args.friction
        space.add(body, shape)
        bodies.append(body)

    step = args.frame_dt / args.substeps
    pos = np.empty((args.frames, n, 2))
    en = {"kinetic": np.empty(args.frames), "potential": np.empty(args.frames)}
    for t in range(args.frames):
        if t:
            for _ in range(args.substeps):
                space.step(step)
        pos[t] = [b.position for b in bodies]
        en["kinetic"][t] = sum(b.kinetic_energy for b in bodies)
        en["potential"][t] = args.gravity * float(masses @ pos[t, :, 1])
    en["energy"] = en["kinetic"] + en["potential"]
    return pos, types, en


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--sims", type=int, default=40)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--discs", type=int, default=60)
    ap.add_argument("--radius-small", type=float, default=0.02)
    ap.add_argument("--radius-large", type=float, default=0.03)
    ap.add_argument("--density", type=float, default=1.0, help="mass per area")
    ap.add_argument("--gravity", type=float, default=1.0)
    ap.add_argument("--damping", type=float, default=0.9,
                    help="share of velocity kept per second (pymunk Space.damping)")
    ap.add_argument("--elasticity", type=float, default=0.9, help="per disc; pairs multiply")
    ap.add_argument("--friction", type=float, default=0.7, help="per disc; pairs multiply")
    ap.add_argument("--wall-elasticity", type=float, default=0.9)
    ap.add_argument("--wall-friction", type=float, default=0.7)
    ap.add_argument("--velocity-std", type=float, default=1.0, help="initial, per component")
    ap.add_argument("--fill-from", type=float, default=0.3, help="lowest initial height")
    ap.add_argument("--frame-dt", type=float, default=0.01)
    ap.add_argument("--substeps", type=int, default=10, help="engine steps per frame")
    ap.add_argument("--iterations", type=int, default=20, help="pymunk solver iterations")
    ap.add_argument("--slop", type=float, default=0.02, help="allowed overlap, x small radius")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args()

    start = time.perf_counter()
    runs = [simulate(np.random.default_rng([args.seed, s]), args) for s in range(args.sims)]
    split = assign_splits(args.sims, args.seed)
    seconds = time.perf_counter() - start
    metadata = {
        "bounds": [[0.0, BOX], [0.0, BOX]], "dim": 2, "dt": args.frame_dt,
        # a contact needs centres within two large radii; the margin covers a frame of motion
        "default_connectivity_radius": 2.5 * args.radius_large,
    }
    params = {k: v for k, v in vars(args).items() if k not in ("out", "overwrite", "seed")}
    params.update(box=[BOX, BOX], type_radius=[args.radius_small, args.radius_large],
                  type_mass=[args.density * np.pi * r**2
                             for r in (args.radius_small, args.radius_large)])
    with output_dir(args.out, args.overwrite) as out:
        write_gns(out, [r[0] for r in runs], [r[1] for r in runs], split, metadata)
        write_energy(out, split, [r[2] for r in runs])
        write_json(out / "engine.json",
                   engine_record("pymunk", pymunk.version, params, args.seed, seconds))
    print(f"wrote {args.out}: {args.sims} x {args.frames} frames, {args.discs} discs, "
          f"{seconds:.1f} s")


if __name__ == "__main__":
    main()
