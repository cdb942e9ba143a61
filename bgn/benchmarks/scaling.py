"""Every model's cost against the number of particles: graph build, training and inference
step, peak memory, fitted exponents, and the fraction of the machine's matmul rate achieved.

Collisions-like frames at the scene's density (200 discs per 10 x 10 box, two types of radius
0.1 and 0.2, equipartition speeds), edges from ``bgn.data.edges.radius_graph`` with a contact
margin of ``margin`` (1.25 gives the edge density of the measurements in
docs/notes/2026-11-26-results-history.md, "Moved here from code comments and configs").
Each model is its checkout's own config composed with
``dataset=collisions`` (``conf/``), so BGN runs with the collisions defaults (vector contact
message)::

    python -m bgn.benchmarks.scaling [models=[bgn,gns,cranmer_gn]]
        [sizes=[200,2000,20000,200000]] [threads=2] [against=8abf3d9]
        [max_gb=12] [report_dir=outputs/benchmarks]   # --help: conf/benchmarks/scaling.yaml

Each (model, N) cell runs in its own process (``_scaling_cell.py``), so its peak resident
memory is its own. A training step is forward + backward + AdamW; an inference step is
``predict`` under ``no_grad``; both are the median of ``repeats`` after a warm-up. The FLOP
count is that of the matrix products of one training step (``torch.utils.flop_counter``:
``Linear`` layers and any other ``mm``), so "matmul fraction" is the achieved FLOP rate
over the float32 matmul rate measured at the start of the same run.

``against=REF`` exports ``git archive REF`` to a temporary folder and runs the same cells with
that checkout in separate processes, interleaved with this one's, and reports the ratios (old
time / new time, old memory / new memory) from this one run: absolute times on a shared
machine drift; ratios taken minutes apart drift less. ``against`` also takes a folder holding
such an export, for a machine without the history. ``device=cuda`` (the default where a GPU
is present) runs the cells there: memory is then the peak GPU memory allocated, and the rates
are the GPU's. A cell whose predicted memory (the
previous size's, scaled by N) exceeds ``max_gb`` is skipped and the report says so. The cell
itself (``_scaling_cell.py``) keeps a private argparse interface: it is no user command, and
it runs other checkouts' code, older than this command style.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from argparse import Namespace
from contextlib import redirect_stdout
from dataclasses import asdict
from io import BytesIO, StringIO
from pathlib import Path
from typing import Any

import numpy as np
import torch

import bgn
from bgn.benchmarks._report import (
    command,
    console,
    need_choices,
    need_ints,
    need_strings,
    options,
    outside_app,
    print_table,
)
from bgn.benchmarks.flow import synthetic_stats
from bgn.data.edges import radius_graph
from bgn.graph import Graph, window_graph
from bgn.model.registry import MODELS
from bgn.provenance import machine
from bgn.sim.collisions import CollisionScene
from bgn.sim.scene import SceneMeta
from bgn.tables import fmt, markdown_table, write_csv

DENSITY = 200 / 10.0**2              # discs per unit area: the collisions scene's
HISTORY = 5
FPS = 50.0
CELL = Path(__file__).with_name("_scaling_cell.py")
GB = 1e9


# ----------------------------------------------------------------------------- the frames
def frame(n: int, margin: float, seed: int = 0) -> Graph:
    """One collisions frame of n discs in a box of side ``sqrt(n / DENSITY)``: the collisions
    scene's own start (``CollisionScene.draw_initial``: its two types, thermal speeds, and
    discs placed without overlap, as in every simulation), in free flight over the window."""
    rng = np.random.default_rng(seed)
    box = math.sqrt(n / DENSITY)
    types, masses, radii, pos, vel = CollisionScene(n_particles=n, box=box).draw_initial(rng)
    # a window of k+2 positions in free flight, oldest first (the last one is x[t])
    steps = np.arange(-HISTORY - 1, 1)[:, None, None] / FPS
    window = torch.from_numpy(pos[None] + steps * vel[None])[None]        # (1, k+2, N, 2)
    edges = torch.from_numpy(radius_graph(pos, radii=radii, margin=margin))
    g = window_graph(window, 1.0 / FPS, edges, torch.from_numpy(masses)[None],
                     torch.from_numpy(radii)[None], torch.from_numpy(types)[None], box,
                     torch.zeros(1), torch.zeros(1))
    snd, rcv = edges
    g.target = g.vel[:, 0].clone()
    touching = (g.pos[rcv] - g.pos[snd]).norm(dim=1) <= g.radius[rcv] + g.radius[snd]
    g.edge_contact = touching.float()
    return g


def scene(n: int) -> SceneMeta:
    return SceneMeta(name="collisions", dim=2, n_particles=n, n_types=2,
                     interaction="contact", target="velocity", graph="radius",
                     box=math.sqrt(n / DENSITY))


# ----------------------------------------------------------------------------- the machine
def matmul_rate(size: int = 2048, device: str = "cpu") -> float:
    """float32 FLOP/s of a ``size`` x ``size`` matrix product on ``device``, best of 3."""
    a, b = (torch.randn(size, size, device=device) for _ in range(2))
    a @ b
    best = min(_seconds(lambda: a @ b, device) for _ in range(3))
    return 2 * size**3 / best


def copy_bandwidth(nbytes: int = 512 * 2**20, device: str = "cpu") -> float:
    """Bytes/s moved (read + write) by copying a tensor of ``nbytes`` on ``device``, best of 3."""
    src = torch.rand(nbytes // 4, device=device)
    dst = torch.empty_like(src)
    dst.copy_(src)
    best = min(_seconds(lambda: dst.copy_(src), device) for _ in range(3))
    return 2 * nbytes / best


def _seconds(fn, device: str = "cpu") -> float:
    """Wall time of ``fn()``; on a GPU, of the work it queued (synchronised before and after)."""
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    sync()
    start = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - start


# ----------------------------------------------------------------------------- the cells
def export(ref: str, into: Path) -> Path:
    """The checkout of ``ref``: a folder holding one (``bgn/`` and ``conf/``) as it is, else
    ``git archive ref`` of this repository extracted under ``into`` (a machine without the git
    history, a lent GPU say, gets a folder exported where the history is)."""
    if (Path(ref) / "bgn").is_dir() and (Path(ref) / "conf").is_dir():
        return Path(ref).resolve()
    repo = Path(bgn.__file__).resolve().parents[1]
    tar = subprocess.run(["git", "-C", str(repo), "archive", ref], check=True,
                         capture_output=True).stdout
    with tarfile.open(fileobj=BytesIO(tar)) as archive:
        archive.extractall(into, filter="data")
    return into


def run_cell(checkout: Path, payload: Path | str, model: str, args: Namespace,
             extra: list[str]) -> dict:
    """One cell in a fresh process with ``checkout`` first on the path; {"error": ...} on a
    failure or a timeout. ``THP_MEM_ALLOC_ENABLE`` is left to each checkout's own ``bgn``."""
    if args.in_process:  # this checkout only: the tests' tiny run
        from bgn.benchmarks import _scaling_cell

        text = StringIO()
        with redirect_stdout(text), outside_app():  # the cell composes conf/train.yaml
            _scaling_cell.main([str(payload), model, "--device", args.device, *extra])
        return json.loads(text.getvalue().strip().splitlines()[-1])
    env = {k: v for k, v in os.environ.items() if k != "THP_MEM_ALLOC_ENABLE"}
    env.update(PYTHONPATH=str(checkout), OMP_NUM_THREADS=str(args.threads),
               MKL_NUM_THREADS=str(args.threads))
    cmd = [sys.executable, str(CELL), str(payload), model, "--device", args.device, *extra]
    try:
        done = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True,
                              timeout=args.timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"over the {args.timeout:g} s limit"}
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["?"])[-1]
        error = f"exit {done.returncode}: {tail[:160]}"
        if lines:  # the timings came out before the FLOP count failed (memory, mostly)
            return {**json.loads(lines[-1]), "note": f"no FLOP count ({error})"}
        return {"error": error}
    return json.loads(lines[-1])


def predicted_gb(rows: list[dict], impl: str, model: str, n: int) -> float:
    """Training memory of a cell, extrapolated linearly in N from the largest smaller one."""
    done = [r for r in rows if r["impl"] == impl and r["model"] == model
            and r.get("train_peak_gb") is not None and r["n"] < n]
    if not done:
        return 0.0
    last = max(done, key=lambda r: r["n"])
    return last["train_peak_gb"] * n / last["n"]


def slope(rows: list[dict], key: str, lo: int) -> float | None:
    """Least-squares exponent of ``key`` against N over the sizes >= lo (None below two)."""
    pts = [(r["n"], r[key]) for r in rows if r["n"] >= lo and (r.get(key) or 0) > 0]
    if len(pts) < 2:
        return None
    n, y = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(n, y, 1)[0])


# ----------------------------------------------------------------------------- the report
COLUMNS = ["impl", "model", "n", "edges", "graph_s", "train_s", "infer_s", "train_peak_gb",
           "infer_peak_gb", "train_gflop", "matmul_fraction", "edges_per_s", "note"]


def exponents(rows: list[dict], lo: int) -> list[dict]:
    out = []
    for impl in dict.fromkeys(r["impl"] for r in rows):
        for model in dict.fromkeys(r["model"] for r in rows):
            mine = [r for r in rows if r["impl"] == impl and r["model"] == model]
            out.append({"impl": impl, "model": model, "from_n": lo,
                        **{f"{k}_exponent": slope(mine, k, lo)
                           for k in ("train_s", "infer_s", "train_peak_gb")}})
    return out


def ratios(rows: list[dict], new: str, old: str) -> list[dict]:
    """old / new of time and memory for every cell both ran."""
    index = {(r["impl"], r["model"], r["n"]): r for r in rows}
    out = []
    for (impl, model, n), r in index.items():
        o = index.get((old, model, n))
        if impl != new or o is None:
            continue
        out.append({"model": model, "n": n, **{
            f"{k}_ratio": (o[k] / r[k] if o.get(k) and r.get(k) else None)
            for k in ("train_s", "infer_s", "train_peak_gb")}})
    return out


def write_plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=110)
    for (impl, model) in dict.fromkeys((r["impl"], r["model"]) for r in rows):
        mine = sorted((r for r in rows if r["impl"] == impl and r["model"] == model
                       and r.get("train_s")), key=lambda r: r["n"])
        if not mine:
            continue
        style = "o-" if impl == "this" else "s:"
        n = [r["n"] for r in mine]
        axes[0].loglog(n, [r["train_s"] for r in mine], style, label=f"{model} ({impl})")
        axes[1].loglog(n, [max(r["train_peak_gb"], 1e-3) for r in mine], style,
                       label=f"{model} ({impl})")
    for ax, what in zip(axes, ("training step s", "peak memory growth GB")):
        ax.set_xlabel("particles N")
        ax.set_ylabel(what)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


TRAINING = ["impl", "loader_samples_s", "step_samples_s", "fit_samples_s", "error"]


def write_report(rows: list[dict], training: list[dict], header: list[str],
                 against: str | None, out: Path) -> None:
    lo = sorted({r["n"] for r in rows})[1 if len({r["n"] for r in rows}) > 2 else 0]
    parts = ["# Scaling benchmark: every model against N", "", *header, "",
             markdown_table(COLUMNS, rows), "",
             f"## Fitted exponents (log-log least squares over N >= {lo:,})", "",
             markdown_table(["impl", "model", "from_n", "train_s_exponent", "infer_s_exponent",
                             "train_peak_gb_exponent"], exponents(rows, lo))]
    if against:
        parts += ["", f"## Ratios: {against} / this checkout (above 1: this one is faster "
                  "or smaller)", "",
                  markdown_table(["model", "n", "train_s_ratio", "infer_s_ratio",
                                  "train_peak_gb_ratio"], ratios(rows, "this", against))]
    if training:
        parts += ["", "## Default collisions training (BGN), samples per second", "",
                  "The data loader alone, the model step alone (forward, backward, optimiser "
                  "on loaded batches) and Lightning's fit loop (both, plus logging, metrics and "
                  "clipping; no validation), each checkout with its own configs.", "",
                  markdown_table(TRAINING, training)]
    parts += ["", "![time and memory against N](scaling.png)"]
    (out / "scaling.md").write_text("\n".join(parts) + "\n")
    write_csv(out / "scaling.csv", COLUMNS, rows)
    write_plot(rows, out / "scaling.png")


# ----------------------------------------------------------------------------- the command
def check(cfg: Any) -> None:
    """Everything ``python -m bgn.benchmarks.scaling`` is given, before any work."""
    from bgn.coerce import ConfigError, need_float, need_int

    if cfg.models is not None:
        need_choices(cfg.models, "models", sorted(MODELS))
    need_ints(cfg.sizes, "sizes", 2, why=" (particles)")
    need_float(cfg.margin, "margin", 0, why=" (the radius graph's contact margin)")
    need_int(cfg.threads, "threads", 1)
    need_int(cfg.repeats, "repeats", 1)
    if cfg.device is not None:
        try:
            device = torch.device(str(cfg.device))
        except RuntimeError:
            device = None
        if device is None or device.type not in ("cpu", "cuda"):
            raise ConfigError("device", cfg.device, "cpu, cuda or cuda:<i> (null: cuda where "
                              "present)")
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ConfigError("device", cfg.device, "no GPU here: device=cpu (or null)")
    need_int(cfg.against_max_n, "against_max_n", 2, optional=True)
    need_float(cfg.max_gb, "max_gb", 0)
    need_int(cfg.train_max_n, "train_max_n", 2, optional=True)
    need_float(cfg.timeout, "timeout", 0, why=" (seconds per cell)")
    need_int(cfg.training_steps, "training_steps", 0, why=" (0: not)")
    if cfg.training_steps == 1:
        raise ConfigError("training_steps", 1, "0 (not) or at least 2: the first step is "
                          "a warm-up, not timed")
    need_strings(cfg.training_overrides, "training_overrides")
    if not isinstance(cfg.in_process, bool):
        raise ConfigError("in_process", cfg.in_process, "true or false")
    if cfg.in_process and cfg.against:
        raise ConfigError("in_process", True, "against needs separate processes: "
                          "in_process=false")


@command("scaling", check)  # key=value; bad input: one line, exit 2
def main(cfg: Any) -> int:
    """Time every (model, N) cell and write the report under ``report_dir``."""
    args = options(cfg)
    args.models = args.models or sorted(MODELS)
    args.device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
    if args.paths.get("data_dir"):  # the training timing's data, for every checkout
        data_dir = Path(args.paths["data_dir"]).expanduser().resolve()
        args.training_overrides = [f"paths.data_dir={data_dir}", *args.training_overrides]
    out = console()
    torch.set_num_threads(args.threads)
    on_gpu = torch.device(args.device).type == "cuda"
    # the rates of the device the cells run on (a GPU's products: 8192, large enough to fill it)
    size = 8192 if on_gpu else 2048
    rate = matmul_rate(size, args.device)
    bandwidth = copy_bandwidth(device=args.device)
    out.log(f"float32 matmul {rate / 1e9:.0f} GFLOP/s, copy {bandwidth / GB:.1f} GB/s "
            f"({args.device}, {args.threads} threads)")
    checkouts = {"this": Path(bgn.__file__).resolve().parents[1]}
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="bgn-scaling-") as tmp:
        if args.against:
            checkouts[args.against] = export(args.against, Path(tmp) / "against")
        stats = synthetic_stats(frame(2000, args.margin, seed=1))  # intensive: any N will do
        for n in sorted(set(args.sizes)):
            start = time.perf_counter()
            g = frame(n, args.margin)
            graph_s = time.perf_counter() - start
            payload = Path(tmp) / f"frame_{n}.pt"
            torch.save({"graph": asdict(g), "stats": stats, "meta": asdict(scene(n)),
                        "history": HISTORY}, payload)
            for model in args.models:
                for impl, checkout in checkouts.items():
                    if impl != "this" and args.against_max_n and n > args.against_max_n:
                        continue
                    row = {"impl": impl, "model": model, "n": n, "graph_s": graph_s}
                    guess = predicted_gb(rows, impl, model, n)
                    skip = guess > args.max_gb
                    if skip:
                        row["note"] = (f"training skipped: ~{guess:.0f} GB predicted "
                                       f"> max_gb={args.max_gb:g}")
                    elif args.train_max_n is not None and n > args.train_max_n:
                        skip = True
                        row["note"] = f"training skipped: N > train_max_n={args.train_max_n}"
                    cell = run_cell(checkout, payload, model, args,
                                    ["--repeats", str(args.repeats)]
                                    + (["--skip-train"] if skip else []))
                    if "error" in cell:
                        row["note"] = cell["error"]
                    else:
                        row.update(edges=cell["edges"], train_s=cell.get("train_s"),
                                   infer_s=cell["infer_s"],
                                   infer_peak_gb=cell["infer_peak_bytes"] / GB)
                        if "train_s" in cell:
                            row.update(train_peak_gb=cell["train_peak_bytes"] / GB,
                                       edges_per_s=cell["edges"] / cell["train_s"])
                        if "train_flop" in cell:
                            flop = cell["train_flop"]
                            row.update(train_gflop=flop / 1e9,
                                       matmul_fraction=flop / cell["train_s"] / rate)
                        if "note" in cell:
                            row["note"] = cell["note"]
                    rows.append(row)
                    out.log(f"{impl} {model} N={n:,}: " + ", ".join(
                        f"{k} {row[k]:.4g}" for k in ("train_s", "infer_s", "train_peak_gb")
                        if row.get(k) is not None) + (f" ({row['note']})" if "note" in row
                                                      else ""))
            payload.unlink()
        training = []  # inside the with: the other checkout lives in tmp
        for impl, checkout in checkouts.items() if args.training_steps else ():
            cell = run_cell(checkout, "-", "bgn", args,
                            ["--repeats", str(args.training_steps),
                             "--training", *args.training_overrides])
            training.append({"impl": impl, **cell})
            out.log(f"{impl} default collisions training: {cell}")
    header = [
        f"Machine: {machine(torch=torch.__version__)}; {args.threads} threads, device "
        f"{args.device}" + (f" ({torch.cuda.get_device_name(args.device)})" if on_gpu
                            else "") + ".",
        f"Measured in this run on {args.device}: float32 matmul {rate / 1e9:.1f} GFLOP/s "
        f"({size} x {size}), "
        f"copy {bandwidth / GB:.1f} GB/s (read + write). THP_MEM_ALLOC_ENABLE="
        f"{os.environ.get('THP_MEM_ALLOC_ENABLE', '(unset)')} in this process; each "
        "checkout's own `bgn` decides for its cells.",
        f"Frames: the collisions scene's start (no overlaps), {DENSITY * 100:g} discs per "
        f"10 x 10, margin {args.margin:g}; "
        f"times are medians of {args.repeats} after a warm-up; memory is the growth of the "
        + ("peak GPU memory allocated" if on_gpu else "peak resident set")
        + " over the cell's baseline (model and frame loaded)."]
    args.report_dir.mkdir(parents=True, exist_ok=True)
    write_report(rows, training, header, args.against, args.report_dir)
    print_table(out, "scaling", COLUMNS, [[fmt(r.get(c)) for c in COLUMNS] for r in rows])
    if args.against:
        for r in ratios(rows, "this", args.against):
            out.print(f"{r['model']} N={r['n']:,}: speed-up train "
                      f"{fmt(r['train_s_ratio'])}x, infer {fmt(r['infer_s_ratio'])}x, "
                      f"memory {fmt(r['train_peak_gb_ratio'])}x smaller")
    out.print(f"wrote {args.report_dir / 'scaling.md'}, .csv, .png")
    return 0


if __name__ == "__main__":
    main()
