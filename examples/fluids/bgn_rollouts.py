"""bgn's rollouts of a LagrangeBench-layout test split, in the form score.py reads.

Each test trajectory is rolled out from its first six frames (LagrangeBench's models are given
six; bgn reads the last ``window_length`` of them) to its end, through the Python API
(``bgn.load``), so that bgn and LagrangeBench's models predict the same frames from the same
start. Runs in bgn's environment:

    python examples/fluids/bgn_rollouts.py outputs/fluids/sph_tgv_bgn_s0 data/external/sph_tgv \
        --out outputs/fluids/sph_tgv_bgn_s0/rollouts_lb.npz

Writes ``predicted`` and ``truth`` (n, T, N, D) and ``seconds_per_frame`` (the rollout's wall
time per predicted frame on this machine, one thread: the speed-against-error table).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import torch

import bgn

INPUT_FRAMES = 6          # what LagrangeBench's models are given (input_seq_length)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a bgn run folder or checkpoint")
    p.add_argument("data", type=Path, help="the LagrangeBench-layout dataset folder")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--split", default="test")
    a = p.parse_args(argv)
    if not (a.data / f"{a.split}.h5").is_file():
        p.error(f"{a.data}: no {a.split}.h5; give a LagrangeBench-layout dataset folder")
    torch.set_num_threads(1)
    model = bgn.load(a.run)
    if model.window_length > INPUT_FRAMES:
        p.error(f"{a.run}: the model reads {model.window_length} frames, more than the "
                f"{INPUT_FRAMES} LagrangeBench's models are given")
    predicted, truth, seconds, frames = [], [], 0.0, 0
    with h5py.File(a.data / f"{a.split}.h5", "r") as f:
        for name in sorted(f):
            pos = f[name]["position"][()].astype(np.float64)
            types = f[name]["particle_type"][()]
            steps = len(pos) - INPUT_FRAMES
            t0 = time.perf_counter()
            # LagrangeBench's layout records no radii and bgn imports them as zeros: its radius
            # graph then joins the pairs within the connectivity radius, as in training
            future = model.rollout(pos[INPUT_FRAMES - model.window_length:INPUT_FRAMES], steps,
                                   types=types, radii=np.zeros(pos.shape[1]))
            seconds += time.perf_counter() - t0
            frames += steps
            predicted.append(np.concatenate([pos[:INPUT_FRAMES], future]).astype(np.float32))
            truth.append(pos.astype(np.float32))
            print(f"{a.split} {name}: {steps} frames in {time.perf_counter() - t0:.1f} s",
                  flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, predicted=np.stack(predicted), truth=np.stack(truth),
                        start=INPUT_FRAMES - 1, seconds_per_frame=seconds / frames)
    print(f"{a.out}: {len(predicted)} rollouts, {seconds / frames * 1e3:.1f} ms per frame")
    return 0


if __name__ == "__main__":
    sys.exit(main())
