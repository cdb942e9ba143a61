"""The learned-simulator layer: graphs as the data builds them, oracle rollouts that reproduce
the recorded frames in every scene, failures counted, batches equal to single simulations."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from bgn.data.targets import targets
from bgn.model import build_model
from bgn.rollout import evaluate_rollouts, particles, rollout, simulator, true_positions

SCENES = ["spring", "gravity_r1", "gravity_r2", "collisions"]


@pytest.fixture(scope="module")
def datasets(small_datamodules):
    """The small val split of every scene (generated once per session)."""
    out = {}
    for scene in SCENES:
        dm = small_datamodules[scene]
        out[scene] = dm.datasets["val"]
        out[scene].train_stats = dm.stats()
    return out


class Oracle(torch.nn.Module):
    """A model that predicts the recorded target of every frame it is asked about (by the
    graph's simulation and frame index), in float64; ``poison`` = (sim, frame) from which it
    predicts inf for that simulation."""

    def __init__(self, ds, poison: tuple[int, int] | None = None) -> None:
        super().__init__()
        self.meta, self.history, self.ds, self.poison = ds.meta, ds.history, ds, poison

    def predict(self, g):
        out = []
        for s, t in zip(g.sim.tolist(), g.frame.tolist()):
            x = self.ds.file.read("positions", (s, slice(t - 1, t + 2)))
            y = targets(x, self.ds.dt, self.meta.target)[0]
            if self.poison is not None and s == self.poison[0] and t >= self.poison[1]:
                y = y * np.inf
            out.append(y)
        return torch.as_tensor(np.concatenate(out))


def start_windows(ds, sims, start):
    k = ds.history
    return torch.as_tensor(true_positions(ds, sims, start - k - 1, start))


@pytest.mark.parametrize("scene", SCENES)
def test_oracle_rollout_reproduces_the_recorded_frames(datasets, scene):
    """The true targets, integrated by the simulator's step rule with the graph rebuilt every
    step, give back every recorded frame of the whole trajectory (two simulations at once)."""
    ds = datasets[scene]
    sims, start = [0, 1], ds.history + 1
    n_steps = ds.file.n_frames - 1 - start
    result = simulator(Oracle(ds), ds).rollout(start_windows(ds, sims, start),
                                               particles(ds, sims), n_steps, start)
    truth = true_positions(ds, sims, start, start + n_steps)
    assert result.positions.shape == truth.shape
    assert not result.failed.any()
    scale = np.abs(truth).max()
    np.testing.assert_allclose(result.positions.numpy(), truth, rtol=0, atol=1e-10 * scale)


@pytest.mark.parametrize("scene", ["spring", "collisions"])
def test_graphs_are_the_training_graphs(datasets, scene):
    """The simulator's graph of a true window is the data layer's training sample, input for
    input (targets and contact labels aside, which a rollout does not know)."""
    ds = datasets[scene]
    index = 7
    sim, t = ds.locate(index)
    g = simulator(Oracle(ds), ds).graph(start_windows(ds, [sim], t), particles(ds, [sim]), t)
    ref = ds[index]
    for name in ("pos", "vel", "edge_index", "mass", "edge_rel_log_mass", "types", "radius",
                 "batch", "num_nodes", "sim", "frame", "dt"):
        torch.testing.assert_close(getattr(g, name), getattr(ref, name), rtol=0, atol=0,
                                   msg=name)
    assert (g.wall is None) == (ref.wall is None)
    if ref.wall is not None:
        torch.testing.assert_close(g.wall, ref.wall, rtol=0, atol=0)


def test_a_failed_rollout_is_counted_and_the_others_go_on(datasets):
    ds = datasets["spring"]
    sims, start = [0, 1], ds.history + 1
    result = simulator(Oracle(ds, poison=(0, start + 3)), ds).rollout(
        start_windows(ds, sims, start), particles(ds, sims), 10, start)
    assert result.first_non_finite.tolist() == [4, -1]
    assert result.failed.tolist() == [True, False]
    assert torch.isnan(result.positions[0, 4:]).all()
    assert torch.isfinite(result.positions[0, :4]).all()
    np.testing.assert_allclose(result.positions[1].numpy(),
                               true_positions(ds, [1], start, start + 10)[0], atol=1e-9)
    # the single-simulation wrapper stops before the bad frame and says where it was
    single = rollout(Oracle(ds, poison=(0, start + 3)), ds, sim=0, start=start, n_steps=10)
    assert int(single["first_non_finite"]) == 4
    assert len(single["predicted"]) == len(single["true"]) == 4
    assert np.isfinite(single["predicted"]).all()


@pytest.mark.parametrize("scene,mass_law", [("spring", "inertial"), ("gravity_r1", "source")])
def test_a_held_mass_fit_is_the_first_windows_kept_along_the_rollout(datasets, scene, mass_law):
    """``rollout_masses=held``: the masses are fitted once, to each rollout's first window
    (the first frame is the window mode's, bit for bit), then kept: no refit from predicted
    frames, each simulation its own row (batch = alone), also after another one failed."""
    ds = datasets[scene]
    torch.manual_seed(0)
    model = build_model({"name": "bgn", "dynamics": "newton", "mass_law": mass_law,
                         "hidden": 16, "decoder_hidden": 16, "flow_hidden": 16,
                         "rollout_masses": "held"}, ds.meta, ds.train_stats, ds.history).eval()
    head, fit = model.force_head, model.force_head.fit
    calls = []
    head.fit = lambda g, terms: calls.append(g.num_graphs) or fit(g, terms)
    sim_, start, steps = simulator(model, ds), ds.history + 1, 5
    windows, parts = start_windows(ds, [0, 1], start), particles(ds, [0, 1])
    held = sim_.rollout(windows, parts, steps, start)
    assert calls == [2]                          # one fit, of both first windows together
    head.rollout_masses = "window"
    calls.clear()
    refit = sim_.rollout(windows, parts, steps, start)
    assert calls == [2] * steps                  # a refit at every step
    assert torch.equal(held.positions[:, 1], refit.positions[:, 1])
    assert not torch.equal(held.positions[:, -1], refit.positions[:, -1])
    head.rollout_masses = "held"
    assert f"masses {mass_law} held" in model.label and "held" in model.physics
    for b in (0, 1):
        alone = sim_.rollout(start_windows(ds, [b], start), particles(ds, [b]), steps, start)
        torch.testing.assert_close(held.positions[b], alone.positions[0], rtol=1e-6, atol=1e-9)
    # simulation 0 fails from its third step: simulation 1 keeps its own held masses
    predict = model.predict
    model.predict = lambda g: predict(g) * torch.where(
        (g.sim[g.batch] == 0) & (g.frame[g.batch] >= start + 2), np.inf, 1.0)[:, None]
    failed = sim_.rollout(windows, parts, steps, start)
    assert failed.first_non_finite.tolist() == [3, -1]
    torch.testing.assert_close(failed.positions[1], held.positions[1], rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("scene", ["spring", "collisions"])
@pytest.mark.parametrize("name", ["bgn", "gns"])
def test_a_model_rolls_out_the_same_alone_and_in_a_batch(datasets, scene, name):
    """Batching simulations changes nothing, and a rollout is next_frame applied repeatedly."""
    ds = datasets[scene]
    torch.manual_seed(0)
    small = ({"hidden": 16, "decoder_hidden": 16, "flow_hidden": 16} if name == "bgn"
             else {"latent": 16, "mlp_hidden": 16, "message_passing_steps": 2})
    model = build_model({"name": name, **small}, ds.meta, ds.train_stats, ds.history).eval()
    sim_, start = simulator(model, ds), ds.history + 1
    batch = sim_.rollout(start_windows(ds, [0, 1], start), particles(ds, [0, 1]), 4, start)
    for b in (0, 1):
        alone = sim_.rollout(start_windows(ds, [b], start), particles(ds, [b]), 4, start)
        torch.testing.assert_close(batch.positions[b], alone.positions[0], rtol=1e-6,
                                   atol=1e-9)
    with torch.no_grad():
        first = sim_.next_frame(start_windows(ds, [0, 1], start), particles(ds, [0, 1]), start)
    torch.testing.assert_close(batch.positions[:, 1], first)
    assert not torch.equal(first, batch.positions[:, 0])  # it moved


def test_bad_windows_are_one_clear_error(datasets):
    ds = datasets["spring"]
    sim_ = simulator(Oracle(ds), ds)
    with pytest.raises(ValueError, match="history \\+ 2"):
        sim_.graph(torch.zeros(1, 3, 4, 2, dtype=torch.float64), particles(ds, [0]))
    with pytest.raises(ValueError, match="particles are"):
        sim_.graph(start_windows(ds, [0, 1], ds.history + 1), particles(ds, [0]))


def test_rollout_metrics_of_an_oracle_are_zero_and_a_poisoned_model_fails(datasets):
    """Through the evaluation: the oracle's rollout error is zero to round-off, the
    references' is not, and a model that blows up in one of two simulations counts as half
    the rollouts failed."""
    ds = datasets["gravity_r2"]
    out = evaluate_rollouts(Oracle(ds), ds, n_steps=30)
    assert out["rollout/rollouts"] == 2 and out["rollout/rollout_steps"] == 30
    assert out["rollout/failed_share"] == 0
    for key in ("pos_err_mean@1", "pos_err_median@10", "pos_err_mean@all", "pos_mse_mean@all",
                "momentum_err@all"):
        assert out[f"rollout/{key}"] < 1e-9, key
    assert out["rollout/energy_err@all"] == pytest.approx(out["rollout/energy_err_truth@all"],
                                                          abs=1e-9)
    assert out["rollout_last/pos_err_mean@all"] > 1e-6
    assert out["rollout_linear/pos_err_mean@all"] > 0
    # the chaos floor: the exact simulator from positions 1e-6 off stays near 1e-6 early on
    assert 1e-8 < out["predictability/pos_err_mean@1"] < 1e-5
    assert out["predictability/pos_err_mean@all"] >= out["predictability/pos_err_mean@1"] * 0.1
    start = ds.history + 1
    poisoned = evaluate_rollouts(Oracle(ds, poison=(0, start + 2)), ds, n_steps=30,
                                 references=False)
    assert poisoned["rollout/failed_share"] == 0.5
    assert "rollout_last/pos_err_mean@1" not in poisoned


# ----------------------------------------------------------------------------- periodic boxes
BOX, REACH, STIFFNESS = 4.0, 1.0, 40.0


def soft_repulsion(dx: np.ndarray | torch.Tensor, masses, receivers, n: int):
    """Accelerations of a soft repulsion ``k (R - r) u`` within R from minimum-image edge
    vectors ``dx`` (E, D), summed at the receivers (numpy or torch alike)."""
    r = (dx**2).sum(-1) ** 0.5
    f = STIFFNESS * (REACH - r) * (r < REACH) / r
    pull = f[:, None] * dx
    if isinstance(dx, torch.Tensor):
        return torch.zeros(n, dx.shape[1], dtype=dx.dtype).index_add(0, receivers, pull) \
            / masses[:, None]
    out = np.zeros((n, dx.shape[1]))
    np.add.at(out, receivers, pull)
    return out / masses[:, None]


class PairLaw(torch.nn.Module):
    """The scene's own law on the graph the simulator builds: edge vectors by the minimum
    image, neighbours within the reach (on the torus when the meta says so)."""

    def __init__(self, meta, history: int) -> None:
        super().__init__()
        self.meta, self.history = meta, history

    def predict(self, g):
        from bgn.model.message_passing import edge_vector
        return soft_repulsion(edge_vector(g.pos, g), g.mass, g.edge_index[1], len(g.pos))


@pytest.fixture(scope="module")
def torus(tmp_path_factory):
    """A soft-disc gas on a periodic box simulated here (Stormer-Verlet at the frame spacing,
    so the finite-difference acceleration is the law's exactly), recorded wrapped into the box
    as an engine writes it, imported with bgn.data.from_arrays."""
    from bgn.data import from_arrays
    from bgn.data.dataset import FrameDataset
    from bgn.data.edges import minimum_image, radius_graph
    from bgn.data.files import DatasetFile

    rng = np.random.default_rng(0)
    s, t, n, dt = 3, 30, 16, 0.02
    period = np.array([BOX, BOX])
    x = np.empty((s, t, n, 2))
    masses = rng.uniform(0.5, 2.0, (s, n))
    for i in range(s):
        grid = np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(-1, 2)
        x[i, 0] = (grid + 0.5 + rng.uniform(-0.2, 0.2, (n, 2))) * BOX / 4
        x[i, 1] = x[i, 0] + dt * rng.normal(0, 2.0, (n, 2))
        for k in range(1, t - 1):
            snd, rcv = radius_graph(x[i, k], cutoff=REACH, period=period)
            dx = minimum_image(x[i, k][rcv] - x[i, k][snd], period)
            x[i, k + 1] = 2 * x[i, k] - x[i, k - 1] + dt**2 * soft_repulsion(
                dx, masses[i], rcv, n)
    paths = from_arrays(x % BOX, dt, masses=masses, box=BOX, periodic=True, name="torus",
                        data_dir=tmp_path_factory.mktemp("torus"), connectivity_radius=REACH,
                        splits={"train": [0], "val": [1], "test": [2]}, history=3)
    return FrameDataset(DatasetFile(paths["val"]), history=3), x[1], DatasetFile(paths["train"])


def test_a_periodic_import_rolls_out_its_recorded_frames_with_its_own_law(torus):
    """The learned simulator, the scene's law as its model, rebuilds the torus's radius graph
    every step and gives back the recorded frames; the same law on a graph that ignores the
    boundary does not (pairs across it interact here)."""
    from dataclasses import replace

    from bgn.simulator import LearnedSimulator

    ds, unwrapped, _ = torus
    assert ds.meta.period == (BOX, BOX) and ds.meta.graph == "radius"
    start = ds.history + 1
    n_steps = ds.file.n_frames - 1 - start
    truth = true_positions(ds, [0], start, start + n_steps)
    turns = (truth[0] - unwrapped[start:]) / BOX                  # the importer's unwrapping
    np.testing.assert_allclose(turns, np.rint(turns), atol=1e-9)

    def roll(meta):
        sim = LearnedSimulator(PairLaw(meta, ds.history), ds.dt, ds.margin, torch.float64)
        return sim.rollout(start_windows(ds, [0], start), particles(ds, [0]), n_steps,
                           start).positions.numpy()

    np.testing.assert_allclose(roll(ds.meta), truth, rtol=0, atol=1e-9 * BOX)
    assert np.abs(roll(replace(ds.meta, period=None)) - truth).max() > 1e-3 * BOX


def test_periodic_graphs_are_the_training_graphs(torus):
    ds, _, train = torus
    # the normalisation's edge vectors are minimum images too: none longer than the reach
    stats = train.stats()["rel_position"]
    assert (stats["max"] <= REACH).all() and (stats["min"] >= -REACH).all()
    assert (stats["max"] > 0.9 * REACH).all()
    for index in (0, len(ds) // 2, len(ds) - 1):
        sim, t = ds.locate(index)
        g = simulator(PairLaw(ds.meta, ds.history), ds).graph(start_windows(ds, [sim], t),
                                                              particles(ds, [sim]), t)
        ref = ds[index]
        for name in ("pos", "vel", "edge_index", "period"):
            torch.testing.assert_close(getattr(g, name), getattr(ref, name), rtol=0, atol=0,
                                       msg=name)
        # the recorded target is the law's acceleration on these edges
        torch.testing.assert_close(PairLaw(ds.meta, ds.history).predict(ref.to("cpu")).float(),
                                   ref.target, rtol=1e-4, atol=1e-4)
