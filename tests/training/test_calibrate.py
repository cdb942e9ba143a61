"""The soft-contact head's rollout calibration (bgn.training.calibrate): the misfit it
minimises, and the damping it recovers from data a known damping made."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bgn.training.calibrate import calibrate_dissipation, speed_misfit
from tests.conftest import compose_config

DT = 0.01


def test_the_misfit_is_the_squared_gap_of_the_log_mean_speeds():
    rng = np.random.default_rng(0)
    steps = rng.normal(size=(3, 20, 5, 2))
    true = np.cumsum(steps, axis=1)
    assert speed_misfit(true, true) == 0.0
    # every displacement twice as long: every mean speed doubles
    doubled = np.cumsum(2 * steps, axis=1)
    assert speed_misfit(doubled, true) == pytest.approx(math.log(2) ** 2)
    assert speed_misfit(true + 5.0, true) == pytest.approx(0.0, abs=1e-20)  # translation
    failed = doubled.copy()
    failed[0, -1] = np.nan
    assert speed_misfit(failed, true) == math.inf


def bouncing_discs(zeta: float, sims: int = 8, frames: int = 220, n: int = 4) -> np.ndarray:
    """(S, T, N, 2) discs of radius 0.03 dropped in the unit box under gravity 1, apart from
    one another, bouncing on the floor with walls of damping ratio ``zeta``: made by the
    soft-contact head itself (so the calibration can recover ``zeta`` exactly)."""
    from tests.model.test_soft_contact import graph, head

    h = head(n=n, n_types=1, substeps=10, replay=0)
    with torch.no_grad():
        h.field.copy_(torch.tensor([0.0, -1.0]) * DT * DT / 1e-3)
        h.wall.friction.fill_(-30.0)
        h.pair.friction.fill_(-30.0)
    h.wall.set_zeta(zeta)
    rng = np.random.default_rng(1)
    out = []
    for _ in range(sims):
        x = torch.tensor(np.column_stack([np.linspace(0.15, 0.85, n),
                                          rng.uniform(0.3, 0.9, n)]))
        v = torch.tensor(rng.normal(0.0, 0.05, (n, 2)))
        g = graph(torch.stack([x - v * DT, x]), [0.03] * n, [0] * n)
        reach = h.reach(g)
        dt = torch.full((n,), DT, dtype=torch.float64)
        traj = [x]
        with torch.no_grad():
            for _ in range(frames - 1):
                moved, v = h.frame(g, x, v, dt, reach)
                x = x + moved
                traj.append(x)
        out.append(torch.stack(traj).numpy())
    return np.stack(out)


def test_the_calibration_recovers_the_damping_that_made_the_data(tmp_path):
    """Discs bouncing on a floor of damping ratio 0.3: a head that has everything else right
    and a damping ratio of 0.02 is set back to about 0.3 by its training rollouts, and its
    misfit falls; the walls keep their ratio to the pairs."""
    from bgn.data import from_arrays
    from bgn.training.run import build

    zeta = 0.3
    x = bouncing_discs(zeta)
    from_arrays(x, DT, radii=np.full(x.shape[2], 0.03), box=1.0, name="bouncing",
                data_dir=tmp_path, splits={"train": list(range(6)), "val": [6], "test": [7]})
    cfg = compose_config("train", ["dataset=imported", "dataset.name=bouncing",
                                   f"paths.data_dir={tmp_path}", "model.dynamics=soft_contact",
                                   f"paths.output_dir={tmp_path / 'run'}"])
    datamodule, module = build(cfg)
    head = module.model.force_head           # the stiffness it starts with made the data
    with torch.no_grad():
        head.field.copy_(torch.tensor([0.0, -1.0]) * DT * DT / 1e-3)
        head.wall.friction.fill_(-30.0)
        head.pair.friction.fill_(-30.0)
    head.wall.set_zeta(0.02)
    head.pair.set_zeta(0.04)                                     # walls at half the pairs'
    record = calibrate_dissipation(module.model, datamodule.datasets["train"], sims=4)
    assert record["wall_zeta"] == pytest.approx(zeta, rel=0.2)
    assert record["pair_zeta"] == pytest.approx(2 * record["wall_zeta"])
    assert record["misfit"] < record["misfit_fit"] / 10
    assert float(head.wall.zeta().detach()) == pytest.approx(record["wall_zeta"])
