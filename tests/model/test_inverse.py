"""Inverse model: both flows train and sample; no NaN with coincident particles."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from bgn.model import BGN, ModelConfig
from bgn.model.inverse import InverseModel, pair_features


def small(flow: str, context: str = "node", frames: int = 1) -> ModelConfig:
    return ModelConfig(hidden=16, decoder_hidden=16, flow=flow, flow_hidden=8,
                       flow_transforms=2, mass_context=context, mass_context_frames=frames)


@pytest.mark.parametrize("flow", ["nsf", "naf"])
def test_flow_forward_backward_and_sampling(meta, stats, graph, flow):
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small(flow))
    g = graph(6, dtype=torch.float32)
    out = model(g)
    assert out.mass_nll.shape == (6,) and out.relmass.shape == (30,)
    model.total_loss(model.loss_terms(g, out)).backward()
    flow_grads = [p.grad for n, p in model.named_parameters() if n.startswith("inverse.flow")]
    assert all(gr is not None and torch.isfinite(gr).all() for gr in flow_grads)
    # The relative-mass loss reaches the flow through the reparameterised sample.
    model.zero_grad()
    model.loss_terms(g, model(g))["relmass"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0
               for n, p in model.named_parameters() if n.startswith("inverse.flow"))
    samples = model.sample_mass(g, 5)
    assert samples.shape == (5, 6) and (samples > 0).all() and torch.isfinite(samples).all()


@pytest.mark.parametrize(("flow", "context", "frames"), [
    ("nsf", "node", 1), ("naf", "node", 1), ("nsf", "pairs", 1), ("nsf", "pairs", 2)])
def test_coincident_particles_have_finite_gradients(meta, stats, graph, flow, context, frames):
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small(flow, context, frames)).double()
    g = graph(6)
    pos, vel = g.pos.clone(), g.vel.clone()
    pos[1], vel[1] = pos[0], vel[0]             # particles 0 and 1 coincide
    g = replace(g, pos=pos, vel=vel)
    out = model(g)
    for name in ("target", "contact", "mass_nll", "relmass", "type_logits"):
        assert torch.isfinite(getattr(out, name)).all(), name
    model.total_loss(model.loss_terms(g, out)).backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_relative_decoder_can_represent_differences():
    """On [z, 1] the bilinear map holds z_i - z_j exactly (with 1-D z alone it could not)."""
    inv = InverseModel(context=4, hidden=2, act="relu").double()
    with torch.no_grad():
        inv.bilinear.weight.zero_()
        inv.bilinear.bias.zero_()
        inv.bilinear.weight[0, 0, 1], inv.bilinear.weight[0, 1, 0] = 1.0, -1.0   # z_i - z_j
        inv.bilinear.weight[1, 0, 1], inv.bilinear.weight[1, 1, 0] = -1.0, 1.0   # z_j - z_i
        inv.linear2.weight.copy_(torch.eye(2))
        inv.linear2.bias.zero_()
        inv.linear3.weight.copy_(torch.tensor([[1.0, -1.0]]))
        inv.linear3.bias.zero_()
    z = torch.randn(5, dtype=torch.float64)
    edge_index = torch.tensor([[0, 1, 2, 3], [1, 2, 3, 4]])
    torch.testing.assert_close(inv.relative(z, edge_index), z[edge_index[1]] - z[edge_index[0]])


def test_unknown_flow():
    with pytest.raises(ValueError, match="flow="):
        ModelConfig(flow="maf")


@pytest.mark.parametrize("flow", ["nsf", "naf"])
def test_log_probabilities_stay_finite_from_1e_4_to_1e2(meta, stats, graph, flow):
    """Masses far outside the training law (log-normal around 1) still get a finite NLL and
    finite gradients: the flows are bounded where their splines end."""
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small(flow))
    g = graph(6, dtype=torch.float32)
    for mass in (1e-4, 1e-2, 1.0, 1e2):
        extreme = replace(g, mass=torch.full((6,), mass))
        out = model(extreme)
        assert torch.isfinite(out.mass_nll).all(), mass
        model.zero_grad()
        out.mass_nll.mean().backward()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters()
                   if p.grad is not None), mass


def test_pair_features_at_the_frame_of_the_newest_acceleration(graph):
    """Positions one frame back (x[t] - dt v[t]) and accelerations (v[t] - v[t-1]) / dt."""
    g = graph(3)
    dt = float(g.dt[0])
    snd, rcv = g.edge_index
    e = 0
    # the newest frame alone, and the second frame of a two-frame window (t-2: one more step)
    for frames, f, prev in ((1, 0, g.pos - dt * g.vel[:, 0]),
                            (2, 1, g.pos - dt * g.vel[:, 0] - dt * g.vel[:, 1])):
        feats = pair_features(g, frames)
        assert feats.shape == (g.edge_index.shape[1], frames, 5)
        acc = (g.vel[:, f] - g.vel[:, f + 1]) / dt
        rel = prev[rcv[e]] - prev[snd[e]]
        unit = rel / rel.norm()
        expected = [rel.norm().log(), acc[rcv[e]].norm().log(), acc[snd[e]].norm().log(),
                    acc[rcv[e]] @ unit / acc[rcv[e]].norm(),
                    acc[snd[e]] @ unit / acc[snd[e]].norm()]
        torch.testing.assert_close(feats[e, f], torch.stack(expected))


def test_pair_context_trains_and_the_posterior_density_matches_the_loss(meta, stats, graph):
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small("nsf", "pairs")).double()
    g = graph(6)
    out = model(g)
    model.total_loss(model.loss_terms(g, out)).backward()
    assert model.inverse.pairs.edge[0].weight.grad.abs().sum() > 0
    model.eval()
    samples, log_density = model.mass_posterior(g, 7)
    assert samples.shape == (7, 6) and torch.isfinite(samples).all()
    # the density of the natural log-mass: the loss's, with the normalisation's Jacobian
    nll = model(g).mass_nll
    torch.testing.assert_close(log_density, -nll - model.normalizer.log_mass_scale.log())


def test_eval_decodes_the_posterior_median_and_training_a_random_draw(meta, stats, graph):
    """Eq. 9-10 read one flow draw per particle: a random one while training (the
    reparameterised sample the relative-mass loss trains through), the posterior's median
    (base draw 0) in eval mode, a point estimate that does not change from call to call."""
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small("nsf", "pairs")).double()
    g = graph(6)
    with torch.no_grad():
        drawn = [model(g).relmass for _ in range(2)]
        model.eval()
        median = model(g).relmass
        given = model(g, noise=torch.zeros(6, dtype=torch.float64)).relmass
        samples = model.sample_log_mass(g, 4000)
    assert not torch.equal(drawn[0], drawn[1])
    torch.testing.assert_close(model(g).relmass, median)
    torch.testing.assert_close(given, median)
    # the median draw is the samples' median, particle by particle
    p, _, _ = model._process(g)
    with torch.no_grad():
        centre = model.inverse.flow(model._mass_context(p, g)).transform.inv(
            torch.zeros(6, 1, dtype=torch.float64)).squeeze(-1)
    torch.testing.assert_close(samples.median(0).values, centre, atol=0.05, rtol=0)


def test_a_linear_radius_map_scales_the_base_and_keeps_the_median(meta, stats, graph):
    """Post-hoc calibration (InverseModel.calibration) with the map m(z) = 2 z: the true
    log-mass maps to the same base value; the density is that of the base N(0, 4); samples sit
    twice as far from the base's centre (their median, the flow's transform of 0, stays)."""
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small("nsf", "pairs")).double().eval()
    g = graph(6)
    u = model.mass_base_value(g)
    _, density = model.mass_posterior(g, 4)
    knots = torch.linspace(0, 3, 7)
    model.inverse.calibration = torch.stack([knots, 2 * knots])
    torch.testing.assert_close(model.mass_base_value(g), u)
    _, scaled = model.mass_posterior(g, 4)
    # log N(u; 0, 4) - log N(u; 0, 1) = -log 2 + 3 u^2 / 8
    torch.testing.assert_close(scaled - density, -torch.log(torch.tensor(2.0)) + 0.375 * u**2)
    torch.manual_seed(1)
    z = model.sample_log_mass(g, 4000)
    p, _, _ = model._process(g)
    with torch.no_grad():
        base = model.inverse.flow(model._mass_context(p, g)).transform(z[..., None]).squeeze(-1)
    assert float(base.std()) == pytest.approx(2.0, rel=0.05)
    assert "calibration" not in model.state_dict()           # fitted after training, not saved


def test_a_calibrated_density_integrates_to_one(meta, stats, graph):
    """A curved radius map (wider tails than centre): the change of variables keeps the
    posterior a density (trapezoid over the normalised log-mass)."""
    torch.manual_seed(0)
    model = BGN(meta(6, 2), stats(), 2, small("nsf", "pairs")).double().eval()
    g = graph(6)
    knots = torch.linspace(0, 3, 13, dtype=torch.float64)
    model.inverse.calibration = torch.stack([knots, 0.6 * knots + 0.3 * knots**2])
    with torch.no_grad():
        p, _, _ = model._process(g)
        context = model._mass_context(p, g)
        grid = torch.linspace(-30, 30, 60001, dtype=torch.float64)
        dens = torch.stack([model.inverse.log_density(context, x.expand(6)) for x in grid[::10]])
    mass = torch.trapezoid(dens.exp(), grid[::10], dim=0)
    torch.testing.assert_close(mass, torch.ones(6, dtype=torch.float64), atol=2e-3, rtol=0)
