"""What a run does when it is stopped by a signal or by its wall-clock cap: SIGTERM (a
cluster pre-empting the job, ``kill``) or SIGINT (Ctrl-C) save a checkpoint and end with one
message naming the resume command and a non-zero exit; the job's deadline
(``bgn.training.budget``) stops a fit after the batch in progress (``FitDeadline``).
"""

from __future__ import annotations

import copy
import logging
import math
import shlex
import signal
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback, Timer
from lightning.pytorch.utilities.exceptions import SIGTERMException

from bgn.training.budget import Deadline, check, clock_text

log = logging.getLogger("bgn.train")


class SignalCheckpoint(Callback):
    """On SIGTERM (a cluster pre-empting the job, ``kill``) or SIGINT (Ctrl-C) during
    training: save ``<dirpath>/last.ckpt`` where training stopped, so ``ckpt_path=last``
    continues from there. Lightning turns both signals into an exception in the training
    loop (``SIGTERMException``, ``KeyboardInterrupt``) and calls ``on_exception``.

    A signal during validation is saved as of the end of the last training batch (the
    weights are the same; Lightning cannot resume a validation stopped half-way, so the
    resumed run validates again)."""

    def __init__(self, dirpath: str | Path) -> None:
        self.dirpath = Path(dirpath)
        self.saved: Path | None = None
        self.signal: str | None = None
        self._loop_state: dict[str, Any] | None = None  # fit loop after the last train batch

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        self._loop_state = copy.deepcopy(trainer.fit_loop.state_dict())

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule,
                     exception: BaseException) -> None:
        if isinstance(exception, SIGTERMException):
            self.signal = "SIGTERM"
        elif isinstance(exception, KeyboardInterrupt):
            self.signal = "SIGINT"
        else:
            return
        if trainer.state.fn != "fit" or self._loop_state is None:  # nothing trained yet
            return
        checkpoint = trainer._checkpoint_connector.dump_checkpoint(weights_only=False)
        if trainer.validating:
            checkpoint["loops"]["fit_loop"] = self._loop_state
        self.saved = self.dirpath / "last.ckpt"
        trainer.strategy.save_checkpoint(checkpoint, self.saved)
        trainer.strategy.barrier("SignalCheckpoint")


def resume_command(run_dir: str | Path, overrides: Sequence[str]) -> str:
    """The command that continues the run in ``run_dir``: its own overrides (those naming a
    checkpoint or a run folder left out), then ``ckpt_path=last hydra.run.dir=<run_dir>``."""
    kept = [shlex.quote(o) for o in overrides
            if not o.lstrip("+~").startswith(("ckpt_path=", "hydra.run.dir="))]
    return " ".join(["python -m bgn.train", *kept, "ckpt_path=last",
                     f"hydra.run.dir={shlex.quote(str(run_dir))}"])


def interrupted(name: str, run_dir: str | Path, overrides: Sequence[str], *,
                phase: str = "training", where: str = "", saved: Path | None = None,
                checkpoint_dir: Path | None = None, log_it: bool = True) -> SystemExit:
    """The exit of a job stopped by signal ``name`` (``"SIGTERM"``, ``"SIGINT"``) during
    ``phase``: one message naming what was saved and the command that resumes the run
    (``run_dir`` with the job's ``overrides``: the run itself, also where the job was
    training one of ``model.dynamics=auto``'s candidates), logged once (``log_it``: the
    rank-zero process), and exit code 128 + the signal."""
    where = f" {where}" if where else ""
    if saved:
        kept = f"checkpoint {saved}"
    elif checkpoint_dir is not None and (Path(checkpoint_dir) / "last.ckpt").is_file():
        kept = f"checkpoint {Path(checkpoint_dir) / 'last.ckpt'}"
    else:
        kept = f"the checkpoints in {checkpoint_dir or run_dir}"
    message = (f"{phase} stopped by {name}{where}; no metrics.json written; {kept}; resume "
               f"with: {resume_command(run_dir, overrides)}")
    if log_it:
        log.error(message)  # on the console and in the run's log (stderr outside Hydra)
    code = 128 + (signal.SIGTERM if name == "SIGTERM" else signal.SIGINT)
    return SystemExit(int(code))

class FitDeadline(Callback):
    """A fit's share of the job's deadline (``bgn.training.run.train``): past ``deadline``,
    the fit stops after the batch in progress, as Lightning's ``Timer`` does (its last steps
    are validated, so they can be ``best.ckpt``), and ``cut`` says so. ``job``: the whole
    job's deadline, which the test checks between its batches (``OutOfTime``).

    The sanity check's validation batches are timed: where the fit's time left is below
    what one validation of the whole validation subset would take, one warning says so
    before the first step (the run would end with nothing validated)."""

    def __init__(self, deadline: Deadline, job: Deadline | None = None) -> None:
        self.deadline, self.job = deadline, job
        self.cut = False
        self._sanity_start: float | None = None
        self.validation_s: float | None = None  # the estimate of one whole validation

    def on_sanity_check_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._sanity_start = time.monotonic()

    def on_sanity_check_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self._sanity_start is None:
            return
        ran = sum(n for n in trainer.num_sanity_val_batches if math.isfinite(n))
        total = sum(n for n in trainer.num_val_batches if math.isfinite(n))
        if ran <= 0 or total <= 0:
            return
        self.validation_s = (time.monotonic() - self._sanity_start) / ran * total
        left = self.deadline.left()
        if left is not None and left < self.validation_s:
            log.warning(
                "trainer.max_time leaves this fit %s, less than one validation takes (about "
                "%s): it may end with nothing validated; raise trainer.max_time",
                clock_text(left), clock_text(self.validation_s))

    def on_train_batch_end(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        # every DDP process stops at the same step, as Lightning's Timer does
        passed = trainer.strategy.reduce_boolean_decision(self.deadline.passed(), all=False)
        if passed and not trainer.should_stop:
            trainer.should_stop = True
            self.cut = True

    def on_test_batch_end(self, trainer: L.Trainer, *args: Any, **kwargs: Any) -> None:
        if trainer.world_size == 1:  # one DDP process alone leaving the test would hang it
            check(self.job, "the test")


def timer_ran_out(trainer: L.Trainer) -> bool:
    """Whether Lightning's own ``Timer`` (``trainer.max_time``) ended the fit."""
    for callback in trainer.callbacks:  # type: ignore[attr-defined]
        if isinstance(callback, Timer):
            left = callback.time_remaining()
            return left is not None and left <= 0
    return False
