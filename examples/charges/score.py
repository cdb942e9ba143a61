"""The masses and charges a trained model infers through the law IT learned, scored against the
hidden truth (issue "The inverse half", item 3): beside ``identify.py``'s fits with the true law.

    python examples/charges/score.py <run> data/external/charges4 --out outputs/charges/score

For each test simulation of the run's imported data (``data/imported/<name>/test.h5``): its
model's pair-force head (``mass_law=coupling``; a run of ``model.dynamics=auto`` whose winner
is another head has nothing to score) fits ``a_i = k_i sum_j c_j f(s_ij) u_ij`` with its own
learned ``f`` to ``--windows`` windows spread over the simulation, pooled
(``bgn.eval.law_posterior.pooled_system``, the accelerations its law misses screened out as
the law posterior does). Scored as ``identify.py`` scores (``identify.scores``: log-masses
``log(c / k)`` centred per simulation, charge signs up to the global sign, charge R^2), against
``_hidden/truth.npz``, which the model never read. Writes ``score.md`` and ``score.csv`` under
``--out``: the row of the learned law, and beside it ``identify.py``'s fit with the true law on
the same windows' frames.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import torch
from omegaconf import OmegaConf

from bgn.data.dataset import FrameDataset
from bgn.data.files import DatasetFile
from bgn.data.frames import evenly_spaced
from bgn.eval.law_posterior import pooled_system, screened
from bgn.model.newton import pair_force_head_of
from bgn.training.checkpoints import resolve_run
from bgn.training.module import load_model

sys.path.insert(0, str(Path(__file__).resolve().parent))
from identify import fit, scores, system  # noqa: E402


def learned_couplings(head: torch.nn.Module, dataset: FrameDataset, windows: int,
                      ) -> tuple[np.ndarray, np.ndarray, list[list[int]]]:
    """k and c (S, N) of every simulation of ``dataset`` through the head's learned law, and
    the frames each fit read."""
    ks, cs, frames = [], [], []
    per = dataset.frames_per_sim
    for s in range(len(dataset.sims)):
        index = [s * per + i for i in evenly_spaced(per, windows)]
        graphs = [dataset[i] for i in index]
        with torch.no_grad():
            g, past, seen, start = pooled_system(head, graphs)
            couplings = head.fit_observed(g, *screened(head, g, past, seen, start))[0]
        k, c = couplings[:, 0].double().numpy(), couplings[:, 1].double().numpy()
        # the learned law's sign is free (f -> -f, c -> -c): turned so that most masses c / k
        # are positive, as bgn.eval.law_posterior does
        turn = np.sign(np.median(c / k)) or 1.0
        ks.append(k)
        cs.append(c * turn)
        frames.append([dataset.locate(i)[1] for i in index])
    return np.stack(ks), np.stack(cs), frames


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a training run's folder")
    ap.add_argument("data", type=Path, help="the folder make.py wrote (its _hidden/truth.npz)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--windows", type=int, default=64, help="windows per simulation")
    ap.add_argument("--charge-floor", type=float, default=0.2)
    args = ap.parse_args(argv)

    ckpt, _, config = resolve_run(str(args.run))
    run_cfg = OmegaConf.load(config)
    module = load_model(ckpt)
    head = pair_force_head_of(module.model)
    if head is None or head.mass_law != "coupling":
        raise SystemExit(f"{args.run}: its model has no pair-force head with mass_law=coupling "
                         f"({module.model.label}): nothing to score")
    test = FrameDataset(DatasetFile(Path(run_cfg.paths.data_dir) / "imported"
                                    / run_cfg.dataset.name / "test.h5"),
                        history=module.model.history)
    truth = np.load(args.data / "_hidden" / "truth.npz")
    rows = np.flatnonzero(truth["split"] == "test")
    masses, charges = truth["masses"][rows], truth["charges"][rows]
    k, c, frames = learned_couplings(head, test, args.windows)
    learned = scores(k, c, masses, charges, args.charge_floor)
    raw = np.load(args.data / "charges.npz")
    positions, dt = raw["positions"][rows], float(raw["dt"])
    softening = json.loads((args.data / "make.json").read_text())["params"]["softening"]
    # the true law on the same frames (identify.py's fit): each window's frames t-k+1 .. t-1
    k_true, c_true = fit([system(positions[s], dt, np.unique(np.concatenate(
        [np.arange(t - module.model.history + 1, t) for t in windows])), softening)
        for s, windows in enumerate(frames)])
    table = [{"law": f"learned ({module.model.label})", **learned},
             {"law": "true (identify.py's fit)",
              **scores(k_true, c_true, masses, charges, args.charge_floor)}]
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "score.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(table[0]))
        writer.writeheader()
        writer.writerows(table)
    lines = ["| " + " | ".join(table[0]) + " |", "|" + "---|" * len(table[0])]
    lines += ["| " + " | ".join(f"{v:.4g}" if isinstance(v, float) else str(v)
                                for v in row.values()) + " |" for row in table]
    text = (f"# Masses and charges through the learned law\n\nRun `{args.run}`, test split "
            f"({len(rows)} simulations, {args.windows} windows each); charge signs scored where "
            f"|q| >= {args.charge_floor} x the simulation's rms charge.\n\n"
            + "\n".join(lines) + "\n")
    (args.out / "score.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
