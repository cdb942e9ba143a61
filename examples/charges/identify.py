"""What the frames of the charge data identify, with the TRUE law: the best any estimator
that learns the law can reach (issue "The inverse half", item 3 and its references).

    python examples/charges/identify.py data/external/charges4 --out outputs/charges/identify

For every trajectory of the data made by ``make.py``: the finite-difference accelerations
``(x[t+1] - 2 x[t] + x[t-1]) / dt^2`` (what a model sees), the true law's pair terms ``X_ij =
u_ij / s_ij^2`` at the same frames, and ``bgn.model.coupling.fit_couplings`` of ``a_i = k_i
sum_j c_j X_ij`` fitted two ways: per window (``--window`` accelerations in a row, as a model's
input window holds, at windows spread along the trajectory), and per simulation (every frame
pooled). Scored against the hidden truth (``_hidden/truth.npz``), per particle: the log-mass
``log(c_i / k_i)`` centred per simulation (the scale is free) against the true one, R^2 over
all particles; the charges' signs up to each simulation's global sign, over the particles whose
|q| is at least ``--charge-floor`` of the simulation's root-mean-square charge; the charges' R^2
(``c`` against ``q`` scaled to unit rms, the global sign aligned). Writes ``identify.md`` and
``identify.csv`` under ``--out``, and ``per_simulation.csv``: each trajectory's worst
log-mass error of the pooled fit beside its closest and farthest pair distances. A third row
pools only the frames at which no pair turns faster than ``--max-turns`` revolutions per frame
(``resolved_frames``), the same number of them where enough pass.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import torch
from rich.progress import track

from bgn.model.coupling import fit_couplings
from bgn.sim.nbody import pair_turns


def pair_terms(x: np.ndarray, softening: float) -> np.ndarray:
    """(F, N, N, D) ``u_ij / s_ij^2`` (the force on i from j per unit coupling, like charges
    repel) at frames ``x`` (F, N, D); zero on the diagonal."""
    diff = x[:, :, None] - x[:, None]
    r = np.linalg.norm(diff, axis=-1)
    n = x.shape[1]
    r[:, np.arange(n), np.arange(n)] = 1.0
    terms = diff / ((r + softening) ** 2 * r)[..., None]
    terms[:, np.arange(n), np.arange(n)] = 0.0
    return terms


def system(x: np.ndarray, dt: float, frames: np.ndarray, softening: float,
           ) -> tuple[np.ndarray, np.ndarray]:
    """The design (N, F * D, N) and target (N, F * D) of the frames ``frames`` (each with a
    frame before and after it) of one trajectory ``x`` (T, N, D)."""
    accel = (x[frames + 1] - 2 * x[frames] + x[frames - 1]) / dt**2          # (F, N, D)
    terms = pair_terms(x[frames], softening)                                 # (F, N, N, D)
    f, n, _, d = terms.shape
    return (terms.transpose(1, 0, 3, 2).reshape(n, f * d, n),
            accel.transpose(1, 0, 2).reshape(n, f * d))


def resolved_frames(x: np.ndarray, dt: float, max_turns: float, count: int) -> np.ndarray:
    """Up to ``count`` frames (evenly thinned) of trajectory ``x`` (T, N, D) at which no pair
    turns faster than ``max_turns`` revolutions per frame (``bgn.sim.nbody.pair_turns``, the
    velocities by central differences of the positions): where a pair turns fast, a frame's
    finite-difference acceleration is far from the instantaneous one. At least ``count // 10``
    frames: the slowest-turning ones where fewer pass."""
    turns = pair_turns(x[1:-1], (x[2:] - x[:-2]) / (2 * dt), dt)            # frames 1..T-2
    frames = np.arange(1, x.shape[0] - 1)
    keep = frames[turns < max_turns]
    if len(keep) < count // 10:
        keep = np.sort(frames[np.argsort(turns)[:count // 10]])
    return keep[np.linspace(0, len(keep) - 1, min(count, len(keep))).astype(int)]


def fit(systems: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """``fit_couplings`` of equal-sized systems, batched: k and c, (B, N)."""
    design = torch.tensor(np.stack([s[0] for s in systems]))
    target = torch.tensor(np.stack([s[1] for s in systems]))
    real = torch.ones(design.shape[0], design.shape[1], dtype=torch.bool)
    with torch.no_grad():
        k, c = fit_couplings(design, target, real)
    return k.numpy(), c.numpy()


def aligned_charges(c: np.ndarray, charges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fitted couplings ``c`` (B, N) turned by each simulation's global sign to agree with
    the true ``charges`` (the one gauge the frames leave), and those charges at unit rms."""
    q = charges / np.sqrt((charges**2).mean(1, keepdims=True))
    return c * np.where((c * q).sum(1, keepdims=True) < 0, -1.0, 1.0), q


def scores(k: np.ndarray, c: np.ndarray, masses: np.ndarray, charges: np.ndarray,
           floor: float) -> dict[str, float]:
    """The fits' scores against the truth, (B, N) arrays each (one row per fitted system)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        log_m = np.log(c / k)
    identified = np.isfinite(log_m).all(1)          # a negative mass: not identified
    fitted = log_m[identified] - log_m[identified].mean(1, keepdims=True)
    true = np.log(masses[identified])
    true = true - true.mean(1, keepdims=True)
    r2_mass = 1 - ((fitted - true) ** 2).sum() / (true**2).sum()
    # the charges of a fit whose couplings came out (a particle whose own accelerations were
    # all left out has k = 0, its mass unknown, its charge still read from its neighbours')
    fitted_c = np.isfinite(c).all(1)
    aligned, q = (a[fitted_c] for a in aligned_charges(c, charges))
    big = np.abs(q) >= floor
    signs_right = float((np.sign(aligned) == np.sign(q))[big].mean())
    r2_charge = 1 - ((aligned - q) ** 2).sum() / ((q - q.mean()) ** 2).sum()
    return {"fits": len(k), "identified": float(identified.mean()),
            "charges fitted": float(fitted_c.mean()),
            "log-mass R^2": float(r2_mass),
            "median |log-mass error|": float(np.median(np.abs(fitted - true))),
            "charge signs right": signs_right, "charge R^2": float(r2_charge)}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="the folder make.py wrote")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--window", type=int, default=4, help="accelerations per window")
    ap.add_argument("--windows", type=int, default=8, help="windows per trajectory")
    ap.add_argument("--stride", type=int, default=2, help="every n-th frame pooled")
    ap.add_argument("--charge-floor", type=float, default=0.2)
    ap.add_argument("--max-turns", type=float, default=0.02,
                    help="the third row pools only frames where no pair turns faster (rev/frame)")
    args = ap.parse_args(argv)

    data = np.load(args.data / "charges.npz")
    truth = np.load(args.data / "_hidden" / "truth.npz")
    softening = json.loads((args.data / "make.json").read_text())["params"]["softening"]
    positions, dt = data["positions"], float(data["dt"])
    n_traj, n_frames = positions.shape[:2]
    per_window, per_sim, resolved, owners = [], [], [], []
    pooled = len(range(1, n_frames - 1, args.stride))
    for s in track(range(n_traj), description="fitting"):
        starts = np.linspace(1, n_frames - 1 - args.window, args.windows).astype(int)
        for start in starts:
            per_window.append(system(positions[s], dt, np.arange(start, start + args.window),
                                     softening))
            owners.append(s)
        per_sim.append(system(positions[s], dt, np.arange(1, n_frames - 1, args.stride),
                              softening))
        resolved.append(system(positions[s], dt, resolved_frames(positions[s], dt,
                                                                 args.max_turns, pooled),
                               softening))
    owners = np.array(owners)
    fits = {"per window": fit(per_window), "per simulation": fit(per_sim),
            "resolved": fit(resolved)}
    k, c = fits["per simulation"]
    with np.errstate(invalid="ignore", divide="ignore"):
        log_m = np.log(c / k)
    true = np.log(truth["masses"])
    worst = np.abs((log_m - log_m.mean(1, keepdims=True)) - (true - true.mean(1, keepdims=True)))
    pairs = np.linalg.norm(positions[:, :, :, None] - positions[:, :, None], axis=-1)
    iu = np.triu_indices(positions.shape[2], 1)
    pairs = pairs[..., iu[0], iu[1]]
    per_sim_rows = [{"trajectory": s, "split": str(data["split"][s]),
                     "worst log-mass error": float(np.nan_to_num(worst[s], nan=np.inf).max()),
                     "closest pair": float(pairs[s].min()),
                     "farthest pair": float(pairs[s].max())} for s in range(n_traj)]
    rows = []
    for key, name, index in (
            ("per window", "per window", owners),
            ("per simulation", "per simulation", np.arange(n_traj)),
            ("resolved", f"per simulation, frames turning < {args.max_turns}", np.arange(n_traj))):
        k, c = fits[key]
        rows.append({"fit": name, "frames": (args.window if name == "per window" else pooled),
                     **scores(k, c, truth["masses"][index], truth["charges"][index],
                              args.charge_floor)})
    args.out.mkdir(parents=True, exist_ok=True)
    for name, table in (("identify.csv", rows), ("per_simulation.csv", per_sim_rows)):
        with open(args.out / name, "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
    off = np.array([r["worst log-mass error"] for r in per_sim_rows])
    header = "| " + " | ".join(rows[0]) + " |"
    lines = [header, "|" + "---|" * len(rows[0])]
    lines += ["| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v)
                                for v in row.values()) + " |" for row in rows]
    text = (f"# What the frames identify, with the true law\n\n`{args.data}`: {n_traj} "
            f"trajectories of {n_frames} frames; charge signs scored where |q| >= "
            f"{args.charge_floor} x the simulation's rms charge.\n\n" + "\n".join(lines) + "\n"
            f"\nPooled per simulation: {int((off > 0.05).sum())} of {n_traj} trajectories have a "
            f"particle off by more than 0.05 in log-mass, {int((off > 1).sum())} by more than 1 "
            "(per_simulation.csv).\n")
    (args.out / "identify.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
