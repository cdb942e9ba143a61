"""The measurements behind force matching (docs/notes/2026-11-26-force-matching.md), on the
imported engines' datasets (examples/engines/README.md). Run from the repository root:

    python docs/notes/force-matching/probe.py readout              # Morse: readout ridges
    python docs/notes/force-matching/probe.py train [overrides]    # match, then train steps
    python docs/notes/force-matching/probe.py masses <auto candidate run>   # window fit vs fixed

Environment: DATA (the import's data dir, default data), NAME (dataset, default
ase_morse_gas), STEPS (training steps, default 200), LR (default 1e-3).
"""

from __future__ import annotations

import itertools
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path[:0] = ["tests", "examples/engines"]

from conftest import compose_config  # noqa: E402

from bgn.model import force_matching as fm  # noqa: E402
from bgn.model.newton import numerov, past_positions  # noqa: E402
from bgn.model.ops import scatter_sum  # noqa: E402
from bgn.model.target_coder import observed_targets  # noqa: E402
from bgn.rollout import rollout_error, rollout_many  # noqa: E402
from bgn.training.run import build  # noqa: E402

DATA, NAME = os.environ.get("DATA", "data"), os.environ.get("NAME", "ase_morse_gas")


def setup(*overrides: str):
    torch.manual_seed(0)
    torch.set_num_threads(2)
    cfg = compose_config("train", ["dataset=imported", f"dataset.name={NAME}",
                                   f"paths.data_dir={DATA}", *overrides])
    dm, module = build(cfg)
    head = getattr(module.model, "force_head", None) or module.model.head
    return dm, module, head


def val_rollouts(module, dm) -> list[float]:
    module.eval()
    with torch.no_grad():
        out = [round(rollout_error(module.model, dm.datasets["val"], n_sims=3, n_steps=n), 5)
               for n in (10, 50)]
    module.train()
    return out


def readout() -> None:
    """The MLP's last layer fitted by least squares over its random features (model=newton):
    the error on validation windows, the coefficients' norm, and the error once the hidden
    layers move by 1e-4 or 1e-3 per weight (what Adam's first steps do)."""
    dm, _, head = setup("model=newton")
    body = head.force_law[:-1]

    def equations(graphs):
        total = None
        for g in graphs:
            rel, dist = head.separations(g, past_positions(g))
            h = body(head.law_input(dist, None))
            h = torch.cat([h, torch.ones_like(h[..., :1])], -1)
            terms = numerov(h[..., None, :] * (rel / dist)[..., None])[:, 1:]
            x = scatter_sum(terms, g.edge_index[1], g.pos.shape[0])
            seen = observed_targets(g, "acceleration")[:, :x.shape[1]]
            x, y = x.reshape(-1, x.shape[-1]).double(), seen.reshape(-1).double()
            eq = fm.NormalEquations(x.T @ x, x.T @ y, y @ y, len(y))
            total = eq if total is None else total + eq
        return total

    with torch.no_grad():
        fit = equations(itertools.islice(dm.train_dataloader(), 30))
        check = equations(itertools.islice(dm.val_dataloader(), 10))
        values, vectors = torch.linalg.eigh(fit.gram)
        projected, scale = vectors.T @ fit.moment, float(fit.gram.diagonal().mean())
        start = [p.detach().clone() for p in body.parameters()]
        for ridge in (10.0**-k for k in range(16, 1, -2)):
            c = vectors @ (projected / (values.clamp_min(0) + ridge * scale))
            moved = []
            for eps in (1e-4, 1e-3):
                gen = torch.Generator().manual_seed(1)
                for p, p0 in zip(body.parameters(), start):
                    p.copy_(p0 + eps * torch.sign(torch.randn(p0.shape, generator=gen)))
                moved.append(equations(itertools.islice(dm.val_dataloader(), 3))
                             .relative_error(c))
                for p, p0 in zip(body.parameters(), start):
                    p.copy_(p0)
            print(f"ridge {ridge:.0e}: validation {check.relative_error(c):.3g}, |c| "
                  f"{float(c.norm()):.3g}, hidden layers moved 1e-4: {moved[0]:.3g}, "
                  f"1e-3: {moved[1]:.3g}")


def train(*overrides: str) -> None:
    """Force matching, then STEPS training steps at LR on every parameter; the validation
    rollout errors after 10 and 50 steps every 100 steps."""
    dm, module, head = setup(*overrides)
    start = time.perf_counter()
    result = fm.match_forces(head, list(itertools.islice(dm.train_dataloader(), 30)),
                             list(itertools.islice(dm.val_dataloader(), 10)),
                             known_masses="law" in module.model.heads)
    print(result, f"({time.perf_counter() - start:.1f} s)")
    module.log = module.log_dict = lambda *a, **k: None
    optimizer = torch.optim.AdamW(module.parameters(), lr=float(os.environ.get("LR", "1e-3")))
    print("step 0: val error @10, @50", val_rollouts(module, dm), flush=True)
    steps, n = int(os.environ.get("STEPS", "200")), 0
    while n < steps:
        for batch in dm.train_dataloader():
            optimizer.zero_grad()
            module.training_step(batch, 0).backward()
            optimizer.step()
            n += 1
            if n % 100 == 0:
                print(f"step {n}: val error @10, @50", val_rollouts(module, dm), flush=True)
            if n >= steps:
                break


def masses(run: str) -> None:
    """A trained pair-force candidate's validation rollouts (from frame 100, 104 steps) with
    its masses fitted to the window at every step, then with one fixed mass (the median fit
    of the first batch) for every particle; ASE's energy of each (engine_energy.py)."""
    import engine_energy
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.training.checkpoints import best_checkpoint
    from bgn.training.module import load_model

    module = load_model(best_checkpoint(Path(run)))
    model = module.model.eval()
    cfg = OmegaConf.load(Path(run) / "train_config.yaml")
    dm = ParticleDataModule(cfg.dataset, cfg.fps, DATA, show_progress=False)
    dm.prepare_data()
    dm.setup()
    val, head = dm.datasets["val"], model.force_head

    def report(label: str) -> None:
        with torch.no_grad():
            t = rollout_many(model, val, list(range(val.file.n_sims)), [100], 104)
        pred, true = np.asarray(t.predicted), np.asarray(t.true)
        err = np.linalg.norm(pred - true.reshape(pred.shape), axis=-1).mean(-1)
        energy = engine_energy.dataset_energy(Path(DATA) / "external" / cfg.dataset.name, pred,
                                              None, "val")
        drift = [abs(e["energy"][102] - e["energy"][2]) / abs(e["energy"][2]) for e in energy]
        print(label, "error @10/50/100", [round(float(err[:, h].mean()), 4)
                                          for h in (10, 50, 100)],
              "energy change after 100 steps", np.round(drift, 3), flush=True)

    report("masses fitted to the window:")
    g = next(iter(dm.val_dataloader()))
    with torch.no_grad():
        fixed = float(head.fit(g, head.window(g)[1]).median())
    head.fit = lambda g, terms: torch.full((g.pos.shape[0],), fixed, dtype=terms.dtype)
    report(f"one fixed mass ({fixed:.3f}):")


if __name__ == "__main__":
    command, *args = sys.argv[1:] or ["readout"]
    {"readout": readout, "train": train, "masses": masses}[command](*args)
