"""Rollout animations: the file written by ``python -m bgn.render`` and the animated image in
TensorBoard."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from PIL import Image

from bgn.figures import rollout_animation
from bgn.studies.render import main
from bgn.training.checkpoints import CheckpointError
from bgn.training.module import add_animation, load_model
from bgn.training.run import train
from tests.conftest import NETWORK_LAW, SMALL, compose_config
from tests.test_paraview import read_vtp


def fake_result(steps: int = 12, n: int = 5, box: float | None = None) -> dict:
    rng = np.random.default_rng(0)
    true = np.cumsum(rng.normal(scale=0.1, size=(steps + 1, n, 2)), axis=0) + 2.0
    return {"true": true, "predicted": true + 0.01 * np.arange(steps + 1)[:, None, None],
            "box": np.array(np.nan if box is None else box)}


@pytest.mark.parametrize("box", [None, 4.0])
def test_animation_is_a_gif_with_every_step(tmp_path: Path, box):
    path = rollout_animation(fake_result(box=box), tmp_path / "a.gif")
    with Image.open(path) as gif:
        assert gif.format == "GIF" and gif.n_frames == 13


def test_animation_refuses_other_formats(tmp_path: Path):
    with pytest.raises(ValueError, match="gif or an .mp4"):
        rollout_animation(fake_result(), tmp_path / "a.png")


def test_animation_lands_in_tensorboard(tmp_path: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(tmp_path))
    add_animation(writer, "val/rollout_animation", fake_result(), step=3)
    writer.close()
    events = EventAccumulator(str(tmp_path)).Reload()
    (image,) = events.Images("val/rollout_animation")
    assert image.step == 3 and image.encoded_image_string[:3] == b"GIF"


def test_render_command_animates_a_trained_checkpoint(tmp_path: Path, shared_data_dir: Path,
                                                      capsys):
    run = tmp_path / "run"
    cfg = compose_config("train", ["dataset=spring", *SMALL["spring"],
                                   f"paths.data_dir={shared_data_dir}",
                                   f"paths.output_dir={run}", "model.hidden=16", NETWORK_LAW,
                                   "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
                                   "trainer.limit_val_batches=1", "test=false",
                                   "figures=false", "val_rollout_steps=0"])
    train(cfg)
    (run / ".hydra").mkdir()
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")  # as Hydra writes it for a real run
    out = main([str(run / "checkpoints" / "last.ckpt"), "steps=6", "sim=1",
                f"out={tmp_path / 'r.gif'}"])
    with Image.open(out) as gif:
        assert gif.n_frames == 7
    # format=vtk: the truth and the rollout as VTK series, with the per-particle fields
    pvd = main([str(run), "steps=6", "sim=1", "format=vtk", f"out={tmp_path / 'vtk'}"])
    assert pvd == tmp_path / "vtk" / "predicted.pvd" and (tmp_path / "vtk" / "truth.pvd").is_file()
    _, arrays = read_vtp(sorted((tmp_path / "vtk" / "predicted").glob("*.vtp"))[-1])
    assert {"velocity", "type", "radius", "error", "mass_posterior_median"} <= set(arrays)
    assert len(sorted((tmp_path / "vtk" / "truth").glob("*.vtp"))) == 7
    lone = tmp_path / "elsewhere" / "checkpoints" / "x.ckpt"
    lone.parent.mkdir(parents=True)
    shutil.copy(run / "checkpoints" / "last.ckpt", lone)
    for args, expected in (([str(lone)], "no run config"),
                           ([str(tmp_path / "missing.ckpt")], "no such file"),
                           ([str(run), "sim=2"], "sim=2"), ([str(run), "--sim", "1"], "sim="),
                           ([str(run), "format=vtk", "out=x.gif"], "folder"),
                           ([str(run), "format=png"], "format='png'"),
                           ([str(run), "out=x.vtp"], "out='x.vtp'")):
        with pytest.raises(SystemExit) as done:
            main(args)
        assert done.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and expected in err, err
    # weights of an older model (as the impulse head's unit buffers, dropped since): one error
    older = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)
    older["state_dict"]["model.node_encoder.length_scale"] = torch.tensor(1.0)
    torch.save(older, tmp_path / "older.ckpt")
    with pytest.raises(CheckpointError, match="does not fit this version of bgn's bgn") as err:
        load_model(tmp_path / "older.ckpt")
    assert "retrain" in str(err.value) and "\n" not in str(err.value)
