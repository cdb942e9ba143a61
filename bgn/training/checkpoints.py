"""Run files: checkpoints read safely, named when unreadable, checked against the run that
loads them; JSON records (``metrics.json``, ``eval.json``, ``cell.json``) written atomically and
named when damaged.

Every checkpoint is read with ``torch.load(weights_only=True)``: tensors and plain values only,
never arbitrary pickled objects (a checkpoint from elsewhere cannot run code). bgn's
checkpoints hold nothing else: the LightningModule's hyperparameters are plain types.

A checkpoint written by ``bgn.train`` records where it comes from (``provenance`` in its
hyperparameters): the scene, a hash of the scene's parameters, the fps, the model and the
input window (``history``). ``check_compatible`` compares that record with the run that wants
to load it and refuses, in one line, a checkpoint of another scene or model.

Errors are ``CheckpointError`` (a ``ValueError``) with a one-line message naming the file.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

# what a run is, for a checkpoint: a difference in any of these and its weights mean
# something else (or do not fit)
PROVENANCE_KEYS = ("scene", "scene_params", "fps", "model", "history")


class CheckpointError(ValueError):
    """A checkpoint that cannot be read, or that belongs to another scene or model."""


def params_hash(params: dict[str, Any]) -> str:
    """Short hash of a scene's full parameter set
    (``DatasetSpec.generating_config()["params"]``)."""
    blob = json.dumps(params, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:10]


def provenance(scene: str, params: dict[str, Any], fps: float, model: str,
               history: int, margin: float = 0.0) -> dict[str, Any]:
    """The record a checkpoint keeps of the run that wrote it (plain types only). ``margin``
    (the training file's radius-graph margin) and ``scene_config`` (the scene's parameters,
    whose hash ``scene_params`` is) are carried for the Python API (``bgn.api``), which
    rebuilds the graph rule and the scene's mass law from the checkpoint alone; they are not
    checked on resume."""
    return {"scene": str(scene), "scene_params": params_hash(params), "fps": float(fps),
            "model": str(model), "history": int(history), "margin": float(margin),
            "scene_config": json.loads(json.dumps(params, default=str))}


def read(path: str | Path) -> dict[str, Any]:
    """The checkpoint's dictionary, loaded with ``weights_only=True`` on the CPU; a missing,
    truncated or foreign file gives one ``CheckpointError`` naming it."""
    import torch  # here: the JSON helpers below serve modules that need no torch

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises RuntimeError, UnpicklingError, EOFError, ...
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        if "weights_only" in str(err) or "Weights only" in str(err):
            reason = ("it holds objects other than tensors and plain values, which bgn does "
                      "not unpickle (torch.load weights_only=True)")
        else:
            reason = ("it is truncated or not a checkpoint (a run killed while saving leaves "
                      "such a file; use another checkpoint of the run, or none); torch says: "
                      f"{first[:120]}")
        raise CheckpointError(f"checkpoint {path} cannot be read: {reason}") from None
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt:
        raise CheckpointError(f"checkpoint {path} is not a Lightning checkpoint of bgn "
                              "(no state_dict)")
    return ckpt


def recorded_provenance(ckpt: dict[str, Any]) -> dict[str, Any]:
    """What a checkpoint says about its run; checkpoints from before the record carry the
    scene, the model and the history in their hyperparameters (the rest is unknown)."""
    hp = ckpt.get("hyper_parameters") or {}
    if hp.get("provenance"):
        return dict(hp["provenance"])
    known = {"scene": (hp.get("meta") or {}).get("name"),
             "model": (hp.get("model_config") or {}).get("name"), "history": hp.get("history")}
    return {k: v for k, v in known.items() if v is not None}


def _show(key: str, value: Any) -> str:
    return f"{key}={value:g}" if key == "fps" else f"{key}={value}"


def check_compatible(path: str | Path, expected: dict[str, Any],
                     model_config: dict[str, Any] | None = None,
                     ckpt: dict[str, Any] | None = None) -> dict[str, Any]:
    """Read ``path`` and refuse it, in one line, when the run it comes from differs from
    ``expected`` (``provenance(...)``) in scene, scene parameters, fps, model or history, or
    (given ``model_config``) in a model option that both configs set. Returns the checkpoint."""
    ckpt = read(path) if ckpt is None else ckpt
    recorded = recorded_provenance(ckpt)
    differ = [(k, recorded[k], expected[k]) for k in PROVENANCE_KEYS
              if k in recorded and k in expected and recorded[k] != expected[k]]
    theirs_model = (ckpt.get("hyper_parameters") or {}).get("model_config") or {}
    if model_config is not None and not any(k == "model" for k, _, _ in differ):
        differ += [(f"model.{k}", theirs_model[k], model_config[k]) for k in sorted(model_config)
                   if k in theirs_model and theirs_model[k] != model_config[k]]
    if differ:
        theirs = ", ".join(_show(k, a) for k, a, _ in differ)
        ours = ", ".join(_show(k, b) for k, _, b in differ)
        what = "scene" if {"scene", "scene_params", "fps"} & {k for k, _, _ in differ} \
            else "model"
        raise CheckpointError(
            f"checkpoint {path} was trained with {theirs} but this run has {ours}: pass a "
            f"checkpoint of this {what} or drop ckpt_path")
    return ckpt


def resolve_last(ckpt_path: str | None, checkpoint_dir: str | Path) -> str | None:
    """``ckpt_path=last`` -> ``<checkpoint_dir>/last.ckpt`` when it exists (a fresh start
    otherwise, ``None``); any other value is returned as given."""
    if ckpt_path != "last":
        return ckpt_path
    last = Path(checkpoint_dir) / "last.ckpt"
    return str(last) if last.is_file() else None


def write_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same folder and a rename:
    a reader (or a killed writer) never leaves a half-written file under ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def save_atomic(obj: Any, path: str | Path) -> None:
    """``torch.save(obj, path)`` through a temporary file and a rename, as ``write_atomic``:
    a killed writer leaves the old checkpoint (or none), never a half-written one."""
    import torch

    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def read_record(path: str | Path) -> dict[str, Any] | None:
    """The JSON record at ``path``; ``None`` when it is missing, or damaged (half-written by a
    killed writer of an older bgn, edited by hand): then a warning names the file, and the
    caller redoes the work that writes it."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
        if not isinstance(record, dict):
            raise ValueError(f"a JSON {type(record).__name__}, not an object")
    except (ValueError, UnicodeDecodeError) as err:
        log.warning("%s is damaged (%s): ignoring it and redoing the work that writes it",
                    path, str(err).splitlines()[0][:100])
        return None
    return record


def best_checkpoint(run_dir: Path) -> Path:
    """best.ckpt (or the newest best-vN.ckpt after a resume), else last.ckpt."""
    ckpts = run_dir / "checkpoints"
    best = sorted(ckpts.glob("best*.ckpt"), key=lambda p: p.stat().st_mtime)
    if best:
        return best[-1]
    if (ckpts / "last.ckpt").exists():
        return ckpts / "last.ckpt"
    raise FileNotFoundError(f"no checkpoint in {ckpts}")


def chosen_checkpoint(run_dir: Path) -> Path:
    """The checkpoint a run stands for: ``laws/formula.ckpt`` where its ``laws/formula.json``
    chose the formula law on validation (``model.law=auto``, or ``python -m bgn.laws <ckpt>
    finetune=true``), else ``best_checkpoint``."""
    law = run_dir / "laws" / "formula.json"
    if law.is_file() and (run_dir / "laws" / "formula.ckpt").is_file():
        record = read_record(law)
        if record is not None and record.get("choice") == "formula":
            return run_dir / "laws" / "formula.ckpt"
    return best_checkpoint(run_dir)


def run_config_paths(ckpt: Path, run_dir: Path) -> list[Path]:
    """Where a run's config may lie, in the order looked at: Hydra's record of a
    ``python -m bgn.train`` run (beside the checkpoints folder, or the checkpoint), or a study
    cell's ``train_config.yaml``."""
    return list(dict.fromkeys([run_dir / ".hydra" / "config.yaml",
                               ckpt.parent / ".hydra" / "config.yaml",
                               run_dir / "train_config.yaml"]))


def resolve_run(path: str, run_config: str | None = None) -> tuple[Path, Path, Path]:
    """``(checkpoint, run directory, run config)`` of a checkpoint or run directory: a run
    directory gives its chosen checkpoint
    (``bgn.training.checkpoints.chosen_checkpoint``: best.ckpt, the newest best-vN.ckpt, else
    last.ckpt), or ``laws/formula.ckpt`` where the run's ``laws/formula.json`` chose the
    formula law on validation (``model.law=auto``, or ``python -m bgn.laws <ckpt>
    finetune=true``); a checkpoint in ``<run>/checkpoints/`` its
    run. Bad input: one ``ConfigError`` naming the path and the fix."""
    from bgn.training.validate import ConfigError  # the one-line refusal

    given = Path(path).expanduser()
    if not given.exists():
        raise ConfigError("ckpt", path, "no such file or directory: give a checkpoint (.ckpt) "
                          "or a run directory of python -m bgn.train")
    if given.is_dir():
        choice = given / "auto" / "auto.json"  # a model.dynamics=auto run: its chosen structure
        if not (given / "checkpoints").is_dir() and choice.is_file():
            given = given / "auto" / str(json.loads(choice.read_text())["choice"])
        run_dir = given
        try:
            ckpt = chosen_checkpoint(given)  # a model.law=auto run: the law it chose
            if ckpt.parent == given / "laws":
                run_dir = ckpt.parent  # its train_config.yaml has the formula's options
        except FileNotFoundError:
            raise ConfigError("ckpt", path, f"the run directory has no checkpoint (looked for "
                              f"{given / 'checkpoints'}/best*.ckpt and last.ckpt): give a run "
                              "that trained, or a checkpoint file") from None
    else:
        ckpt = given
        run_dir = given.parent.parent if given.parent.name == "checkpoints" else given.parent
    if run_config is not None:
        config = Path(run_config).expanduser()
        if not config.is_file():
            raise ConfigError("run_config", run_config, "no such file: give the run's "
                              ".hydra/config.yaml")
        return ckpt, run_dir, config
    for config in run_config_paths(ckpt, run_dir):
        if config.is_file():
            return ckpt, run_dir, config
    looked = ", ".join(str(p) for p in run_config_paths(ckpt, run_dir))
    raise ConfigError("ckpt", path, f"no run config beside the checkpoint (looked for {looked}): "
                      "pass run_config=<the run's .hydra/config.yaml>")


def run_config(checkpoint: Path) -> Path:
    """The training config of the run that wrote ``checkpoint`` (``<run>/checkpoints/x.ckpt``)."""
    checkpoint = checkpoint.resolve()
    candidates = run_config_paths(checkpoint, checkpoint.parent.parent)
    for candidate in candidates:
        if candidate.exists():
            return candidate
    raise FileNotFoundError(f"{checkpoint}: no run config beside it (looked for "
                            f"{', '.join(map(str, candidates))}); pass --config <the run's "
                            "config.yaml>")
