"""LagrangeBench's own GNS and SEGNN on a dataset in its layout: timed, trained for a number
of optimiser steps, then rolled out over the test split's full length.

Runs in the peer environment (setup_peer.sh); everything below is LagrangeBench 0.2.0's code
(its data loader, feature builder, models, trainer and rollout), driven with the settings its
authors published for the 2D cases (configs/<case>_2d/{gns,segnn}.yaml: GNS 10 message-passing
steps of width 128, SEGNN 10 of width 64 with isotropic normalisation, learning rate 5e-4,
noise 3e-4, 1e-3 on the dam break whose gravity the models read as an external force).

    # seconds per optimiser step, measured alone after compilation (for equal wall time)
    .venv-peer/bin/python examples/fluids/peer.py time data/external/sph_tgv gns
    # train for N steps, then the test rollouts -> <out>/rollouts.npz, <out>/peer.json
    .venv-peer/bin/python examples/fluids/peer.py train data/external/sph_tgv gns \
        --steps N --seed 0 --out outputs/fluids/sph_tgv_gns_s0

score.py scores these rollouts and bgn's the same way.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import h5py
import haiku as hk
import jax
import jmp
import numpy as np
from lagrangebench import Trainer, infer
from lagrangebench.case_setup import case_builder
from lagrangebench.data import H5Dataset
from lagrangebench.defaults import set_defaults
from lagrangebench.runner import setup_model

jax.config.update("jax_enable_x64", True)       # LagrangeBench's default: f64 outside the model

RECIPES = {"gns": dict(name="gns", num_mp_steps=10, latent_dim=128),
           "segnn": dict(name="segnn", num_mp_steps=10, latent_dim=64, isotropic_norm=True)}
INPUT_FRAMES = 6                                  # LagrangeBench's input_seq_length


def configure(data: Path, model: str, seed: int, steps: int, out: Path | None):
    cfg = set_defaults()
    cfg.dataset.src = str(data.resolve())
    cfg.dataset.name = data.name
    for k, v in RECIPES[model].items():
        cfg.model[k] = v
    cfg.seed = seed
    cfg.train.step_max = steps
    cfg.train.num_workers = 0
    cfg.train.optimizer.lr_start = 5e-4
    dam = (data / "force.py").is_file()
    cfg.train.noise_std = 1e-3 if dam else 3e-4
    cfg.neighbors.multiplier = 2.0 if dam else 1.25
    cfg.logging.log_steps = max(steps // 10, 1)
    cfg.logging.eval_steps = max(steps, 1)        # validate once, at the end: the saved model
    cfg.logging.ckp_dir = str(out / "ckp") if out else None
    cfg.logging.run_name = "run"
    with h5py.File(data / "valid.h5", "r") as f:                 # validation rollouts: 20
        length = f[sorted(f)[0]]["position"].shape[0]             # steps, as LagrangeBench's
    cfg.eval.n_rollout_steps = min(20, length - INPUT_FRAMES)
    cfg.eval.train.n_trajs = -1
    return cfg


def build(cfg):
    """LagrangeBench's runner, up to the trainer: data, case (features, integration), model."""
    data_train = H5Dataset("train", cfg.dataset.src, cfg.dataset.name, INPUT_FRAMES,
                           cfg.train.pushforward.unrolls[-1])
    data_valid = H5Dataset("valid", cfg.dataset.src, cfg.dataset.name, INPUT_FRAMES,
                           cfg.eval.n_rollout_steps)
    meta = data_train.metadata
    bounds = np.array(meta["bounds"])
    case = case_builder(box=bounds[:, 1] - bounds[:, 0], metadata=meta,
                        input_seq_length=INPUT_FRAMES, cfg_neighbors=cfg.neighbors,
                        cfg_model=cfg.model, noise_std=cfg.train.noise_std,
                        external_force_fn=data_train.external_force_fn, dtype=cfg.dtype)
    _, types = data_train[0]
    model, module = setup_model(cfg, metadata=meta,
                                homogeneous_particles=types.max() == types.min(),
                                has_external_force=data_train.external_force_fn is not None,
                                normalization_stats=case.normalization_stats)
    model = hk.without_apply_rng(hk.transform_with_state(model))
    hk.mixed_precision.set_policy(
        module, jmp.get_policy("params=float32,compute=float32,output=float32"))
    trainer = Trainer(model, case, data_train, data_valid, cfg.train, cfg.eval, cfg.logging,
                      input_seq_length=INPUT_FRAMES, seed=cfg.seed)
    return model, case, trainer


def time_steps(data: Path, model: str, steps: int = 30) -> dict:
    """Seconds per optimiser step: two runs of different length, their difference, so that
    compilation and start-up cancel."""
    took = []
    for n in (steps, 2 * steps):
        cfg = configure(data, model, 0, n, None)
        cfg.logging.eval_steps = 10 ** 9          # no validation while timing
        _, _, trainer = build(cfg)
        t0 = time.perf_counter()
        trainer.train(step_max=n, store_ckp=None)
        took.append(time.perf_counter() - t0)
    per_step = (took[1] - took[0]) / steps
    if per_step <= 0:
        raise SystemExit(f"{model} on {data}: {steps} more steps took {took[1] - took[0]:.1f} s, "
                         f"within the start-up's noise; time more steps (--steps {4 * steps})")
    return {"model": model, "data": str(data), "seconds_per_step": per_step,
            "timed_steps": [steps, 2 * steps], "seconds": took}


def train(data: Path, model: str, steps: int, seed: int, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    cfg = configure(data, model, seed, steps, out)
    t0 = time.perf_counter()
    net, case, trainer = build(cfg)
    params, state, _ = trainer.train(step_max=steps, store_ckp=str(out / "ckp" / "run"))
    train_s = time.perf_counter() - t0
    data_test = H5Dataset("test", cfg.dataset.src, cfg.dataset.name, INPUT_FRAMES, 1)
    length = data_test.sequence_length
    data_test = H5Dataset("test", cfg.dataset.src, cfg.dataset.name, INPUT_FRAMES,
                          length - INPUT_FRAMES)
    t0 = time.perf_counter()
    rollout_dir = out / "rollout"
    infer(net, case, data_test, params=params, state=state,
          cfg_eval_infer={"metrics": ["mse"], "out_type": "pkl", "n_trajs": -1,
                          "batch_size": 1},
          rollout_dir=str(rollout_dir), n_rollout_steps=length - INPUT_FRAMES, seed=seed)
    rollout_s = time.perf_counter() - t0
    predicted, truth = collect(rollout_dir, data_test.num_samples)
    np.savez_compressed(out / "rollouts.npz", predicted=predicted, truth=truth,
                        start=INPUT_FRAMES - 1)
    record = {"model": model, "peer": "lagrangebench 0.2.0", "data": str(data), "seed": seed,
              "steps": steps, "train_s": train_s, "rollout_s": rollout_s,
              "rollout_frames": int(predicted.shape[1] - INPUT_FRAMES),
              "given": given(data)}
    (out / "peer.json").write_text(json.dumps(record, indent=1))
    return record


def given(data: Path) -> str:
    """What LagrangeBench's models read beyond the positions (its feature builder): the
    distance to the box's faces where the box is closed, the external force where force.py
    gives one."""
    meta = json.loads((data / "metadata.json").read_text())
    parts = ["positions of the last 6 frames", "particle types"]
    if not any(meta["periodic_boundary_conditions"]):
        parts.append("distance to the box's faces")
    if (data / "force.py").is_file():
        parts.append("gravity (force.py)")
    return ", ".join(parts)


def collect(rollout_dir: Path, n: int) -> tuple[np.ndarray, np.ndarray]:
    """LagrangeBench's per-trajectory rollout files -> (n, T, N, D) predicted and true."""
    import pickle  # LagrangeBench writes its rollouts so; files this script just wrote
    pred, truth = [], []
    for i in range(n):
        with open(rollout_dir / f"rollout_{i}.pkl", "rb") as f:
            r = pickle.load(f)
        pred.append(np.asarray(r["predicted_rollout"]))
        truth.append(np.asarray(r["ground_truth_rollout"]))
    return np.stack(pred), np.stack(truth)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("time", help="seconds per optimiser step")
    t.add_argument("data", type=Path)
    t.add_argument("model", choices=sorted(RECIPES))
    t.add_argument("--steps", type=int, default=30, help="the shorter of the two timed runs")
    t.add_argument("--json", type=Path)
    r = sub.add_parser("train", help="train for --steps, then roll out the test split")
    r.add_argument("data", type=Path)
    r.add_argument("model", choices=sorted(RECIPES))
    r.add_argument("--steps", type=int, required=True)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", type=Path, required=True)
    a = p.parse_args(argv)
    if not (a.data / "metadata.json").is_file():
        p.error(f"{a.data}: no metadata.json; make the dataset first (make_sph.py)")
    if a.command == "time":
        rec = time_steps(a.data, a.model, a.steps)
        if a.json:
            a.json.write_text(json.dumps(rec, indent=1))
    else:
        rec = train(a.data, a.model, a.steps, a.seed, a.out)
    print(json.dumps(rec, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
