"""Animate a model's rollout against the truth: ``python -m bgn.render <run folder or
checkpoint> [split=test] [sim=0] [steps=200] ...`` (``--help`` lists the keys,
``conf/render.yaml``).

The model is the one ``python -m bgn.evaluate`` scores (``bgn.training.checkpoints.resolve_run``: a
run folder's chosen checkpoint, or a checkpoint file), with the run's config
(``<run>/.hydra/config.yaml``, or a study cell's ``train_config.yaml``) for the dataset; it is
rolled out through the learned simulator from a frame of a simulation of the chosen split,
and a GIF (or an MP4 with ffmpeg) of the true and predicted particles is written, or with
``format=vtk`` both as VTK time series that ParaView opens (``bgn.paraview``), each particle
with its velocity, type, radius, the model's mass posterior from the recorded frames up to
the start (``bgn.api.Model.infer``) and, on the predicted frames, its error against the truth.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from bgn.training.validate import ConfigError, cli, need_int

SPLITS = ("train", "val", "test")
FORMATS = ("gif", "mp4", "vtk")


def validate_render(cfg: Any) -> tuple[Path, Path, Path]:
    """Everything ``python -m bgn.render`` is given, before any data or model is read;
    returns ``resolve_run``'s (checkpoint, run folder, run config)."""
    from bgn.training.checkpoints import resolve_run

    if not cfg.get("ckpt"):
        raise ConfigError("ckpt", None, "give a run folder or checkpoint: python -m bgn.render "
                          "outputs/train/runs/<run> [split=test] [sim=0]")
    if cfg.split not in SPLITS:
        raise ConfigError("split", cfg.split, f"choose one of {list(SPLITS)}")
    need_int(cfg.sim, "sim", 0, why=" (a simulation of the split)")
    need_int(cfg.start, "start", 1, optional=True, why=" (null: frame 100, or the first possible)")
    need_int(cfg.steps, "steps", 1)
    need_int(cfg.fps, "fps", 1, why=" (frames per second of the file)")
    fmt = output_format(cfg)
    if fmt == "vtk" and cfg.out is not None and Path(str(cfg.out)).suffix:
        raise ConfigError("out", cfg.out, "with format=vtk a folder (no suffix): the .pvd "
                          "series and their .vtp frames are written in it")
    if fmt != "vtk" and cfg.out is not None and Path(str(cfg.out)).suffix != f".{fmt}":
        raise ConfigError("out", cfg.out, f"a .{fmt} file (format={fmt})" if cfg.get("format")
                          else "a .gif or .mp4 file, or a folder with format=vtk")
    return resolve_run(str(cfg.ckpt), cfg.get("run_config"))


def output_format(cfg: Any) -> str:
    """``format``, or null: the suffix of ``out`` (.gif, .mp4), else gif."""
    fmt = cfg.get("format")
    if fmt is None:
        suffix = Path(str(cfg.out)).suffix.lstrip(".") if cfg.out is not None else ""
        return suffix if suffix in ("gif", "mp4") else "gif"
    if fmt not in FORMATS:
        raise ConfigError("format", fmt, f"choose one of {list(FORMATS)} (null: from out)")
    return str(fmt)


def vtk_fields(model: Any, dataset: Any, sim: int, start: int, result: dict[str, Any],
               ) -> tuple[dict[str, Any], dict[str, Any], str]:
    """The per-particle fields of the true and the predicted series, and a line on the
    masses: velocity (backward differences; the window's last for the first frame), type,
    radius, the mass posterior of the recorded frames 0 .. ``start`` (median and log-spread,
    ``bgn.api.MassPosterior``) where the model infers masses, and the predicted frames'
    distance to the truth."""
    import numpy as np

    from bgn.api import Model
    from bgn.model.newton import pair_force_head_of
    from bgn.rollout import true_positions

    radii, types = dataset.file.read("radii", sim), dataset.file.read("types", sim)
    shared: dict[str, Any] = {"type": np.asarray(types, dtype=np.int32),
                              "radius": np.asarray(radii, dtype=np.float64)}
    note = "no masses inferred (the model has neither an inverse model nor a pair law)"
    head = pair_force_head_of(model)  # per-type masses fit nothing to the frames
    infers = model.has_inverse or (head is not None and head.mass_law != "type")
    recorded = true_positions(dataset, [sim], 0, start)[0]
    if infers and len(recorded) <= model.history + 2:
        note = f"no masses inferred (frame {start} leaves no window before the start)"
    elif infers:
        posterior = Model(model, dataset.dt, dataset.margin).infer(recorded, radii=radii,
                                                                     types=types)
        shared["mass_posterior_median"] = posterior.median()
        shared["mass_posterior_log_std"] = posterior.log_std()
        note = f"masses: {posterior.describe()}"
    before = true_positions(dataset, [sim], start - 1, start)[0, 0]

    def velocity(x: Any) -> Any:
        return np.diff(np.concatenate([before[None], x]), axis=0) / dataset.dt

    true, predicted = result["true"], result["predicted"]
    error = np.linalg.norm(predicted - true[:len(predicted)], axis=-1)
    return ({**shared, "velocity": velocity(true)},
            {**shared, "velocity": velocity(predicted), "error": error}, note)


def _run_name(given: str, ckpt: Path) -> str:
    """The default file's stem: the run folder's name (a checkpoint's: its run's)."""
    path = Path(given).expanduser()
    if path.is_dir():
        return path.resolve().name
    return ckpt.resolve().parent.parent.name


@cli("render", validate_render, positional="ckpt")  # bad input: one line, exit 2
def main(cfg: Any) -> Path:
    """Roll the model out and write the animation; returns its path."""
    from bgn.data.datamodule import ParticleDataModule
    from bgn.figures import rollout_animation
    from bgn.rollout import REFERENCE_START, rollout
    from bgn.training.checkpoints import resolve_run
    from bgn.training.module import load_model

    ckpt, _, config = resolve_run(str(cfg.ckpt), cfg.get("run_config"))
    run_cfg = OmegaConf.load(config)
    data_dir = cfg.paths.data_dir or OmegaConf.select(run_cfg, "paths.data_dir", default="data")
    model = load_model(ckpt).model  # an unusable checkpoint fails before any data are made
    datamodule = ParticleDataModule(run_cfg.dataset, run_cfg.fps, data_dir)
    datamodule.prepare_data()
    datamodule.setup()
    dataset = datamodule.datasets[cfg.split]
    n_sims = dataset.file.n_sims
    if cfg.sim >= n_sims:
        raise ConfigError("sim", cfg.sim, f"the {cfg.split} split has {n_sims} simulations "
                          f"(0..{n_sims - 1})")
    start = cfg.start
    if start is None:
        start = min(REFERENCE_START, max(dataset.history + 1,
                                         dataset.file.n_frames - 1 - cfg.steps))
    result = rollout(model, dataset, int(cfg.sim), int(start), int(cfg.steps))
    fmt = output_format(cfg)
    stem = f"{_run_name(str(cfg.ckpt), ckpt)}_{cfg.split}{cfg.sim}"
    if fmt == "vtk":
        from bgn.paraview import write_series

        folder = Path(cfg.out) if cfg.out else Path("outputs/render") / stem
        true_fields, predicted_fields, note = vtk_fields(model, dataset, int(cfg.sim),
                                                         int(start), result)
        t0 = start * dataset.dt
        write_series(folder, "truth", result["true"], dataset.dt, true_fields, t0)
        path = write_series(folder, "predicted", result["predicted"], dataset.dt,
                            predicted_fields, t0)
        print(f"{len(result['predicted']) - 1} steps from frame {start} of {cfg.split} "
              f"simulation {cfg.sim} as VTK series (open {path} and {folder / 'truth.pvd'} "
              f"in ParaView); {note}")
        return path
    out = Path(cfg.out) if cfg.out else Path("outputs/render") / f"{stem}.{fmt}"
    path = rollout_animation(result, out, fps=int(cfg.fps))
    print(f"{len(result['predicted']) - 1} steps from frame {start} of {cfg.split} "
          f"simulation {cfg.sim}: {path}")
    return path
