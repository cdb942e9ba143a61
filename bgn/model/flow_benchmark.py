"""NSF vs NAF inside the whole BGN model, on CPU: speed and what a short training reaches.

    python -m bgn.model.flow_benchmark [--particles 2000] [--steps 300] [--threads 2]

A synthetic collisions-like task, no files: frames of ``particles_per_frame`` discs in a box
with a radius graph, two particle types whose log-masses are bimodal (modes 0.001 and 0.4, as
in the collisions scene) and whose speeds follow equipartition (``|v| ~ 1/sqrt(m)``), so the
mass of a particle can be read from its velocity window. Reported per flow:

- forward+backward time of one training step of the whole model (hidden 128 by default);
- time to sample every particle's mass once (and 10 times);
- after ``--steps`` Adam steps cycling through ``--pool`` batches: held-out NLL of the
  normalised log-mass (mean and median over particles), the R^2 of the relative log-mass
  ``log m_i - log m_j`` on edges from one posterior sample (the paper's Eq. 9-10 path), the
  R^2 of the mean of 16 posterior log-mass samples, and the training wall time.

The model uses degree normalisation by default here (``--degree-normalize 0`` for the paper's
plain ``Â = A + I``, with which neither flow trains in 300 steps on this task).
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
import torch

from bgn.graph import Graph, collate
from bgn.model import BGN, ModelConfig
from bgn.sim.scene import SceneMeta

BOX = 10.0
RADIUS = 0.3
CUTOFF = 1.0       # candidate pairs: about 6 neighbours per particle at 200 per frame
HISTORY = 5
MODES = (math.log(0.001), math.log(0.4))
LOG_MASS_JITTER = 0.2
DT = 0.02


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


def summarize(x: torch.Tensor) -> dict[str, np.ndarray]:
    x = x.double().reshape(len(x), -1).numpy()
    median = np.median(x, 0)
    return {"mean": x.mean(0), "std": x.std(0), "median": median,
            "robust_scale": 1.4826 * np.median(np.abs(x - median), 0)}


def synthetic_stats(g: Graph) -> dict[str, dict[str, np.ndarray]]:
    snd, rcv = g.edge_index
    return {"velocity": summarize(g.vel[:, 0]), "target": summarize(g.target),
            "log_mass": summarize(torch.log(g.mass)[:, None]),
            "rel_position": summarize(g.pos[rcv] - g.pos[snd]),
            "rel_velocity": summarize(g.vel[rcv, 0] - g.vel[snd, 0]),
            "contact": summarize(g.edge_contact[:, None]),
            "rel_log_mass": summarize(g.edge_rel_log_mass[:, None])}


def timed(fn, repeat: int) -> float:
    """Median wall time of ``repeat`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def r2(pred: torch.Tensor, true: torch.Tensor) -> float:
    return float(1 - ((pred - true) ** 2).sum() / ((true - true.mean()) ** 2).sum())


def benchmark(flow: str, args: argparse.Namespace) -> dict[str, float]:
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    frames = max(1, args.particles // args.per_frame)
    meta = SceneMeta(name="synthetic_collisions", dim=2, n_particles=args.per_frame, n_types=2,
                     interaction="contact", target="velocity", graph="radius", box=BOX)
    stats_batch = synthetic_batch(frames, args.per_frame, gen)
    cfg = ModelConfig(hidden=args.hidden, flow=flow, degree_normalize=bool(args.degree_normalize))
    model = BGN(meta, synthetic_stats(stats_batch), HISTORY, cfg)
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
    t0 = time.perf_counter()
    for i in range(args.steps):
        step(pool[i % len(pool)])
    result["train_s"] = time.perf_counter() - t0
    test = synthetic_batch(frames, args.per_frame, gen)
    model.eval()
    with torch.no_grad():
        out = model(test)
        result["nll_mean"] = float(out.mass_nll.mean())
        result["nll_median"] = float(out.mass_nll.median())
        rel = model.denormalize_relmass(out.relmass)
        result["relmass_r2"] = r2(rel, test.edge_rel_log_mass)
        samples = torch.log(model.sample_mass(test, 16))
        result["logmass_r2_mean16"] = r2(samples.mean(0), torch.log(test.mass))
        result["dynamics_loss"] = float(model.loss_terms(test, out)["dynamics"])
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--particles", type=int, default=2000)
    parser.add_argument("--per-frame", type=int, default=200)
    parser.add_argument("--hidden", type=int, default=128)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--pool", type=int, default=20, help="training batches cycled through")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--degree-normalize", type=int, choices=(0, 1), default=1,
                        help="1: D^-1/2 Â D^-1/2 (trains here); 0: the paper's plain Â = A + I")
    parser.add_argument("--flows", nargs="+", default=["nsf", "naf"])
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"hidden {args.hidden}, {args.particles} particles, {args.steps} training steps, "
          f"degree_normalize={bool(args.degree_normalize)}")
    rows = {flow: benchmark(flow, args) for flow in args.flows}
    keys = ["particles", "edges", "step_s", "sample_1_s", "sample_10_s", "train_s", "nll_mean",
            "nll_median",
            "relmass_r2", "logmass_r2_mean16", "dynamics_loss"]
    print(f"{'':20s}" + "".join(f"{f:>12s}" for f in rows))
    for key in keys:
        print(f"{key:20s}" + "".join(f"{rows[f][key]:12.4g}" for f in rows))


if __name__ == "__main__":
    main()
