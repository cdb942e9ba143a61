"""bgn.laws.options: the typed options keep the values of the module constants they replace
(less the old term list's choice, which the law search replaced), and the command's keys set
their fields (``max_terms``: the search's)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bgn.laws.options import (
    COMMAND_KEYS,
    DEFAULTS,
    SEARCH_DEFAULTS,
    LawOptions,
    SearchOptions,
    from_keys,
)

# the module constants of bgn/eval/laws.py before the laws had a package (commit 536f519),
# and the settings added since (finetune_restarts: 63b1503)
OLD_CONSTANTS = {
    "zero_crossing_width": 0.1, "size_floor": 0.01, "grid_points": 240,
    "distance_quantiles": np.linspace(0.01, 0.99, 99), "kde_points": 20_000,
    "band_quantiles": (0.0, 0.01, 0.1, 0.5, 0.9, 0.99, 1.0), "c_grid": 41,
    "c_grid_pair": 25, "refine_per_complexity": 4, "calibration_frames": 256,
    "max_distances": 2_000_000, "significant": 4, "tolerance": 0.02,
    "finetune_steps": 80, "finetune_restarts": 1, "finetune_substeps": 16, "polish_factor": 4,
    "finetune_batch_size": 512, "amplitude_step": 0.1, "c_step": 2.0,
    "form_tolerance": 0.02, "negligible": 0.01, "finetune_horizon": 50,
    "rollout_chunk": 4096, "typical_floor": 1e-9, "close_share": 0.25,
    "robust_scale": 0.1, "turn_quantile": 1e-3, "below_floor": np.geomspace(1e-3, 1.0, 61),
    # finetune_formula's literal default
    "finetune_val_sims": None,
    # the law search's (wired in as the stage's read-back): its options, the front members
    # tuned on the frames
    "search": SEARCH_DEFAULTS, "finetune_members": 6,
    # validation rollouts from more start frames (docs/design.md, "Choosing on validation
    # rollouts"): a new default, not an old constant
    "finetune_val_rollouts": 100,
}


def test_the_defaults_are_the_old_constants_exactly():
    assert {f.name for f in dataclasses.fields(LawOptions)} == set(OLD_CONSTANTS)
    for name, old in OLD_CONSTANTS.items():
        new = getattr(DEFAULTS, name)
        if isinstance(old, np.ndarray):
            assert new.dtype == old.dtype and np.array_equal(new, old), name  # bit for bit
        else:
            assert type(new) is type(old) and new == old, name


def test_the_command_keys_are_fields_and_conf_laws_sets_their_defaults():
    from omegaconf import OmegaConf

    from tests.laws.conftest import ROOT

    conf = OmegaConf.load(ROOT / "conf" / "laws.yaml")
    for key in COMMAND_KEYS:
        owner = DEFAULTS if hasattr(DEFAULTS, key) else DEFAULTS.search  # max_terms: the search's
        assert conf[key] is None or conf[key] == getattr(owner, key), key


@given(st.integers(1, 4), st.floats(0, 1), st.one_of(st.none(), st.integers(1, 500)))
@settings(deadline=None)  # a loaded machine: no example's time is what is tested
def test_keys_set_their_fields_and_none_keeps_the_default(max_terms, tolerance, steps):
    options = from_keys({"max_terms": max_terms, "tolerance": tolerance,
                         "finetune_steps": steps})
    assert options.search.max_terms == max_terms and options.tolerance == tolerance
    assert options.finetune_steps == (DEFAULTS.finetune_steps if steps is None else steps)
    assert options.grid_points == DEFAULTS.grid_points  # the rest untouched
    assert options.search == SearchOptions(max_terms=max_terms)


def test_an_unknown_key_is_refused():
    with pytest.raises(ValueError, match="no law option 'finetune_stpes'"):
        from_keys({"finetune_stpes": 3})
