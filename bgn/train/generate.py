"""``python -m bgn.train.generate dataset=<scene> fps=<frames per time unit>``: write a
dataset's train, val and test files (``bgn.data.generate``) without training.

A command of the training stage: its config is the training's ``dataset`` node and ``fps``,
typed by ``bgn.training.config`` and checked by ``bgn.training.validate`` before any simulation.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from bgn.data.files import DatasetFile
from bgn.data.generate import ensure_splits
from bgn.training.validate import cli, validate_generate


def main(cfg: Any) -> dict[str, Path]:
    """Entry point body: generate every split of ``cfg.dataset`` at ``cfg.fps``."""
    spec = validate_generate(cfg)  # bad values fail here, before any simulation
    start = time.perf_counter()
    paths = ensure_splits(spec, cfg.paths.data_dir, cfg.get("workers"))
    elapsed = time.perf_counter() - start
    for split, path in paths.items():
        f = DatasetFile(path, check_values=False)
        print(f"{split:>5}: {path}  ({path.stat().st_size / 1e6:.1f} MB, {f.n_sims} sims x "
              f"{f.n_frames} frames x {f.attrs['n_particles']} particles)")
        f.close()
    print(f"done in {elapsed:.1f} s")
    return paths


if __name__ == "__main__":
    # a Hydra app; bad input: one line, exit 2 (main validates first)
    cli("generate", prog="bgn.train.generate")(main)()
