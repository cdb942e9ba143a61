"""Normalisation: robust scales with fallbacks, buffers in the state dict, round trips."""

from __future__ import annotations

import pytest
import torch

from bgn.model import BGN, ModelConfig, Normalizer


def test_scales_are_robust_with_fallbacks(stats):
    s = stats()
    norm = Normalizer(s, 2)
    # Heavy-tailed target: the robust scale (2.0), not the std (50.0).
    assert float(norm.target_scale) == pytest.approx(2.0)
    torch.testing.assert_close(norm.target_center, torch.full((2,), 0.2))
    # Contact robust scale is 0 (most values equal): falls back to std.
    assert float(norm.contact_scale) == pytest.approx(0.8)
    # Log-mass: mean and std (a flow prefers standardised values).
    assert float(norm.log_mass_center) == pytest.approx(0.2)
    assert float(norm.log_mass_scale) == pytest.approx(1.1)
    s["rel_velocity"]["robust_scale"][:] = 0.0
    s["rel_velocity"]["std"][:] = 0.0
    assert float(Normalizer(s, 2).rel_velocity_scale) == 1.0  # both zero: 1


def test_round_trips(stats):
    norm = Normalizer(stats(), 2)
    y = torch.randn(10, 2)
    torch.testing.assert_close(norm.denormalize_target(norm.target(y)), y)
    logm = torch.randn(10)
    torch.testing.assert_close(norm.denormalize_log_mass(norm.log_mass(logm)), logm)
    r = torch.randn(10)
    torch.testing.assert_close(norm.denormalize_rel_log_mass(norm.rel_log_mass(r)), r)


def test_statistics_travel_with_the_checkpoint(meta, stats):
    model = BGN(meta(), stats(), 2, ModelConfig(hidden=8))
    state = model.state_dict()
    assert float(state["normalizer.target_scale"]) == pytest.approx(2.0)
    other = stats()
    other["target"]["robust_scale"][:] = 7.0
    restored = BGN(meta(), other, 2, ModelConfig(hidden=8))
    restored.load_state_dict(state)
    assert float(restored.normalizer.target_scale) == pytest.approx(2.0)


def test_missing_statistics_are_named(stats):
    s = stats()
    del s["rel_position"]
    with pytest.raises(KeyError, match="rel_position"):
        Normalizer(s, 2)
