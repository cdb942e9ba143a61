"""Unrolled training (bgn.training.unroll): samples carry the true future, an oracle's unrolled
steps are the dataset's own next samples, and the unrolled loss trains every model."""

import pytest
import torch

from bgn.data.datamodule import ParticleDataModule
from bgn.graph import collate
from bgn.model import build_model
from bgn.training.unroll import advance, unrolled_loss

UNROLL = 3


def _datasets(cfg):
    """The train split with and without unrolled futures (same file)."""
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, generate_workers=1,
                            show_progress=False)
    dm.prepare_data()
    dm.setup()
    plain = dm.datasets["train"]
    unrolled = type(plain)(plain.file, plain.history, unroll=UNROLL)
    return plain, unrolled


@pytest.mark.parametrize("scene", ["spring", "collisions"])
def test_an_oracles_unrolled_steps_are_the_next_samples(small_cfg, scene):
    plain, unrolled = _datasets(small_cfg(scene, "dataset.history=2"))
    assert len(unrolled) == len(plain) - UNROLL * plain.file.n_sims
    index = 5
    g = unrolled[index]
    assert g.future_vel.shape == (g.pos.shape[0], UNROLL, g.pos.shape[1])
    for s in range(UNROLL):
        g = advance(g, g.target, plain.meta.target, s)   # the oracle steps with the truth
        truth = plain[index + s + 1]
        assert int(g.frame) == int(truth.frame)
        torch.testing.assert_close(g.pos, truth.pos, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(g.vel, truth.vel, atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(g.target, truth.target, atol=1e-3, rtol=1e-4)
        if truth.wall is not None:
            torch.testing.assert_close(g.wall, truth.wall, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("name", ["bgn", "gns", "cranmer_gn"])
def test_unrolled_loss_is_finite_and_trains_every_model(small_cfg, name):
    plain, unrolled = _datasets(small_cfg("spring", "dataset.history=2"))
    torch.manual_seed(0)
    model = build_model({"name": name}, plain.meta, plain.file.stats(), plain.history)
    g = collate([unrolled[i] for i in range(0, 40, 5)])
    loss = unrolled_loss(model, g, model(g))
    assert torch.isfinite(loss) and loss > 0
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_unrolled_loss_without_future_names_the_setting(small_cfg):
    plain, _ = _datasets(small_cfg("spring", "dataset.history=2"))
    model = build_model({"name": "bgn"}, plain.meta, plain.file.stats(), plain.history)
    g = plain[0]
    with pytest.raises(ValueError, match="dataset.unroll"):
        unrolled_loss(model, g, model(g))
    with pytest.raises(ValueError, match="dataset.unroll"):
        type(plain)(plain.file, plain.history, unroll=-1)
