"""Samples, windows, targets, edges and batches of the DataModule."""

import numpy as np
import pytest
import torch

from bgn.data.datamodule import ParticleDataModule
from bgn.data.targets import step
from bgn.graph import collate


def _datamodule(cfg, **kw):
    dm = ParticleDataModule(cfg.dataset, cfg.fps, cfg.paths.data_dir, generate_workers=1,
                            show_progress=False, **kw)
    dm.prepare_data()
    dm.setup()
    return dm


@pytest.mark.parametrize("scene", ["spring", "collisions"])
def test_sample_window_and_target_match_the_file(small_cfg, scene):
    dm = _datamodule(small_cfg(scene, "dataset.history=3"))
    ds = dm.datasets["train"]
    g = ds[7]
    sim, t = int(g.sim), int(g.frame)
    x = ds.file.read("positions", sim)
    dt = ds.dt
    n, d = x.shape[1:]
    assert g.vel.shape == (n, 4, d)
    for lag in range(4):  # newest first: v[t - lag] = (x[t-lag] - x[t-lag-1]) / dt
        expected = (x[t - lag] - x[t - lag - 1]) / dt
        np.testing.assert_allclose(g.vel[:, lag].numpy(), expected, rtol=1e-5, atol=1e-5)
    nxt, _ = step(x[t], (x[t] - x[t - 1]) / dt, g.target.double().numpy(), dt, ds.meta.target)
    np.testing.assert_allclose(nxt, x[t + 1], atol=1e-4 * max(1.0, np.abs(x).max()))
    snd, rcv = g.edge_index
    log_m = np.log(ds.file.read("masses", sim))
    np.testing.assert_allclose(g.edge_rel_log_mass.numpy(), log_m[rcv] - log_m[snd], atol=1e-6)


def test_first_and_last_samples_stay_inside_the_simulation(small_cfg):
    dm = _datamodule(small_cfg("spring", "dataset.history=5"))
    ds = dm.datasets["val"]
    first, last = ds.locate(0), ds.locate(len(ds) - 1)
    assert first == (0, 6) and last == (ds.file.n_sims - 1, ds.file.n_frames - 2)
    assert len(ds) == ds.file.n_sims * (ds.file.n_frames - 7)
    with pytest.raises(IndexError):
        ds.locate(len(ds))


def test_collision_contact_targets_are_recorded_contacts(small_cfg):
    dm = _datamodule(small_cfg("collisions"))
    ds = dm.datasets["train"]
    contacts = {tuple(r) for r in ds.file.read("contacts", ...).tolist()}
    found = 0
    for i in range(len(ds)):
        g = ds[i]
        s, t = int(g.sim), int(g.frame)
        snd, rcv = g.edge_index.tolist()
        for a, b, c in zip(snd, rcv, g.edge_contact.tolist()):
            assert c == float((s, t, min(a, b), max(a, b)) in contacts)
            found += c
    assert found > 0
    assert g.wall is not None and g.wall.shape == (30, 4)


def test_force_contact_target_is_pairwise_force(small_cfg):
    dm = _datamodule(small_cfg("spring"))
    g = dm.datasets["train"][0]
    snd, rcv = g.edge_index
    assert g.edge_index.shape[1] == 12  # full graph of 4 bodies
    # spring: |dphi/ds| = 2 |s - 1| with s = r + 0.01
    r = (g.pos[rcv] - g.pos[snd]).norm(dim=1)
    torch.testing.assert_close(g.edge_contact, 2 * (r + 0.01 - 1).abs(), rtol=1e-4, atol=1e-5)


def test_batches_are_disjoint_unions(small_cfg):
    dm = _datamodule(small_cfg("collisions"))
    ds = dm.datasets["train"]
    parts = [ds[0], ds[5], ds[len(ds) - 1]]
    b = collate(parts)
    assert b.num_graphs == 3 and b.pos.shape[0] == sum(p.pos.shape[0] for p in parts)
    offset = 0
    start = 0
    for gi, p in enumerate(parts):
        e = p.edge_index.shape[1]
        assert torch.equal(b.edge_index[:, start:start + e], p.edge_index + offset)
        assert (b.batch[offset:offset + p.pos.shape[0]] == gi).all()
        offset += p.pos.shape[0]
        start += e
    batch = next(iter(dm.train_dataloader()))
    assert batch.num_graphs == dm.batch_size
    assert (batch.edge_index[0] != batch.edge_index[1]).all()
    assert (batch.batch[batch.edge_index[0]] == batch.batch[batch.edge_index[1]]).all()


def test_splits_by_simulation_and_train_sims(small_cfg):
    dm = _datamodule(small_cfg("spring", "dataset.n_sims=3", "+dataset.train_sims=1"))
    assert {dm.datasets["train"].locate(i)[0] for i in range(len(dm.datasets["train"]))} == {0}
    train_x = dm.datasets["train"].file.read("positions", ...)
    test_x = dm.datasets["test"].file.read("positions", ...)
    for a in train_x[:, 0]:
        for b in test_x[:, 0]:
            assert not np.allclose(a, b)


def test_stats_come_from_training_split(small_cfg):
    dm = _datamodule(small_cfg("gravity_r2"))
    stats = dm.stats()
    for name in ("velocity", "target", "log_mass", "rel_position", "rel_velocity", "contact",
                 "rel_log_mass"):
        for key in ("mean", "std", "median", "robust_scale"):
            assert np.isfinite(stats[name][key]).all(), (name, key)
        assert (stats[name]["std"] >= 0).all()
    y = np.moveaxis(np.stack([np.diff(x, 2, axis=0) for x in dm.datasets["train"].file.read(
        "positions", ...)]) / dm.dt**2, 1, 0)  # targets (T-2, S, N, D)
    for name, n in (("target_diff1", 1), ("target_diff2", 2)):
        np.testing.assert_allclose(stats[name]["std"],
                                   np.diff(y, n, axis=0).reshape(-1, 2).std(0), rtol=1e-8)
    x = dm.datasets["train"].file.read("positions", ...)
    v = np.diff(x, axis=1) / dm.dt
    np.testing.assert_allclose(stats["velocity"]["mean"], v.reshape(-1, 2).mean(0), rtol=1e-10)
    with pytest.raises(Exception, match="only train files"):
        dm.datasets["val"].file.stats()


def test_validation_subset_spreads_over_all_simulations(small_cfg):
    dm = _datamodule(small_cfg("spring", "dataset.n_sims=3", "dataset.val_samples=7",
                               "dataset.batch_size=100"))
    loader = dm.val_dataloader()
    (g,) = list(loader)
    assert g.num_graphs == 7
    assert set(g.sim.tolist()) == {0, 1, 2}  # not a prefix of the split
    assert len(dm.test_dataloader().dataset) == len(dm.datasets["test"])  # fewer: whole split
    capped = _datamodule(small_cfg("spring", "dataset.n_sims=3", "dataset.test_samples=5",
                                   "dataset.batch_size=100"))
    (g,) = list(capped.test_dataloader())
    assert g.num_graphs == 5 and set(g.sim.tolist()) == {0, 1, 2}


def test_datamodule_rejects_bad_values(small_cfg):
    with pytest.raises(ValueError, match="train_sims"):
        ParticleDataModule(small_cfg("spring", "+dataset.train_sims=5").dataset, 50)
    with pytest.raises(ValueError, match="val_samples"):
        ParticleDataModule(small_cfg("spring", "dataset.val_samples=0").dataset, 50)
    with pytest.raises(ValueError, match="test_samples"):
        ParticleDataModule(small_cfg("spring", "dataset.test_samples=0").dataset, 50)
    with pytest.raises(ValueError, match="batch_size"):
        ParticleDataModule(small_cfg("spring", "dataset.batch_size=0").dataset, 50)


def test_a_larger_split_keeps_the_runs_simulations_and_its_training_file(small_cfg):
    """``larger_split``: the run's simulations first, bit for bit, then new ones; a
    radius-graph scene's val and test take the training file's margin, so the run's training
    file is read, not a larger one made; a count below 1 is refused."""
    from bgn.coerce import ConfigError

    dm = _datamodule(small_cfg("collisions"))
    data_dir = dm.datasets["train"].file.path.parent
    files = set(data_dir.glob("*.h5"))
    test = dm.datasets["test"]
    larger = dm.larger_split("test", test.file.n_sims + 1)
    assert larger.file.n_sims == test.file.n_sims + 1
    for sim in range(test.file.n_sims):
        np.testing.assert_array_equal(larger.file.read("positions", sim),
                                      test.file.read("positions", sim))
    assert set(data_dir.glob("*.h5")) - files == {larger.file.path}   # no other file made
    assert larger.margin == test.margin
    with pytest.raises(ConfigError, match="sims"):
        dm.larger_split("test", 0)
