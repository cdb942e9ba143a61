"""The pair-force head with couplings of either sign (``mass_law=coupling``, bgn.model.newton):
fitted per simulation over a batch's windows, held in a rollout from the frames before its
start (bgn.simulator), on trajectories of charged bodies with the true law written in."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from bgn.data import from_arrays
from bgn.data.dataset import FrameDataset
from bgn.data.files import DatasetFile
from bgn.graph import collate
from bgn.model import build_model
from bgn.model.coupling import simulation_system
from bgn.rollout import rollout_many
from bgn.sim.nbody import NBodyScene
from bgn.sim.scene import State

DT, FRAMES, N = 0.02, 160, 4
# the law that made the frames: like charges repel with 1 / (r + 0.01)^2 (bgn.sim.nbody)
TRUE_LAW = json.dumps([{"types": [0, 0], "terms": [
    {"kind": "shifted", "power": -2.0, "a": 1.0, "c": 0.01}]}])


def charged(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (T, N, 2) of one simulation of charged bodies, its masses and charges."""
    scene = NBodyScene("r2", n_particles=N)
    rng = np.random.default_rng(seed)
    state = scene.draw_state(rng)
    charges = rng.choice([-1.0, 1.0], N) * np.exp(0.5 * rng.standard_normal(N))
    traj = scene.simulate_from(State(state.positions, state.velocities, state.masses,
                                     charges=charges), np.arange(FRAMES) * DT)
    return traj.positions, state.masses, charges


@pytest.fixture(scope="module")
def charged_data(tmp_path_factory) -> tuple[dict[str, FrameDataset], list[tuple]]:
    """Five charged simulations imported without masses or charges: 3 train, 1 val, 1 test."""
    sims = [charged(seed) for seed in range(5)]
    root = Path(tmp_path_factory.mktemp("charged"))
    paths = from_arrays(np.stack([s[0] for s in sims]), DT, name="charged",
                        data_dir=root / "data",
                        splits={"train": [0, 1, 2], "val": [3], "test": [4]})
    data = {split: FrameDataset(DatasetFile(path), history=5) for split, path in paths.items()}
    return data, sims


def true_law_model(ds: FrameDataset, train: FrameDataset) -> torch.nn.Module:
    return build_model({"name": "newton", "mass_law": "coupling", "law": "formula",
                        "law_formula": TRUE_LAW}, ds.meta, train.file.stats(),
                       ds.history).double()


def double(g):
    from dataclasses import fields, replace
    return replace(g, **{f.name: getattr(g, f.name).double() for f in fields(g)
                         if torch.is_tensor(getattr(g, f.name))
                         and getattr(g, f.name).is_floating_point()})


def windows(ds: FrameDataset, sim: int, frames: range) -> list:
    return [ds[sim * ds.frames_per_sim + t - ds.history - 1] for t in frames]


def test_the_batches_windows_of_each_simulation_give_its_charges_and_masses(charged_data):
    """Windows of two simulations shuffled into one batch: each simulation's couplings from its
    own windows pooled, the same as from its windows alone and whatever their order; the
    masses c / k and the charges c as the truth's (up to scale and global sign)."""
    data, sims = charged_data
    ds = data["train"]
    model = true_law_model(ds, ds)
    head = model.head
    graphs = windows(ds, 0, range(10, 150, 9)) + windows(ds, 1, range(12, 150, 11))
    order = np.random.default_rng(0).permutation(len(graphs))
    g = double(collate([graphs[i] for i in order]))
    fit = head.fit(g, head.window(g)[1])
    node_sim = g.sim[g.batch]
    for sim in (0, 1):
        alone = double(collate([x for x in graphs if int(x.sim[0]) == sim]))
        own = head.fit(alone, head.window(alone)[1])
        torch.testing.assert_close(fit[node_sim == sim], own, rtol=1e-6, atol=1e-9)
        k, c = own[:N, 0].detach().numpy(), own[:N, 1].detach().numpy()
        _, masses, charges = sims[sim]
        log_m = np.log(c / k)
        np.testing.assert_allclose(log_m - log_m.mean(), np.log(masses) - np.log(masses).mean(),
                                   atol=1e-3)
        unit = charges / np.sqrt((charges**2).mean())
        assert min(np.abs(c - unit).max(), np.abs(c + unit).max()) < 1e-3
    # the fit predicts the batch's targets (finite differences of the recorded frames; a
    # close encounter's few are the frame rate's, not the fit's)
    predicted = head(g)[0].detach()
    rel = ((predicted - g.target).norm(dim=-1) / g.target.norm(dim=-1)).numpy()
    assert np.median(rel) < 1e-3 and np.mean(rel < 1e-2) > 0.9, np.sort(rel)[-10:]


def test_the_system_pads_a_simulation_with_fewer_windows_with_empty_rows(charged_data):
    data, _ = charged_data
    ds = data["train"]
    head = true_law_model(ds, ds).head
    g = double(collate(windows(ds, 0, range(20, 30)) + windows(ds, 2, range(40, 43))))
    past, seen = head.observed_system(g, head.window(g)[1])
    design, target, real, (group, local) = simulation_system(g, past, seen)
    assert design.shape == (2, N, 10 * seen.shape[1] * 2, N) and real.all()
    assert target[1, :, 3 * seen.shape[1] * 2:].abs().sum() == 0      # sim 2: 3 windows
    assert design[1, :, 3 * seen.shape[1] * 2:].abs().sum() == 0
    assert torch.equal(local, torch.arange(N).repeat(13))
    assert torch.equal(group, torch.tensor([0] * 40 + [1] * 12))


def test_a_rollout_holds_the_couplings_of_the_frames_before_its_start(charged_data):
    """The held fit reads windows of the recorded frames up to the start (not one window):
    with the true law the rollout follows the recorded frames; given only its first window
    (no context), the fit of those few frames is what the rollout holds."""
    data, sims = charged_data
    ds = data["test"]
    model = true_law_model(ds, data["train"])
    assert model.held_fit_windows > 1 and "masses coupling held" in model.label
    # frames 60-100 hold no close encounter (one step per frame does not resolve one,
    # whatever the couplings: model.substeps); the fit reads frames 0-60, one of them
    rolled = rollout_many(model, ds, [0], [60], 40)
    err = np.sqrt(((rolled.predicted - rolled.true) ** 2).sum(-1).mean(-1))[0]
    scale = np.sqrt((sims[4][0] ** 2).sum(-1).mean())
    assert (rolled.first_non_finite == -1).all()
    assert err[-1] < 1e-3 * scale, err[-1]
    from bgn.rollout import particles, simulator
    sim = simulator(model, ds)
    context = torch.as_tensor(sims[4][0][None, :101])
    parts = particles(ds, [0])
    held = sim.held(context[:, -7:], parts, 100, context)
    pooled = collate([sim.graph(context[:, e - 6:e + 1], parts, e) for e in range(6, 101)])
    assert held.shape == (1, N, 2)
    alone = sim.held(context[:, -7:], parts, 100, None)
    assert alone.shape == (1, N, 2) and not torch.allclose(alone, held)
    fit = model.head.fit(double(pooled), model.head.window(double(pooled))[1])
    # 32 windows spread over the context (the simulator's float32 graphs) against all 95 of
    # them in float64: the same couplings
    torch.testing.assert_close(held[0], fit[-N:].to(held.dtype), rtol=2e-3, atol=1e-5)
    with pytest.raises(ValueError, match="end with its first window"):
        sim.held(context[:, -7:] + 1, parts, 100, context)


def test_simulation_batches_hold_an_equal_share_of_each_of_their_simulations():
    from bgn.data.datamodule import SimulationBatches

    torch.manual_seed(0)
    sampler = SimulationBatches(n_sims=5, frames_per_sim=40, batch_size=16, per_batch=2)
    batches = list(sampler)
    assert len(batches) == len(sampler) == 12
    seen = []
    for batch in batches:
        sims = [i // 40 for i in batch]
        assert len(batch) == 16 and sorted(set(sims)) == sorted(set(sims))[:2]
        assert len(set(sims)) == 2 and all(sims.count(s) == 8 for s in set(sims))
        seen += batch
    # an epoch draws (about) every window once: no window twice within a simulation's pass
    assert len(set(seen)) >= 0.9 * len(seen)
    assert len(list(SimulationBatches(1, 10, 8, 3))) == 1  # more per batch than simulations


def test_the_law_posterior_reads_masses_through_the_couplings(charged_data):
    """``bgn.eval.law_posterior.fit_simulation`` under the coupling law: the masses ``c / k``
    of one simulation's windows pooled, with small standard deviations."""
    from bgn.eval.law_posterior import fit_simulation

    data, sims = charged_data
    ds = data["train"]
    head = true_law_model(ds, ds).head.float()
    log_mass, log_std = fit_simulation(head, windows(ds, 1, range(10, 150, 4)))
    masses = sims[1][1]
    assert np.isfinite(log_mass).all() and (log_std < 0.05).all(), log_std
    np.testing.assert_allclose(log_mass - log_mass.mean(), np.log(masses) - np.log(masses).mean(),
                               atol=2e-3)


def test_a_coupling_head_is_tuned_on_its_dynamics_loss_where_the_model_trains_a_law_head(
        charged_data):
    """A model that trains its law on the recorded masses (BGN's ``law`` head, the built-in
    gravity scenes' default) with the coupling law, as ``model.dynamics=auto``'s coupling
    candidate there: the law has no recorded couplings to train with, so the formula stage
    tunes it on the dynamics loss (it divided None by a number)."""
    from bgn.laws.finetune import law_objective

    data, _ = charged_data
    ds = data["train"]
    model = build_model({"name": "newton", "mass_law": "coupling", "law": "formula",
                         "law_formula": TRUE_LAW}, ds.meta, ds.file.stats(), ds.history).double()
    model.eval()
    batch = double(collate([w for s in range(2) for w in windows(ds, s, range(8, 40, 4))]))
    with torch.no_grad():
        alone = float(law_objective(model, model.head, batch))
        model.heads = ("law",)
        with_law_head = float(law_objective(model, model.head, batch))
    assert math.isfinite(alone) and with_law_head == alone


def test_the_formula_tuning_holds_the_couplings_and_reports_its_loss_with_them_refitted(
        charged_data, monkeypatch):
    """Under the coupling law the formula stage tunes the law's constants with each
    simulation's couplings fitted once, through the starting constants, and held (their
    multi-start fit costs far more than the law): two fits per batch whatever the number of
    evaluations; a softening constant set 3x off moves back to the truth's (through substeps
    that resolve the encounters, as the stage tunes: one step per frame favours a softer law);
    the loss returned is the tuned law's with the couplings fitted again through it."""
    import bgn.model.newton as newton
    from bgn.laws.finetune import law_objective, tune_constants
    from bgn.laws.options import DEFAULTS

    data, _ = charged_data
    ds = data["train"]
    off = TRUE_LAW.replace('"c": 0.01', '"c": 0.03')
    model = build_model({"name": "newton", "mass_law": "coupling", "law": "formula",
                         "law_formula": off, "substeps": 4}, ds.meta, ds.file.stats(),
                        ds.history).double()
    model.eval()
    head = model.head
    batch = double(collate([w for s in range(3) for w in windows(ds, s, range(8, 156, 4))]))
    fits = []
    real_fit = newton.fit_couplings
    monkeypatch.setattr(newton, "fit_couplings", lambda *a: fits.append(1) or real_fit(*a))
    with torch.no_grad():
        before = float(law_objective(model, head, batch))
    fits.clear()
    loss, evaluations = tune_constants(model, head, [(1.0, batch)], 60, None)
    # 60 evaluations a pass, a pass and its restarts (DEFAULTS.finetune_restarts), one refit
    passes = 1 + DEFAULTS.finetune_restarts
    assert len(fits) == 2 and evaluations == 60 * passes + 1, (len(fits), evaluations)
    with torch.no_grad():
        assert loss == pytest.approx(float(law_objective(model, head, batch)), rel=1e-9)
    c = float(torch.exp(head.force_law.log_c[0]))
    assert loss < 0.5 * before and abs(c - 0.01) < 0.002, (loss, before, c)
