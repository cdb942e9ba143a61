"""Hydra's ConfigStore entries: the typed schemas of every config group a user sets.

- ``model/<name>_base``: each model's config dataclass (``cls.config_class`` of every model in
  ``bgn.model.registry.MODELS``), the one source of the model defaults; ``conf/model/<name>.yaml``
  only names its base (``defaults: [<name>_base, _self_]``) and the model.
- ``dataset/<scene>_base``: the scene's own parameters (the fields of its ``bgn.sim`` class, so
  the scene dataclass stays their one source), the sizes and seed (``DatasetNode``) and the
  loader keys; ``conf/dataset/<scene>.yaml`` builds on it.
- ``dataset/imported_base``: ``dataset=imported`` (the import's name and the loader keys).
- ``train_base``, ``generate_base`` and ``import_base``: the top-level keys of
  ``conf/train.yaml``, ``conf/generate.yaml`` and ``conf/import.yaml`` (fps, seed, ...); the
  config groups are untyped slots there.

A composed node is then typed: ``model.hidden=abc`` or ``fps=abc`` is refused at composition
and a typo (``model.hiden=3``) is an error. Ranges and cross-checks (``fps > 0``, enough
frames for the window, ...) are ``bgn.training.validate``'s.

Call ``register_configs()`` before composing a config (``bgn.train`` and
``bgn.train.generate`` do it at import, the tests in ``compose_config``); calling it again does
nothing.
"""

from __future__ import annotations

import typing
from dataclasses import MISSING, dataclass, field, fields, make_dataclass
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING as REQUIRED  # "???": a value the config must set (after defaults)

from bgn.data.spec import LoaderOptions
from bgn.sim import SCENES
from bgn.sim.collisions import ParticleType

_registered: set[str] = set()  # the parts stored so far


def model_schema(model: type) -> type:
    """The model's config dataclass plus its ``name`` (the registry key), for Hydra."""
    cfg = model.config_class
    return make_dataclass(f"{cfg.__name__}Node", [("name", str, field(default=model.name))],
                          bases=(cfg,))


# ----------------------------------------------------------------------------- dataset
# A collisions particle type in config: ``ParticleType``'s fields, not frozen (a frozen
# dataclass would make the config node read-only)
ParticleTypeNode = make_dataclass(
    "ParticleTypeNode", [(f.name, float, field(default=f.default)) for f in fields(ParticleType)])


@dataclass
class LoaderNode(LoaderOptions):
    """How a dataset is loaded (``bgn.data.spec.LOADER_KEYS``: not part of the cache key): the
    keys and defaults of ``bgn.data.spec.LoaderOptions``, their one home."""


@dataclass
class DatasetNode(LoaderNode):
    """Keys of every generated ``dataset`` node besides the scene's own parameters."""

    scene: str = REQUIRED
    # sizes and seed (keyed into the cache file name with the scene parameters)
    n_sims: int = 10                  # simulations per split (train, val, test)
    n_frames: int = 1000              # frames per simulation (>= history + 3)
    seed: int = 0
    generate_workers: int | None = None  # simulation processes (null: one per core)


@dataclass
class ImportedDatasetNode(LoaderNode):
    """``dataset=imported``: trajectories written by ``python -m bgn.data.import``; sizes,
    frame rate and scene come from the files (``bgn.data.importing``)."""

    scene: str = "imported"
    name: str = REQUIRED              # the name given at import: <data_dir>/imported/<name>/


def _config_type(tp: Any) -> Any:
    """A scene field's annotation as OmegaConf accepts it (``tuple`` of types -> a list)."""
    if tp is tuple:
        return list[ParticleTypeNode]
    return tp


def _config_default(value: Any) -> Any:
    if isinstance(value, tuple) and value and isinstance(value[0], ParticleType):
        nodes = [ParticleTypeNode(**{f.name: getattr(t, f.name) for f in fields(t)})
                 for t in value]
        return field(default_factory=lambda: list(nodes))
    return field(default=value)


def dataset_schema(scene: str) -> type:
    """``DatasetNode`` plus the parameters of scene ``scene`` (its class's fields, less those
    fixed by the scene's name), with the class's defaults."""
    cls, fixed = SCENES[scene]
    hints = typing.get_type_hints(cls)
    own = [(f.name, _config_type(hints[f.name]), _config_default(f.default))
           for f in fields(cls) if f.name not in fixed]
    name = "".join(part.title() for part in scene.split("_")) + "DatasetNode"
    return make_dataclass(name, own, bases=(DatasetNode,))


# ----------------------------------------------------------------------------- top level
@dataclass
class AutoKeys:
    """``auto``: how ``model.dynamics=auto`` (``bgn.studies.auto``) spends the budget and scores."""

    share: float = 0.5                # of the step budget, split evenly among the candidates
    min_steps: int = 100              # fewer steps: "not trained", never scored or chosen
    horizon: int = 50                 # rollout steps the choice is made at (capped by the files)
    val_sims: int | None = None       # validation simulations rolled out (null: all)
    val_rollouts: int = 100           # ... from as many start frames each as give this many
    references: list[str] = field(default_factory=lambda: ["gns", "cranmer_gn"])  # not chosen


@dataclass
class TrainKeys:
    """Top-level keys of ``conf/train.yaml`` (``TrainNode`` adds its groups' slots)."""

    task_name: str = "train"
    fps: float = 50.0                 # frames per unit of simulated time (> 0)
    seed: int = 0                     # training seed (the data seed is dataset.seed)
    # torch's CPU threads (null: torch's default, one per core). One: on small batches a second
    # thread gains little on an idle machine and, spin-waiting, costs many times that on a
    # busy one; and the same count everywhere keeps the model the same (docs/design.md#budgets)
    threads: int | None = 1
    figures: bool = True
    rollout_steps: int = 50           # validation rollout figure length (>= 0)
    animation_every: int = 25         # validations between TensorBoard animations (0: off)
    val_rollout_steps: int = 50       # val/rollout_error rollout length (0: off)
    val_rollout_sims: int = 2
    test: bool = True
    test_rollouts: bool = True        # the test phase's rollouts (bgn.rollout.test_rollouts)
    ckpt_path: str | None = None      # resume from this checkpoint
    auto: AutoKeys = field(default_factory=AutoKeys)  # model.dynamics=auto (bgn.studies.auto)


@dataclass
class GenerateKeys:
    """Top-level keys of ``conf/generate.yaml``."""

    fps: float = 50.0
    workers: int | None = None        # simulation processes (null: one per core)


@dataclass
class ImportKeys:
    """Top-level keys of ``conf/import.yaml`` (``python -m bgn.data.import``)."""

    path: str = MISSING               # the file or directory to import
    name: str = MISSING               # the dataset's name: dataset=imported dataset.name=<name>
    format: str | None = None         # null: detected from the files (bgn.data.formats)
    split_seed: int = 0               # splits by trajectory where the source has none
    overwrite: bool = False           # replace an earlier import of the same name
    history: int = 5                  # the window the import checks every trajectory holds
    target: str = "acceleration"      # velocity: contact data (a next-velocity target)
    # radius of each particle type ([type 0's, type 1's, ...]) for sources that record types
    # but no radii (the GNS layout): the discs' contact metrics need them
    radii_by_type: list[float] | None = None
    # unpickle GNS .npz files of pickled objects (unpickling can run code: trusted files only)
    allow_pickle: bool = False
    paths: Any = None


@dataclass
class EvaluateRolloutKeys:
    """``rollout`` of ``conf/evaluate.yaml``: from frame 100 of every simulation of the split."""

    steps: int = 100                  # rollout length (capped by the files' length)
    starts_per_sim: int = 1           # start frames per simulation (frame 100 first)
    max_sims: int | None = None       # simulations rolled out (null: every one of the split)
    sinkhorn_stride: int = 10         # LagrangeBench's Sinkhorn on every n-th step ...
    sinkhorn_rollouts: int | None = 4  # ... of this many rollouts (null: all; it is the costly one)
    # the pair-force head's mass fit along a rollout (model.rollout_masses): null, the
    # checkpoint's own | window | held; one-step and inverse metrics do not depend on it
    masses: str | None = None


@dataclass
class EvaluateKeys:
    """Top-level keys of ``conf/evaluate.yaml`` (``python -m bgn.evaluate <run or ckpt>``),
    stored as ``evaluate_base``."""

    ckpt: str | None = None           # a checkpoint or a run directory (the positional path)
    run_config: str | None = None     # null: the run's .hydra/config.yaml (or train_config.yaml)
    split: str = "test"               # the split scored
    sims: int | None = None           # score that split with this many simulations, the run's
                                      # first and new ones of the same scene (null: the run's)
    calibration_split: str = "val"    # the split the mass flow is recalibrated on
    calibration_sims: int | None = None  # that split with this many simulations, as sims=
    out_dir: str | None = None        # null: <run>/eval/<split>
    paths: Any = None                 # paths.data_dir (null: the run's paths.data_dir)
    max_frames: int | None = None     # one-step frames, evenly spread (null: the frames the
                                      # training run's own phase scores, dataset.<split>_samples)
    mass_frames: int = 32             # frames of the inverse metrics and of the calibration
    mass_samples: int = 32            # posterior samples per particle
    law_frames: int = 0               # more frames per simulation for the posteriors through
                                      # the learned law or the contact head's impacts
                                      # (bgn.eval.law_posterior, impact_posterior), beyond
                                      # mass_frames
    batch_size: int = 16
    seed: int = 0                     # the flow's samples
    # Eq. 9-10's input z in relmass_r2: median (the flow's base draw 0, as the model decodes in
    # eval mode) | draw (a random posterior sample, the paper's training-time decode)
    relmass_decode: str = "median"
    figures: bool = True
    progress: bool = True             # a progress bar on the long parts
    rollout: EvaluateRolloutKeys = field(default_factory=EvaluateRolloutKeys)


def with_groups(keys: type, groups: tuple[str, ...]) -> type:
    """``keys`` plus an untyped slot per config group (each group is typed by its own
    schema, or is Lightning's / Hydra's)."""
    slots = [(group, Any, field(default=None)) for group in groups]
    return make_dataclass(keys.__name__.replace("Keys", "Node"), slots, bases=(keys,))


TrainNode = with_groups(TrainKeys, ("paths", "dataset", "model", "optimizer", "scheduler",
                                    "trainer", "logger", "callbacks"))
GenerateNode = with_groups(GenerateKeys, ("paths", "dataset"))


def register_configs(models: bool = True) -> None:
    """Store the dataset and top-level schemas and, with ``models``, the model schemas (which
    import torch; ``conf/generate.yaml`` needs none). Idempotent."""
    cs = ConfigStore.instance()
    if "data" not in _registered:
        for scene in SCENES:
            cs.store(group="dataset", name=f"{scene}_base",
                     node=ImportedDatasetNode if scene == "imported" else dataset_schema(scene))
        cs.store(name="import_base", node=ImportKeys)
        cs.store(name="train_base", node=TrainNode)
        cs.store(name="generate_base", node=GenerateNode)
        cs.store(name="evaluate_base", node=EvaluateKeys)
        _registered.add("data")
    if models and "models" not in _registered:
        from bgn.model.registry import MODELS  # torch

        for name, model in MODELS.items():
            cs.store(group="model", name=f"{name}_base", node=model_schema(model))
        _registered.add("models")
