"""NSF against NAF inside the whole BGN model: speed, and what a short training reaches.

A synthetic collisions-like task, no files: frames of ``per_frame`` discs in a box with a
radius graph, two particle types whose log-masses are bimodal (modes 0.001 and 0.4, as in the
collisions scene) and whose speeds follow equipartition (``|v| ~ 1/sqrt(m)``), so the mass of a
particle can be read from its velocity window. Writes ``flow.md``, ``flow.csv`` and ``flow.png``
(the training mass NLL against the step, and the times) under ``report_dir``::

    python -m bgn.benchmarks.flow [particles=2000] [hidden=128] [steps=300] [threads=2]
        [flows=[nsf,naf]] [report_dir=outputs/benchmarks]   # --help: conf/benchmarks/flow.yaml

Reported per flow:

- forward+backward+Adam time of one training step of the whole model;
- time to sample every particle's mass once (and 10 times);
- after ``steps`` Adam steps cycling through ``pool`` batches: held-out NLL of the
  normalised log-mass (mean and median over particles), the R^2 of the relative log-mass
  ``log m_i - log m_j`` on edges from one posterior sample (the paper's Eq. 9-10 path), the
  R^2 of the mean of 16 posterior log-mass samples, the dynamics loss and the training time.

The model is BGN with its defaults (``conf/model/bgn.yaml``: degree normalisation, the ``auto``
target prior) except ``hidden`` and ``flow``. ``degree_normalize=false`` gives the paper's plain
``Â = A + I``, with which neither flow trains in 300 steps on this task.
"""

from __future__ import annotations

import math
import time
from argparse import Namespace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bgn.benchmarks._report import command, console, need_choices, options, print_table
from bgn.data.stats import summarize
from bgn.eval.evaluate import r2_score
from bgn.graph import Graph, collate
from bgn.model.registry import build_model
from bgn.model.target_coder import observed_targets
from bgn.provenance import machine
from bgn.sim.scene import SceneMeta
from bgn.tables import markdown_table, write_csv

BOX = 10.0
RADIUS = 0.3
CUTOFF = 1.0       # candidate pairs: about 6 neighbours per particle at 200 per frame
HISTORY = 5
MODES = (math.log(0.001), math.log(0.4))
LOG_MASS_JITTER = 0.2

# (key, label, format) of the reported figures, in table order
FIGURES = [
    ("particles", "particles", "{:,.0f}"),
    ("edges", "edges", "{:,.0f}"),
    ("step_s", "training step s", "{:.3f}"),
    ("sample_1_s", "sample all masses s", "{:.4f}"),
    ("sample_10_s", "sample x10 s", "{:.4f}"),
    ("train_s", "training s", "{:.1f}"),
    ("nll_mean", "held-out NLL mean", "{:.3f}"),
    ("nll_median", "held-out NLL median", "{:.3f}"),
    ("relmass_r2", "relative-mass R^2", "{:.3f}"),
    ("logmass_r2_mean16", "log-mass R^2 (mean of 16)", "{:.3f}"),
    ("dynamics_loss", "dynamics loss", "{:.4g}"),
]


def synthetic_frame(n: int, gen: torch.Generator, frame: int) -> Graph:
    types = torch.randint(0, 2, (n,), generator=gen)
    log_m = torch.tensor(MODES)[types] + LOG_MASS_JITTER * torch.randn(n, generator=gen)
    mass = torch.exp(log_m)
    pos = RADIUS + (BOX - 2 * RADIUS) * torch.rand(n, 2, generator=gen)
    speed_scale = 0.05 / torch.sqrt(mass)                    # equipartition: m v^2 ~ const
    v0 = speed_scale[:, None] * torch.randn(n, 2, generator=gen)
    # a slowly turning velocity window, newest first, with a little noise
    drift = 0.1 * speed_scale[:, None, None] * torch.randn(n, 1, 2, generator=gen)
    steps = torch.arange(HISTORY + 1, dtype=torch.float32)[None, :, None]
    vel = v0[:, None, :] + drift * steps + 0.01 * torch.randn(n, HISTORY + 1, 2, generator=gen)
    target = v0 - drift[:, 0]                                # next velocity
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    dist = torch.linalg.vector_norm(pos[:, None] - pos[None, :], dim=-1)  # 200 per frame: fine
    keep = (i != j) & (dist < CUTOFF)
    rcv, snd = i[keep], j[keep]
    return Graph(
        pos=pos, vel=vel, edge_index=torch.stack([snd, rcv]), target=target,
        edge_contact=(dist[rcv, snd] < 2 * RADIUS).float(), mass=mass,
        edge_rel_log_mass=log_m[rcv] - log_m[snd], types=types,
        radius=torch.full((n,), RADIUS), wall=torch.cat([pos, BOX - pos], 1),
        batch=torch.zeros(n, dtype=torch.long), num_nodes=torch.tensor([n]),
        sim=torch.tensor([0]), frame=torch.tensor([frame]), dt=torch.tensor([1.0]))


def synthetic_batch(n_frames: int, per_frame: int, gen: torch.Generator) -> Graph:
    return collate([synthetic_frame(per_frame, gen, f) for f in range(n_frames)])


def synthetic_stats(g: Graph, kind: str = "velocity") -> dict[str, dict[str, np.ndarray]]:
    """The statistics ``bgn.data.stats.compute_stats`` gives a training split, from a batch.

    Each particle's window and target make a short time series (oldest to newest: the observed
    targets, then the target), and the entries that are differences along time
    (``velocity_increment``, ``target_diff1``, ``target_diff2``) are taken along it, as
    ``compute_stats`` takes them along a simulation's frames.
    """
    snd, rcv = g.edge_index
    series = torch.cat([observed_targets(g, kind).flip(1), g.target[:, None]], 1).numpy()
    d = g.target.shape[1]
    return {
        "velocity": summarize(g.vel[:, 0].numpy()),
        "velocity_increment": summarize((g.vel[:, :-1] - g.vel[:, 1:]).reshape(-1, d).numpy()),
        "target": summarize(g.target.numpy()),
        "target_diff1": summarize(np.diff(series, n=1, axis=1).reshape(-1, d)),
        "target_diff2": summarize(np.diff(series, n=2, axis=1).reshape(-1, d)),
        "log_mass": summarize(torch.log(g.mass)[:, None].numpy()),
        "rel_position": summarize((g.pos[rcv] - g.pos[snd]).numpy()),
        "rel_velocity": summarize((g.vel[rcv, 0] - g.vel[snd, 0]).numpy()),
        "rel_log_mass": summarize(g.edge_rel_log_mass[:, None].numpy()),
        "contact": summarize(g.edge_contact[:, None].numpy()),
    }


def timed(fn, repeat: int) -> float:
    """Median wall time of ``repeat`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def benchmark(flow: str, args: Namespace) -> tuple[dict[str, float], list[float]]:
    """The figures of one flow, and the training mass NLL of every step."""
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    frames = max(1, args.particles // args.per_frame)
    meta = SceneMeta(name="synthetic_collisions", dim=2, n_particles=args.per_frame, n_types=2,
                     interaction="contact", target="velocity", graph="radius", box=BOX)
    config = {"name": "bgn", "hidden": args.hidden, "flow": flow,
              "degree_normalize": bool(args.degree_normalize)}
    model = build_model(config, meta, synthetic_stats(synthetic_batch(frames, args.per_frame,
                                                                      gen)), HISTORY)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    batch = synthetic_batch(frames, args.per_frame, gen)

    def step(g: Graph) -> dict[str, torch.Tensor]:
        terms = model.loss_terms(g, model(g))
        opt.zero_grad()
        model.total_loss(terms).backward()
        opt.step()
        return terms

    result = {"particles": float(batch.pos.shape[0]), "edges": float(batch.edge_index.shape[1])}
    result["step_s"] = timed(lambda: step(batch), args.repeat)
    result["sample_1_s"] = timed(lambda: model.sample_mass(batch, 1), args.repeat)
    result["sample_10_s"] = timed(lambda: model.sample_mass(batch, 10), max(1, args.repeat // 3))

    # A short training on fresh frames, then held-out inverse metrics.
    pool = [synthetic_batch(frames, args.per_frame, gen) for _ in range(args.pool)]
    curve = []
    t0 = time.perf_counter()
    for i in range(args.steps):
        curve.append(float(step(pool[i % len(pool)])["mass_nll"].detach()))
    result["train_s"] = time.perf_counter() - t0
    test = synthetic_batch(frames, args.per_frame, gen)
    model.eval()
    with torch.no_grad():
        out = model(test)
        result["nll_mean"] = float(out.mass_nll.mean())
        result["nll_median"] = float(out.mass_nll.median())
        rel = model.denormalize_relmass(out.relmass)
        result["relmass_r2"] = r2_score(rel.numpy(), test.edge_rel_log_mass.numpy())
        samples = torch.log(model.sample_mass(test, 16))
        result["logmass_r2_mean16"] = r2_score(samples.mean(0).numpy(),
                                               torch.log(test.mass).numpy())
        result["dynamics_loss"] = float(model.loss_terms(test, out)["dynamics"])
    return result, curve


def write_markdown(rows: dict[str, dict[str, float]], args: Namespace,
                   path: Path) -> None:
    lines = [
        "# Flow benchmark: NSF against NAF inside BGN",
        "",
        f"Synthetic collisions-like frames ({args.per_frame} discs per frame, radius graph, "
        "bimodal log-masses, equipartition speeds), BGN with hidden "
        f"{args.hidden}, degree_normalize={bool(args.degree_normalize)}; {args.steps} Adam "
        f"steps (lr {args.lr:g}) over {args.pool} batches, then a held-out batch. Times are "
        f"medians of {args.repeat} calls after a warm-up; the training step is "
        "forward+backward+Adam; sampling draws every particle's mass once (x10).",
        "",
        f"Machine: {machine(torch=torch.__version__)}; {torch.get_num_threads()} torch threads.",
        "",
        markdown_table(["", *rows], [dict(zip(["", *rows], [label, *(fmt.format(r[key])
                                                                 for r in rows.values())]))
                                      for key, label, fmt in FIGURES]),
        "",
        "![training mass NLL and times](flow.png)",
    ]
    path.write_text("\n".join(lines) + "\n")


def write_plot(rows: dict[str, dict[str, float]], curves: dict[str, list[float]],
               path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(9.5, 3.8), dpi=120)
    for flow, curve in curves.items():
        steps = np.arange(1, len(curve) + 1)
        window = max(1, len(curve) // 20)
        smooth = np.convolve(curve, np.ones(window) / window, mode="valid")
        left.plot(steps[window - 1:], smooth, label=flow.upper())
    left.set_xlabel("training step")
    left.set_ylabel("mass NLL (running mean)")
    left.set_title("training")
    left.grid(True, alpha=0.3)
    left.legend()
    keys = [("step_s", "training step"), ("sample_1_s", "sample x1"),
            ("sample_10_s", "sample x10")]
    x = np.arange(len(keys))
    width = 0.8 / len(rows)
    for k, (flow, row) in enumerate(rows.items()):
        right.bar(x + k * width, [row[key] for key, _ in keys], width, label=flow.upper())
    right.set_xticks(x + width * (len(rows) - 1) / 2, [label for _, label in keys])
    right.set_yscale("log")
    right.set_ylabel("seconds")
    right.set_title(f"{int(next(iter(rows.values()))['particles']):,} particles")
    right.grid(True, axis="y", which="both", alpha=0.3)
    right.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def check(cfg: Any) -> None:
    """Everything ``python -m bgn.benchmarks.flow`` is given, before any work."""
    from bgn.coerce import ConfigError, need_float, need_int

    for key in ("particles", "per_frame", "hidden", "steps", "pool", "repeat"):
        need_int(cfg[key], key, 1)
    if cfg.particles < cfg.per_frame:
        raise ConfigError("particles", cfg.particles, f"must be >= per_frame ({cfg.per_frame})")
    need_float(cfg.lr, "lr", 0)
    need_int(cfg.threads, "threads", 1, optional=True, why=" (null: torch's default)")
    need_int(cfg.seed, "seed", 0)
    if not isinstance(cfg.degree_normalize, bool):
        raise ConfigError("degree_normalize", cfg.degree_normalize, "true or false")
    need_choices(cfg.flows, "flows", ("nsf", "naf"))


@command("flow", check)  # key=value; bad input: one line, exit 2
def main(cfg: Any) -> int:
    """Measure each flow and write the report under ``report_dir``."""
    args = options(cfg)
    if args.threads:
        torch.set_num_threads(args.threads)
    out = console()
    out.print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, hidden "
              f"{args.hidden}, {args.particles} particles, {args.steps} training steps, "
              f"degree_normalize={bool(args.degree_normalize)}")
    rows, curves = {}, {}
    for flow in dict.fromkeys(args.flows):
        rows[flow], curves[flow] = benchmark(flow, args)
        out.log(f"{flow}: step {rows[flow]['step_s']:.3f} s, NLL {rows[flow]['nll_mean']:.3f}")
    print_table(out, "NSF vs NAF inside BGN", ["", *rows],
                [[label, *(fmt.format(r[key]) for r in rows.values())]
                 for key, label, fmt in FIGURES])

    args.report_dir.mkdir(parents=True, exist_ok=True)
    write_csv(args.report_dir / "flow.csv", ["flow", *(key for key, _, _ in FIGURES)],
              [{"flow": flow, **{key: f"{r[key]:.6g}" for key, _, _ in FIGURES}}
               for flow, r in rows.items()])
    write_markdown(rows, args, args.report_dir / "flow.md")
    write_plot(rows, curves, args.report_dir / "flow.png")
    out.print(f"wrote {args.report_dir / 'flow.md'}, .csv, .png")
    return 0


if __name__ == "__main__":
    main()
