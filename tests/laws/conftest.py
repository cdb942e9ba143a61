"""Shared by the laws' tests: known laws (the n-body laws as bgn.sim writes them, Morse's and
Lennard-Jones' forces), a pair-force head trained on springs, a tiny run and the command."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from bgn.graph import collate
from bgn.laws.options import DEFAULTS, SearchOptions
from bgn.laws.terms import Term
from bgn.training.run import build, train
from tests.conftest import SMALL, compose_config

ROOT = Path(__file__).resolve().parents[2]
SOFTENING = 0.01
R0, RHO = 1.122462048309373, 6.0  # the Morse gas of examples/engines (ASE's MorsePotential)
# known laws: (law, distances, terms, values: amplitudes then constants c); the n-body laws
# as bgn.sim writes them (dphi/ds, s = r + 0.01), Morse's and Lennard-Jones' forces
KNOWN = {
    "spring": (lambda r: 2 * (r + SOFTENING - 1), (0.05, 5),
               [Term("const"), Term("power", 1)], [-1.98, 2.0]),
    "r1": (lambda r: 1 / (r + SOFTENING), (0.05, 5), [Term("shifted", -1)], [1.0, SOFTENING]),
    "r2": (lambda r: 1 / (r + SOFTENING) ** 2, (0.05, 5), [Term("shifted", -2)],
           [1.0, SOFTENING]),
    "morse": (lambda r: 2 * RHO / R0 * (np.exp(-2 * RHO * (r / R0 - 1))
                                        - np.exp(-RHO * (r / R0 - 1))), (0.9, 2.5),
              [Term("exp"), Term("exp")],
              [2 * RHO / R0 * np.exp(2 * RHO), -2 * RHO / R0 * np.exp(RHO), R0 / (2 * RHO),
               R0 / RHO]),
    "lennard_jones": (lambda r: 24 * (2 / r**13 - 1 / r**7), (0.9, 2.5),
                      [Term("power", -13), Term("power", -7)], [48.0, -24.0]),
}



# a far cheaper law search than the default, so that a test reads a law in seconds: sums and
# products of at most TWO terms, forces only (no potentials), few starts
CHEAP_SEARCH = SearchOptions(max_terms=2, potentials=False, beam=1, random_starts=2,
                             random_forms=1, fixed_starts=2, child_starts=1, refine_per_size=4)
CHEAP = dataclasses.replace(DEFAULTS, search=CHEAP_SEARCH)
# ... and one that always chooses a formula (the simplest member: a tolerance of 100 %), so
# that a tiny run's formula stage fine-tunes one whatever its barely trained law looks like
ANY_FORMULA = dataclasses.replace(CHEAP, search=dataclasses.replace(CHEAP_SEARCH, max_terms=1),
                                  tolerance=1.0)

TRAIN_STEPS = 400  # full-batch Adam steps on the small spring data: about 10 s on one core


@pytest.fixture(scope="module")
def trained_spring(tmp_path_factory):
    """model=newton trained on SMALL spring data (its own loss: the mass fit, the scale free),
    seed 0; (module, train dataset)."""
    data_dir = tmp_path_factory.mktemp("laws_data")
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"],
                                   f"paths.data_dir={data_dir}", "model=newton",
                                   "model.hidden=16", "figures=false", "val_rollout_steps=0"])
    torch.manual_seed(0)
    datamodule, module = build(cfg)
    data = datamodule.datasets["train"]
    batch = collate([data[i] for i in range(len(data))])
    model = module.model.train()
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    for _ in range(TRAIN_STEPS):
        opt.zero_grad()
        model.total_loss(model.loss_terms(batch, model(batch))).backward()
        opt.step()
    return module.eval(), data


CLI_ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}


def tiny_run(tmp_path: Path, data_dir: Path, model: str, *extra: str) -> Path:
    """A run dir with a checkpoint of ``model`` (two training batches) and its config."""
    overrides = ["dataset=spring", *SMALL["spring"], f"paths.data_dir={data_dir}",
                 f"paths.output_dir={tmp_path / model}", f"model={model}", "figures=false",
                 "val_rollout_steps=0", "test=false", "trainer.max_epochs=1",
                 "+trainer.limit_train_batches=2", "trainer.limit_val_batches=1",
                 "callbacks.progress_bar=null", *extra]
    cfg = compose_config("train", overrides)
    train(cfg)
    OmegaConf.save(cfg, tmp_path / model / "train_config.yaml")
    return tmp_path / model / "checkpoints" / "last.ckpt"


def laws_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bgn.laws", *args], capture_output=True,
                          text=True, env=CLI_ENV, cwd=ROOT, timeout=300)


def spring_spec(const: float, slope: float) -> str:
    return json.dumps([{"types": [0, 0], "terms": [
        {"kind": "const", "power": 0, "a": const, "c": None},
        {"kind": "power", "power": 1, "a": slope, "c": None}]}])


def zero_crossing(pairs: list[dict]) -> float:
    """Where the spring formula const + slope r crosses zero (the truth: s = 1, r = 0.99);
    the model=newton loss (the window's mass fit) pins the law's shape, not its scale."""
    const, slope = (t["a"] for t in pairs[0]["terms"])
    return -const / slope


def law_auto_overrides(run: Path, data_dir: Path) -> list[str]:
    """A tiny model.law=auto run on spring (one epoch of four batches)."""
    return ["dataset=spring", *SMALL["spring"], f"paths.data_dir={data_dir}",
            f"paths.output_dir={run}", "model=newton", "model.hidden=16",
            "model.law=auto", "figures=false", "val_rollout_steps=0",
            "trainer.max_epochs=1", "+trainer.limit_train_batches=4",
            "trainer.limit_val_batches=1", "+trainer.limit_test_batches=1",
            "callbacks.progress_bar=null"]
