"""Charged bodies of hidden masses, in the plain-arrays layout ``python -m bgn.data.import``
reads: the development data of per-particle couplings of either sign (issue "Laws found, not
looked up", item 3; docs/design.md#n-body-scenes, "Charges").

    python examples/charges/make.py --out data/external/charges4
    python -m bgn.data.import data/external/charges4/charges.npz name=charges4

Made with bgn's own simulator (``bgn.sim.nbody``: gravity_r2's softened 1/s^2 law with charges
in place of the masses, like charges repel; DOP853 at rtol = atol = 1e-10), not an engine's.
Each trajectory draws its bodies' masses log-normal and their charges of random sign with
log-normal size. ``charges.npz`` records positions only (S, T, N, D), dt and each trajectory's
split, as a user's file without masses or charges would; ``_hidden/truth.npz`` (masses and
charges, (S, N), and the split) lies beside it, outside the imported file, for scoring only.
``make.json`` records the parameters, the seed and the command.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from rich.progress import track

from bgn.sim.nbody import NBodyScene
from bgn.sim.scene import State

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "engines"))
from layouts import assign_splits, output_dir, write_json, write_plain_npz  # noqa: E402


def charged_state(scene: NBodyScene, rng: np.random.Generator, charge_log_std: float) -> State:
    """The scene's drawn state (masses, positions, velocities) and charges of random sign."""
    state = scene.draw_state(rng)
    size = np.exp(charge_log_std * rng.standard_normal(scene.n_particles))
    sign = rng.choice([-1.0, 1.0], scene.n_particles)
    return State(state.positions, state.velocities, state.masses, charges=sign * size)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--sims", type=int, default=40)
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--bodies", type=int, default=4)
    ap.add_argument("--dim", type=int, default=2)
    ap.add_argument("--frame-dt", type=float, default=0.02, help="time between frames")
    ap.add_argument("--softening", type=float, default=0.01, help="s = r + softening")
    ap.add_argument("--mass-log-std", type=float, default=1.0, help="m = exp(std * z)")
    ap.add_argument("--charge-log-std", type=float, default=0.5, help="|q| = exp(std * z)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)

    scene = NBodyScene("r2", n_particles=args.bodies, dim=args.dim, softening=args.softening,
                       mass_log_std=args.mass_log_std)
    times = np.arange(args.frames) * args.frame_dt
    start = time.perf_counter()
    positions, masses, charges = [], [], []
    for s in track(range(args.sims), description="simulating"):
        state = charged_state(scene, np.random.default_rng([args.seed, s]), args.charge_log_std)
        positions.append(scene.simulate_from(state, times).positions)
        masses.append(state.masses)
        charges.append(state.charges)
    split = assign_splits(args.sims, args.seed)
    seconds = time.perf_counter() - start
    params = {k: getattr(args, k) for k in ("sims", "frames", "bodies", "dim", "frame_dt",
                                            "softening", "mass_log_std", "charge_log_std")}
    with output_dir(args.out, args.overwrite) as out:
        write_plain_npz(out / "charges.npz", positions=np.stack(positions), dt=args.frame_dt,
                        split=split)
        (out / "_hidden").mkdir()
        np.savez(out / "_hidden" / "truth.npz", masses=np.stack(masses),
                 charges=np.stack(charges), split=split.astype("U5"))
        write_json(out / "make.json", {
            "simulator": "bgn.sim.nbody (r2 potential, charges)", "params": params,
            "seed": args.seed, "command": "python " + " ".join(sys.argv),
            "generation_seconds": round(seconds, 2)})
    print(f"wrote {args.out}: {args.sims} x {args.frames} frames, {args.bodies} bodies in "
          f"{args.dim}D, masses and charges hidden (_hidden/truth.npz), {seconds:.1f} s")


if __name__ == "__main__":
    main()
