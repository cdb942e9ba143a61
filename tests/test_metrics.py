"""Metrics on synthetic arrays: calibrated, shifted and collapsed mass samples, KDE modes,
R^2 and type metrics."""

from __future__ import annotations

import numpy as np
import pytest

from bgn.metrics import inverse_metrics, kde_modes, r2_score, recovered_modes, type_metrics


def bimodal_log_masses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Two types, as in collisions: log-masses around log 0.001 and log 0.4."""
    centre = np.where(rng.random(n) < 0.5, np.log(0.001), np.log(0.4))
    return centre + 0.1 * rng.standard_normal(n)


def test_perfect_samples_are_calibrated() -> None:
    rng = np.random.default_rng(0)
    n, s = 400, 64
    centre = np.where(rng.random(n) < 0.5, np.log(0.001), np.log(0.4))
    true = centre + 0.1 * rng.standard_normal(n)
    # each particle's samples from the same distribution its true value came from
    samples = centre + 0.1 * rng.standard_normal((s, n))
    m = inverse_metrics(true, samples)
    assert m["coverage50"] == pytest.approx(0.5, abs=0.08)
    assert m["coverage90"] == pytest.approx(0.9, abs=0.05)
    assert m["wasserstein1"] < 0.1
    assert m["welch_p"] > 0.01
    assert m["modes_true"] == 2 and m["modes_recovered"] == 2


def test_shifted_samples_are_not() -> None:
    rng = np.random.default_rng(1)
    true = bimodal_log_masses(rng, 400)
    samples = true[None, :] + 2.0 + 0.1 * rng.standard_normal((64, 400))
    m = inverse_metrics(true, samples)
    assert m["coverage50"] < 0.05 and m["coverage90"] < 0.05
    assert m["wasserstein1"] == pytest.approx(2.0, abs=0.1)
    assert m["welch_p"] < 1e-6
    assert m["modes_recovered"] == 0


def test_collapsed_samples_lose_a_mode() -> None:
    rng = np.random.default_rng(2)
    true = bimodal_log_masses(rng, 400)
    samples = np.log(0.4) + 0.1 * rng.standard_normal((32, 400))  # every particle "heavy"
    n_true, n_matched = recovered_modes(true, samples)
    assert (n_true, n_matched) == (2, 1)


def test_kde_modes_and_r2() -> None:
    grid = np.linspace(-5, 5, 501)
    values = np.concatenate([np.full(50, -2.0), np.full(50, 2.0)])
    values = values + 0.05 * np.random.default_rng(3).standard_normal(100)
    assert np.allclose(kde_modes(values, grid), [-2, 2], atol=0.1)
    x = np.arange(10.0)
    assert r2_score(x, x) == 1.0 and r2_score(np.full(10, x.mean()), x) == pytest.approx(0.0)
    assert np.isnan(r2_score(x, np.ones(10)))


def test_bad_sample_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="n_samples"):
        inverse_metrics(np.zeros(5), np.zeros((3, 4)))


def test_type_metrics() -> None:
    logits = np.array([[2.0, 0.0], [0.0, 2.0], [1.0, 0.0], [0.0, 1.0]])
    assert type_metrics(logits, np.array([0, 1, 0, 1])) == {"type_accuracy": 1.0,
                                                            "type_auroc": 1.0}
    assert type_metrics(logits, np.array([1, 0, 1, 0]))["type_accuracy"] == 0.0
