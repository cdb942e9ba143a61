"""What a model is trained with (``PhysicsModel.supervision``, ``trained_with``): the recorded
quantities its training loss reads beyond the frames, derived from its heads and loss weights
(a term weighted 0 reads nothing), never written per table; beside what it is given at
inference (``given``)."""

from __future__ import annotations

import functools

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bgn.model.base import LOSS_KEYS, SUPERVISION
from tests.model.test_base import CASES, built

MASS_TERMS = ("mass_nll", "relmass", "law", "impulse_mass")
# (scene, overrides) -> what the training loss reads beyond the frames, with its terms
TRAINED = {
    # collisions' BGN: the recorded contacts (the impulse head's gate), types (classifier)
    # and masses (the flow, the relative masses, the impulse head's masses)
    ("collisions", "model=bgn"): {"contacts": ["contact"], "types": ["type"],
                                  "masses": ["mass_nll", "relmass", "impulse_mass"]},
    # gravity's law is trained on the recorded masses (dynamics weighted 0)
    ("gravity_r2", "model=bgn"): {"pair forces": ["contact"],
                                  "masses": ["mass_nll", "relmass", "law"]},
    ("spring", "model=bgn"): {"pair forces": ["contact"], "masses": ["mass_nll", "relmass"]},
    ("collisions", "model=newton"): {"contacts": ["contact"], "masses": ["impulse_mass"]},
    ("spring", "model=newton"): {},
    ("gravity_r2", "model=bgn", "ablation=unsupervised"): {"pair forces": ["contact"]},
    ("collisions", "model=bgn", "ablation=unsupervised"): {"contacts": ["contact"],
                                                            "types": ["type"]},
    ("spring", "model=bgn", "model.loss_weights.mass_nll=0", "model.loss_weights.relmass=0"):
        {"pair forces": ["contact"]},  # weighted 0: no masses
    ("collisions", "model=bgn", "ablation=no_contact"):
        {"types": ["type"], "masses": ["mass_nll", "relmass", "impulse_mass"]},
    ("collisions", "model=bgn", "ablation=no_inverse", "model.loss_weights.impulse_mass=0",
     "model.loss_weights.type=0", "model.loss_weights.contact=0"): {},
}


@pytest.mark.parametrize(("scene", "overrides"), [(k[0], k[1:]) for k in TRAINED],
                         ids=[" ".join(k) for k in TRAINED])
def test_trained_with_follows_the_heads_and_loss_weights(scene, overrides) -> None:
    model = built(scene, overrides)
    assert model.supervision == TRAINED[(scene, *overrides)]
    assert model.trained_with == tuple(TRAINED[(scene, *overrides)])
    record = model.describe()
    assert record["trained_with"] == list(model.trained_with)
    assert record["supervision"] == model.supervision


@pytest.mark.parametrize(("scene", "overrides"), [(k[0], k[1:]) for k in CASES
                                                  if "gns" in k[1] or "cranmer" in k[1]],
                         ids=[" ".join(k) for k in CASES if "gns" in k[1] or "cranmer" in k[1]])
def test_the_baselines_are_trained_on_the_frames_alone(scene, overrides) -> None:
    """A baseline's loss is the dynamics alone: neither masses nor contacts, whatever it is
    given at inference (the oracle reads the true masses as inputs, not as a target)."""
    model = built(scene, overrides)
    assert model.trained_with == () and model.supervision == {}


@functools.cache
def _collisions_bgn():
    return built("collisions", ("model=bgn",))


@given(st.dictionaries(st.sampled_from(LOSS_KEYS), st.sampled_from([0.0, 0.5, 1.0])))
@settings(max_examples=40, deadline=None)
def test_a_term_weighted_zero_is_not_supervision(weights) -> None:
    """Whatever the weights, a quantity is claimed exactly when a head the model has reads it
    with a positive weight."""
    model = _collisions_bgn()  # built once: only its weights change
    model.loss_weights = dict(weights)
    claimed = {q for q, terms in model.supervision.items() for _ in terms}
    expected = {q for k in model.heads if weights.get(k, 1.0) > 0 for q in SUPERVISION[k]}
    assert claimed == expected
    assert ("masses" in claimed) == any(weights.get(k, 1.0) > 0 for k in MASS_TERMS
                                        if k in model.heads)
