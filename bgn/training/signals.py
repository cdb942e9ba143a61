"""What a run does when it is stopped by a signal: SIGTERM (a cluster pre-empting the job,
``kill``) or SIGINT (Ctrl-C) save a checkpoint and end with one message and a non-zero exit.
"""

from __future__ import annotations

import copy
import logging
import signal
import sys
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities.exceptions import SIGTERMException

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


def interrupted(stop: SignalCheckpoint, trainer: L.Trainer, output_dir: Path) -> SystemExit:
    """The exit of a run stopped by a signal: one message, exit code 128 + the signal."""
    name = stop.signal or "SIGINT"
    where = f"at epoch {trainer.current_epoch}, step {trainer.global_step}"
    saved = (f"checkpoint {stop.saved}" if stop.saved
             else f"the checkpoints in {stop.dirpath}")
    command = " ".join(a for a in sys.argv[1:]
                       if not a.startswith(("ckpt_path=", "hydra.run.dir=")))
    command = command if sys.argv[0].endswith("train.py") else "<the same overrides>"
    message = (f"training stopped by {name} {where}; no metrics.json written; {saved}; resume "
               f"with: python -m bgn.train {command} ckpt_path=last hydra.run.dir={output_dir}")
    if trainer.is_global_zero:
        log.error(message)  # on the console and in the run's log (stderr outside Hydra)
    code = 128 + (signal.SIGTERM if name == "SIGTERM" else signal.SIGINT)
    return SystemExit(int(code))
