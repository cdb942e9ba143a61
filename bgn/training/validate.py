"""Bad input, refused at once: config checks before any work, and the one-line exit.

The typed schemas (``bgn.training.config``) fix the types at composition; here are the ranges and
the cross-checks, run by every entry point (``bgn.train``, ``bgn.train.generate``,
``bgn.studies.grid``) before data are generated or a model is built:

- ``fps`` > 0 and low enough that the frame spacing is resolved by the stored float64
  positions (``check_resolution``); the sizes ``dataset.n_sims``, ``n_frames``,
  ``n_particles``, ``dim`` >= 1, ``history`` >= 0, ``n_frames >= history + 3`` (the window
  and the next frame, what ``bgn.data.dataset.FrameDataset`` samples), ``batch_size``,
  ``val_samples``, ``train_sims``; the scene's own parameter checks (``bgn.sim``);
- the model's options (its config dataclass: sizes >= 1, choices) and whether the window of
  ``dataset.history`` past velocities feeds its ``target_prior``;
- ``optimizer.lr`` > 0 and the other optimiser and scheduler numbers;
- the top-level keys (``seed``, ``rollout_steps``, ...).

A bad value raises ``ConfigError`` (a ``ValueError``) naming the key, the value and what is
accepted. ``cli`` turns an entry point into a Hydra app whose bad input (a value refused at
composition, an unknown config, a ``ConfigError``) ends with that one line on stderr and exit
code 2, and a bad dataset file or import (``DataImportError``) with its one line and exit
code 1; ``BGN_FULL_ERROR=1`` (or
Hydra's ``HYDRA_FULL_ERROR=1``) shows the full trace instead.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import re
import sys
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from bgn.coerce import ConfigError, need_float, need_int
from bgn.data.spec import IMPORTED, DatasetSpec, LoaderOptions, check_fps, data_dir_problem
from bgn.sim import SCENES, Scene
from bgn.training.config import TrainKeys

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
FULL_ERROR_ENV = "BGN_FULL_ERROR"
CONFIG_EXIT = 2       # bad input (the usual exit code of a command-line usage error)
DATA_EXIT = 1         # a dataset file that cannot be used
# Largest accepted round-off of a finite-difference target relative to its typical size
MAX_ROUNDOFF = 1e-4
MAX_SEED = 2**32 - 1  # numpy's and Lightning's seed range


def _get(node: Any, key: str, default: Any = None) -> Any:
    if isinstance(node, Mapping) or hasattr(node, "get"):
        return node.get(key, default)
    return getattr(node, key, default)


def _keys(node: Any) -> list[Any]:
    return list(node.keys()) if hasattr(node, "keys") else []


# ----------------------------------------------------------------------------- data
def frame_roundoff(scene: Scene, fps: float) -> tuple[float, float]:
    """``(round-off, largest fps)``: the relative float64 round-off of the finite-difference
    target of a typical frame at ``fps``, and the largest fps that keeps it <= MAX_ROUNDOFF.

    Typical sizes from the scene's parameters: positions ``box`` (walls) or 3 x
    ``position_std``; speeds ``velocity_std``; accelerations speed^2 / position. The velocity
    target is a first difference of positions (step v dt), the acceleration target a second
    one (step a dt^2); a position x carries an absolute round-off of eps x.
    """
    meta = scene.meta
    eps = float(np.finfo(np.float64).eps)
    size = float(meta.box) if meta.box else 3.0 * float(getattr(scene, "position_std", 1.0))
    speed = float(getattr(scene, "velocity_std", 0.0)) or 1.0
    dt = 1.0 / fps
    floor = eps * size / MAX_ROUNDOFF  # the smallest step resolved well enough
    if meta.target == "velocity":
        return eps * size / (speed * dt), speed / floor
    accel = speed * speed / size
    return eps * size / (accel * dt * dt), math.sqrt(accel / floor)


def check_resolution(scene: Scene, fps: float) -> None:
    """Refuse an fps whose frame spacing the stored float64 positions do not resolve (the
    targets would be round-off: at fps=1e9 the spring's target median is exactly 0)."""
    roundoff, fps_max = frame_roundoff(scene, fps)
    if roundoff > MAX_ROUNDOFF:
        raise ConfigError("fps", fps, (
            f"too high for {scene.meta.name}: the frame spacing is below what float64 positions "
            f"resolve (round-off {roundoff:.1e} of a typical {scene.meta.target} target, at most "
            f"{MAX_ROUNDOFF:g} accepted); use fps <= {fps_max:.3g}"))


def validate_imported(dataset: Any, data_dir: Any) -> DatasetSpec:
    """``dataset=imported``: the name, the loader keys and the files' sizes (which the import
    wrote: ``bgn.data.importing``); returns the train split's ``DatasetSpec``."""
    try:
        name = _get(dataset, "name")
    except Exception:  # noqa: BLE001 (OmegaConf: a missing mandatory value)
        name = None
    if not name or name == "???":
        raise ConfigError("dataset.name", message=(
            "dataset.name is missing: give the name of an import (python -m bgn.data.import "
            "<path> name=<name>), e.g. dataset=imported dataset.name=<name>"))
    from bgn.data.raw import DataImportError

    try:
        spec = DatasetSpec.from_config(dataset, 1.0, "train", data_dir or "data")
    except DataImportError:  # the import's files are damaged (exit 1), not the name
        raise
    except ValueError as err:
        raise ConfigError("dataset.name", message=str(err)) from None
    loader = LoaderOptions.from_config(
        dataset, spec.n_sims, sims_why=f" (at most the {spec.n_sims} imported training "
        "trajectories)")
    history, unroll = loader.history, loader.unroll
    for split, (_, n_frames) in zip(("train", "val", "test"), spec.sizes):
        if n_frames < history + 3 + unroll:
            raise ConfigError("dataset.history", history, (
                f"too long for the {split} split of {name!r} ({n_frames} frames): a sample needs "
                f"dataset.history + 3{' + dataset.unroll' if unroll else ''} = "
                f"{history + 3 + unroll}; lower dataset.history"))
    return spec


def validate_dataset(dataset: Any, fps: Any, data_dir: Any = None) -> DatasetSpec:
    """Check a ``dataset`` node and ``fps`` (types, ranges, the scene's parameters, enough
    frames, a resolved frame spacing); returns the train split's ``DatasetSpec``. Imported
    data (``scene: imported``) are read from their files under ``data_dir``."""
    if data_dir is not None and (problem := data_dir_problem(data_dir)):
        raise ConfigError("paths.data_dir", message=problem)  # not a NotADirectoryError later
    fps = check_fps(fps)
    scene_name = _get(dataset, "scene")
    if scene_name not in SCENES:
        raise ConfigError("dataset.scene", scene_name, f"choose one of {sorted(SCENES)}")
    if scene_name == IMPORTED:
        return validate_imported(dataset, data_dir)
    n_sims = need_int(_get(dataset, "n_sims"), "dataset.n_sims", 1)
    assert n_sims is not None
    loader = LoaderOptions.from_config(dataset, n_sims)  # history, batch_size, train_sims, ...
    history, unroll = loader.history, loader.unroll
    n_frames = need_int(_get(dataset, "n_frames"), "dataset.n_frames", 3)
    if n_frames is not None and n_frames < history + 3 + unroll:
        unrolled = (" + dataset.unroll", f" and the {unroll} unrolled ones") if unroll else ("", "")
        raise ConfigError("dataset.n_frames", n_frames, (
            f"must be >= dataset.history + 3{unrolled[0]} = {history + 3 + unroll} (a "
            f"sample needs the {history + 2} frames of its velocity window, the next "
            f"frame{unrolled[1]}); raise dataset.n_frames or lower dataset.history"))
    need_int(_get(dataset, "seed"), "dataset.seed", 0, MAX_SEED)
    for key in ("n_particles", "dim"):
        if _get(dataset, key) is not None:
            need_int(_get(dataset, key), f"dataset.{key}", 1)
    need_int(_get(dataset, "generate_workers"), "dataset.generate_workers", 1, optional=True)
    try:
        spec = DatasetSpec.from_config(dataset, fps, "train")
    except ValueError as err:  # the scene's own check of its parameters: "name must be ..."
        text = str(err).removeprefix("CollisionScene.")
        key = text.split()[0].split("=")[0].split("[")[0] if text else ""
        if key in set(map(str, _keys(dataset))):
            text = f"dataset.{text}"
        raise ConfigError("dataset", message=f"{text} (scene {scene_name})") from None
    check_resolution(spec.build_scene(), fps)
    return spec


# ----------------------------------------------------------------------------- model
def validate_model(model: Any, scene: Scene, history: int) -> None:
    """The model's options (its config dataclass checks them) and whether the window of
    ``history`` past velocities feeds its target prior."""
    from bgn.model.base import config_from_params
    from bgn.model.registry import MODELS
    from bgn.model.target_coder import prior_hint, resolve_prior

    name = _get(model, "name")
    if name not in MODELS:
        raise ConfigError("model", name, f"choose one of {sorted(MODELS)}")
    params = {str(k): v for k, v in (model.items() if hasattr(model, "items") else {})}
    from bgn.model.newton import DYNAMICS

    if "dynamics" in params and params["dynamics"] not in (*DYNAMICS, "auto"):
        raise ConfigError("model.dynamics", params["dynamics"], (
            f"choose one of {[*DYNAMICS, 'auto']} (auto: every structure the data admit, "
            "chosen on validation)"))
    if params.get("dynamics") == "auto":  # bgn.studies.auto composes and checks each candidate; the
        params["dynamics"] = "decoder"    # rest of the options are checked with the decoder
    try:
        cfg = config_from_params(MODELS[name].config_class, params, name)
    except (TypeError, ValueError) as err:  # messages start with the option: "hidden=0 ..."
        raise ConfigError("model", message=f"model.{err}") from None
    weights = getattr(cfg, "loss_weights", None) or {}
    # a scene's defaults may train the pair-force law alone (conf/dataset_model/gravity_*):
    # with the decoder, which the law loss does not reach, nothing would train the dynamics
    # (auto sets each candidate's weights itself)
    if (_get(model, "dynamics") not in (None, "auto") and weights.get("dynamics", 1.0) == 0
            and not (getattr(cfg, "dynamics", None) == "newton" and weights.get("law", 0.0))):
        raise ConfigError("model.loss_weights.dynamics", message=(
            f"model.loss_weights.dynamics=0 with model.dynamics={cfg.dynamics}: nothing trains "
            "the dynamics head (the law loss is the pair-force head's); use model=bgn_decoder, "
            "or model.loss_weights.dynamics=1"))
    if (getattr(cfg, "dynamics", "newton") == "newton" and hasattr(cfg, "mass_law")
            and scene.meta.interaction != "contact"):  # contacts: the impulse head, no mass law
        from bgn.model.newton import check_mass_law

        try:
            check_mass_law(scene.meta, cfg.mass_law, "the pair-force head (model.mass_law)")
        except ValueError as err:
            raise ConfigError("model.mass_law", message=str(err)) from None
    if getattr(cfg, "dynamics", None) == "soft_contact" and scene.meta.target != "acceleration":
        raise ConfigError("model.dynamics", "soft_contact", (
            f"the soft-contact head predicts an acceleration target; {scene.meta.name} has a "
            f"{scene.meta.target} target: use model.dynamics=newton (its impulse head) or "
            "decoder"))
    prior, needed, available = resolve_prior(cfg.target_prior, scene.meta.target, history)
    if available < needed:
        raise ConfigError("model.target_prior", message=prior_hint(
            prior, needed, history, available, asked=cfg.target_prior))


def validate_optimization(optimizer: Any, scheduler: Any) -> None:
    """Numbers of the optimiser and scheduler partials (when present)."""
    if optimizer is not None:
        if _get(optimizer, "lr") is not None:
            need_float(_get(optimizer, "lr"), "optimizer.lr", 0.0, why=" (the learning rate)")
        if _get(optimizer, "weight_decay") is not None:
            need_float(_get(optimizer, "weight_decay"), "optimizer.weight_decay", 0.0,
                       strict_low=False)
        if _get(optimizer, "eps") is not None:
            need_float(_get(optimizer, "eps"), "optimizer.eps", 0.0)
        for i, beta in enumerate(_get(optimizer, "betas") or ()):
            need_float(beta, f"optimizer.betas.{i}", 0.0, 1.0, strict_low=False,
                       strict_high=True)
    if scheduler is not None:
        if _get(scheduler, "factor") is not None:
            need_float(_get(scheduler, "factor"), "scheduler.factor", 0.0, 1.0,
                       strict_high=True)
        if _get(scheduler, "patience") is not None:
            need_int(_get(scheduler, "patience"), "scheduler.patience", 0)
        if _get(scheduler, "lr_min_ratio") is not None:
            need_float(_get(scheduler, "lr_min_ratio"), "scheduler.lr_min_ratio", 0.0, 1.0,
                       strict_low=False)


def validate_auto(auto: Any) -> None:
    """The ``auto`` keys of ``model.dynamics=auto`` (``bgn.studies.auto``)."""
    from bgn.model.registry import MODELS

    if auto is None:
        return
    need_float(_get(auto, "share", 0.5), "auto.share", 0.0, 1.0, strict_high=True,
               why=" (the budget's share spent on the candidates)")
    need_int(_get(auto, "horizon", 50), "auto.horizon", 1, why=" (rollout steps)")
    need_int(_get(auto, "val_sims"), "auto.val_sims", 1, optional=True,
             why=" (validation simulations; null: all)")
    need_int(_get(auto, "val_rollouts", 100), "auto.val_rollouts", 1,
             why=" (validation rollouts: start frames per simulation as give this many)")
    for name in _get(auto, "references") or ():
        if name not in MODELS or name == "bgn":
            raise ConfigError("auto.references", name,
                              f"model names among {sorted(set(MODELS) - {'bgn'})}")


# ----------------------------------------------------------------------------- entry configs
def typed(key: str) -> bool:
    """Whether the command line as typed (``ARGV``, set by ``cli``) sets ``key``."""
    return any(arg.split("=", 1)[0].lstrip("+~") == key for arg in ARGV[1:])


def validate_train(cfg: Any) -> DatasetSpec:
    """Everything ``bgn.train`` is given, before data or a model are made."""
    need_int(_get(cfg, "seed", 0), "seed", 0, MAX_SEED)
    for key in ("rollout_steps", "val_rollout_steps", "animation_every"):
        need_int(_get(cfg, key, 0), key, 0, why=" (0: off)")
    spec = validate_dataset(_get(cfg, "dataset"), _get(cfg, "fps"),
                            _get(_get(cfg, "paths"), "data_dir"))
    if (_get(cfg, "val_rollout_steps", 0) or 0) > 0:
        n_val = spec.with_split("val").n_sims  # imported data: each split its own
        sims = _get(cfg, "val_rollout_sims", 1)
        if sims == TrainKeys.val_rollout_sims and n_val < sims and not typed("val_rollout_sims"):
            # the default asks for more than a small split has (an import of one validation
            # trajectory): all of them; a value the user gave stays refused
            cfg["val_rollout_sims"] = sims = n_val
        need_int(sims, "val_rollout_sims", 1, n_val, why=f" (validation simulations: {n_val})")
    history = need_int(_get(_get(cfg, "dataset"), "history", LoaderOptions.history),
                       "dataset.history", 0)
    assert history is not None
    if _get(cfg, "model") is not None:
        validate_model(_get(cfg, "model"), spec.build_scene(), history)
        if _get(_get(cfg, "model"), "dynamics") == "auto":
            validate_auto(_get(cfg, "auto"))
    validate_optimization(_get(cfg, "optimizer"), _get(cfg, "scheduler"))
    return spec


def validate_generate(cfg: Any) -> DatasetSpec:
    """Everything ``bgn.train.generate`` is given."""
    need_int(_get(cfg, "workers"), "workers", 1, optional=True,
             why=" (simulation processes; null: one per core)")
    if _get(_get(cfg, "dataset"), "scene") == IMPORTED:
        raise ConfigError("dataset", message="dataset=imported is not generated: import "
                          "trajectories with python -m bgn.data.import <path> name=<name>")
    return validate_dataset(_get(cfg, "dataset"), _get(cfg, "fps"),
                            _get(_get(cfg, "paths"), "data_dir"))


# ----------------------------------------------------------------------------- the exit
def _env_set(name: str) -> bool:
    return os.environ.get(name, "") not in ("", "0")


def full_error() -> bool:
    """Whether the user asked for full traces (``BGN_FULL_ERROR`` or ``HYDRA_FULL_ERROR``)."""
    return _env_set(FULL_ERROR_ENV) or _env_set("HYDRA_FULL_ERROR")


def one_line(err: BaseException) -> str:
    """The message of ``err`` (and of its cause, as Hydra reports composition errors) on one
    line, without OmegaConf's ``full_key``/``object_type`` detail lines."""
    parts = []
    for e in (err, err.__cause__):
        if e is None:
            continue
        lines = [ln.strip() for ln in str(e).splitlines()
                 if ln.strip() and not ln.strip().startswith(("full_key:", "object_type=",
                                                              "reference_type="))]
        if lines and (not parts or lines[0] not in parts[-1]):
            parts.append(" ".join(lines))
    text = ": ".join(parts) or type(err).__name__
    return text.split(" Config search path:")[0]  # Hydra's search path: no help here


def fail(err: BaseException, code: int) -> None:
    """Print ``err`` as one line on stderr and exit with ``code``."""
    sys.stderr.write(f"bgn: error: {one_line(err)}  [{FULL_ERROR_ENV}=1 for the full trace]\n")
    sys.stderr.flush()
    raise SystemExit(code)


@contextmanager
def reported() -> Iterator[None]:
    """Inside: a ``ConfigError`` exits 2 and a ``DatasetFileError`` exits 1, each with one
    line (the full trace when ``full_error()``)."""
    from bgn.data.files import DatasetFileError
    from bgn.data.raw import DataImportError

    try:
        yield
    except (ConfigError, DatasetFileError, DataImportError) as err:
        if full_error():
            raise
        fail(err, CONFIG_EXIT if isinstance(err, ConfigError) else DATA_EXIT)


_NOT_SET = object()
_saved_hydra_env: list[Any] = []  # HYDRA_FULL_ERROR as the user set it, while cli forces it
ARGV: list[str] = []  # the command line as typed (before ``positional_override``): provenance

# Hydra's own options; those that take the next argument as their value (not a positional path)
_VALUE_OPTIONS = {"-cp", "--config-path", "-cn", "--config-name", "-cd", "--config-dir",
                  "-c", "--cfg", "-p", "--package", "--experimental-rerun", "-i", "--info"}
_HYDRA_OPTIONS = _VALUE_OPTIONS | {"-h", "--help", "--hydra-help", "--version", "--resolve",
                                   "-r", "--run", "-m", "--multirun", "-sc",
                                   "--shell-completion"}


def _restore_hydra_env() -> None:
    while _saved_hydra_env:
        saved = _saved_hydra_env.pop()
        if saved is _NOT_SET:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = saved


def positional_override(argv: list[str], key: str) -> list[str]:
    """``argv`` (the arguments, without the program) with its first positional argument (no
    ``=``, not an option nor an option's value) turned into the override ``<key>=<it>``,
    quoted where Hydra's override grammar needs it: ``python -m bgn.evaluate <run> split=val``
    reads as Hydra overrides. A second positional argument is left for Hydra to refuse."""
    out, taken, after_option = [], False, False
    for arg in argv:
        if not taken and not after_option and "=" not in arg and not arg.startswith("-"):
            if not re.fullmatch(r"[\w./~+:@-]+", arg):
                arg = "'" + arg.replace("\\", "\\\\").replace("'", "\\'") + "'"
            out.append(f"{key}={arg}")
            taken = True
        else:
            out.append(arg)
        after_option = arg in _VALUE_OPTIONS
    return out


def check_options(argv: list[str], prog: str) -> None:
    """Refuse, in one line, an option Hydra does not know (``--split test``: every bgn
    command takes ``key=value``)."""
    for arg in argv:
        name = arg.split("=", 1)[0]
        if arg.startswith("-") and name not in _HYDRA_OPTIONS:
            key = name.lstrip("-").replace("-", "_")
            raise ConfigError(key, message=(
                f"{name} is not an option of python -m {prog}: its arguments are key=value "
                f"overrides, e.g. {key}=<value> (python -m {prog} --help lists them)"))


def _remove_refused_run() -> None:
    """After a refusal inside a Hydra run: remove the run folder Hydra made for it where it
    holds nothing but Hydra's ``.hydra/`` (its three yaml files) and the job's log; anything
    else in it, or any other folder, is kept."""
    import shutil

    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return
    hydra_cfg = HydraConfig.get()
    out = Path(hydra_cfg.runtime.output_dir)
    if not out.is_dir() or out.resolve() == Path.cwd().resolve():
        return
    subdir = out / str(hydra_cfg.output_subdir) if hydra_cfg.output_subdir else None
    expected = {f"{hydra_cfg.job.name}.log"} | ({subdir.name} if subdir else set())
    if {p.name for p in out.iterdir()} - expected:
        return
    if subdir is not None and subdir.exists() and not (
            subdir.is_dir() and not subdir.is_symlink() and all(
                p.is_file() and p.suffix == ".yaml" for p in subdir.iterdir())):
        return
    if subdir is not None and subdir.exists():
        shutil.rmtree(subdir)
    (out / f"{hydra_cfg.job.name}.log").unlink(missing_ok=True)
    out.rmdir()


# Lightning's messages that ask nothing of the user: an advertisement, and warnings about
# what bgn does on purpose or about Lightning's own use of torch (each filtered by its text
# and category, so that any other message still shows)
QUIET_MESSAGES = ("Tip: For seamless", "litmodels", "litlogger")
QUIET_WARNINGS = (
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning),  # Lightning's pytree
    (r"`\.\w+\(ckpt_path=None\)` was called without a model", UserWarning),  # bgn names it
    (r'\.\w+\(ckpt_path="last"\) is set, but there is no last checkpoint', UserWarning),
    (r"You have overridden `transfer_batch_to_device` in `LightningModule`", UserWarning),
    (r"The number of training batches \(\d+\) is smaller than the logging interval",
     UserWarning),
)
LIGHTNING_COMMANDS = ("train", "experiments")  # those that train in their own process


class _Quiet(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not any(text in record.getMessage() for text in QUIET_MESSAGES)


def quiet_logs(lightning: bool = False) -> None:
    """One line per Lightning log record, without its advertisement or the warnings the user
    cannot act on (``QUIET_WARNINGS``). Lightning gives its loggers console handlers of their
    own at import, and Hydra's logging config the root one, so each record printed twice:
    here Lightning's records go to Hydra's handlers alone. With ``lightning`` it is imported
    first (a command that trains), else only an already imported Lightning is quietened."""
    if lightning:
        import lightning as _  # noqa: F401 (its import adds the handlers removed below)
    for name in ("lightning.pytorch", "lightning.fabric", "lightning"):
        if name not in sys.modules:
            continue
        log = logging.getLogger(name)
        for handler in list(log.handlers):
            if type(handler) is logging.StreamHandler:  # Lightning's own console handler
                log.removeHandler(handler)
        log.propagate = True
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, _Quiet) for f in handler.filters):
            handler.addFilter(_Quiet())
    for message, category in QUIET_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category)


def leaf_keys(cfg: Any, prefix: str = "") -> list[str]:
    """The dotted names of a config's values (``paths.data_dir``, ``rollout.steps``, ...)."""
    from omegaconf import OmegaConf

    out = []
    for key in cfg:
        if key == "hydra":
            continue
        node = cfg._get_node(key)
        name = f"{prefix}{key}"
        out += leaf_keys(node, f"{name}.") if OmegaConf.is_dict(node) else [name]
    return out


def unknown_key(err: BaseException, prog: str, defaults: Callable[[], Any]) -> BaseException:
    """Hydra's refusal of a key the config does not have ("Could not override 'x'. To append
    to your config use +x=...", whose advice does not apply) as one line naming the key, the
    closest keys the command has (``defaults``: its config) and where they are listed;
    any other error as it is."""
    import difflib

    found = re.match(r"Could not override '([^']+)'", str(err))
    if not found:
        return err
    key = found.group(1)
    try:
        keys = leaf_keys(defaults())
    except Exception:  # noqa: BLE001 (the hint is a nicety; the refusal stands)
        keys = []
    close = [k for k in keys if k.endswith(f".{key}") or key.endswith(f".{k}")]
    close += [k for k in difflib.get_close_matches(key, keys, n=2) if k not in close]
    hint = f"; did you mean {' or '.join(close[:2])}?" if close else ""
    return ConfigError(key, message=f"{key} is not a key of python -m {prog}{hint} "
                       f"(python -m {prog} --help lists them)")


def cli(config_name: str, validate: Callable[[Any], Any] | None = None,
        config_dir: Path = CONF_DIR, positional: str | None = None,
        prog: str | None = None) -> Callable[[Callable[[Any], Any]], Callable[..., Any]]:
    """``@cli("train", validate_train)`` on ``def main(cfg)``: the command style of every
    ``python -m bgn.*`` command. A Hydra app (``<config_dir>/<config_name>.yaml``, its
    ``--help`` the config's ``hydra.help.template``) taking ``key=value`` overrides, whose
    bad input ends with one line and exit code 2 before any work; with ``positional`` (a key)
    its first positional argument is that key's value (``python -m bgn.evaluate <run>``:
    ``ckpt=<run>``).

    Hydra reports its own errors (a value the schema refuses, an unknown config) in several
    lines with exit code 1; so until the task starts, ``HYDRA_FULL_ERROR`` is set and the
    error reaches this wrapper, which prints it on one line (or re-raises it: full trace). The
    task restores the user's setting first thing (unless ``BGN_FULL_ERROR`` is set), so
    errors at run time keep Hydra's usual report. A refused run leaves no run folder behind
    (``_remove_refused_run``). The decorated function is called with nothing (the console:
    ``sys.argv``), with a list of arguments (the same, in the caller's process, composed
    without a run folder or logging set-up) or with a config (validated and run as it is).
    """
    name = prog or f"bgn.{config_name}"

    def decorate(task: Callable[[Any], Any]) -> Callable[..., Any]:
        @functools.wraps(task)
        def checked(cfg: Any) -> Any:
            if not _env_set(FULL_ERROR_ENV):  # BGN_FULL_ERROR: full traces at run time too
                _restore_hydra_env()
            quiet_logs(lightning=config_name in LIGHTNING_COMMANDS)
            try:
                with reported():
                    if validate is not None:
                        validate(cfg)
                    return task(cfg)
            except SystemExit as exit_:
                if exit_.code not in (0, None):
                    _remove_refused_run()
                raise

        import hydra

        app = hydra.main(config_path=str(config_dir), config_name=config_name,
                         version_base="1.3")(checked)

        def compose_args(args: list[str]) -> Any:
            from hydra import compose, initialize_config_dir

            with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
                return compose(config_name=config_name, overrides=args)

        @functools.wraps(task)
        def main(cfg: Any = None) -> Any:
            if cfg is not None and not isinstance(cfg, (list, tuple)):
                return checked(cfg)
            from bgn.training.config import register_configs

            register_configs(models=False)  # the schemas the configs build on (idempotent)
            full = full_error()
            typed = list(sys.argv[1:] if cfg is None else cfg)
            ARGV[:] = [f"python -m {name}", *typed]
            args = positional_override(typed, positional) if positional else typed
            _saved_hydra_env.append(os.environ.get("HYDRA_FULL_ERROR", _NOT_SET))
            os.environ["HYDRA_FULL_ERROR"] = "1"
            saved_argv = sys.argv
            try:
                check_options(args, name)
                if cfg is None:
                    sys.argv = [saved_argv[0], *args]
                    return app()
                composed = compose_args(args)  # in this process: composed, then run
            except BrokenPipeError:  # --help | head: the reader left; nothing to report
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                raise SystemExit(0) from None
            except Exception as err:  # raised before the task ran: bad input (an unknown
                if full:              # option, or Hydra's own: a refused value or config)
                    raise
                fail(unknown_key(err, name, lambda: compose_args([])), CONFIG_EXIT)
            finally:
                sys.argv = saved_argv
                _restore_hydra_env()
            return checked(composed)

        return main

    return decorate
