"""Target priors (bgn.model.target_coder): exact on the motions they extrapolate, invertible, built
from the input window only, and shared by BGN and the baselines."""

from dataclasses import fields, replace

import numpy as np
import pytest
import torch

from bgn.data.dataset import frame_graph
from bgn.model import build_model
from bgn.model.normalizer import Normalizer
from bgn.model.target_coder import RELATIVE_FLOOR, TargetCoder, observed_targets
from bgn.sim import make_scene

DT = 0.05


def polynomial_graph(degree: int, kind: str, history: int = 3):
    """A frame of a 4-body spring scene whose particles move on polynomials of ``degree``."""
    scene = make_scene("spring")
    rng = np.random.default_rng(degree)
    coef = rng.normal(size=(degree + 1, 4, 2))
    t = np.arange(history + 3)[:, None, None] * DT
    x = sum(c * t**p for p, c in enumerate(coef))  # (history + 3, 4, 2)
    meta = replace(scene.meta, target=kind)
    g = frame_graph(x[:-1], DT, meta, scene, np.ones(4), np.full(4, 0.1), np.zeros(4, int),
                    margin=0.0, next_position=x[-1])
    return replace(g, **{f.name: getattr(g, f.name).double() for f in fields(g)
                         if torch.is_tensor(getattr(g, f.name))
                         and getattr(g, f.name).is_floating_point()}), meta


def coder(stats, meta, prior, history=3):
    return TargetCoder(Normalizer(stats(), 2), stats(), meta, history, prior).double()


@pytest.mark.parametrize(("kind", "prior", "degree"), [
    ("acceleration", "last", 2),     # constant acceleration: the last one is the next one
    ("acceleration", "linear", 3),   # linearly changing acceleration: extrapolation is exact
    ("velocity", "last", 1),         # constant velocity
    ("velocity", "linear", 2),
])
def test_prior_is_exact_on_the_motion_it_extrapolates(stats, kind, prior, degree):
    g, meta = polynomial_graph(degree, kind)
    c = coder(stats, meta, prior)
    # float32 frames (as the files hold them): finite differences / dt carry ~1e-6 round-off
    torch.testing.assert_close(c.prior(g), g.target, rtol=0, atol=2e-5)
    scale = 1.0 if c.residual_scale is None else float(c.residual_scale)
    torch.testing.assert_close(c.encode(g) * scale, torch.zeros_like(g.target), rtol=0,
                               atol=2e-5)


def test_observed_accelerations_are_the_finite_differences_of_the_file_targets():
    g, _ = polynomial_graph(4, "acceleration")
    y = observed_targets(g, "acceleration")
    assert y.shape == (4, 3, 2)  # k observed accelerations from k + 1 velocities
    torch.testing.assert_close(y[:, 0], (g.vel[:, 0] - g.vel[:, 1]) / DT)


@pytest.mark.parametrize("prior", ["none", "last", "linear"])
@pytest.mark.parametrize("kind", ["acceleration", "velocity"])
def test_encode_decode_roundtrip_and_no_target_leak(stats, prior, kind):
    g, meta = polynomial_graph(4, kind)
    c = coder(stats, meta, prior)
    torch.testing.assert_close(c.decode(g, c.encode(g)), g.target)
    moved = replace(g, target=g.target + 1.0)
    torch.testing.assert_close(c.prior(moved), c.prior(g))  # the prior never sees the target


def test_residual_scale_comes_from_target_differences(stats):
    _, meta = polynomial_graph(2, "acceleration")
    assert float(coder(stats, meta, "last").residual_scale) == pytest.approx(0.4)
    assert float(coder(stats, meta, "linear").residual_scale) == pytest.approx(0.05)


def test_bad_priors_get_one_clear_error(stats):
    _, meta = polynomial_graph(2, "acceleration")
    with pytest.raises(ValueError, match="choose one of"):
        coder(stats, meta, "quadratic")
    with pytest.raises(ValueError, match="history=1"):
        coder(stats, meta, "linear", history=1)
    old = {k: v for k, v in stats().items() if not k.startswith("target_diff")}
    with pytest.raises(KeyError, match="regenerate"):
        TargetCoder(Normalizer(old, 2), old, meta, 3, "last")


@pytest.mark.parametrize("name", ["bgn", "cranmer_gn", "gns"])
def test_models_predict_prior_plus_scaled_output(stats, name):
    g, meta = polynomial_graph(3, "acceleration")
    model = build_model({"name": name, "target_prior": "linear"}, meta, stats(), 3).double()
    model.eval()
    out, coder = model(g).target, model.target_coder
    torch.testing.assert_close(model.predict(g), out * coder.residual_scale + coder.prior(g))
    torch.testing.assert_close(model.denormalize_target(out, g), model.predict(g))


@pytest.mark.parametrize(("kind", "prior", "loss"), [("acceleration", "linear", "huber"),
                                                     ("velocity", "last", "mse")])
def test_auto_picks_prior_and_loss_by_target_kind(stats, kind, prior, loss):
    g, meta = polynomial_graph(4, kind)
    c = TargetCoder(Normalizer(stats(), 2), stats(), meta, 3, "auto", "auto").double()
    assert (c.prior_name, c.loss_name) == (prior, loss)
    out = torch.randn_like(g.target) * 5
    y = c.encode(g)
    expected = (torch.nn.functional.huber_loss(out, y) if loss == "huber"
                else torch.nn.functional.mse_loss(out, y))
    torch.testing.assert_close(c.loss(out, g), expected)


def test_no_prior_means_the_papers_mse_under_auto(stats):
    """target_prior=none (gravity_r2's default) with dynamics_loss=auto: the paper's target and
    loss, in the normaliser's units."""
    g, meta = polynomial_graph(2, "acceleration")
    c = TargetCoder(Normalizer(stats(), 2), stats(), meta, 3, "none", "auto").double()
    assert (c.prior_name, c.loss_name, c.residual_scale) == ("none", "mse", None)
    torch.testing.assert_close(c.encode(g), c.normalizer.target(g.target))


@pytest.mark.parametrize("prior", ["none", "linear"])
def test_the_relative_loss_weighs_a_small_target_as_a_large_one(stats, prior):
    """dynamics_loss=relative: each particle's squared error over its own physical target's
    size (a floor of RELATIVE_FLOOR of the median size), whatever the head's units (with a
    prior: residuals), so the same relative miss costs the same on a small acceleration (a far
    pair's) as on a large one (an encounter's), where the MSE is the large one's alone; and
    it is scale-free in the target."""
    g, meta = polynomial_graph(2, "acceleration")
    c = TargetCoder(Normalizer(stats(), 2), stats(), meta, 3, prior, "relative").double()
    a = torch.tensor([[1.0, 0.5], [0.1, -0.05], [-30.0, 12.0], [0.7, -1.0]],
                     dtype=torch.float64)             # physical targets, sizes far apart
    g.target = a
    size = (a * a).sum(-1)
    expected = (0.01 * size / (size + RELATIVE_FLOOR * size.median())).mean()
    missed = c.loss(c.code(g, a * 1.1), g)            # every particle 10 % off
    torch.testing.assert_close(missed, expected, rtol=1e-6, atol=0)
    assert abs(float(missed) - 0.01) < 5e-4
    small = a.clone()
    small[1] *= 1.1                                   # the small target alone missed
    assert float(c.loss(c.code(g, small), g)) > 0.2 * float(missed)  # a quarter of them
    assert float(((small - a) ** 2).mean()) < 1e-4 * float(((0.1 * a) ** 2).mean())
    g.target = 7.0 * a                                # every target 7 times larger
    torch.testing.assert_close(c.loss(c.code(g, 7.0 * a * 1.1), g), missed, rtol=1e-6, atol=0)
