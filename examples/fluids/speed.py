"""Speed against error against the engine: seconds of wall time per unit of simulated time for
JAX-SPH at its own step and for bgn's rollout at the frame spacing it was trained on, on the
same CPU (one thread each), at several particle counts, beside bgn's error; the particle count
at which the learned rollout becomes cheaper than the engine, from the measured scaling.

    # the engine (peer environment): the Taylor-Green vortex in boxes of 1, 2 and 3 periods
    .venv-peer/bin/python examples/fluids/speed.py engine tgv --tiles 1 2 3 \\
        --json outputs/fluids/sph_tgv_speed_engine.json
    .venv-peer/bin/python examples/fluids/speed.py engine dam \\
        --json outputs/fluids/sph_dam_speed_engine.json
    # bgn's rollout (bgn's environment) on the same counts: the test split's first window,
    # tiled over the same boxes (exact for a periodic flow; the script checks the tiles agree)
    python examples/fluids/speed.py learned outputs/fluids/sph_tgv_bgn_s0 data/external/sph_tgv \\
        --tiles 1 2 3 --json outputs/fluids/sph_tgv_speed_bgn.json
    python examples/fluids/speed.py learned outputs/fluids/sph_dam_bgn_s0 data/external/sph_dam \\
        --json outputs/fluids/sph_dam_speed_bgn.json
    # the table, its CSV and figure: outputs/fluids/<name>_speed.{md,csv,png}
    python examples/fluids/speed.py table outputs/fluids sph_tgv

Why tiles: at a fixed particle spacing a larger domain adds particles with the same number of
neighbours each, so both costs grow with the particle count alone; the engine's step and the
frame spacing stay those of the dataset. The dam break does not tile (walls): its row is the
dataset's own count, and its crossover uses the tgv scaling exponents (said so in the table).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

INPUT_FRAMES = 6          # as bgn_rollouts.py: the window is cut from the first six frames


def engine(case: str, tiles: list[int], t_end: float, seed: int) -> list[dict]:
    """JAX-SPH's seconds per step (after compilation) for ``t_end`` of simulated time at each
    tiling; one thread (run with XLA_FLAGS as run.sh sets them)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from make_sph import DEFAULTS, simulate

    d = DEFAULTS[case]
    rows = []
    for k in tiles:
        rng = np.random.default_rng([seed, k])
        pos, _, info = simulate(case, seed, d["dx"], d["write_every"], rng, t_end, tiles=k)
        rows.append({"tiles": k, "particles": int(pos.shape[1]), "dt": info["dt"],
                     "steps": info["steps"], "seconds_per_step": info["seconds_per_step"]})
        print(f"engine {case} tiles {k}: {pos.shape[1]} particles, {info['steps']} steps of "
              f"{info['dt']:.3g}, {info['seconds_per_step'] * 1e3:.2f} ms/step", flush=True)
    return rows


def learned(run: Path, data: Path, tiles: list[int], steps: int, split: str) -> list[dict]:
    """bgn's seconds per rollout frame (one thread, after a warm-up frame) from the first window
    of ``split``'s first trajectory, tiled ``k x k`` over a periodic box ``k`` periods wide;
    for ``k > 1`` the largest difference between each tile's rollout and the untiled one."""
    import h5py
    import torch

    import bgn

    torch.set_num_threads(1)
    meta = json.loads((data / "metadata.json").read_text())
    with h5py.File(data / f"{split}.h5", "r") as f:
        first = sorted(f)[0]
        pos = f[first]["position"][:INPUT_FRAMES].astype(np.float64)
        types = f[first]["particle_type"][()]
    extent = np.array([hi - lo for lo, hi in meta["bounds"]])
    rows, alone = [], None
    for k in tiles:
        model = bgn.load(run)
        window = pos[INPUT_FRAMES - model.window_length:]
        n = window.shape[1]
        if k > 1:
            if not all(meta["periodic_boundary_conditions"]):
                raise SystemExit(f"{data}: tiles={k} needs a periodic dataset")
            shifts = [np.array([i, j]) * extent for i in range(k) for j in range(k)]
            window = np.concatenate([window + s for s in shifts], axis=1)
            # the same model in a box k periods wide: only the period of its graphs changes
            wide = replace(model.meta, period=tuple(k * extent), box=float(k * extent.max()),
                           n_particles=window.shape[1])
            model.model.meta = model.meta = model.simulator.meta = wide
        kinds = np.tile(types, k * k)
        radii = np.zeros(window.shape[1])
        model.rollout(window, 1, types=kinds, radii=radii)            # warm-up
        t0 = time.perf_counter()
        out = model.rollout(window, steps, types=kinds, radii=radii)
        seconds = (time.perf_counter() - t0) / steps
        row = {"tiles": k, "particles": int(window.shape[1]), "dt_frame": float(
            meta["dt"] * meta["write_every"]), "seconds_per_frame": seconds}
        if k == 1:
            alone = out
        elif alone is not None:
            tiled = out.reshape(steps, k * k, n, -1) - np.stack(shifts)[None, :, None]
            row["tile_difference"] = float(np.abs(tiled - alone[:, None]).max())
        rows.append(row)
        print(f"bgn tiles {k}: {row['particles']} particles, {seconds * 1e3:.1f} ms/frame"
              + (f", tiles differ by {row['tile_difference']:.2g}" if "tile_difference" in row
                 else ""), flush=True)
    return rows


def power_fit(n: np.ndarray, seconds: np.ndarray) -> tuple[float, float]:
    """``seconds = a n^b`` by least squares in logs: (a, b); b = 1 from one point."""
    if len(n) < 2:
        return float(seconds[0] / n[0]), 1.0
    b, log_a = np.polyfit(np.log(n), np.log(seconds), 1)
    return float(np.exp(log_a)), float(b)


def table(out: Path, name: str, exponents_from: str | None) -> str:
    """The speed table of ``name`` (``<out>/<name>_speed.{md,csv,png}``): per particle count,
    seconds per unit simulated time of the engine and of bgn, their ratio; bgn's test error
    over seeds (score.json of ``<name>_bgn_s*``); the crossover from power fits."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    eng = json.loads((out / f"{name}_speed_engine.json").read_text())
    lrn = json.loads((out / f"{name}_speed_bgn.json").read_text())
    scores = [json.loads(p.read_text()) for p in sorted(out.glob(f"{name}_bgn_s*/score.json"))]
    mse20 = np.array([s["mse20"] for s in scores])
    e_rows = {r["particles"]: r["seconds_per_step"] / r["dt"] for r in eng["rows"]}
    l_rows = {r["particles"]: r["seconds_per_frame"] / r["dt_frame"] for r in lrn["rows"]}
    fits = {"engine": power_fit(np.array(list(e_rows)), np.array(list(e_rows.values()))),
            "bgn": power_fit(np.array(list(l_rows)), np.array(list(l_rows.values())))}
    note = ""
    if exponents_from:   # one count only: the exponents of another case's measured scaling
        other = json.loads((out / f"{exponents_from}_speed_fit.json").read_text())
        for key in fits:
            a, _ = fits[key]
            n0 = next(iter(e_rows if key == "engine" else l_rows))
            b = other[key][1]
            fits[key] = (a * n0 / n0 ** b, b)
        note = f" (scaling exponents measured on {exponents_from})"
    (out / f"{name}_speed_fit.json").write_text(json.dumps(fits))
    (ae, be), (al, bl) = fits["engine"], fits["bgn"]
    if abs(be - bl) < 1e-9:
        cross = "never (the same scaling)" if al > ae else "always"
    else:
        n_cross = (al / ae) ** (1.0 / (be - bl))
        cheaper_above = be > bl
        cross = (f"{n_cross:,.0f} particles (bgn cheaper {'above' if cheaper_above else 'below'}"
                 f"){note}")
    rows = []
    for n in sorted(set(e_rows) | set(l_rows)):
        e, lr = e_rows.get(n), l_rows.get(n)
        rows.append({"particles": n, "engine s per unit time": e, "bgn s per unit time": lr,
                     "engine / bgn": (e / lr) if e and lr else None})
    with open(out / f"{name}_speed.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)

    def show(v: float | None) -> str:
        return "-" if v is None else f"{v:.3g}"

    err = (f"{mse20.mean():.3g} ± {mse20.std(ddof=1):.2g} over {len(mse20)} seeds"
           if len(mse20) > 1 else (f"{mse20[0]:.3g} (1 seed)" if len(mse20) else "-"))
    lines = [f"{name}: seconds of wall time per unit of simulated time, one CPU thread each; "
             f"the engine (JAX-SPH) at its step {eng['rows'][0]['dt']:.3g}, bgn at its frame "
             f"spacing {lrn['rows'][0]['dt_frame']:.3g}. bgn's test MSE over the first 20 "
             f"frames: {err}. Power fits: engine {ae:.3g} N^{be:.2f}, bgn {al:.3g} N^{bl:.2f}; "
             f"bgn becomes cheaper than the engine at: {cross}.", "",
             "| particles | engine s / unit time | bgn s / unit time | engine / bgn |",
             "|---|---|---|---|"]
    lines += [f"| {r['particles']} | {show(r['engine s per unit time'])} | "
              f"{show(r['bgn s per unit time'])} | {show(r['engine / bgn'])} |" for r in rows]
    text = "\n".join(lines) + "\n"
    (out / f"{name}_speed.md").write_text(text)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    grid = np.geomspace(min(min(e_rows), min(l_rows)) / 2, max(max(e_rows), max(l_rows)) * 4)
    for key, pts, style in (("engine", e_rows, "o"), ("bgn", l_rows, "s")):
        a, b = fits[key]
        ax.loglog(list(pts), list(pts.values()), style, label=f"{key} (measured)")
        ax.loglog(grid, a * grid ** b, "--", lw=0.8)
    ax.set_xlabel("particles")
    ax.set_ylabel("wall s per unit simulated time")
    ax.set_title(name)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / f"{name}_speed.png", dpi=120)
    plt.close(fig)
    print(text)
    return text


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    e = sub.add_parser("engine", help="JAX-SPH's seconds per step (peer environment)")
    e.add_argument("case", choices=("tgv", "dam"))
    e.add_argument("--tiles", type=int, nargs="+", default=[1])
    e.add_argument("--t-end", type=float, default=0.1, help="simulated time timed per count")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--json", type=Path, required=True)
    lr = sub.add_parser("learned", help="bgn's seconds per rollout frame (bgn's environment)")
    lr.add_argument("run", type=Path)
    lr.add_argument("data", type=Path)
    lr.add_argument("--tiles", type=int, nargs="+", default=[1])
    lr.add_argument("--steps", type=int, default=10, help="rollout frames timed per count")
    lr.add_argument("--split", default="test")
    lr.add_argument("--json", type=Path, required=True)
    t = sub.add_parser("table", help="the table, CSV and figure")
    t.add_argument("out", type=Path)
    t.add_argument("name")
    t.add_argument("--exponents-from", help="a case whose measured scaling a one-count case uses")
    a = p.parse_args(argv)
    if a.command in ("engine", "learned") and any(k < 1 for k in a.tiles):
        p.error("--tiles: integers >= 1")
    if a.command == "engine":
        rows = engine(a.case, a.tiles, a.t_end, a.seed)
    elif a.command == "learned":
        if not (a.data / "metadata.json").is_file():
            p.error(f"{a.data}: no metadata.json; give a LagrangeBench-layout dataset folder")
        rows = learned(a.run, a.data, a.tiles, a.steps, a.split)
    else:
        table(a.out, a.name, a.exponents_from)
        return 0
    a.json.parent.mkdir(parents=True, exist_ok=True)
    a.json.write_text(json.dumps({"command": " ".join(sys.argv), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
