"""Make an SPH dataset with JAX-SPH, written in LagrangeBench's HDF5 layout.

Runs in the peer environment (setup_peer.sh):

    .venv-peer/bin/python examples/fluids/make_sph.py tgv --out data/external/sph_tgv
    .venv-peer/bin/python examples/fluids/make_sph.py dam --out data/external/sph_dam

writes ``{train,valid,test}.h5`` (one group per trajectory: ``position`` (T, N, 2),
``particle_type`` (N,), 0 fluid and 1 wall) and ``metadata.json`` with the keys
LagrangeBench's loader reads (``dt`` the engine's step, ``write_every`` steps per frame,
``bounds``, ``periodic_boundary_conditions``, ``default_connectivity_radius``,
``num_particles_max``, ``dx``, statistics of per-frame velocity and acceleration over the
training split) plus the engine's own cost, ``engine_seconds_per_step`` (after compilation,
on this machine, one value per split: its last trajectory's; a figure for the speed table
wants the machine otherwise idle) and the fluid's kinetic energy per frame (``ekin``, the same
trajectory). Each trajectory is saved to ``parts/`` as soon as it is made, so a run that is
stopped continues where it was (each one's parameters are drawn from its own seed, not from
the order they are made in); a split's file is written when all its trajectories are there. A
split already there is kept unless --overwrite.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import h5py
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)     # JAX-SPH's default precision

from jax import jit  # noqa: E402
from jax_sph import partition  # noqa: E402
from jax_sph.integrator import si_euler  # noqa: E402
from jax_sph.jax_md.partition import Sparse  # noqa: E402
from jax_sph.solver import WCSPH  # noqa: E402
from jax_sph.utils import Tag  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sph_cases import CASES, config  # noqa: E402

# per case: particle spacing, steps per frame, trajectories per split (train, valid, test)
DEFAULTS = {"tgv": dict(dx=0.02, write_every=100, trajectories=(12, 4, 4)),
            "dam": dict(dx=0.04, write_every=50, trajectories=(12, 4, 4))}
SPLITS = ("train", "valid", "test")
GRAVITY_FILE = """# gravity on every particle, per unit mass: LagrangeBench's external force
import jax.numpy as jnp


def force_fn(r):
    return jnp.zeros_like(r).at[1].set(-1.0)
"""
CONNECTIVITY = 1.45          # LagrangeBench's default connectivity radius, in units of dx


def simulate(case: str, seed: int, dx: float, write_every: int, rng: np.random.Generator,
             t_end: float | None = None, tiles: int = 1) -> tuple[np.ndarray, np.ndarray, dict]:
    """One trajectory: positions every ``write_every`` engine steps, the particle types, and
    what the engine reports (its step, the box, seconds per step after compilation).
    ``tiles``: ``sph_cases.config``'s."""
    cfg = config(case, seed, dx, rng, tiles)
    if t_end is not None:
        cfg.solver.t_end = t_end
    setup = CASES[case](cfg)
    cfg, box, state, g_ext_fn, bc_fn, nw_fn, eos, _, displacement_fn, shift_fn = \
        setup.initialize()
    solver = WCSPH(displacement_fn, eos, g_ext_fn, cfg.case.dx, cfg.case.dim, cfg.solver.dt,
                   cfg.case.c_ref, cfg.solver.eta_limiter, cfg.solver.name, cfg.kernel.name,
                   cfg.solver.is_bc_trick, cfg.solver.density_evolution,
                   cfg.solver.artificial_alpha, cfg.solver.free_slip,
                   cfg.solver.density_renormalize, cfg.solver.heat_conduction)
    neighbor_fn = partition.neighbor_list(
        displacement_fn, box, r_cutoff=solver._kernel_fn.cutoff, backend=cfg.nl.backend,
        capacity_multiplier=1.25, mask_self=False, format=Sparse,
        num_particles_max=state["r"].shape[0], num_partitions=cfg.nl.num_partitions,
        pbc=np.array(cfg.case.pbc))
    n = int((state["tag"] != Tag.PAD_VALUE).sum())
    neighbors = neighbor_fn.allocate(state["r"], num_particles=n)
    advance = jit(si_euler(cfg.solver.tvf, solver.forward_wrapper(), shift_fn, bc_fn, nw_fn))
    state, neighbors = advance(0.0, state, neighbors)          # compile, initial accelerations
    state["r"].block_until_ready()

    steps = cfg.solver.sequence_length
    frames, ekin = [np.asarray(state["r"])], []
    fluid = np.asarray(state["tag"]) == Tag.FLUID
    start = time.perf_counter()
    for step in range(1, steps + 1):
        new_state, new_neighbors = advance(cfg.solver.dt, state, neighbors)
        if new_neighbors.did_buffer_overflow:                   # more pairs than allocated
            neighbors = neighbor_fn.allocate(state["r"], num_particles=n)
            new_state, new_neighbors = advance(cfg.solver.dt, state, neighbors)
        state, neighbors = new_state, new_neighbors
        if step % write_every == 0:
            r = np.asarray(state["r"])
            if not np.isfinite(r).all():
                raise FloatingPointError(f"{case} seed {seed}: the engine diverged at step "
                                         f"{step}; try a smaller dx or cfl")
            frames.append(r)
            v = np.asarray(state["v"])[fluid]
            ekin.append(0.5 * float((v ** 2).sum()) * dx ** 2)
    seconds = time.perf_counter() - start
    info = dict(dt=float(cfg.solver.dt), box=np.asarray(box).tolist(),
                seconds_per_step=seconds / steps, steps=steps, ekin=ekin,
                varied=OmegaConf.to_container(cfg.case.special))
    return np.stack(frames).astype(np.float32), np.asarray(state["tag"], dtype=np.int64), info


def frame_statistics(trajectories: list[np.ndarray], box: np.ndarray,
                     periodic: bool) -> dict[str, list[float]]:
    """Mean and standard deviation of per-frame displacement and its change (LagrangeBench's
    ``vel_*`` and ``acc_*``), over every particle and frame of the training split."""
    vel, acc = [], []
    for pos in trajectories:
        d = np.diff(pos.astype(np.float64), axis=0)
        if periodic:
            d -= box * np.round(d / box)
        vel.append(d.reshape(-1, d.shape[-1]))
        acc.append(np.diff(d, axis=0).reshape(-1, d.shape[-1]))
    vel, acc = np.concatenate(vel), np.concatenate(acc)
    return {"vel_mean": vel.mean(0).tolist(), "vel_std": vel.std(0).tolist(),
            "acc_mean": acc.mean(0).tolist(), "acc_std": acc.std(0).tolist()}


def trajectory(case: str, seed: int, base_seed: int, dx: float, write_every: int,
               t_end: float | None, part: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """The trajectory of engine seed ``seed``: read from ``part`` if an earlier run made it,
    else simulated and saved there (written whole, then renamed, so a stop leaves no half)."""
    if part.is_file():
        with np.load(part) as z:
            return z["position"], z["particle_type"], json.loads(str(z["info"]))
    rng = np.random.default_rng([base_seed, seed])
    pos, typ, info = simulate(case, seed, dx, write_every, rng, t_end)
    part.parent.mkdir(parents=True, exist_ok=True)
    tmp = part.with_name(part.stem + ".part.npz")
    np.savez(tmp, position=pos, particle_type=typ, info=json.dumps(info))
    os.replace(tmp, part)
    return pos, typ, info


def write_split(path: Path, trajectories: list[np.ndarray], types: list[np.ndarray]) -> None:
    tmp = path.with_suffix(".h5.part")
    with h5py.File(tmp, "w") as f:
        for i, (pos, typ) in enumerate(zip(trajectories, types)):
            g = f.create_group(f"{i:05d}")
            g.create_dataset("position", data=pos)
            g.create_dataset("particle_type", data=typ)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case", choices=sorted(CASES))
    p.add_argument("--out", type=Path, required=True, help="folder to write the dataset to")
    p.add_argument("--dx", type=float, help="particle spacing (default per case)")
    p.add_argument("--write-every", type=int, help="engine steps per recorded frame")
    p.add_argument("--trajectories", type=int, nargs=3, metavar=("TRAIN", "VALID", "TEST"))
    p.add_argument("--t-end", type=float, help="simulated time per trajectory (default per case)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--overwrite", action="store_true")
    a = p.parse_args(argv)
    d = DEFAULTS[a.case]
    dx = a.dx or d["dx"]
    write_every = a.write_every or d["write_every"]
    counts = a.trajectories or d["trajectories"]
    a.out.mkdir(parents=True, exist_ok=True)
    meta_path = a.out / "metadata.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    train = None
    for k, (split, count) in enumerate(zip(SPLITS, counts)):
        f = a.out / f"{split}.h5"
        if f.is_file() and not a.overwrite:
            print(f"{f}: kept (--overwrite to make it again)")
            continue
        trajs, types = [], []
        for i in range(count):
            seed = a.seed * 100_000 + k * 10_000 + i      # a split's seeds do not depend on counts
            part = a.out / "parts" / f"{split}_{seed}.npz"
            if a.overwrite:
                part.unlink(missing_ok=True)
            pos, typ, info = trajectory(a.case, seed, a.seed, dx, write_every, a.t_end, part)
            trajs.append(pos)
            types.append(typ)
            print(f"{split} {i + 1}/{count}: {pos.shape[1]} particles, {pos.shape[0]} frames, "
                  f"{info['steps']} steps at {info['seconds_per_step'] * 1e3:.2f} ms/step, "
                  f"kinetic energy {info['ekin'][0]:.4g} -> {info['ekin'][-1]:.4g}", flush=True)
        write_split(f, trajs, types)
        if split == "train":
            train = (trajs, info)
        meta.setdefault("engine_seconds_per_step", []).append(info["seconds_per_step"])
        meta.setdefault("ekin", {})[split] = info["ekin"]
    if train is not None:
        trajs, info = train
        box = np.asarray(info["box"])
        periodic = a.case == "tgv"
        meta.update(
            case=a.case, engine="jax-sph 0.1.0", solver="SPH", dim=2, dx=dx, dt=info["dt"],
            write_every=write_every, t_end=info["steps"] * info["dt"],
            bounds=[[0.0, float(b)] for b in box],
            periodic_boundary_conditions=[periodic, periodic],
            default_connectivity_radius=CONNECTIVITY * dx,
            num_particles_max=int(max(t.shape[1] for t in trajs)),
            sequence_length_train=int(trajs[0].shape[0]),
            **frame_statistics(trajs, box, periodic))
    meta_path.write_text(json.dumps(meta, indent=1))
    if a.case == "dam":
        # LagrangeBench's models read a uniform external force from the dataset's force.py
        (a.out / "force.py").write_text(GRAVITY_FILE)
    print(f"{a.out}: {', '.join(f'{s} {c}' for s, c in zip(SPLITS, counts))} trajectories")
    return 0


if __name__ == "__main__":
    sys.exit(main())
