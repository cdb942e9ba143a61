"""Nelder-Mead restarts on a run's formula-stage forms (issue 56): each form of
``<run>/laws/formula.json`` (``forms``, by index) tuned from its own start as the stage tunes it
(``bgn.laws.finetune.tune_constants``, ``finetune_steps`` evaluations, the tuning's substeps,
the stage's fixed batch of training frames), then restarted from a fresh simplex about its best
point, ``--passes`` passes in all; the loss after each pass and the constants after the last.
Training split only: nothing here reads validation or test. Run before ``finetune_restarts``
existed, it shows what one restart does; at or after it, each "pass" is the stage's own
tuning with its restarts.

    python docs/notes/laws/restart_trial.py outputs/s26/gravity_r2_s1 4 5 --passes 4
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch


def main() -> None:
    from omegaconf import OmegaConf

    from bgn.data.datamodule import ParticleDataModule
    from bgn.laws.finetune import formula_module, tune_constants, tuning_batches
    from bgn.laws.options import DEFAULTS
    from bgn.laws.sample import pair_force_head
    from bgn.training.budget import NO_DEADLINE
    from bgn.training.checkpoints import best_checkpoint

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("forms", nargs="+", type=int, help="indices into formula.json's forms")
    parser.add_argument("--passes", type=int, default=4)
    args = parser.parse_args()
    cfg = OmegaConf.load(args.run / ".hydra" / "config.yaml")
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, show_progress=False)
    dm.prepare_data()
    dm.setup()
    # the stage's batch: seed 0, as bgn.laws.finetune.finetune_formula's default
    batches = tuning_batches(dm.datasets["train"], DEFAULTS.finetune_batch_size, 0)
    record = json.loads((args.run / "laws" / "formula.json").read_text())
    checkpoint = Path(record.get("checkpoint") or best_checkpoint(args.run))
    print("| form | start | loss after each pass | constants after the last |")
    print("|---|---|---|---|")
    for i in args.forms:
        start = record["forms"][i]["start"]
        spec = start if isinstance(start, str) else json.dumps(start)
        module, _ = formula_module(checkpoint, spec, DEFAULTS.finetune_substeps)
        model, head = pair_force_head(module)
        model.requires_grad_(False)
        model.eval()
        losses = [tune_constants(model, head, batches, DEFAULTS.finetune_steps, NO_DEADLINE)[0]
                  for _ in range(args.passes)]
        tuned = json.loads(head.force_law.spec())
        print(f"| {i} | `{json.dumps(json.loads(spec))}` | "
              f"{' / '.join(f'{x:.4g}' for x in losses)} | `{json.dumps(tuned)}` |", flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
