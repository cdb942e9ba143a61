"""The command line: every dataset, model and ablation composes and runs in-process; checkpoints
reload exactly; (slow tier) a multirun sweep ends with a summary table, and DDP runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from bgn.graph import collate
from bgn.module import PhysicsModule
from bgn.train import build, train
from tests.conftest import SMALL, compose_config

ROOT = Path(__file__).resolve().parents[1]
ABLATIONS = ["full", "no_classifier", "no_contact", "no_inverse"]
SMALL_MODELS = {  # test-sized versions of every model
    "bgn": ["model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16"],
    "cranmer_gn": ["model.hidden=16", "model.message_dim=8", "model.hidden_layers=1"],
    "gns": ["model.latent=16", "model.mlp_hidden=16", "model.mlp_layers=1",
            "model.message_passing_steps=2"],
}


@pytest.fixture
def tiny_train_cfg(tmp_path: Path, shared_data_dir: Path):
    """``tiny_train_cfg(scene, *overrides, model="bgn")``: a small real train config; the run
    writes to tmp_path/run, datasets are shared by the whole session."""

    def make(scene: str, *overrides: str, model: str = "bgn"):
        return compose_config("train", [
            f"dataset={scene}", *SMALL[scene], f"paths.data_dir={shared_data_dir}",
            f"paths.output_dir={tmp_path / 'run'}", f"model={model}", *SMALL_MODELS[model],
            "rollout_steps=3", "val_rollout_steps=5", *overrides])

    return make


@pytest.mark.parametrize("scene", ["spring", "gravity_r1", "gravity_r2", "collisions"])
def test_every_dataset_runs_fast_dev_run(tiny_train_cfg, tmp_path, scene):
    cfg = tiny_train_cfg(scene, "+trainer.fast_dev_run=true")
    metrics = train(cfg)
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["dataset"] == scene


@pytest.mark.parametrize("model", ["cranmer_gn", "gns"])  # bgn: every dataset, above
def test_every_model_runs_fast_dev_run(tiny_train_cfg, tmp_path, model):
    metrics = train(tiny_train_cfg("spring", "+trainer.fast_dev_run=true", model=model))
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["model"] == model


@pytest.mark.parametrize("ablation", [*ABLATIONS, "dense_contact"])
def test_every_ablation_runs_fast_dev_run(tiny_train_cfg, tmp_path, ablation):
    metrics = train(tiny_train_cfg("spring", f"ablation={ablation}",
                                   "+trainer.fast_dev_run=true"))
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))


def test_dense_contact_is_refused_for_radius_graphs(tiny_train_cfg, tmp_path):
    with pytest.raises(ValueError, match="dense"):
        build(tiny_train_cfg("collisions", "ablation=dense_contact"))


def test_each_task_is_logged_on_its_own(tiny_train_cfg, tmp_path):
    metrics = train(tiny_train_cfg("collisions", "trainer.max_epochs=1",
                                   "+trainer.limit_train_batches=2", "trainer.limit_val_batches=2",
                                   "test=false"))
    for task in ("dynamics", "contact", "type", "mass_nll", "relmass"):
        assert f"train/loss_{task}" in metrics and f"val/loss_{task}" in metrics
    for name in ("val/nmse", "val/type_accuracy", "val/type_auroc", "val/contact_f1",
                 "val/contact_auroc", "val/relmass_r2", "val/median_relative_error",
                 "val/rollout_error"):
        assert name in metrics, name
    events = list((tmp_path / "run" / "tensorboard").glob("events.out.tfevents.*"))
    assert events


def test_rollout_error_can_pick_checkpoints_and_stop_training(tiny_train_cfg, tmp_path):
    """val/rollout_error is logged every validation, finite even when a rollout fails, and
    usable as the checkpoint and early-stopping monitor."""
    metrics = train(tiny_train_cfg(
        "spring", "trainer.max_epochs=2", "+trainer.limit_train_batches=2",
        "trainer.limit_val_batches=2", "test=false", "figures=false",
        "callbacks.model_checkpoint.monitor=val/rollout_error",
        "callbacks.early_stopping.monitor=val/rollout_error"))
    assert np.isfinite(metrics["val/rollout_error"]) and metrics["val/rollout_error"] > 0
    best = torch.load(tmp_path / "run" / "checkpoints" / "best.ckpt", map_location="cpu",
                      weights_only=True)
    callback = next(v for k, v in best["callbacks"].items() if "ModelCheckpoint" in k)
    assert callback["monitor"] == "val/rollout_error"
    assert np.isfinite(float(callback["best_model_score"]))


def test_non_finite_gradient_stops_training_and_keeps_good_checkpoints(tiny_train_cfg,
                                                                       tmp_path, monkeypatch):
    """A finite loss whose gradient is NaN (from step 3 on) stops training with one clear
    error before the weights change; the checkpoints written before it stay finite."""
    real = PhysicsModule.training_step

    def poisoned(self, g, batch_idx):
        loss = real(self, g, batch_idx)
        if self.global_step >= 3:
            loss.register_hook(lambda grad: grad * float("nan"))
        return loss

    monkeypatch.setattr(PhysicsModule, "training_step", poisoned)
    with pytest.raises(FloatingPointError, match="gradient became non-finite at step 3"):
        train(tiny_train_cfg("spring", "trainer.max_epochs=3", "+trainer.limit_train_batches=2",
                             "trainer.limit_val_batches=1", "test=false", "figures=false",
                             "val_rollout_steps=0"))
    for name in ("last.ckpt", "on_exception.ckpt"):
        state = torch.load(tmp_path / "run" / "checkpoints" / name, map_location="cpu",
                           weights_only=True)["state_dict"]
        assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())


def test_checkpoint_reload_reproduces_predictions(tiny_train_cfg, tmp_path):
    cfg = tiny_train_cfg("spring", "trainer.max_epochs=1",
                         "+trainer.limit_train_batches=3", "trainer.limit_val_batches=2",
                         "test=false", "figures=false")
    train(cfg)
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert ckpt.exists()
    datamodule, _ = build(cfg)
    batch = collate([datamodule.datasets["test"][i] for i in range(5)])
    loaded = PhysicsModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    again = PhysicsModule.load_from_checkpoint(ckpt, map_location="cpu").eval()
    state = torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]
    for name, value in loaded.state_dict().items():
        assert torch.equal(value, state[name]), name
    with torch.no_grad():
        assert torch.equal(loaded.model.predict(batch), again.model.predict(batch))


@pytest.mark.slow  # a Hydra multirun in a subprocess: two trainings
def test_multirun_sweep_writes_summary(tmp_path, shared_data_dir):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "bgn.train", "-m", "dataset=spring", "fps=10,50",
           *SMALL["spring"], f"paths.data_dir={shared_data_dir}",
           f"hydra.sweep.dir={tmp_path / 'sweep'}", "trainer.max_epochs=1",
           "+trainer.limit_train_batches=2", "trainer.limit_val_batches=2", "model.hidden=16",
           "figures=false"]
    result = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    summary = (tmp_path / "sweep" / "summary.md").read_text()
    assert summary.count("\n") == 2 + 2  # header, rule, one row per combination
    runs = sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert len(runs) == 2 and all((tmp_path / "sweep" / r / "tensorboard").exists()
                                  for r in runs)


@pytest.mark.slow  # two DDP processes started from the command line
def test_ddp_on_two_cpu_processes_splits_the_epoch_and_writes_one_record(tmp_path,
                                                                         shared_data_dir):
    """trainer=ddp through the real command line (Lightning relaunches the Hydra command for
    rank 1): each process takes half of the epoch's batches, rank 0 alone writes the record."""
    common = ["dataset=spring", *SMALL["spring"], f"paths.data_dir={shared_data_dir}",
              "model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16",
              "figures=false", "trainer.max_epochs=1", "dataset.batch_size=8"]
    datamodule, _ = build(compose_config("train", common))
    single_process_steps = len(datamodule.train_dataloader())
    run = tmp_path / "ddp"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "bgn.train", *common, "trainer=ddp", "trainer.accelerator=cpu",
           "trainer.devices=2", f"hydra.run.dir={run}"]
    result = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    record = json.loads((run / "metrics.json").read_text())
    assert record["dataset"] == "spring" and "test/nmse" in record["metrics"]
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["global_step"] == -(-single_process_steps // 2)  # ceil: DistributedSampler pads
    assert (run / ".hydra" / "config.yaml").exists()
    # both processes share the pipe: only process 0 prints the final summary
    assert sum(line.startswith(' "test/nmse":') for line in result.stdout.splitlines()) == 1
