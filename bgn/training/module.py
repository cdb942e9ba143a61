"""The LightningModule: wraps any forward model (BGN or a baseline), sums its task losses
(Eq. 12), logs every task on its own, computes the metrics and draws validation figures.

Every model fulfils one contract (``bgn.model.PhysicsModel``): ``forward(g)``, ``loss_terms``,
``total_loss`` (Eq. 12), ``predict(g)`` (physical units), ``heads`` and, with an inverse head,
``sample_mass(g, n)``; the module uses nothing else, but for force matching before the first
step of a pair-force head asked for it (``law_init=match``, ``bgn.model.force_matching``).
Rollouts (the validation figure, animation and ``val/rollout_error``) come in as callables
from the entry point.

The optimiser and its learning-rate schedule are callables handed in by the entry point
(``bgn.train`` instantiates ``conf/optimizer/`` and ``conf/scheduler/``, Hydra partials); without
them the module uses ``DEFAULT_OPTIMIZER`` and ``reduce_on_plateau`` on val/nmse.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from functools import partial
from itertools import islice
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from torch import nn
from torchmetrics import MeanSquaredError, MetricCollection, R2Score
from torchmetrics.aggregation import CatMetric
from torchmetrics.classification import (
    BinaryAUROC,
    BinaryF1Score,
    MulticlassAccuracy,
    MulticlassAUROC,
)

from bgn.graph import Graph
from bgn.model import build_model
from bgn.model.force_matching import MATCHED_LAW_LR, matched_law_parameters, prepare
from bgn.model.soft_contact import SoftContactHead
from bgn.sim import SceneMeta
from bgn.training.budget import Deadline, OutOfTime
from bgn.training.budget import check as budget_check
from bgn.training.checkpoints import CheckpointError, read
from bgn.training.unroll import unrolled_loss

STAGES = ("train", "val", "test")
# the loss terms whose target is a recorded mass besides the inverse model's (``for_scene``)
MASS_TERMS = ("law", "impulse_mass")
MATCH_BATCHES = (30, 10)  # training and validation batches of force matching (law_init=match)
log = logging.getLogger("bgn.train")

# What conf/optimizer/adamw.yaml and conf/scheduler/plateau.yaml give, for a module built
# without them (a notebook, PhysicsModule.load_from_checkpoint).
DEFAULT_OPTIMIZER = partial(torch.optim.AdamW, lr=1e-3, weight_decay=0.0)
DEFAULT_SCHEDULER_CONFIG = {"monitor": "val/nmse", "interval": "epoch", "frequency": 1,
                            "strict": False}


def reduce_on_plateau(optimizer: torch.optim.Optimizer, mode: str = "min", factor: float = 0.5,
                      patience: int = 5, lr_min_ratio: float = 0.01,
                      **kwargs: Any) -> torch.optim.lr_scheduler.ReduceLROnPlateau:
    """``ReduceLROnPlateau`` whose floor follows the optimiser's lr: ``min_lr = lr_min_ratio x``
    each parameter group's lr. On plateaus rather than on a fixed schedule: runs end by a time
    budget (``max_time``), so the number of epochs is not known in advance."""
    min_lr = [group["lr"] * lr_min_ratio for group in optimizer.param_groups]
    return torch.optim.lr_scheduler.ReduceLROnPlateau(optimizer, mode=mode, factor=factor,
                                                      patience=patience, min_lr=min_lr,
                                                      **kwargs)


# Options whose default changed after checkpoints were written without them: a checkpoint
# that lacks one was trained with the value given here (a config composed by Hydra always
# carries every option, so only such checkpoints and hand-made partial configs take these).
CHANGED_DEFAULTS: dict[str, dict[str, Any]] = {"bgn": {"mass_context": "node"}}


def fit_deadline(trainer: Any) -> Deadline | None:
    """The deadline of the trainer's fit: its callback that carries one (``deadline``, as
    ``bgn.training.signals.FitDeadline``), else None."""
    for callback in getattr(trainer, "callbacks", None) or ():
        if isinstance(getattr(callback, "deadline", None), Deadline):
            return callback.deadline
    return None


def for_scene(model_config: Mapping[str, Any], meta: SceneMeta) -> dict[str, Any]:
    """``model_config`` less the heads the scene's files cannot train: where they record no
    masses (imported data, ``meta.masses_known`` false: the files hold ones) every loss term
    whose target is a recorded mass is left out (docs/design.md#the-scene-record): the
    inverse model (``mass_nll``, ``relmass``: on a constant the flow's likelihood grows
    without bound and its relative masses turned NaN), the law loss and the impulse head's
    masses (``law``, ``impulse_mass``: weighted 0). Checkpoints rebuild the same model, as
    the meta they record is the same."""
    config = dict(model_config)
    if getattr(meta, "masses_known", True):
        return config
    if config.get("inverse"):
        config["inverse"] = False
    if "loss_weights" in config:
        config["loss_weights"] = {**dict(config["loss_weights"] or {}),
                                  **{k: 0.0 for k in MASS_TERMS}}
    return config


def with_changed_defaults(model_config: Mapping[str, Any]) -> dict[str, Any]:
    """``model_config`` with the values older checkpoints were trained with where it lacks
    an option whose default has changed since (``CHANGED_DEFAULTS``)."""
    config = dict(model_config)
    return {**CHANGED_DEFAULTS.get(str(config.get("name", "bgn")), {}), **config}


class PhysicsModule(L.LightningModule):
    """Training, validation and test of one model on one scene.

    ``model_config`` names the model (``name``: bgn or a baseline) and its parameters; ``meta``
    is the scene's metadata record as a dict; ``stats`` the training split's statistics (plain
    lists are fine). The target variance of the training split turns the MSE into the
    normalised MSE of Table 1, comparable across frame rates.

    ``optimizer(params)`` builds the optimiser, ``scheduler(optimizer)`` its lr scheduler and
    ``scheduler_config`` says how Lightning steps it (``monitor``, ``interval``, ``frequency``,
    ``strict``); absent, today's defaults (``DEFAULT_OPTIMIZER``, ``reduce_on_plateau``,
    ``DEFAULT_SCHEDULER_CONFIG``). ``provenance`` is kept in the checkpoint only.
    """

    def __init__(self, model_config: dict[str, Any], meta: dict[str, Any],
                 stats: dict[str, dict[str, Any]], history: int,
                 optimizer: Callable[[Iterable[nn.Parameter]], torch.optim.Optimizer]
                 | None = None,
                 scheduler: Callable[[torch.optim.Optimizer], Any] | None = None,
                 scheduler_config: Mapping[str, Any] | None = None, figures: bool = True,
                 rollout: Callable[[nn.Module], dict] | None = None,
                 rollout_error: Callable[[nn.Module], float] | None = None,
                 animation_every: int = 25,
                 provenance: dict[str, Any] | None = None) -> None:
        super().__init__()
        # everything needed to rebuild the model goes into the checkpoint's hyperparameters,
        # so PhysicsModule.load_from_checkpoint(path) alone restores it; the optimiser and
        # scheduler callables are training settings (in the run's .hydra/config.yaml), and
        # hyperparameters of older checkpoints that __init__ no longer takes (lr, ...) are
        # dropped by Lightning when loading. All are plain types (checkpoints are read with
        # weights_only=True). ``provenance``: the run that trained it (scene, scene
        # parameters hash, fps, model, history: bgn.training.checkpoints.provenance), checked
        # when a run resumes.
        self.save_hyperparameters(ignore=["rollout", "rollout_error", "optimizer", "scheduler"])
        self.meta = SceneMeta(**meta)
        stats_arrays = {g: {k: np.asarray(v, dtype=np.float64) for k, v in entries.items()}
                        for g, entries in stats.items()}
        self.model = build_model(for_scene(with_changed_defaults(model_config), self.meta),
                                 self.meta, stats_arrays,
                                 history)
        target_variance = stats_arrays["target"]["std"] ** 2
        self.optimizer_factory = optimizer or DEFAULT_OPTIMIZER
        self.scheduler_factory = scheduler or reduce_on_plateau
        self.scheduler_config = {**DEFAULT_SCHEDULER_CONFIG, **dict(scheduler_config or {})}
        self.figures = figures
        self.rollout = rollout  # draws the validation rollout figure; not part of the state
        self.rollout_error = rollout_error  # val/rollout_error of the model; not in the state
        self.animation_every = animation_every  # validations between rollout animations
        self._validations = 0
        self.register_buffer("target_variance",
                             torch.as_tensor(np.asarray(target_variance), dtype=torch.float32))
        # "train" is taken by nn.Module.train, hence the suffix
        self.metrics = nn.ModuleDict({f"{stage}_": self._stage_metrics() for stage in STAGES})
        self._figure_batch: Graph | None = None
        self.law_match: dict[str, Any] | None = None  # what force matching did (on_train_start)

    # -- metrics --------------------------------------------------------------------------
    def _stage_metrics(self) -> MetricCollection:
        metrics: dict[str, Any] = {"mse": MeanSquaredError(),
                                   "relative_error": CatMetric(nan_strategy="ignore")}
        heads = self.model.heads
        if "type" in heads:
            n = self.meta.n_types
            metrics["type_accuracy"] = MulticlassAccuracy(num_classes=n, average="micro")
            metrics["type_auroc"] = MulticlassAUROC(num_classes=n)
        if "contact" in heads:
            if self.meta.interaction == "contact":
                metrics["contact_f1"] = BinaryF1Score()
                metrics["contact_auroc"] = BinaryAUROC()
            else:
                metrics["contact_r2"] = R2Score()
        if "relmass" in heads and self.meta.masses_known:  # unknown masses: nothing to score
            metrics["relmass_r2"] = R2Score()
        return MetricCollection(metrics)

    def _update_metrics(self, stage: str, g: Graph, out: Any) -> None:
        m = self.metrics[f"{stage}_"]
        pred, target = self.model.denormalize_target(out.target, g), g.target
        if g.kinematic is not None:  # moved by the source: never scored
            pred, target = pred[~g.kinematic], target[~g.kinematic]
        m["mse"].update(pred, target)
        # robust error next to MSE: heavy tails make MSE a few-frame statistic
        # (docs/design.md#one-step)
        m["relative_error"].update((pred - target).norm(dim=-1)
                                   / target.norm(dim=-1).clamp_min(1e-12))
        if "type_accuracy" in m:
            m["type_accuracy"].update(out.type_logits, g.types)
            m["type_auroc"].update(out.type_logits.softmax(-1), g.types)
        if "contact_f1" in m:
            prob = torch.sigmoid(out.contact)
            m["contact_f1"].update(prob, g.edge_contact.long())
            m["contact_auroc"].update(prob, g.edge_contact.long())
        if "contact_r2" in m:
            m["contact_r2"].update(out.contact, self.model.contact_target(g))
        if "relmass_r2" in m:
            m["relmass_r2"].update(self.model.denormalize_relmass(out.relmass),
                                   g.edge_rel_log_mass)

    def _log_metrics(self, stage: str) -> None:
        values = {}
        for name, metric in self.metrics[f"{stage}_"].items():
            if not metric.update_called:
                continue
            value = metric.compute()
            if name == "relative_error":
                value = value.median() if value.numel() else torch.tensor(float("nan"))
                name = "median_relative_error"
            values[f"{stage}/{name}"] = value
            if name == "mse":
                values[f"{stage}/nmse"] = value / self.target_variance.mean()
            metric.reset()
        self.log_dict(values, sync_dist=True)

    # -- steps ----------------------------------------------------------------------------
    def _step(self, stage: str, g: Graph) -> torch.Tensor:
        out = self.model(g)
        terms = self.model.loss_terms(g, out)
        if stage == "train" and g.future_vel is not None:  # dataset.unroll > 0
            terms["unroll"] = unrolled_loss(self.model, g, out)
        loss = self.model.total_loss(terms)
        if not torch.isfinite(loss):
            raise FloatingPointError(
                f"{stage} loss became {loss.item()} at step {self.global_step} "
                f"(terms: { {k: float(v) for k, v in terms.items()} }); lower optimizer.lr or "
                "check the data; the last good checkpoint is in the run's checkpoints/ folder")
        n = g.num_graphs
        self.log(f"{stage}/loss", loss, batch_size=n, prog_bar=stage != "test",
                 on_step=stage == "train", on_epoch=True)
        # No sync_dist on the losses: with it a 2-process CPU DDP run hung at the first epoch
        # end (tests/test_train.py runs DDP). Under DDP these are process 0's means; the
        # torchmetrics (val/nmse, watched by checkpoints and early stopping) are reduced.
        for name, value in terms.items():
            self.log(f"{stage}/loss_{name}", value, batch_size=n, on_step=False, on_epoch=True)
        with torch.no_grad():  # metrics only read the outputs: no autograd graph for them
            self._update_metrics(stage, g, out)
        return loss

    def training_step(self, g: Graph, batch_idx: int) -> torch.Tensor:
        return self._step("train", self.model.corrupt(g))  # rollout noise: training only

    def on_fit_start(self) -> None:
        # before the sanity check's validation steps, which already need the distances
        self._measure_reach()

    def on_train_start(self) -> None:
        self._match_law()

    def _measure_reach(self) -> None:
        """The soft-contact head's contact distances, the closest approaches in the training
        split (``bgn.data.contacts.closest_approach``), when a fit starts and the model has
        none (a resumed or fine-tuned one keeps those its checkpoint holds): used where the
        data give no radii."""
        from bgn.data.contacts import closest_approach, contact_cutoff

        head = getattr(self.model, "force_head", None)
        datamodule = getattr(self.trainer, "datamodule", None)
        if not isinstance(head, SoftContactHead) or head.measured or datamodule is None:
            return
        meta = datamodule.meta
        train = datamodule.datasets["train"].file
        approach = closest_approach(train, meta, contact_cutoff(train))
        radii = (np.asarray(train.read("radii", ...)) if "radii" in train.handle
                 else np.zeros(1))
        head.set_reach(approach.pair, approach.wall, radii_given=bool((radii > 0).all()))
        log.info("soft contacts: closest approaches in the training split, per pair of types "
                 "%s, per type to a wall %s (the contact distances where the data give no "
                 "radii)", *approach.as_dict().values())

    def _match_law(self) -> None:
        """Force matching (``law_init=match``, ``bgn.model.force_matching``) before the first
        step of a fresh run (a resumed one has its law already): the pair law fitted on
        ``MATCH_BATCHES`` training batches, its smoothness chosen on validation ones. Where
        it is not kept, the law trains at the full rate."""
        if self.global_step > 0 or not matched_law_parameters(self.model):
            return
        datamodule = getattr(self.trainer, "datamodule", None)
        result = None
        deadline = fit_deadline(self.trainer)

        def check() -> None:  # the fit's clock and SIGTERM, between force matching's steps
            budget_check(deadline, "force matching (law_init=match)")

        if datamodule is not None:
            def batches(loader: Iterable[Graph], n: int) -> Iterable[Graph]:
                for g in islice(loader, n):
                    check()
                    yield self.transfer_batch_to_device(g, self.device, 0)
            try:
                result = prepare(self.model,
                                 batches(datamodule.train_dataloader(), MATCH_BATCHES[0]),
                                 batches(datamodule.val_dataloader(), MATCH_BATCHES[1]),
                                 check=check)
            except OutOfTime as err:  # the law as initialised; the fit ends at its first step
                log.warning("%s: the law starts as initialised", err)
                self.trainer.should_stop = True
                return
        if result is None or not result.kept:
            optimizer = self.optimizers()
            getattr(optimizer, "optimizer", optimizer).param_groups[-1]["lr"] /= MATCHED_LAW_LR
            scheduler = self.lr_schedulers()
            if isinstance(scheduler, torch.optim.lr_scheduler.ReduceLROnPlateau):
                scheduler.min_lrs[-1] /= MATCHED_LAW_LR
        if result is None:
            log.info("law_init=match: no pairs to fit; the law starts as initialised")
            return
        self.law_match = result.as_dict()
        log.info("law_init=match: the pair law fitted to %d acceleration components of the "
                 "training split (relative squared error %.3g as a table, validation %.3g; "
                 "the MLP fitted to it %.3g on validation, %.3g before): %s", result.rows,
                 result.table_train_error, result.table_val_error, result.val_error,
                 result.val_error_before,
                 "kept" if result.kept else "not kept (no better than the initial law)")

    def on_train_batch_end(self, outputs: Any, batch: Graph, batch_idx: int) -> None:
        """At a step budget's end (``trainer.max_steps``) mid-epoch, stop as a time budget
        does, so the last steps are validated (and can be ``best.ckpt``): Lightning ends a
        step budget without validating the part epoch."""
        max_steps = self.trainer.max_steps
        if max_steps is not None and 0 < max_steps <= self.global_step:
            self.trainer.should_stop = True

    def on_before_optimizer_step(self, optimizer: torch.optim.Optimizer) -> None:
        """A finite loss can still give a non-finite gradient (a 0/0 in a backward): stop
        with one clear error before the optimiser writes it into the weights."""
        grads = [p.grad for p in self.parameters() if p.grad is not None]
        # one fused norm over every gradient: non-finite exactly when one entry is (training step)
        if grads and not torch.isfinite(torch.nn.utils.get_total_norm(grads)):
            bad = [n for n, p in self.named_parameters()
                   if p.grad is not None and not torch.isfinite(p.grad).all()]
            where = (f"in {len(bad)} parameters (first: {bad[0]})" if bad else
                     "in its norm (every entry finite, their norm beyond float range)")
            raise FloatingPointError(
                f"the gradient became non-finite at step {self.global_step} {where}; lower "
                "optimizer.lr or check the data; the last good checkpoint is in the run's "
                "checkpoints/ folder")

    def validation_step(self, g: Graph, batch_idx: int) -> None:
        if batch_idx == 0:
            self._figure_batch = g
        self._step("val", g)

    def test_step(self, g: Graph, batch_idx: int) -> None:
        self._step("test", g)

    def on_train_epoch_end(self) -> None:
        self._log_metrics("train")

    def on_validation_epoch_end(self) -> None:
        self._log_metrics("val")
        if self.rollout_error is not None and not self.trainer.sanity_checking:
            with torch.no_grad():  # every process rolls out the same starts: no reduction
                self.log("val/rollout_error", float(self.rollout_error(self.model)))
        if self.figures and self._figure_batch is not None and not self.trainer.sanity_checking:
            self._log_figures(self._figure_batch)

    def on_test_epoch_end(self) -> None:
        self._log_metrics("test")

    def transfer_batch_to_device(self, batch: Graph, device: torch.device,
                                 dataloader_idx: int) -> Graph:
        return batch.to(device)

    def configure_optimizers(self) -> dict[str, Any]:
        law = matched_law_parameters(self.model)
        if not law:
            optimizer = self.optimizer_factory(self.parameters())
        else:  # a law started from force matching trains slower (MATCHED_LAW_LR)
            ids = {id(p) for p in law}
            optimizer = self.optimizer_factory(
                [{"params": [p for p in self.parameters() if id(p) not in ids]},
                 {"params": law}])
            optimizer.param_groups[1]["lr"] *= MATCHED_LAW_LR
        scheduler = self.scheduler_factory(optimizer)
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": scheduler, **self.scheduler_config}}

    # -- figures --------------------------------------------------------------------------
    def _log_figures(self, g: Graph) -> None:
        experiment = getattr(self.logger, "experiment", None)
        if experiment is None or not hasattr(experiment, "add_figure"):
            return
        from bgn import figures

        with torch.no_grad():
            pred = self.model.predict(g).cpu().numpy()
        step = self.global_step
        experiment.add_figure("val/predicted_vs_true", figures.predicted_vs_true(
            pred, g.target.cpu().numpy(), self.meta.target), step)
        if self.model.has_inverse:
            with torch.no_grad():
                samples = self.model.sample_mass(g, 16).cpu().numpy()
            experiment.add_figure("val/mass_density", figures.mass_density(
                g.mass.cpu().numpy(), samples.ravel()), step)
        law = pair_law_figure(self.model, g)
        if law is not None:
            experiment.add_figure("val/pair_law", law, step)
        if self.rollout is not None:
            result = self.rollout(self.model)
            experiment.add_figure("val/rollout", figures.rollout(result), step)
            if self.animation_every > 0 and self._validations % self.animation_every == 0:
                add_animation(experiment, "val/rollout_animation", result, step)
        self._validations += 1


def pair_law_figure(model: nn.Module, g: Graph) -> Any:
    """The learned pair law of a model's pair-force head over the 1-99 % range of the edge
    lengths of graph ``g`` (per pair of types, at most 3 types), in physical units where
    ``law_scale`` says so; None for a model without that head."""
    from bgn import figures
    from bgn.model.newton import pair_force_head_of

    head = pair_force_head_of(model)
    if head is None:
        return None
    with torch.no_grad():  # the head's own edge lengths (minimum image where periodic)
        _, dist = head.separations(g, g.pos[:, None])
        dist = (dist * head.length_scale).reshape(-1).double().cpu().numpy()
    dist = dist[dist > 0]
    if dist.size == 0:
        return None
    lo, hi = np.quantile(dist, [0.01, 0.99])
    r = np.geomspace(lo, max(hi, lo * 1.01), 64)
    n_types = min(int(head.types), 3)
    pairs = [(a, b) for a in range(n_types) for b in range(a, n_types)] or [(0, 0)]
    laws = {f"types {a}-{b}" if n_types > 1 else "f(r)":
            head.labelled_law_at(r, g.pos.shape[1], (a, b)) for a, b in pairs}
    return figures.pair_law(r, laws, dist)


def add_animation(experiment: Any, tag: str, result: dict[str, np.ndarray], step: int) -> None:
    """A rollout animation as an animated GIF image in TensorBoard (the way torch's
    ``add_video`` stores one, without its moviepy dependency)."""
    import tempfile

    from PIL import Image
    from tensorboard.compat.proto.summary_pb2 import Summary

    from bgn.figures import rollout_animation

    get_writer = getattr(experiment, "_get_file_writer", None)
    writer = get_writer() if callable(get_writer) else None
    if writer is None or not hasattr(writer, "add_summary"):
        return  # not torch's SummaryWriter (fast_dev_run's dummy logger): no animations
    with tempfile.TemporaryDirectory() as tmp:
        path = rollout_animation(result, Path(tmp) / "rollout.gif", max_frames=60, dpi=60)
        data = path.read_bytes()
        width, height = Image.open(path).size
    image = Summary.Image(height=height, width=width, colorspace=4, encoded_image_string=data)
    writer.add_summary(Summary(value=[Summary.Value(tag=tag, image=image)]), step)


def load_model(ckpt: str | Path) -> PhysicsModule:
    """The LightningModule of a checkpoint, on the CPU, in eval mode; read with
    ``weights_only=True``, and an unreadable file is named (``bgn.training.checkpoints.read``)."""
    record = read(ckpt)  # a missing, truncated or foreign file: one CheckpointError naming it
    try:
        module = PhysicsModule.load_from_checkpoint(ckpt, map_location="cpu", weights_only=True)
    except RuntimeError as err:  # torch: "Error(s) in loading state_dict ... key(s) ..."
        if "state_dict" not in str(err):
            raise
        model = ((record.get("hyper_parameters") or {}).get("model_config") or {}).get("name")
        detail = " ".join(str(err).split())[:300]
        raise CheckpointError(
            f"checkpoint {ckpt} does not fit this version of bgn's {model or 'model'}: it was "
            "written by a bgn whose model had other weights (torch says: "
            f"{detail}); retrain it with this version (python -m bgn.train ...)") from None
    return module.eval()
