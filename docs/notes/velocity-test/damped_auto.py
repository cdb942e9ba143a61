"""model.dynamics=auto on springs damped along the line between the particles (central, so
momentum and angular momentum are kept): which structure does it choose at a tiny budget?

    python docs/notes/velocity-test/damped_auto.py <damping> <max_steps> <frames> <out_dir>

The data: tests/model/test_force_matching.py's ``damped_springs`` (8 simulations: 5 train, 2
validation, 1 test), imported with ``bgn.data.from_arrays``; then ``python -m bgn.train``
with ``model.dynamics=auto`` at small sizes (hidden 16, ``max_steps`` in all, three quarters
for the candidates, no references). Prints the choice and each candidate's validation error
after 10 and 50 steps. ``max_steps`` 0: the data only (``<out_dir>/data/imported/damped/``).
Before the velocity test (at 16f852b) damping 0.2, 0.5 and 1.0 with
800 steps and 200 frames chose a pair-force head (docs/results.md, "What the data
conserve"); since, the pair-force heads are not admitted on them.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(ROOT))

from bgn.data import from_arrays  # noqa: E402
from tests.model.test_force_matching import damped_springs  # noqa: E402


def main() -> None:
    damping, steps, frames, out = (float(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]),
                                   Path(sys.argv[4]).resolve())
    from_arrays(damped_springs(damping, sims=8, frames=frames), 0.02, name="damped",
                data_dir=out / "data", splits={"train": [0, 1, 2, 3, 4], "val": [5, 6],
                                               "test": [7]}, overwrite=True)
    if steps == 0:  # the data alone (docs/results.md's balance table reads them)
        return
    cmd = [sys.executable, "-m", "bgn.train", "dataset=imported", "dataset.name=damped",
           f"paths.data_dir={out / 'data'}", f"hydra.run.dir={out / 'run'}",
           "model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16",
           "figures=false", "val_rollout_steps=0", "animation_every=0",
           "callbacks.progress_bar=null", "dataset.batch_size=16",
           "trainer.check_val_every_n_epoch=5", "trainer.max_epochs=-1",
           f"trainer.max_steps={steps}", "auto.share=0.75", "auto.references=[]",
           "test=false"]
    proc = subprocess.run(cmd, cwd=ROOT, env={**os.environ, "OMP_NUM_THREADS": "1"},
                          capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(proc.stderr[-2000:])
    record = json.loads((out / "run" / "auto" / "auto.json").read_text())
    print("choice:", record["choice"])
    for c in record["candidates"]:
        print(c["candidate"], "admitted" if c["admitted"] else f"not admitted ({c['reason']})",
              c.get("val_err@10"), c.get("val_err@50"))


if __name__ == "__main__":
    main()
