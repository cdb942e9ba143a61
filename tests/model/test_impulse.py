"""The impulse head (bgn.model.impulse): times of impact, equal and opposite impulses, and the
exact next frame of a single elastic impact."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from bgn.graph import window_graph
from bgn.model.impulse import (
    RULE_LOGIT,
    ContactImpulseHead,
    scene_speed,
    time_of_impact,
    wall_impact,
    walls,
)
from bgn.sim.collisions import integrate
from tests.model.conftest import make_meta

DT = 0.1


def head(box: float = 10.0) -> ContactImpulseHead:
    meta = replace(make_meta(n=2, n_types=2, interaction="contact", graph="radius", box=box))
    torch.manual_seed(0)
    h = ContactImpulseHead(meta, 16, "silu").double()
    with torch.no_grad():  # elastic, and gates that pass every impact of the rule
        h.restitution.fill_(-40.0)
        h.wall_restitution.fill_(-40.0)
        h.gate[-1].bias.fill_(40.0)
        h.wall_gate[-1].bias.fill_(40.0)
    return h


def disc_graph(window: torch.Tensor, radii: list[float], box: float = 10.0):
    """A graph of one frame from positions (k+2, N, D), every pair an edge."""
    n = window.shape[1]
    i, j = torch.meshgrid(torch.arange(n), torch.arange(n), indexing="ij")
    edges = torch.stack([j[i != j], i[i != j]])
    return window_graph(window[None].double(), DT, edges, torch.ones(1, n),
                        torch.tensor([radii], dtype=torch.float64),
                        torch.zeros(1, n, dtype=torch.long), box,
                        torch.tensor([0]), torch.tensor([0]), dtype=torch.float64)


def test_time_of_impact_of_a_head_on_approach_and_of_pairs_that_miss():
    dx = torch.tensor([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    dv = torch.tensor([[-4.0, 0.0], [4.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    frac, hit = time_of_impact(dx, dv, torch.full((3,), 0.7, dtype=torch.float64),
                               torch.full((3,), DT, dtype=torch.float64))
    assert hit.tolist() == [True, False, False]
    torch.testing.assert_close(frac[0], torch.tensor(0.075 / DT, dtype=torch.float64))
    assert frac[1:].tolist() == [1.0, 1.0]
    x = torch.tensor([[0.25, 5.0]], dtype=torch.float64)
    box = (torch.zeros(1, 2, dtype=torch.float64), torch.full((1, 2), 10.0, dtype=torch.float64))
    wall_frac, wall_hit = wall_impact(x, torch.tensor([[-1.0, 0.0]], dtype=torch.float64),
                                      torch.tensor([0.2], dtype=torch.float64), box,
                                      torch.tensor([DT], dtype=torch.float64))
    assert wall_hit.tolist() == [[True, False]]
    torch.testing.assert_close(wall_frac[0, 0], torch.tensor(0.05 / DT, dtype=torch.float64))


def test_a_head_on_elastic_impact_gives_the_exact_next_frame():
    # two equal discs (radius 0.5) approach at speed 2 each; they touch 0.025 into the next
    # frame of 0.1 and swap velocities: in free flight before, nothing happened in the window
    h = head()
    with torch.no_grad():
        h.log_mass[-1].weight.zero_()  # equal masses whatever the radius
    t = torch.arange(-4, 1, dtype=torch.float64)[:, None] * DT      # frames t-3 .. t
    left = torch.stack([4.35 + 2 * t[:, 0], torch.full((5,), 5.0, dtype=torch.float64)], -1)
    right = torch.stack([5.45 - 2 * t[:, 0], torch.full((5,), 5.0, dtype=torch.float64)], -1)
    g = disc_graph(torch.stack([left, right], 1), [0.5, 0.5])
    v_next, logits = h(g)
    # left reaches x = 4.5 at 0.025 (gap 0.05 closed at speed 4), then moves back at -2
    expected_left = (4.35 + 2 * 0.025 - 2 * 0.075 - 4.35) / DT
    torch.testing.assert_close(v_next[:, 0], torch.tensor([expected_left, -expected_left],
                                                          dtype=torch.float64))
    assert (logits > 0).all()


def test_pair_impulses_are_equal_and_opposite_for_any_masses():
    h = head()
    torch.manual_seed(1)
    n = 12
    x = torch.rand(n, 2, dtype=torch.float64) * 3 + 3.5
    v = torch.randn(n, 2, dtype=torch.float64) * 5
    radii = [0.2 if k % 2 else 0.4 for k in range(n)]
    window = torch.stack([x + v * DT * s for s in range(-3, 1)])
    g = disc_graph(window, radii)
    frame = h.resolve(g, g.pos, g.vel[:, 0], g.dt[g.batch])
    assert len(frame.pairs) > 0  # some pairs do meet
    masses = torch.exp(h.log_masses(g))[:, None]
    for after in (frame.velocity, frame.mean_velocity):
        torch.testing.assert_close((masses * (after - g.vel[:, 0])).sum(0),
                                   torch.zeros(2, dtype=torch.float64), atol=1e-10, rtol=0)


def dense_gas(n: int = 14, box: float = 4.0, seed: int = 3):
    """Discs of radii 0.25 and 0.375 (exact in float32, as the test graphs store radii)
    placed without overlap in a box, fast enough that several of them meet two or more discs
    or walls within one frame of DT."""
    rng = np.random.default_rng(seed)
    radii = np.where(np.arange(n) % 2, 0.25, 0.375)
    pos: list[np.ndarray] = []
    while len(pos) < n:
        p = rng.uniform(0.4, box - 0.4, 2)
        if all(np.linalg.norm(p - q) > 0.76 for q in pos):
            pos.append(p)
    return np.array(pos), rng.normal(0.0, 6.0, (n, 2)), radii


def test_several_impacts_in_a_frame_resolve_as_the_simulator_does():
    # one at a time in time order from where each disc is: the simulator's next frame exactly,
    # kinetic energy kept; the sum of every impulse from the frame's start velocities is not
    box = 4.0
    h = head(box)
    with torch.no_grad():
        h.log_mass[-1].weight.zero_()  # equal masses whatever the radius
    pos, vel, radii = dense_gas(box=box)
    n = len(pos)
    window = torch.as_tensor(np.stack([pos - vel * DT * s for s in range(3, -1, -1)]))
    g = disc_graph(window, radii.tolist(), box=box)
    dt = float(g.dt[0])
    xs, vs, _, _ = integrate(pos, vel, np.ones(n), radii, box, np.array([0.0, dt]))
    frame = h.resolve(g, torch.as_tensor(pos), torch.as_tensor(vel), g.dt[g.batch])
    per_disc = torch.bincount(torch.cat([g.edge_index[1][frame.pairs],
                                         g.edge_index[0][frame.pairs]]), minlength=n)
    assert int(per_disc.max()) >= 2       # the case the Jacobi sum got wrong
    torch.testing.assert_close(frame.mean_velocity,
                               torch.as_tensor((xs[1] - xs[0]) / dt), atol=1e-9, rtol=0)
    torch.testing.assert_close(frame.velocity, torch.as_tensor(vs[1]), atol=1e-9, rtol=0)
    energy = (frame.velocity ** 2).sum()
    torch.testing.assert_close(energy, torch.as_tensor((vel ** 2).sum()), atol=1e-9, rtol=0)


def test_impacts_never_create_kinetic_energy_whatever_the_gates_masses_and_restitution():
    # each impact scales the approach speed along its normal by 1 - (1 + e) gate, in [-1, 1]:
    # one at a time, a disc hit several times within a frame cannot gain energy either
    box = 4.0
    h = head(box)
    torch.manual_seed(7)
    with torch.no_grad():
        for net in (h.gate, h.wall_gate, h.log_mass):
            net[-1].weight.normal_()
            net[-1].bias.normal_()
        h.log_mass[-1].weight.mul_(10)  # masses of the two sizes well apart
        h.restitution.fill_(-0.5)
        h.wall_restitution.fill_(0.5)
    pos, vel, radii = dense_gas(box=box, seed=11)
    window = torch.as_tensor(np.stack([pos - vel * DT * s for s in range(3, -1, -1)]))
    g = disc_graph(window, radii.tolist(), box=box)
    frame = h.resolve(g, torch.as_tensor(pos), torch.as_tensor(vel), g.dt[g.batch])
    per_disc = torch.bincount(torch.cat([g.edge_index[1][frame.pairs],
                                         g.edge_index[0][frame.pairs]]), minlength=len(pos))
    assert int(per_disc.max()) >= 2
    masses = torch.exp(h.log_masses(g))
    assert masses.max() / masses.min() > 1.5      # unequal: the types' masses differ
    before = (masses[:, None] * torch.as_tensor(vel) ** 2).sum()
    after = (masses[:, None] * frame.velocity ** 2).sum()
    assert after < before


@pytest.mark.parametrize("factor", [1e-3, 1e3])
def test_the_head_is_the_same_motion_at_any_length_scale(factor):
    # every length x factor at the same frame rate (bgn.sim.transform.scaled): elastic impacts
    # in a box are the same motion, and the head's prediction too, gates and masses included
    box = 4.0
    h = head(box)
    torch.manual_seed(3)
    with torch.no_grad():  # gates and masses that are not the rule alone
        for net in (h.gate, h.wall_gate, h.log_mass):
            net[-1].weight.normal_()
            net[-1].bias.normal_()
    pos, vel, radii = dense_gas(box=box, seed=5)
    window = torch.as_tensor(np.stack([pos - vel * DT * s for s in range(3, -1, -1)]))
    v_next, logits = h(disc_graph(window, radii.tolist(), box=box))
    v_scaled, logits_scaled = h(disc_graph(window * factor, (radii * factor).tolist(),
                                           box=box * factor))
    torch.testing.assert_close(v_scaled / factor, v_next, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(logits_scaled, logits, atol=1e-9, rtol=1e-9)
    assert (logits > 0).any() and (torch.exp(h.log_masses(disc_graph(
        window, radii.tolist(), box=box))).unique().numel() == 2)


def test_walls_come_from_the_graph_not_the_training_box():
    # a model of the box of side 10 rolling out a box of side 30: no phantom wall at 10
    h = head(box=10.0)
    t = torch.arange(-4, 1, dtype=torch.float64) * DT
    x = torch.stack([9.87 + 1.0 * t, torch.full((5,), 5.0, dtype=torch.float64)], -1)
    far = torch.stack([torch.full((5,), 20.0, dtype=torch.float64),
                       torch.full((5,), 20.0, dtype=torch.float64)], -1)
    v_next, _ = h(disc_graph(torch.stack([x, far], 1), [0.1, 0.1], box=30.0))
    torch.testing.assert_close(v_next[0], torch.tensor([1.0, 0.0], dtype=torch.float64))
    v_next, _ = h(disc_graph(torch.stack([x, far], 1), [0.1, 0.1], box=10.0))
    # in the box of side 10 it bounces off the wall at 10, 0.3 into the frame
    torch.testing.assert_close(v_next[0, 0], torch.tensor(1.0 - 2 * 0.7, dtype=torch.float64))


def test_window_contacts_finds_the_impact_the_window_replays_and_the_gate_can_veto_it():
    # equal discs (radius 0.5) approach at speed 2 each and swap velocities 0.05 after frame 4
    # of the window 0 .. 6: the head's replay of frames 3 .. 6 meets it between t-2 and t-1
    h = head()
    tau = torch.arange(7, dtype=torch.float64) * DT
    hit = 0.45
    left = torch.where(tau < hit, 4.0 + 2 * tau, 4.9 - 2 * (tau - hit))
    right = torch.where(tau < hit, 6.8 - 2 * tau, 5.9 + 2 * (tau - hit))
    y = torch.full((7,), 5.0, dtype=torch.float64)
    g = disc_graph(torch.stack([torch.stack([left, y], -1), torch.stack([right, y], -1)], 1),
                   [0.5, 0.5])
    assert h.window_contacts(g).tolist() == [[2, 0, 1]]   # (frames back from t, i < k)
    with torch.no_grad():
        h.gate[-1].bias.fill_(-40.0)
    assert h.window_contacts(g).shape == (0, 3)


def test_the_replays_carry_no_gradient_and_the_predicted_frame_trains_the_head():
    # two pairs of equal discs approach at speed 2 each: the lower pair touches within the
    # window (0.05 after frame 4 of 0 .. 6, in a replayed frame), the upper one in the frame
    # ahead (0.05 after t)
    h = head()
    with torch.no_grad():  # gates and restitution off their saturated test values
        h.gate[-1].bias.zero_()
        h.restitution.fill_(-5.0)
    tau = torch.arange(7, dtype=torch.float64) * DT
    hit = 0.45
    left = torch.where(tau < hit, 4.0 + 2 * tau, 4.9 - 2 * (tau - hit))
    right = torch.where(tau < hit, 6.8 - 2 * tau, 5.9 + 2 * (tau - hit))
    low, high = (torch.full((7,), y, dtype=torch.float64) for y in (2.0, 8.0))
    discs = [torch.stack(xy, -1) for xy in ((left, low), (right, low),
                                            (4.0 + 2 * tau, high), (7.6 - 2 * tau, high))]
    g = disc_graph(torch.stack(discs, 1), [0.5] * 4)
    v, _, frames = h._replay(g)
    assert sum(len(f.pairs) for f in frames) == 1      # the lower pair's impact, replayed once
    assert not v.requires_grad
    prediction, _ = h(g)
    prediction[2, 0].backward()                        # the upper pair's impact ahead
    for p in (h.gate[-1].weight, h.restitution):
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_the_gate_runs_on_candidates_and_leaves_the_velocities_as_on_every_edge(monkeypatch):
    # a random gas: candidates are the pairs with a time of impact or a gap their speeds close
    # within a frame; elsewhere the logit is the rule's -RULE_LOGIT and the kick is zero
    h = head()
    with torch.no_grad():  # a gate that is not the rule alone: the MLP matters where it runs
        h.gate[-1].weight.normal_()
        h.gate[-1].bias.fill_(0.3)
    torch.manual_seed(2)
    n = 40
    x = torch.rand(n, 2, dtype=torch.float64) * 6 + 2
    v = torch.randn(n, 2, dtype=torch.float64) * 3
    window = torch.stack([x + v * DT * s for s in range(-3, 1)])
    g = disc_graph(window, [0.2 if k % 2 else 0.3 for k in range(n)])
    dt = g.dt[g.batch].double()
    _, hit, _, _, gap, _ = h.pair_geometry(g, g.pos, g.vel[:, 0], dt)
    chosen = h.candidates(g, g.vel[:, 0], dt, hit, gap)
    assert 0 < int(hit.sum()) < int(chosen.sum()) < chosen.numel()  # hits, near pairs, others

    frame = h.resolve(g, g.pos, g.vel[:, 0], dt)
    monkeypatch.setattr(ContactImpulseHead, "candidates",
                        lambda self, g, v, dt, hit, gap: torch.ones_like(hit))
    every = h.resolve(g, g.pos, g.vel[:, 0], dt)
    torch.testing.assert_close(frame.mean_velocity, every.mean_velocity, atol=0, rtol=0)
    torch.testing.assert_close(frame.velocity, every.velocity, atol=0, rtol=0)
    torch.testing.assert_close(frame.logits[chosen], every.logits[chosen])
    assert (frame.logits[~chosen] == -RULE_LOGIT).all()
    # a replayed frame (no logits) resolves the same impacts
    replayed = h.resolve(g, g.pos, g.vel[:, 0], dt, every_edge=False)
    assert replayed.logits is None
    torch.testing.assert_close(replayed.mean_velocity, frame.mean_velocity, atol=0, rtol=0)


def test_the_wall_gate_on_the_wall_hits_equals_the_gate_on_every_disc():
    # discs on a grid, too slow to meet each other within the frame: walls alone
    h = head(box=4.0)
    with torch.no_grad():
        h.wall_gate[-1].weight.normal_()
        h.wall_gate[-1].bias.fill_(-2.0)
    torch.manual_seed(5)
    grid = torch.arange(5, dtype=torch.float64) * 0.9 + 0.2
    x = torch.cartesian_prod(grid, grid)
    v = (torch.rand(len(x), 2, dtype=torch.float64) * 2 - 1) * 2.4
    g = disc_graph(torch.stack([x + v * DT * s for s in range(-3, 1)]), [0.1] * len(x), box=4.0)
    dt = g.dt[g.batch].double()
    frame = h.resolve(g, g.pos, g.vel[:, 0], dt)
    assert len(frame.pairs) == 0
    frac, hit = wall_impact(g.pos, g.vel[:, 0], g.radius, walls(g), dt)
    assert 0 < int(hit.sum()) < hit.numel()
    feats = torch.stack([frac, hit.double(), g.vel[:, 0].abs() / scene_speed(g)[:, None]], -1)
    gate = torch.sigmoid(h.wall_gate(feats).squeeze(-1) + RULE_LOGIT * (2 * hit.double() - 1))
    _, e_wall = h.restitutions()
    wall_dv = -(1 + e_wall) * g.vel[:, 0] * gate * hit
    torch.testing.assert_close(frame.velocity, g.vel[:, 0] + wall_dv)
    torch.testing.assert_close(frame.mean_velocity, g.vel[:, 0] + wall_dv * (1 - frac))


def test_no_time_left_or_a_disc_at_rest_keeps_every_gradient_finite():
    # a disc whose last impact ends the frame solves its next impacts in no time at all
    dx = torch.tensor([[1.0, 0.0], [0.5, 0.0]], dtype=torch.float64, requires_grad=True)
    dv = torch.tensor([[-4.0, 0.0], [0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    dt = torch.tensor([0.0, DT], dtype=torch.float64, requires_grad=True)
    frac, hit = time_of_impact(dx, dv, torch.full((2,), 0.7, dtype=torch.float64), dt)
    assert hit.tolist() == [False, False]
    frac.sum().backward()
    for t in (dx, dv, dt):
        assert torch.isfinite(t.grad).all()
    # at rest along x: float32 is where a 1 / (|v| + tiny) backward overflowed to inf
    for dtype in (torch.float32, torch.float64):
        x = torch.tensor([[0.25, 5.0]], dtype=dtype, requires_grad=True)
        v = torch.tensor([[0.0, 1.0]], dtype=dtype, requires_grad=True)
        box = (torch.zeros(1, 2, dtype=dtype), torch.full((1, 2), 10.0, dtype=dtype))
        for span in (0.0, DT):
            x.grad = v.grad = None
            frac, hit = wall_impact(x, v, torch.tensor([0.2], dtype=dtype), box,
                                    torch.tensor([span], dtype=dtype))
            assert not hit.any()
            frac.sum().backward()
            assert torch.isfinite(x.grad).all() and torch.isfinite(v.grad).all()
