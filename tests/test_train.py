"""The command line: every dataset, model and ablation composes and runs in-process; checkpoints
reload exactly; (slow tier) a multirun sweep ends with a summary table, and DDP runs."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from lightning.pytorch.callbacks import Callback

from bgn.graph import collate
from bgn.training.budget import reset_signals
from bgn.training.checkpoints import CheckpointError
from bgn.training.module import PhysicsModule
from bgn.training.run import build, train
from tests.conftest import NETWORK_LAW, SMALL, compose_config

ROOT = Path(__file__).resolve().parents[1]
ABLATIONS = ["full", "no_classifier", "no_contact", "no_inverse", "unsupervised"]
SMALL_MODELS = {  # test-sized versions of every model
    "bgn": ["model.hidden=16", "model.decoder_hidden=16", "model.flow_hidden=16"],
    "cranmer_gn": ["model.hidden=16", "model.message_dim=8", "model.hidden_layers=1"],
    "gns": ["model.latent=16", "model.mlp_hidden=16", "model.mlp_layers=1",
            "model.message_passing_steps=2"],
    "newton": ["model.hidden=16"],
}
# the baselines given radii and types (conf/model/<name>_given.yaml), at the same sizes
SMALL_MODELS.update({f"{name}_given": SMALL_MODELS[name] for name in ("cranmer_gn", "gns")})


class SendSignal(Callback):
    """Test helper: the process sends itself ``signal`` (a name) once training reaches
    ``step``, at the end of a training batch (``at=train``) or of a validation batch."""

    def __init__(self, signal: str = "SIGTERM", step: int = 3, at: str = "train") -> None:
        self.signal, self.step, self.at = getattr(__import__("signal"), signal), step, at

    def _maybe(self, trainer, at: str) -> None:
        if at == self.at and trainer.global_step >= self.step and not trainer.sanity_checking:
            os.kill(os.getpid(), self.signal)

    def on_train_batch_end(self, trainer, *args, **kwargs) -> None:
        self._maybe(trainer, "train")

    def on_validation_batch_end(self, trainer, *args, **kwargs) -> None:
        self._maybe(trainer, "validation")


def command_line(*overrides: str) -> list[str]:
    return [sys.executable, "-m", "bgn.train", *overrides]


CLI_ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
TINY_CLI = ["dataset=spring", *SMALL["spring"], "model.hidden=16", "model.decoder_hidden=16",
            "model.flow_hidden=16", "figures=false", "val_rollout_steps=0",
            "callbacks.progress_bar=null", "dataset.batch_size=16"]


@pytest.fixture
def tiny_train_cfg(tmp_path: Path, shared_data_dir: Path):
    """``tiny_train_cfg(scene, *overrides, model="bgn")``: a small real train config; the run
    writes to tmp_path/run, datasets are shared by the whole session."""

    def make(scene: str, *overrides: str, model: str = "bgn"):
        return compose_config("train", [
            f"dataset={scene}", *SMALL[scene], f"paths.data_dir={shared_data_dir}",
            f"paths.output_dir={tmp_path / 'run'}", f"model={model}", *SMALL_MODELS[model],
            # the network law where the scene's BGN default reads it back as a formula (a stage
            # train() runs only when handed it, as bgn.train does)
            *([NETWORK_LAW] if model == "bgn" and scene in ("spring", "gravity_r1") else []),
            "rollout_steps=3", "val_rollout_steps=5", *overrides])

    return make


@pytest.mark.parametrize("scene", ["spring", "gravity_r1", "gravity_r2", "collisions"])
def test_every_dataset_runs_fast_dev_run(tiny_train_cfg, tmp_path, scene):
    cfg = tiny_train_cfg(scene, "+trainer.fast_dev_run=true")
    metrics = train(cfg)
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["dataset"] == scene


@pytest.mark.parametrize("model", ["cranmer_gn", "gns", "newton"])  # bgn: every dataset
def test_every_model_runs_fast_dev_run(tiny_train_cfg, tmp_path, model):
    metrics = train(tiny_train_cfg("spring", "+trainer.fast_dev_run=true", model=model))
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["model"] == model


@pytest.mark.parametrize("model", ["cranmer_gn_given", "gns_given"])
def test_baselines_given_radii_and_types_run_fast_dev_run(tiny_train_cfg, tmp_path, model):
    """model=<baseline>_given on collisions: trains, and its record says what it is given."""
    metrics = train(tiny_train_cfg("collisions", "+trainer.fast_dev_run=true", model=model))
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["model"] == model.removesuffix("_given")
    assert record["variant"]["given"] == ["radii", "types"]
    assert record["variant"]["label"].endswith(" + radii/types")


def test_a_step_budget_ending_mid_epoch_validates_its_last_steps(tiny_train_cfg, tmp_path):
    """trainer.max_steps inside the first epoch: the run stops as a time budget does, so
    its last steps are validated and checkpointed (Lightning alone would end with no
    validation, so no best.ckpt)."""
    train(tiny_train_cfg("spring", "trainer.max_steps=3", "trainer.max_time=null",
                         "dataset.batch_size=2",  # an epoch of many more than 3 batches
                         "+trainer.num_sanity_val_steps=0", "trainer.limit_val_batches=1",
                         "test=false"))
    best = torch.load(tmp_path / "run" / "checkpoints" / "best.ckpt", map_location="cpu",
                      weights_only=False)
    assert best["global_step"] == 3 and best["epoch"] == 0  # mid-epoch: epoch 0 unfinished


@pytest.mark.parametrize("scene", ["gravity_r2", "collisions"])  # spring: its default
def test_bgn_with_the_structured_dynamics_head_trains(tiny_train_cfg, tmp_path, scene):
    metrics = train(tiny_train_cfg(scene, "model.dynamics=newton", "+trainer.fast_dev_run=true"))
    assert torch.isfinite(torch.tensor(metrics["train/loss"]))


@pytest.mark.parametrize("scene", ["spring", "collisions"])
def test_training_for_rollouts_logs_the_unrolled_loss(tiny_train_cfg, tmp_path, scene):
    metrics = train(tiny_train_cfg(scene, "dataset.unroll=2", "model.rollout_noise=0.01",
                                   "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
                                   "trainer.limit_val_batches=1", "test=false"))
    assert torch.isfinite(torch.tensor(metrics["train/loss_unroll"]))
    assert "val/loss_unroll" not in metrics  # validation scores the one-step loss only


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


def test_the_dashboard_shows_the_learned_law_and_the_rollout(tiny_train_cfg, tmp_path):
    """At validation: the pair law of the pair-force head (spring's BGN), the rollout beside
    the truth and its animation, as images in TensorBoard."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train(tiny_train_cfg("spring", "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
                         "trainer.limit_val_batches=1", "test=false", "figures=true",
                         "animation_every=1", "rollout_steps=5"))
    events = EventAccumulator(str(tmp_path / "run" / "tensorboard")).Reload()
    tags = set(events.Tags()["images"])
    assert {"val/pair_law", "val/rollout", "val/rollout_animation"} <= tags, tags


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


def test_a_gradient_whose_norm_overflows_is_named_so():
    """Every entry finite and their norm beyond float range (an exp that grew): the error
    says so, where it once failed on naming the first non-finite entry, which there is not."""
    layer = torch.nn.Linear(2, 2)
    for p in layer.parameters():
        p.grad = torch.full_like(p, 3e38)
    stand_in = SimpleNamespace(parameters=layer.parameters,
                               named_parameters=layer.named_parameters, global_step=7)
    with pytest.raises(FloatingPointError, match="at step 7 in its norm"):
        PhysicsModule.on_before_optimizer_step(stand_in, None)


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


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (CI has none)")
@pytest.mark.parametrize("scene", ["spring", "gravity_r2", "collisions"])
def test_trainer_gpu_trains_and_evaluates_end_to_end(tiny_train_cfg, tmp_path, scene):
    """trainer=gpu: training, validation rollouts, figures and the test evaluation of the best
    checkpoint (rollouts included) all run with the model on the GPU; gravity_r2's default
    formula stage (model.law=auto) too, handed in as the command line does."""
    from bgn.laws.stage import law_stage

    metrics = train(tiny_train_cfg(scene, "trainer=gpu", "trainer.max_epochs=1",
                                   "+trainer.limit_train_batches=3",
                                   "trainer.limit_val_batches=2", "figures=true"),
                    law_stage=law_stage)
    assert np.isfinite(metrics["train/loss"]) and np.isfinite(metrics["val/rollout_error"])
    record = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert record["dataset"] == scene and np.isfinite(record["metrics"]["test/nmse"])


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
    # both processes share the pipe: only process 0 prints the closing summary
    assert sum("one-step test NMSE" in line for line in result.stdout.splitlines()) == 1


# ----------------------------------------------------------------------------- checkpoints
def test_a_checkpoint_of_another_scene_or_model_is_refused_in_one_line(tiny_train_cfg,
                                                                       tmp_path):
    """A spring checkpoint with dataset=gravity_r1 (once silently tested on gravity data), or
    with another model or model size: one line saying what differs, before any data is made."""
    train(tiny_train_cfg("spring", "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
                         "trainer.limit_val_batches=1", "test=false", "figures=false"))
    ckpt = tmp_path / "run" / "checkpoints" / "last.ckpt"
    saved = torch.load(ckpt, map_location="cpu", weights_only=True)  # plain types only
    assert saved["hyper_parameters"]["provenance"]["scene"] == "spring"
    # (the spring and gravity defaults of the model differ as well: the message lists them)
    cases = {("dataset=gravity_r1",): ("scene=spring", "this run has scene=gravity_r1"),
             ("fps=10",): "fps=50 but this run has fps=10",
             ("dataset.n_particles=5",): "scene_params=",
             ("model.hidden=32",): "model.hidden=16 but this run has model.hidden=32"}
    for overrides, expected in cases.items():
        scene = overrides[0].split("=")[1] if overrides[0].startswith("dataset=") else "spring"
        cfg = tiny_train_cfg(scene, *overrides[1:] if scene != "spring" else overrides,
                             f"ckpt_path={ckpt}", f"paths.output_dir={tmp_path / 'other'}",
                             f"paths.data_dir={tmp_path / 'no_data'}")
        with pytest.raises(CheckpointError) as err:
            train(cfg)
        message = str(err.value)
        parts = expected if isinstance(expected, tuple) else (expected,)
        assert all(p in message for p in parts), message
        assert str(ckpt) in message and "\n" not in message, message
        assert not (tmp_path / "no_data").exists()  # refused before generating anything
    # a collisions checkpoint (other heads and sizes) with dataset=spring
    forged = dict(saved, hyper_parameters={**saved["hyper_parameters"], "provenance": {
        **saved["hyper_parameters"]["provenance"], "scene": "collisions"}})
    torch.save(forged, tmp_path / "collisions.ckpt")
    with pytest.raises(CheckpointError, match="scene=collisions but this run has scene=spring"):
        train(tiny_train_cfg("spring", f"ckpt_path={tmp_path / 'collisions.ckpt'}"))


def test_a_truncated_checkpoint_is_named_in_one_line(tmp_path, shared_data_dir):
    """From the command line: exit 1, one line naming the file, no traceback."""
    bad = tmp_path / "cut.ckpt"
    bad.write_bytes(b"PK\x03\x04" + bytes(5000))  # the head of a zip, cut short
    result = subprocess.run(
        command_line(*TINY_CLI, f"paths.data_dir={shared_data_dir}", f"ckpt_path={bad}",
                     f"hydra.run.dir={tmp_path / 'run'}"),
        cwd=tmp_path, env=CLI_ENV, capture_output=True, text=True, timeout=300)
    assert result.returncode == 1, result.stderr[-2000:]
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith(f"bgn.train: checkpoint {bad} cannot be read: it is truncated")
    assert "Traceback" not in result.stderr


@pytest.fixture
def interactive_sigint():
    """A shell starts background jobs with SIGINT ignored, and CI may run the tests so; Python
    then never raises KeyboardInterrupt. Give the test the handler an interactive run has;
    after it, no SIGTERM recorded (bgn.training.budget) and the SIGTERM handler as before."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    before_term = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGINT, before)
    signal.signal(signal.SIGTERM, before_term)
    reset_signals()


@pytest.mark.parametrize(("name", "at", "code"), [("SIGTERM", "validation", 143),
                                                  ("SIGINT", "train", 130)])
def test_a_signal_saves_last_ckpt_and_exits_non_zero(tiny_train_cfg, tmp_path, caplog, name,
                                                     at, code, interactive_sigint):
    """SIGTERM (also during validation) and SIGINT: last.ckpt where training stopped, no
    metrics.json, exit 128 + signal with a message; ckpt_path=last then finishes the run."""
    common = ["trainer.max_epochs=3", "test=false", "figures=false", "trainer.max_time=null",
              "dataset.batch_size=16"]
    kill = [f"+callbacks.kill._target_={__name__}.SendSignal", f"+callbacks.kill.signal={name}",
            "+callbacks.kill.step=9", f"+callbacks.kill.at={at}"]
    with pytest.raises(SystemExit) as stop, caplog.at_level("ERROR"):
        train(tiny_train_cfg("spring", *common, *kill))
    assert stop.value.code == code
    assert f"training stopped by {name}" in caplog.text and "ckpt_path=last" in caplog.text
    run = tmp_path / "run"
    assert not (run / "metrics.json").exists()
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["global_step"] >= 9
    reset_signals()  # a new job in this process (the command exited above)
    train(tiny_train_cfg("spring", *common, "ckpt_path=last"))  # continues and ends
    final = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert final["global_step"] > last["global_step"] and final["epoch"] == 3  # all 3 done
    assert (run / "metrics.json").exists()


@pytest.mark.slow  # a real training process killed by SIGTERM
def test_sigterm_to_a_training_process_saves_a_checkpoint_and_exits_non_zero(tmp_path,
                                                                            shared_data_dir):
    """SIGTERM in the middle of a long fit: the process exits within seconds, with last.ckpt
    and one message whose resume command is the run's own (its overrides, its folder)."""
    run = tmp_path / "run"
    overrides = [*TINY_CLI, f"paths.data_dir={shared_data_dir}", "trainer.max_epochs=10000",
                 "trainer.max_steps=-1", "trainer.max_time=null", "seed=7"]
    proc = subprocess.Popen(command_line(*overrides, f"hydra.run.dir={run}"),
                            cwd=tmp_path, env=CLI_ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not (run / "checkpoints" / "last.ckpt").exists() and time.monotonic() < deadline:
        time.sleep(0.5)  # training has run an epoch
    time.sleep(1.0)
    sent = time.time()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-3000:]
    # acted on within seconds: the message's own time stamp (Hydra's log format); the
    # interpreter's exit after it (unloading torch and Lightning) is not the job's doing
    stamp = re.search(r"\[([\d-]+ [\d:]+),(\d+)\]\[bgn\.train\]\[ERROR\] - training stopped by "
                      r"SIGTERM", out + err)
    assert stamp, err[-3000:]
    said = datetime.strptime(stamp[1], "%Y-%m-%d %H:%M:%S").timestamp() + int(stamp[2]) / 1e3
    assert said - sent < 5.0, f"{said - sent:.1f} s from SIGTERM to its message"
    assert f"python -m bgn.train {' '.join(overrides)} ckpt_path=last hydra.run.dir={run}" \
        in out + err
    assert not (run / "metrics.json").exists()
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=True)
    assert last["global_step"] > 0


@pytest.mark.slow  # three training processes, one killed with SIGKILL
def test_kill_9_mid_epoch_then_resume_ends_like_an_uninterrupted_run(tmp_path,
                                                                     shared_data_dir):
    """A time-based last.ckpt (here every ~10 ms: every batch) survives kill -9 mid-epoch;
    rerunning the command with ckpt_path=last in the same run directory ends at the same
    step with the same metrics, within tolerance (the interrupted epoch's remaining batches
    come in a new order)."""
    # (the network law: the formula stage after training is not what resuming is about)
    common = [*TINY_CLI, NETWORK_LAW, f"paths.data_dir={shared_data_dir}",
              "trainer.max_steps=40", "trainer.max_time=null", "seed=3",
              "callbacks.time_checkpoint.train_time_interval.minutes=0.0002"]

    def train_run(run: Path, *extra: str) -> subprocess.CompletedProcess:
        return subprocess.run(command_line(*common, f"hydra.run.dir={run}", *extra),
                              cwd=tmp_path, env=CLI_ENV, capture_output=True, text=True,
                              timeout=600)

    whole, killed = tmp_path / "whole", tmp_path / "killed"
    assert train_run(whole).returncode == 0
    result = train_run(killed, f"+callbacks.kill._target_={__name__}.SendSignal",
                       "+callbacks.kill.signal=SIGKILL", "+callbacks.kill.step=23")
    assert result.returncode == -signal.SIGKILL
    assert not (killed / "metrics.json").exists()
    saved = torch.load(killed / "checkpoints" / "last.ckpt", map_location="cpu",
                       weights_only=True)
    batches_per_epoch = saved["global_step"] // max(saved["epoch"], 1)
    assert 15 <= saved["global_step"] <= 23 and saved["global_step"] % batches_per_epoch
    result = train_run(killed, "ckpt_path=last")
    assert result.returncode == 0, result.stderr[-3000:]
    # Lightning's records go through the command's one log handler (bgn.training.validate)
    assert "Restored all states from the checkpoint" in result.stdout + result.stderr
    a = json.loads((whole / "metrics.json").read_text())["metrics"]
    b = json.loads((killed / "metrics.json").read_text())["metrics"]
    for run in (whole, killed):
        end = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu",
                         weights_only=True)
        assert end["global_step"] == 40
    # The resumed epoch's remaining batches come in a new order, and a 40-step model's error
    # depends on that order: with spring's structured head the two ended 13 % apart (0.0845
    # and 0.0952). Equal to within 25 %; a bit-exact resume needs the sampler's state.
    for key in ("val/nmse", "test/nmse"):
        assert b[key] == pytest.approx(a[key], rel=0.25), key
