"""Would the formula stage's exponent rounding pass if it were tried after the polish? For a
run whose formula kept a free exponent (``<run>/laws/formula.json``'s ``tuned``), the law
loss the stage tunes on (``bgn.laws.finetune.tune_constants`` over the same training batch)
of: the tuned formula as it is; the same with its exponent rounded as ``snapped_exponent``
rounds it, as is and re-tuned (80 evaluations); each through 16 substeps (where the stage
tries the rounding, before the polish) and 64 (the polish's). Training split only.

    python docs/notes/laws/snap_after_polish.py outputs/gravity_r2_s2
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from omegaconf import OmegaConf

from bgn.data.datamodule import ParticleDataModule
from bgn.laws import finetune


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    args = parser.parse_args()
    record = json.loads((args.run / "laws" / "formula.json").read_text())
    cfg = OmegaConf.load(args.run / ".hydra" / "config.yaml")
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, show_progress=False)
    dm.prepare_data()
    dm.setup()
    batches = finetune.tuning_batches(dm.datasets["train"],
                                      finetune.DEFAULTS.finetune_batch_size, 0)
    checkpoint, spec = Path(record["checkpoint"]), json.dumps(record["tuned"])
    trial = finetune.snapped_exponent(spec, set())
    if trial is None:
        raise SystemExit(f"{args.run}: the tuned formula has no exponent near a round value")

    def loss(law: str, substeps: int, steps: int) -> tuple[float, str]:
        module, _ = finetune.formula_module(checkpoint, law, substeps)
        model, head = finetune.pair_force_head(module)
        model.requires_grad_(False)
        model.eval()
        value, _ = finetune.tune_constants(model, head, batches, steps, None)
        return value, head.force_law.spec()

    print(f"{args.run}: {spec}; rounding: {trial[2]}")
    for substeps in (finetune.DEFAULTS.finetune_substeps,
                     finetune.DEFAULTS.polish_factor * finetune.DEFAULTS.finetune_substeps):
        free = loss(spec, substeps, 1)[0]
        as_is = loss(trial[0], substeps, 1)[0]
        tuned, law = loss(trial[0], substeps, finetune.DEFAULTS.finetune_steps)
        print(f"substeps {substeps}: free exponent {free:.5g}; rounded {as_is:.5g}, re-tuned "
              f"{tuned:.5g} ({tuned / free - 1:+.2%} against the free one): {law}", flush=True)


if __name__ == "__main__":
    main()
